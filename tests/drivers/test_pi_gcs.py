"""PI GCS 2.0 controller: the bytes on the wire and the driver, against the emulator on a real pty.

The first group talks to the emulated controller byte by byte, as the GCS manual describes the
commands; the second drives it through ``drivers.pi_gcs`` and checks what the driver sent.
"""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest
import serial

from drivers.base import DeviceError, DeviceLost, DeviceTimeout
from drivers.pi_gcs import DRIVER, parse_gcs_array


class LinearWorld:
    """output = 2 um/V * input: simple enough that every recorded value can be checked exactly."""

    um_per_v = 2.0

    def __init__(self) -> None:
        self.u = 0.0

    def command(self, value: float) -> None:
        self.u = float(value)

    def read(self, channel: str) -> float:
        return self.um_per_v * self.u if channel == "output" else self.u

    def play(self, waveform: np.ndarray, rate_hz: float) -> dict[str, np.ndarray]:
        self.u = float(waveform[-1])
        return {"input": np.array(waveform, dtype=float), "output": self.um_per_v * np.asarray(waveform, float)}


@pytest.fixture
def world() -> LinearWorld:
    return LinearWorld()


@pytest.fixture
def emulator(world, request):
    emu = DRIVER.emulator({"url": "unused", "tcp_port": 0}, world)
    request.addfinalizer(emu.close)
    return emu


@pytest.fixture
def device(emulator, request):
    dev = DRIVER.open({"url": emulator.url, "timeout_s": 0.1, "backoff_s": 0.01, "slew_v_per_s": 2000.0})
    request.addfinalizer(dev.close)
    return dev


@pytest.fixture
def wire(emulator, request):
    """A raw serial connection to the emulator: send bytes, read reply lines."""
    port = serial.serial_for_url(emulator.url, timeout=0.5)
    request.addfinalizer(port.close)

    def talk(command: bytes, lines: int = 1) -> list[bytes]:
        port.write(command)
        return [port.read_until(b"\n") for _ in range(lines)]

    talk.port = port
    return talk


def sent(emulator, prefix: bytes) -> list[bytes]:
    return [data for direction, data in emulator.traffic if direction == "in" and data.startswith(prefix)]


# -- the protocol, byte by byte -----------------------------------------------------------------------------
def test_idn_is_one_line_naming_pi_and_the_model(wire):
    (reply,) = wire(b"*IDN?\n")
    assert reply.endswith(b"\n") and not reply.endswith(b" \n")
    assert b"Physik Instrumente" in reply and b"E-727" in reply


def test_unknown_command_gets_no_reply_and_err_reports_2_once(wire):
    wire.port.write(b"FOO 1\n")  # GCS: set commands and failing commands are silent
    assert wire(b"ERR?\n") == [b"2\n"]  # 2 = unknown command
    assert wire(b"ERR?\n") == [b"0\n"]  # ERR? clears the register


def test_open_loop_voltage_and_position(wire, world):
    wire.port.write(b"SVO 1 0\nSVA 1 12.5\n")
    assert wire(b"ERR?\n") == [b"0\n"]
    assert wire(b"SVA? 1\n") == [b"1=12.500000\n"]
    assert wire(b"VOL? 1\n") == [b"1=12.500000\n"]
    assert wire(b"POS? 1\n") == [b"1=25.000000\n"]  # the world: 2 um/V
    assert world.u == 12.5


def test_sva_out_of_range_is_error_17_and_servo_on_is_error_79(wire):
    wire.port.write(b"SVA 1 500\n")
    assert wire(b"ERR?\n") == [b"17\n"]  # parameter out of range
    wire.port.write(b"SVO 1 1\nSVA 1 5\n")
    assert wire(b"ERR?\n") == [b"79\n"]  # open-loop value set when servo on
    assert wire(b"SVO? 1\n") == [b"1=1\n"]


def test_failing_query_is_answered_by_an_empty_line_and_err_says_why(wire):
    # docs/decisions/0095: the query ends (LF) so a client waiting for it does not time out
    assert wire(b"POS? 9\n") == [b"\n"]  # no axis 9
    assert wire(b"ERR?\n") == [b"15\n"]  # invalid axis identifier
    assert wire(b"FOO?\n") == [b"\n"]
    assert wire(b"ERR?\n") == [b"2\n"]  # unknown command


def test_closed_loop_move_reaches_target(wire):
    wire.port.write(b"SVO 1 1\nMOV 1 10\n")
    assert wire(b"ERR?\n") == [b"0\n"]
    deadline = time.monotonic() + 2.0  # the stage settles in ~15 ms at its 100 Hz bandwidth (wall-clock servo)
    while time.monotonic() < deadline:  # polled by time, not by count: a loaded machine answers polls slower
        (ont,) = wire(b"ONT? 1\n")
        if ont == b"1=1\n":
            break
    assert ont == b"1=1\n"
    (pos,) = wire(b"POS? 1\n")
    assert abs(float(pos.split(b"=")[1]) - 10.0) <= 0.02


def test_multiline_reply_continues_with_space_before_lf(wire):
    wire.port.write(b"HDR?\n")
    lines = []
    while not lines or lines[-1].endswith(b" \n"):
        lines.append(wire.port.read_until(b"\n"))
    assert lines[0] == b"#RecordOptions \n"
    assert all(line.endswith(b" \n") for line in lines[:-1]) and not lines[-1].endswith(b" \n")
    assert lines[-1] == b"131072 datapoints per table\n"


def test_wave_table_points_append_with_ampersand(wire):
    wire.port.write(b"WAV 1 X PNT 1 3 1.0 2.0 3.0\nWAV 1 & PNT 4 2 4.0 5.0\n")
    assert wire(b"ERR?\n") == [b"0\n"]
    assert wire(b"WAV? 1 1\n") == [b"1 1=5\n"]
    wire.port.write(b"WAV 1 & PNT 9 1 1.0\n")  # must continue at point 6
    assert wire(b"ERR?\n") == [b"17\n"]
    wire.port.write(b"WAV 1 X SIN 2000 20 10 2000 0 1000\n")
    assert wire(b"ERR?\n") == [b"402\n"]  # a real GCS wave type the emulator does not generate


def test_wave_generator_and_data_recorder_by_hand(wire, world):
    wire.port.write(b"WAV 1 X PNT 1 4 1 2 3 4\nWSL 1 1\nWGC 1 1\nWTR 1 2 0\nRTR 2\nDRC 1 1 2\nDRC 2 1 7\nWGO 1 1\n")
    assert wire(b"ERR?\n") == [b"0\n"]
    for _ in range(100):  # #9 (byte 0x09, no LF): hex mask of running generators
        (status,) = wire(b"\x09")
        if status == b"0\n":
            break
    assert status == b"0\n"
    assert wire(b"DRL? 1\n") == [b"1=4\n"]
    wire.port.write(b"DRR? 1 4 1 2\n")
    lines = []
    while not lines or lines[-1].endswith(b" \n"):
        lines.append(wire.port.read_until(b"\n"))
    assert lines[-2:] == [b"6.000000 3.000000 \n", b"8.000000 4.000000\n"]
    header, data = parse_gcs_array([x.decode()[:-1] for x in lines], "DRR?", "test")
    assert header["NDATA"] == "4" and header["DIM"] == "2"
    assert float(header["SAMPLE_TIME"]) == pytest.approx(2 / 20000.0)  # RTR 2 servo cycles of 50 us
    assert header["NAME0"].startswith("Actual Position")
    np.testing.assert_allclose(data, [[2, 1], [4, 2], [6, 3], [8, 4]])


def test_tcp_port_serves_the_same_protocol(emulator):
    assert emulator.tcp_url.startswith("socket://127.0.0.1:")
    dev = DRIVER.open({"url": emulator.tcp_url, "timeout_s": 0.2})
    try:
        assert "E-727" in dev.identity()
        dev.write(3.0)
        assert dev.read() == {"output": 6.0, "input": 3.0}
    finally:
        dev.close()


# -- the driver ----------------------------------------------------------------------------------------------
def test_identity_and_capabilities_come_from_the_controller(device, emulator):
    assert "E-727" in device.identity()
    caps = device.capabilities()
    assert caps["servo_rate_hz"] == pytest.approx(20000.0)  # from SPA? 1 0x0E000200 = 5e-05 s
    assert caps["record_points_per_table"] == 131072  # from HDR?
    assert sent(emulator, b"SPA? 1 0x0E000200") and sent(emulator, b"SVO 1 0")


def test_write_is_sva_checked_with_err_and_read_is_pos_and_vol(device, emulator):
    device.write(10.0)
    assert device.read() == {"output": 20.0, "input": 10.0}
    traffic = list(emulator.traffic)
    i = traffic.index(("in", b"SVA 1 10.000000"))
    assert traffic[i + 1:i + 3] == [("in", b"ERR?"), ("out", b"0\n")]


def test_gcs_error_becomes_device_error_with_number_and_text(device, emulator):
    emulator.fail_next(17)
    with pytest.raises(DeviceError, match="GCS error 17: Parameter out of range"):
        device.write(1.0)
    with pytest.raises(DeviceError, match="outside the allowed"):
        device.write(1000.0)  # refused before anything is sent
    emulator.fail_next(15)  # a failing query: silence, then ERR? tells why
    with pytest.raises(DeviceError, match="GCS error 15: Invalid axis identifier") as info:
        device.read()
    assert not isinstance(info.value, DeviceTimeout)


def test_play_uploads_in_chunks_and_returns_what_was_recorded(device, emulator):
    wave = 5.0 + 4.0 * np.sin(np.linspace(0.0, 4 * np.pi, 250))
    result = device.play(wave, 2000.0)
    np.testing.assert_allclose(result["input"], wave, atol=1e-6)
    np.testing.assert_allclose(result["output"], 2.0 * wave, atol=2e-6)
    np.testing.assert_allclose(np.diff(result["time"]), 1 / 2000.0)
    waves = sent(emulator, b"WAV 1 ")
    assert [w.split(b" PNT ")[0] for w in waves] == [b"WAV 1 X", b"WAV 1 &", b"WAV 1 &"]
    assert [w.split()[4:6] for w in waves] == [[b"1", b"100"], [b"101", b"100"], [b"201", b"50"]]
    assert sent(emulator, b"WTR 1 ") == [b"WTR 1 10 0"] and sent(emulator, b"RTR ") == [b"RTR 10"]
    assert sent(emulator, b"WGO 1 1") and sent(emulator, b"DRR? 1 250 1 2")


def test_play_refuses_a_rate_that_is_not_an_integer_divider(device, emulator):
    with pytest.raises(DeviceError, match=r"3000 Hz.*nearest: 3333.33 Hz \(divider 6\), 2857.14 Hz \(divider 7\)"):
        device.play(np.zeros(10), 3000.0)
    assert not sent(emulator, b"WGO 1 1") and not sent(emulator, b"WAV")


def test_play_reads_long_recordings_in_drr_chunks(emulator):
    dev = DRIVER.open({"url": emulator.url, "timeout_s": 0.2, "drr_chunk_points": 1000, "wave_chunk_points": 500})
    try:
        wave = np.linspace(0.0, 10.0, 2500)
        result = dev.play(wave, 20000.0)
        np.testing.assert_allclose(result["output"], 2.0 * wave, atol=2e-6)
        assert sent(emulator, b"DRR? ") == [b"DRR? 1 1000 1 2", b"DRR? 1001 1000 1 2", b"DRR? 2001 500 1 2"]
    finally:
        dev.close()


def test_timeout_is_retried(device, emulator):
    emulator.silence(0.15)  # longer than one timeout (0.1 s), shorter than the retries
    assert device.read() == {"output": 0.0, "input": 0.0}
    assert len(sent(emulator, b"POS? 1")) >= 2


def test_timeouts_exhausted_raise_device_timeout(device, emulator):
    emulator.drop_replies(1000)
    with pytest.raises(DeviceTimeout, match=r"POS\? 1 / VOL\? 1: no valid answer after 3 tries"):
        device.read()
    assert len(sent(emulator, b"POS? 1")) == 3


def test_garbage_is_a_one_line_device_error(device, emulator):
    emulator.garble_next()
    with pytest.raises(DeviceError) as info:
        device.read()
    assert "garbled reply to POS? 1" in str(info.value) and "\n" not in str(info.value)
    assert not isinstance(info.value, DeviceTimeout)
    assert device.read() == {"output": 0.0, "input": 0.0}  # and the next transaction is clean


def test_disconnect_mid_use_is_device_lost_naming_the_device(device, emulator):
    device.write(1.0)
    emulator.disconnect()
    with pytest.raises(DeviceLost, match=r"pi-gcs \(/dev/pts/\d+\)"):
        device.write(2.0)


def test_stop_false_ramps_to_rest_then_leaves_servo_off(device, emulator):
    device.write(10.0)
    device.stop(False)
    ramp = emulator.commanded_v[emulator.commanded_v.index(10.0):]
    assert ramp[-1] == 0.0 and len(ramp) >= 3  # a few steps, not a jump
    assert all(b < a for a, b in itertools.pairwise(ramp))
    assert emulator.servo is False and emulator.voltage == 0.0
    assert sent(emulator, b"WGO 1 0")


def test_settings_are_checked_without_opening_anything():
    assert DRIVER.problems({}) == [("missing key 'url' for driver 'pi-gcs' (serial port or pyserial URL: "
                                    "/dev/ttyUSB0, a pty path, socket://host:50000)")]
    assert DRIVER.problems({"url": "/dev/ttyUSB0", "baud": "fast"}) == [
        "key 'baud' for driver 'pi-gcs': expected int, got 'fast'"]


# -- faults, as the other drivers' tests have them -------------------------------------------------------
def test_a_refused_query_is_a_device_error_at_once_not_a_retried_timeout(device, emulator):
    before = len(sent(emulator, b"POS? 1"))
    emulator.fail_next(15)
    with pytest.raises(DeviceError, match=r"POS\? 1 refused: GCS error 15") as info:
        device.read()
    assert not isinstance(info.value, DeviceTimeout)
    assert len(sent(emulator, b"POS? 1")) == before + 1  # one try: an empty reply is an answer
    assert device.read() == {"output": 0.0, "input": 0.0}  # and the next transaction is clean


def test_firmware_that_stays_silent_on_a_failed_query_is_still_understood(device, emulator):
    """Some GCS firmware sends nothing at all for a query it refuses: ERR? after the silence says why."""
    emulator.fail_next(15)
    emulator.drop_replies(1)  # the empty line is not sent
    with pytest.raises(DeviceError, match="GCS error 15: Invalid axis identifier") as info:
        device.read()
    assert not isinstance(info.value, DeviceTimeout)


def test_a_closed_transport_is_device_lost_naming_the_device(device):
    device.close()
    with pytest.raises(DeviceLost, match=r"pi-gcs \(/dev/pts/\d+\).*closed"):
        device.read()
    with pytest.raises(DeviceLost):
        device.write(1.0)


def test_opening_a_port_that_is_not_there_is_a_one_line_device_error(tmp_path):
    with pytest.raises(DeviceError, match="cannot open") as info:
        DRIVER.open({"url": str(tmp_path / "ttyUSB9"), "timeout_s": 0.1})
    assert "\n" not in str(info.value)


def test_the_tcp_server_gone_mid_use_is_device_lost(emulator):
    dev = DRIVER.open({"url": emulator.tcp_url, "timeout_s": 0.2, "attempts": 2, "backoff_s": 0.01})
    try:
        dev.write(1.0)
        emulator.disconnect()
        with pytest.raises(DeviceLost) as info:  # the socket's EOF, not a timeout
            dev.write(2.0)
        assert "pi-gcs (socket://127.0.0.1:" in str(info.value)
    finally:
        dev.close()
