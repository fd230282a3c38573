"""Protocol tests of the modbus-aio driver against its emulator (a real pymodbus server on 127.0.0.1).

They read like the module's manual: which register is written with which function and value, the
exact frames on the wire, and how counts become amps and micrometres.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from importlib import import_module
from pathlib import Path
from typing import Any

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

from drivers.base import DeviceError, DeviceLost, DeviceTimeout
from drivers.emulators.modbus_aio import ModbusAIOEmulator
from drivers.modbus_aio import DRIVER, ModbusAIO, stale_transactions


class TinyWorld:
    """An amplifier that follows its input at once, and a sensor reading 25 um per A."""

    def __init__(self) -> None:
        self.commands: list[float] = []
        self.fixed: dict[str, float] = {}

    def command(self, value: float) -> None:
        self.commands.append(value)

    def read(self, channel: str) -> float:
        if channel in self.fixed:
            return self.fixed[channel]
        amps = self.commands[-1] if self.commands else 0.0
        return {"current": amps, "output": 25.0 * amps}[channel]

    def play(self, waveform: Any, rate_hz: float) -> dict[str, Any]:
        raise NotImplementedError


# One AO count is 10 V / 4095 at the amplifier input, times 0.1 A/V.
AO_LSB_A = 10.0 / 4095 * 0.1
Rig = tuple[ModbusAIOEmulator, ModbusAIO, TinyWorld]


@pytest.fixture
def make_rig() -> Iterator[Callable[..., Rig]]:
    """Start an emulator and open the driver on it with the given settings; all closed afterwards."""
    opened: list[Any] = []

    def make(**table: Any) -> Rig:
        world = TinyWorld()
        # 0.25 s: generous for a loaded machine; only the timeout tests wait for it to pass.
        base = {"url": "tcp://127.0.0.1:0", "timeout_s": 0.25} | table
        emulator = DRIVER.emulator(DRIVER.complete(base), world)
        opened.append(emulator)
        device = DRIVER.open(base | {"url": emulator.url})
        opened.append(device)
        return emulator, device, world

    yield make
    for thing in reversed(opened):
        thing.close()


def requests(emulator: ModbusAIOEmulator) -> list[bytes]:
    return [frame for direction, frame in emulator.frames if direction == "rx"]


def replies(emulator: ModbusAIOEmulator) -> list[bytes]:
    return [frame for direction, frame in emulator.frames if direction == "tx"]


# -- the actuator: AO holding register 40011 ----------------------------------------------------------
def test_write_sets_ao_register_40011_with_function_06(make_rig: Callable[..., Rig]) -> None:
    emulator, device, world = make_rig()
    device.write(0.5)  # 0.5 A / 0.1 A/V = 5 V -> 5/10 * 4095 = 2047.5 -> 2048 counts
    # MBAP: transaction 1, protocol 0, length 6, unit 1 | PDU: 06, address 0x000A, value 0x0800
    assert requests(emulator) == [bytes.fromhex("0001 0000 0006 01 06 000A 0800")]
    assert replies(emulator) == [bytes.fromhex("0001 0000 0006 01 06 000A 0800")]  # the echo
    assert world.commands == [pytest.approx(2048 / 4095 * 10 * 0.1)]
    assert emulator.last_ao == pytest.approx(0.5, abs=AO_LSB_A)
    assert device.last_a == pytest.approx(emulator.last_ao)


def test_write_beyond_the_ao_range_is_clamped_to_full_scale(make_rig: Callable[..., Rig]) -> None:
    emulator, device, _ = make_rig()
    device.write(5.0)  # 50 V wanted, the AO gives 10 V: 4095 counts = 1 A
    device.write(-1.0)  # below 0 V: 0 counts
    assert [frame[-2:] for frame in requests(emulator)] == [bytes.fromhex("0FFF"), bytes.fromhex("0000")]
    assert emulator.ao_writes == [pytest.approx(1.0), 0.0]
    assert device.clamped_writes == 2


# -- the sensor: AI registers 40001, 40002 ---------------------------------------------------------------
def test_read_gets_both_ai_registers_in_one_function_03_request(make_rig: Callable[..., Rig]) -> None:
    emulator, device, world = make_rig()
    world.fixed = {"current": 0.25, "output": -12.5}
    values = device.read()
    # 0.25 A * 10 V/A = 2.5 V -> (2.5 + 10) / 20 * 65535 = 40959 counts (0x9FFF);
    # -12.5 um / 10 um/V = -1.25 V -> 8.75 / 20 * 65535 = 28671.6 -> 28672 counts (0x7000)
    assert requests(emulator) == [bytes.fromhex("0001 0000 0006 01 03 0000 0002")]
    assert replies(emulator) == [bytes.fromhex("0001 0000 0007 01 03 04 9FFF 7000")]
    ai_lsb_v = 20.0 / 65535
    assert values["current"] == pytest.approx(0.25, abs=ai_lsb_v / 10)
    assert values["output"] == pytest.approx(-12.5, abs=ai_lsb_v * 10)


def test_a_module_with_another_map_reads_input_registers_with_function_04(make_rig: Callable[..., Rig]) -> None:
    emulator, device, world = make_rig(unit_id=7, ao_register=0, ai_current_register=5, ai_output_register=4,
                                       ai_function="input", ai_counts_min=0, ai_counts_max=4095,
                                       ai_volts_min=0.0, ai_volts_max=10.0)
    world.fixed = {"current": 0.5, "output": 40.0}  # 5 V -> 2048 (0x0800); 4 V -> 1638 (0x0666)
    values = device.read()
    device.write(0.0)
    assert requests(emulator) == [bytes.fromhex("0001 0000 0006 07 04 0004 0002"),
                                  bytes.fromhex("0002 0000 0006 07 06 0000 0000")]
    assert replies(emulator)[0] == bytes.fromhex("0001 0000 0007 07 04 04 0666 0800")
    assert values == {"current": pytest.approx(0.5, abs=1e-3), "output": pytest.approx(40.0, abs=0.01)}


def test_counts_outside_the_ai_range_read_as_nan(make_rig: Callable[..., Rig]) -> None:
    emulator, device, _ = make_rig(ai_counts_max=4095)
    emulator.out_of_range()  # the module answers 4096 counts on a 12-bit range
    values = device.read()
    assert replies(emulator)[-1][-4:] == bytes.fromhex("1000 1000")
    assert math.isnan(values["current"]) and math.isnan(values["output"])


def test_rtu_frames_carry_the_unit_and_a_crc(make_rig: Callable[..., Rig]) -> None:
    emulator, device, _ = make_rig(url="/dev/ttyUSB0", unit_id=3)  # the emulator serves RTU on a socket
    assert emulator.url.startswith("socket://")
    device.write(0.5)
    frame = requests(emulator)[0]
    assert frame[:-2] == bytes.fromhex("03 06 000A 0800")
    assert frame[-2:] == crc16_modbus(frame[:-2]).to_bytes(2, "little")


def crc16_modbus(data: bytes) -> int:
    """CRC-16/MODBUS (polynomial 0xA001 reflected, initial 0xFFFF), sent low byte first."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


# -- errors ------------------------------------------------------------------------------------------------
def test_a_lost_reply_is_retried_and_the_read_succeeds(make_rig: Callable[..., Rig]) -> None:
    emulator, device, world = make_rig(attempts=3)
    world.fixed = {"current": 0.0, "output": 0.0}
    emulator.drop_replies(2)
    assert device.read()["current"] == pytest.approx(0.0, abs=1e-3)
    assert len(requests(emulator)) == 3  # two unanswered, the third answered


def test_no_reply_after_the_retries_raises_device_timeout(make_rig: Callable[..., Rig]) -> None:
    emulator, device, _ = make_rig(attempts=3)
    emulator.drop_replies(3)
    with pytest.raises(DeviceTimeout, match=r"read AI registers 0\.\.1: no valid answer after 3 tries") as info:
        device.read()
    assert info.value.device == device.name
    assert len(requests(emulator)) == 3


def test_a_reply_that_is_not_modbus_is_retried_and_the_read_succeeds(make_rig: Callable[..., Rig]) -> None:
    emulator, device, world = make_rig(attempts=3)
    world.fixed = {"current": 0.25, "output": 0.0}
    emulator.garbage_replies(1)  # e.g. another service answering on the module's port
    assert device.read()["current"] == pytest.approx(0.25, abs=1e-3)
    assert replies(emulator)[0] == b"HTTP/1.1 400 Bad Request\r\n\r\n"
    assert len(requests(emulator)) == 2  # the garbled one and the one answered


@pytest.mark.parametrize("garbage", [
    b"HTTP/1.1 400 Bad Request\r\n\r\n",  # not even an MBAP header (protocol id 0x5450)
    bytes.fromhex("0001 0000 0006 01 03 04 00"),  # an MBAP header, then a reply cut short
    bytes.fromhex("0001 0000 0002 01 99"),  # an exception function without its code
], ids=["text", "truncated", "no-exception-code"])
def test_replies_that_are_never_modbus_raise_device_timeout_showing_the_bytes(
        make_rig: Callable[..., Rig], garbage: bytes) -> None:
    emulator, device, _ = make_rig(attempts=2, timeout_s=0.1)
    emulator.garbage_replies(2, garbage)
    with pytest.raises(DeviceTimeout, match=r"no valid answer after 2 tries \(.*a reply that is not Modbus") as info:
        device.write(0.1)
    assert garbage[:4].hex(" ") in str(info.value) and "\n" not in str(info.value)
    assert len(requests(emulator)) == 2
    device.write(0.2)  # the connection is usable again once the module answers properly
    assert emulator.last_ao == pytest.approx(0.2, abs=AO_LSB_A)


def test_late_replies_to_timed_out_requests_are_named_as_such(make_rig: Callable[..., Rig]) -> None:
    """A module slower than timeout_s answers each request after the driver gave up on it: what comes
    back is the answer to an earlier transaction, which the client skips. The error says so (late
    replies, their transaction ids, the timeout), not that the reply is not Modbus."""
    emulator, device, _ = make_rig(attempts=2, timeout_s=0.1)
    late = bytes.fromhex("7fff 0000 0005 01 03 02 7c f4")  # a read's answer, transaction 32767
    emulator.garbage_replies(2, late)
    with pytest.raises(DeviceTimeout, match=r"only late replies to earlier requests came back \(transaction ids "
                                            r"32767\), none to this one within 0.1 s") as info:
        device.read()
    assert "not Modbus" not in str(info.value) and "\n" not in str(info.value)
    assert device.read() is not None  # answered in time again: the read succeeds


def test_stale_transactions_reads_only_complete_well_formed_replies() -> None:
    # two answers to holding-register reads that arrived together (seen on a loaded CI machine)
    both = bytes.fromhex("0335 0000 0005 01 03 02 7cf4 0336 0000 0005 01 03 02 7cf5")
    assert stale_transactions(both) == [821, 822]
    assert stale_transactions(bytes.fromhex("0007 0000 0006 01 06 0000 0100")) == [7]  # a write's echo
    assert stale_transactions(bytes.fromhex("0008 0000 0003 01 83 02")) == [8]  # an exception response
    assert stale_transactions(both[:-1]) is None  # the second cut short
    assert stale_transactions(bytes.fromhex("0001 0000 0002 01 99")) is None  # an exception without its code
    assert stale_transactions(bytes.fromhex("0001 0000 0006 01 03 04 0000")) is None  # byte count against length
    assert stale_transactions(b"HTTP/1.1 400 Bad Request\r\n\r\n") is None
    assert stale_transactions(b"") is None


def test_an_exception_response_is_a_one_line_device_error(make_rig: Callable[..., Rig]) -> None:
    emulator, device, _ = make_rig()
    emulator.exception_next(4)
    with pytest.raises(DeviceError) as info:
        device.write(0.1)
    assert type(info.value) is DeviceError  # refused, not retried as a timeout
    assert replies(emulator) == [bytes.fromhex("0001 0000 0003 01 86 04")]  # function 0x80 | 06, code 4
    assert "function 06 (Write Single Register): code 4 SERVER DEVICE FAILURE" in str(info.value)
    assert "\n" not in str(info.value)
    assert len(requests(emulator)) == 1


def test_a_register_the_module_lacks_answers_illegal_data_address(make_rig: Callable[..., Rig]) -> None:
    emulator, device, _ = make_rig()
    # A map that does not fit the ADAM-6024: 40001..40008, but 40007 and 40008 are not in its table
    device.ai_regs = {"current": 0, "output": 7}
    with pytest.raises(DeviceError, match="function 03 .*code 2 ILLEGAL DATA ADDRESS"):
        device.read()
    assert requests(emulator) == [bytes.fromhex("0001 0000 0006 01 03 0000 0008")]
    assert replies(emulator) == [bytes.fromhex("0001 0000 0003 01 83 02")]


def test_server_gone_mid_use_raises_device_lost_naming_the_device(make_rig: Callable[..., Rig]) -> None:
    emulator, device, _ = make_rig()
    device.write(0.2)
    emulator.disconnect()
    with pytest.raises(DeviceLost) as info:
        device.read()
    assert emulator.url in str(info.value) and "unit 1" in str(info.value)
    with pytest.raises(DeviceLost):  # and it stays lost: the server refuses new connections
        device.write(0.0)


def test_opening_a_module_that_is_not_there_raises_device_lost() -> None:
    emulator = ModbusAIOEmulator(DRIVER.complete({"url": "tcp://127.0.0.1:0"}), TinyWorld())
    url = emulator.url
    emulator.close()
    with pytest.raises(DeviceLost, match="cannot connect"):
        DRIVER.open({"url": url, "timeout_s": 0.1})


# -- making safe ------------------------------------------------------------------------------------------
def test_stop_false_ramps_the_ao_to_rest_at_the_slew_rate(make_rig: Callable[..., Rig]) -> None:
    emulator, device, _ = make_rig(rest=0.1, slew_per_s=20.0, ramp_step_s=0.005)  # 0.1 A per step
    device.write(0.8)
    device.stop(False)
    ramp = emulator.ao_writes[1:]
    assert len(ramp) == 7  # 0.8 -> 0.1 A in 0.1 A steps
    assert all(b < a for a, b in zip([emulator.ao_writes[0], *ramp], ramp))
    assert all(a - b <= 0.1 + AO_LSB_A for a, b in zip([emulator.ao_writes[0], *ramp], ramp))
    assert emulator.last_ao == pytest.approx(0.1, abs=AO_LSB_A)


def test_stop_false_before_any_write_still_sets_rest(make_rig: Callable[..., Rig]) -> None:
    emulator, device, _ = make_rig(rest=0.3)
    device.stop(False)
    assert emulator.ao_writes == [pytest.approx(0.3, abs=AO_LSB_A)]


def test_stop_true_at_rest_writes_nothing_more(make_rig: Callable[..., Rig]) -> None:
    emulator, device, _ = make_rig()
    device.write(0.0)
    device.stop(True)
    assert len(emulator.ao_writes) == 1


# -- the driver table -------------------------------------------------------------------------------------
def test_the_driver_table_is_checked_and_completed() -> None:
    assert DRIVER.problems({}) == [
        ("missing key 'url' for driver 'modbus-aio' (tcp://host:port (Modbus TCP) or a serial port / pyserial URL "
         "such as /dev/ttyUSB0 or socket://host:port (RTU))")]
    assert DRIVER.problems({"url": "tcp://10.0.0.5:502", "unit_id": "1"}) == [
        "key 'unit_id' for driver 'modbus-aio': expected int, got '1'"]
    table = DRIVER.complete({"url": "tcp://10.0.0.5:502"})
    assert (table["ao_register"], table["ai_current_register"], table["ai_output_register"]) == (10, 0, 1)


def test_the_entry_point_names_this_driver() -> None:
    pyproject = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    target = pyproject["project"]["entry-points"]["hilbench.drivers"]["modbus-aio"]
    module, _, attr = target.partition(":")
    assert getattr(import_module(module), attr) is DRIVER
