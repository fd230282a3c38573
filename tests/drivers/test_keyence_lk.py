"""Keyence LK-G: the bytes on the wire (CR-terminated commands and replies) and the driver, on a pty."""

from __future__ import annotations

import math

import numpy as np
import pytest
import serial

from drivers.base import DeviceError, DeviceLost, DeviceTimeout
from drivers.keyence_lk import DRIVER, parse_measured_value


class LinearWorld:
    """output = 2 um/V * input; the test sets the input to put the sensor where it wants."""

    def __init__(self) -> None:
        self.u = 0.0

    def command(self, value: float) -> None:
        self.u = float(value)

    def read(self, channel: str) -> float:
        if channel != "output":
            raise KeyError(channel)
        return 2.0 * self.u

    def play(self, waveform: np.ndarray, rate_hz: float) -> dict[str, np.ndarray]:
        return {"input": np.asarray(waveform, float), "output": 2.0 * np.asarray(waveform, float)}


@pytest.fixture
def world() -> LinearWorld:
    return LinearWorld()


@pytest.fixture
def emulator(world, request):
    emu = DRIVER.emulator({"url": "unused"}, world)
    request.addfinalizer(emu.close)
    return emu


@pytest.fixture
def sensor(emulator, request):
    dev = DRIVER.open({"url": emulator.url, "timeout_s": 0.1, "backoff_s": 0.01})
    request.addfinalizer(dev.close)
    return dev


@pytest.fixture
def wire(emulator, request):
    port = serial.serial_for_url(emulator.url, timeout=0.5)
    request.addfinalizer(port.close)

    def talk(command: bytes) -> bytes:
        port.write(command)
        return port.read_until(b"\r")

    return talk


# -- the protocol, byte by byte -----------------------------------------------------------------------------
def test_m1_replies_with_header_and_8_character_value(wire, world):
    world.u = 617.25  # 1234.5 um = 1.2345 mm
    assert wire(b"M1\r") == b"M1,+01.2345\r"
    world.u = -6.0  # -12 um
    assert wire(b"M1\r") == b"M1,-00.0120\r"
    assert wire(b"m1\r") == b"M1,-00.0120\r"  # lower case is accepted too


def test_m0_outputs_both_outs_and_an_lk_g3000_does_not_know_ms(wire, world):
    world.u = 500.0
    assert wire(b"M0\r") == b"M0,+01.0000,+01.0000\r"
    assert wire(b"MS,01\r") == b"ER,MS,00\r"  # the LK-G5000 form: a command error on an LK-G3000


def test_the_lk_g5000_has_ms_mm_ma_and_its_own_error_codes(world, request):
    emu = DRIVER.emulator({"url": "unused", "protocol": "MS"}, world)
    request.addfinalizer(emu.close)
    port = serial.serial_for_url(emu.url, timeout=0.5)
    request.addfinalizer(port.close)

    def talk(command: bytes) -> bytes:
        port.write(command)
        return port.read_until(b"\r")

    world.u = 500.0
    assert talk(b"MS,01\r") == b"MS,01,+01.0000\r"
    assert talk(b"MM,110000000000\r") == b"MM,110000000000,+01.0000,+01.0000\r"
    assert talk(b"MA\r") == b"MA,+01.0000,+01.0000\r"
    assert talk(b"M1\r") == b"ER,M1,50\r"  # command error
    assert talk(b"MS,13\r") == b"ER,MS,62\r"  # parameter range error
    assert talk(b"MS\r") == b"ER,MS,61\r"  # parameter count error
    assert talk(b"Q0\r") == b"Q0\r"
    assert talk(b"MS,01\r") == b"ER,MS,51\r"  # status error: no measuring in communication mode


def test_over_range_is_seven_f_signed(wire, world):
    world.u = 60000.0  # 120 mm does not fit "99.9999"
    assert wire(b"M1\r") == b"M1,+FFFFFFF\r"
    world.u = -60000.0
    assert wire(b"M1\r") == b"M1,-FFFFFFF\r"


def test_errors_are_er_command_code(wire):
    assert wire(b"ZZ\r") == b"ER,ZZ,00\r"  # command error
    assert wire(b"M3\r") == b"ER,M3,22\r"  # invalid parameter: no OUT3
    assert wire(b"Q0\r") == b"Q0\r"  # communication (set-up) mode
    assert wire(b"M1\r") == b"ER,M1,01\r"  # status error: no measuring in set-up mode
    assert wire(b"R0\r") == b"R0\r"


def test_measured_value_format_parser():
    assert parse_measured_value("+01.2345") == (1.2345, "ok")
    assert parse_measured_value("-00001.2") == (-1.2, "ok")
    assert parse_measured_value("+1234.56") == (1234.56, "ok")
    assert math.isnan(parse_measured_value("-FFFFFFF")[0])
    assert parse_measured_value("XXXXXXXX")[1] == "alarm"
    for bad in ("+1.2345", "01.23456", "+01.2.45", "+.......", "+0A.2345"):
        with pytest.raises(ValueError):
            parse_measured_value(bad)


# -- the driver ----------------------------------------------------------------------------------------------
def test_read_converts_mm_to_um(sensor, world, emulator):
    world.u = 617.25
    assert sensor.read() == {"output": pytest.approx(1234.5)}
    assert ("in", b"M1") in emulator.traffic and ("out", b"M1,+01.2345\r") in emulator.traffic
    assert sensor.last_status == "ok"


def test_controller_in_um_needs_no_scaling(world, request):
    emu = DRIVER.emulator({"url": "unused", "unit": "um", "decimals": 2}, world)
    request.addfinalizer(emu.close)
    dev = DRIVER.open({"url": emu.url, "unit": "um", "timeout_s": 0.1})
    request.addfinalizer(dev.close)
    world.u = 61.5
    assert dev.read() == {"output": pytest.approx(123.0)}
    assert ("out", b"M1,+0123.00\r") in emu.traffic


def test_lk_g5000_ms_command(world, request):
    emu = DRIVER.emulator({"url": "unused", "protocol": "MS"}, world)
    request.addfinalizer(emu.close)
    dev = DRIVER.open({"url": emu.url, "protocol": "MS", "model": "LK-G5000", "timeout_s": 0.1})
    request.addfinalizer(dev.close)
    world.u = 1.0
    assert dev.read() == {"output": pytest.approx(2.0)}
    assert ("in", b"MS,01") in emu.traffic and dev.identity() == f"Keyence LK-G5000 OUT1 at {emu.url}"


def test_open_sends_r0_and_takes_the_status_error_of_a_controller_in_general_mode(sensor, emulator):
    assert list(emulator.traffic)[:2] == [("in", b"R0"), ("out", b"ER,R0,01\r")]
    assert emulator.general_mode


def test_a_controller_left_in_communication_mode_measures_again_after_open(world, emulator, request):
    emulator.general_mode = False  # a set-up tool sent Q0 and went away
    dev = DRIVER.open({"url": emulator.url, "timeout_s": 0.1})
    request.addfinalizer(dev.close)
    world.u = 1.0
    assert dev.read() == {"output": pytest.approx(2.0)} and emulator.general_mode
    assert ("out", b"R0\r") in emulator.traffic


def test_open_fails_on_another_refusal_of_r0_and_can_skip_it(emulator, request):
    emulator.error_next("99")
    with pytest.raises(DeviceError, match=r"R0 refused: ER code 99: other error"):
        DRIVER.open({"url": emulator.url, "timeout_s": 0.1})
    emulator.traffic.clear()
    dev = DRIVER.open({"url": emulator.url, "timeout_s": 0.1, "general_mode_on_open": False})
    request.addfinalizer(dev.close)
    dev.read()
    assert [data for direction, data in emulator.traffic if direction == "in"] == [b"M1"]


def test_lk_g5000_error_codes_have_their_meanings(world, request):
    emu = DRIVER.emulator({"url": "unused", "protocol": "MS"}, world)
    request.addfinalizer(emu.close)
    dev = DRIVER.open({"url": emu.url, "protocol": "MS", "timeout_s": 0.1})
    request.addfinalizer(dev.close)
    assert ("out", b"ER,R0,51\r") in emu.traffic  # the LK-G5000's status error, taken on open
    emu.general_mode = False
    with pytest.raises(DeviceError, match=r"MS,01 refused: ER code 51: status error"):
        dev.read()


def test_out_of_range_and_alarm_read_as_nan(sensor, world, emulator):
    world.u = 60000.0
    assert math.isnan(sensor.read()["output"]) and sensor.last_status == "over_range_positive"
    emulator.force("-FFFFFFF")
    assert math.isnan(sensor.read()["output"]) and sensor.last_status == "over_range_negative"
    emulator.force("XXXXXXXX")
    assert math.isnan(sensor.read()["output"]) and sensor.last_status == "alarm"
    assert "NaN" in sensor.capabilities()["out_of_range"]


def test_er_reply_is_device_error_with_the_code_meaning(sensor, emulator):
    emulator.error_next("01")
    with pytest.raises(DeviceError, match="M1 refused: ER code 01: status error") as info:
        sensor.read()
    assert not isinstance(info.value, DeviceTimeout)


def test_timeout_is_retried(sensor, emulator, world):
    world.u = 1.0
    emulator.silence(0.15)
    assert sensor.read() == {"output": pytest.approx(2.0)}
    assert sum(1 for d, data in emulator.traffic if d == "in" and data == b"M1") >= 2


def test_timeouts_exhausted_raise_device_timeout(sensor, emulator):
    emulator.drop_replies(1000)
    with pytest.raises(DeviceTimeout, match="M1: no valid answer after 3 tries"):
        sensor.read()


def test_garbage_is_a_one_line_device_error(sensor, emulator):
    emulator.garble_next()
    with pytest.raises(DeviceError, match="garbled reply to M1") as info:
        sensor.read()
    assert "\n" not in str(info.value) and "\r" not in str(info.value)
    emulator.garble_next(b"M1,+0x.FFFF\r")  # ASCII, but not a measured value
    with pytest.raises(DeviceError, match="unexpected reply to M1"):
        sensor.read()


def test_disconnect_is_device_lost_naming_the_device(sensor, emulator):
    sensor.read()
    emulator.disconnect()
    with pytest.raises(DeviceLost, match=r"keyence-lk \(/dev/pts/\d+\)"):
        sensor.read()


def test_bad_settings_are_refused():
    assert DRIVER.problems({"url": "/dev/ttyUSB0", "out": "one"}) == [
        "key 'out' for driver 'keyence-lk': expected int, got 'one'"]
    with pytest.raises(DeviceError, match="out 3 does not exist"):
        DRIVER.open({"url": "/dev/null-not-opened", "out": 3})
    with pytest.raises(DeviceError, match=r"out 13 does not exist on an LK-G5000 \(1..12\)"):
        DRIVER.open({"url": "/dev/null-not-opened", "out": 13, "protocol": "MS"})
