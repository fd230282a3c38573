"""Protocol tests of the canopen-sensor driver against its emulator on a python-can virtual bus.

A third bus instance on the same channel watches the wire, so the tests read like the manual: the
NMT commands, the SDO downloads that configure the node, SYNC and the TPDO bytes it triggers, and
the heartbeat frames.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from importlib import import_module
from pathlib import Path
from typing import Any

import can
import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

from drivers.base import DeviceError, DeviceLost, DeviceTimeout
from drivers.canopen_sensor import DRIVER, CanopenSensor
from drivers.emulators.canopen_sensor import CanopenSensorEmulator

NODE = 5


class TinyWorld:
    """A sensor that reads whatever the test sets."""

    def __init__(self) -> None:
        self.values = {"output": 0.0, "temperature": 20.0}

    def command(self, value: float) -> None:
        raise AssertionError("a sensor is never commanded")

    def read(self, channel: str) -> float:
        return self.values[channel]

    def play(self, waveform: Any, rate_hz: float) -> dict[str, Any]:
        raise NotImplementedError


class Wire:
    """A bus monitor: every frame anyone sends on the channel, as (COB-ID, data bytes)."""

    def __init__(self, channel: str):
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.log: list[tuple[int, bytes]] = []

    def frames(self, *cob_ids: int) -> list[tuple[int, bytes]]:
        while (msg := self.bus.recv(timeout=0)) is not None:
            self.log.append((msg.arbitration_id, bytes(msg.data)))
        return [f for f in self.log if not cob_ids or f[0] in cob_ids]

    def send(self, cob_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def close(self) -> None:
        self.bus.shutdown()


class Bench:
    """One channel with a wire monitor, an emulated node and (when opened) the driver."""

    def __init__(self, channel: str, table: dict[str, Any]):
        # Generous timeouts: the tests share two busy cores; none of them waits for a timeout to pass
        # except the ones about timeouts.
        self.table = {"channel": channel, "node_id": NODE, "timeout_s": 0.3, "heartbeat_ms": 50,
                      "heartbeat_consumer_ms": 400} | table
        self.world = TinyWorld()
        self.wire = Wire(channel)  # first, so it sees the boot-up message
        self.emulator = CanopenSensorEmulator(DRIVER.complete(self.table), self.world)
        self.device: CanopenSensor | None = None

    def open(self, **override: Any) -> CanopenSensor:
        self.device = DRIVER.open(self.table | override)
        return self.device

    def close(self) -> None:
        if self.device is not None:
            self.device.close()
        self.emulator.close()
        self.wire.close()


@pytest.fixture
def bench(request: pytest.FixtureRequest) -> Iterator[Callable[..., Bench]]:
    made: list[Bench] = []

    def make(**table: Any) -> Bench:
        b = Bench(f"canopen-{request.node.name}-{len(made)}", table)
        made.append(b)
        return b

    yield make
    for b in made:
        b.close()


def sdo(command: int, index: int, subindex: int, value: bytes = b"") -> bytes:
    """An SDO frame: command byte, index (little endian), subindex, 4 data bytes."""
    return bytes([command]) + index.to_bytes(2, "little") + bytes([subindex]) + value.ljust(4, b"\0")


def wait_for(predicate: Callable[[], bool], timeout_s: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


def first_error(call: Callable[[], object], timeout_s: float = 2.0) -> Exception | None:
    """Call until it raises (what the background side noticed arrives asynchronously); bounded."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            call()
        except Exception as exc:  # noqa: BLE001 - returned for the test to inspect
            return exc
        time.sleep(0.01)
    return None


# -- configuration -------------------------------------------------------------------------------------
def test_open_configures_heartbeat_and_tpdo1_by_sdo_then_starts_the_node(bench: Callable[..., Bench]) -> None:
    b = bench()
    b.open()
    ok = 0x60  # download response
    expected = [
        (0x000, bytes([0x80, NODE])),  # NMT: enter pre-operational
        (0x605, sdo(0x2B, 0x1017, 0, (50).to_bytes(2, "little"))), (0x585, sdo(ok, 0x1017, 0)),
        (0x605, sdo(0x23, 0x1800, 1, bytes.fromhex("85010080"))), (0x585, sdo(ok, 0x1800, 1)),  # TPDO1 invalid
        (0x605, sdo(0x2F, 0x1A00, 0, b"\x00")), (0x585, sdo(ok, 0x1A00, 0)),  # no mapped objects
        (0x605, sdo(0x23, 0x1A00, 1, bytes.fromhex("20013061"))), (0x585, sdo(ok, 0x1A00, 1)),  # 6130h:01, 32 bit
        (0x605, sdo(0x23, 0x1A00, 2, bytes.fromhex("08015061"))), (0x585, sdo(ok, 0x1A00, 2)),  # 6150h:01, 8 bit
        (0x605, sdo(0x2F, 0x1A00, 0, b"\x02")), (0x585, sdo(ok, 0x1A00, 0)),  # two mapped objects
        (0x605, sdo(0x2F, 0x1800, 2, b"\x01")), (0x585, sdo(ok, 0x1800, 2)),  # synchronous, every SYNC
        (0x605, sdo(0x23, 0x1800, 1, bytes.fromhex("85010000"))), (0x585, sdo(ok, 0x1800, 1)),  # TPDO1 valid
        (0x000, bytes([0x01, NODE])),  # NMT: start remote node
    ]
    assert b.wire.frames(0x000, 0x605, 0x585) == expected
    assert b.emulator.nmt_state == "OPERATIONAL"


def test_heartbeat_frames_boot_up_then_operational(bench: Callable[..., Bench]) -> None:
    b = bench()
    b.open()
    heartbeats = b.wire.frames(0x700 + NODE)
    assert heartbeats[0] == (0x705, b"\x00")  # boot-up message
    assert heartbeats[-1] == (0x705, b"\x05")  # open() waited for OPERATIONAL
    assert set(heartbeats[1:]) <= {(0x705, b"\x7f"), (0x705, b"\x05")}


def test_an_object_that_cannot_be_mapped_is_refused_with_the_sdo_abort_code(bench: Callable[..., Bench]) -> None:
    b = bench(status_index=0x1017, status_subindex=0)  # producer heartbeat time is not PDO-mappable
    with pytest.raises(DeviceError) as info:
        b.open()
    assert str(info.value) == (f"canopen-sensor node {NODE} on virtual:{b.table['channel']}: SDO write 1A00h:02 = "
                               "10170008h aborted: Code 0x06040041, Object cannot be mapped to the PDO")
    assert b.wire.frames(0x585)[-1] == (0x585, sdo(0x80, 0x1A00, 2, bytes.fromhex("41000406")))  # abort


def test_a_mapping_change_while_the_pdo_is_valid_is_refused(bench: Callable[..., Bench]) -> None:
    b = bench()
    device = b.open()
    with pytest.raises(DeviceError, match="0x08000022"):
        device.sdo_write(0x1A00, 1, bytes.fromhex("20013091"))


def test_a_node_that_does_not_answer_sdo_times_out_after_the_retries(bench: Callable[..., Bench]) -> None:
    b = bench()
    with pytest.raises(DeviceTimeout, match=r"node 6 .*SDO write 1017h:00 = 0032h: no valid answer after 3 tries"):
        b.open(node_id=6)
    assert len([f for f in b.wire.frames(0x606) if f[1][0] == 0x2B]) == 3  # the request, sent three times


# -- SYNC -> TPDO1 -------------------------------------------------------------------------------------
def test_sync_triggers_one_tpdo_with_the_real32_pv_and_status(bench: Callable[..., Bench]) -> None:
    b = bench()
    device = b.open()
    b.world.values["output"] = 12.5
    before = len(b.wire.frames())
    assert device.read() == {"output": 12.5}
    after = [f for f in b.wire.frames()[before:] if f[0] != 0x705]
    assert after == [(0x080, b""), (0x185, bytes.fromhex("00004841") + b"\x00")]  # 12.5 as REAL32, status 0


def test_an_integer16_pv_is_scaled_to_the_configured_unit(bench: Callable[..., Bench]) -> None:
    b = bench(quantity="temperature", pv_index=0x7130, scale=0.01, offset=0.0)  # 0.01 degC per count
    device = b.open()
    b.world.values["temperature"] = 23.45
    assert device.read() == {"temperature": pytest.approx(23.45)}
    assert b.wire.frames(0x185)[-1] == (0x185, (2345).to_bytes(2, "little") + b"\x00")
    assert (0x605, sdo(0x23, 0x1A00, 1, bytes.fromhex("10013071"))) in b.wire.frames(0x605)  # 7130h:01, 16 bit


def test_an_integer_pv_beyond_its_type_is_flagged_as_overload_and_read_as_nan(bench: Callable[..., Bench]) -> None:
    b = bench(pv_index=0x7130, scale=0.01)
    device = b.open()
    b.world.values["output"] = -400.0  # -40000 counts do not fit INTEGER16
    assert math.isnan(device.read()["output"])
    assert b.wire.frames(0x185)[-1] == (0x185, bytes.fromhex("0080") + b"\x05")  # -32768, not valid + negative


def test_the_out_of_range_status_reads_as_nan(bench: Callable[..., Bench]) -> None:
    b = bench()
    device = b.open()
    b.emulator.out_of_range()
    assert math.isnan(device.read()["output"])
    assert b.wire.frames(0x185)[-1][1][-1] == 0x03  # not valid + positive overload
    b.emulator.out_of_range(False)
    assert device.read() == {"output": 0.0}


def test_no_tpdo_after_sync_is_retried_then_device_timeout(bench: Callable[..., Bench]) -> None:
    b = bench()
    device = b.open()
    b.emulator.mute_tpdo()
    syncs_before = len(b.wire.frames(0x080))
    with pytest.raises(DeviceTimeout, match=r"no valid answer after 3 tries \(no TPDO1 \(COB-ID 185h\)"):
        device.read()
    assert len(b.wire.frames(0x080)) - syncs_before == 3
    b.emulator.mute_tpdo(False)
    assert device.read() == {"output": 0.0}


# -- supervision ---------------------------------------------------------------------------------------
def test_heartbeat_lost_mid_use_raises_device_lost_naming_the_node(bench: Callable[..., Bench]) -> None:
    b = bench()
    device = b.open()
    assert device.read() == {"output": 0.0}
    b.emulator.stop_heartbeat()  # the node still answers SYNC: only the heartbeat tells it is gone
    error = first_error(device.read)
    assert isinstance(error, DeviceLost)
    assert f"node {NODE} on virtual:" in str(error) and "no heartbeat for" in str(error)
    with pytest.raises(DeviceLost):  # and it stays lost
        device.read()


def test_a_reboot_of_the_node_is_a_lost_device(bench: Callable[..., Bench]) -> None:
    b = bench()
    device = b.open()
    b.emulator.reboot()
    assert wait_for(lambda: (0x705, b"\x00") in b.wire.frames(0x705)[1:])
    with pytest.raises(DeviceLost, match="rebooted"):
        device.read()


def test_an_error_in_the_receive_thread_is_raised_on_the_next_call(bench: Callable[..., Bench]) -> None:
    b = bench()
    device = b.open()
    b.wire.send(0x705, b"")  # a malformed heartbeat: the callback fails in canopen's receive thread
    error = first_error(device.read)
    assert type(error) is DeviceError and "empty heartbeat frame" in str(error)
    assert device.read() == {"output": 0.0}  # reported once, then work goes on


def test_an_emcy_is_raised_once_as_a_device_error(bench: Callable[..., Bench]) -> None:
    b = bench()
    device = b.open()
    b.emulator.emcy(0x4210, register=0x09)  # temperature too high, error register: generic + temperature
    assert wait_for(lambda: bool(b.wire.frames(0x085)))
    assert b.wire.frames(0x085)[-1] == (0x085, bytes.fromhex("1042 09 0000000000"))
    error = first_error(device.read)
    assert type(error) is DeviceError and "EMCY error code 0x4210, error register 0x09" in str(error)
    assert device.read() == {"output": 0.0}


# -- the driver table -------------------------------------------------------------------------------------
def test_the_driver_table_is_checked() -> None:
    assert DRIVER.problems({}) == ["missing key 'node_id' for driver 'canopen-sensor' (CANopen node id, 1..127)"]
    with pytest.raises(DeviceError, match="heartbeat_consumer_ms"):
        DRIVER.open({"node_id": 3, "channel": "canopen-table", "heartbeat_ms": 200, "heartbeat_consumer_ms": 100})


def test_the_entry_point_names_this_driver() -> None:
    pyproject = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    target = pyproject["project"]["entry-points"]["hilbench.drivers"]["canopen-sensor"]
    module, _, attr = target.partition(":")
    assert getattr(import_module(module), attr) is DRIVER
