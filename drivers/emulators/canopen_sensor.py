"""Emulator of a CANopen CiA 404 sensor: a canopen ``LocalNode`` on a python-can bus.

The node has an object dictionary built in code (1000h device type, 1001h error register, 1005h
COB-ID SYNC, 1008h name, 1017h producer heartbeat time, 1800h/1A00h TPDO1 communication and
mapping, 6130h/7130h/9130h AI PV in REAL32/INTEGER16/INTEGER32, 6150h AI status). canopen's
``LocalNode`` serves SDO and NMT and produces the heartbeat once 1017h is written; this module adds
what it lacks: TPDO1 on SYNC, packed from the node's own 1A00h mapping (so a wrong mapping shows),
and the CiA 301 rules on changing a mapping (only while the PDO is invalid and 1A00h:00 is 0).

Process values come from ``world.read(quantity)`` converted back through the driver table's
``scale``/``offset`` (PV = (value - offset) / scale). An integer PV that does not fit its type is
saturated and flagged in the status byte (not valid + positive/negative overload).

Fault injection for tests: :meth:`stop_heartbeat` (a lost node), :meth:`out_of_range` (status
0x03), :meth:`mute_tpdo` (no TPDO after SYNC), :meth:`emcy` (an emergency message), :meth:`reboot`.
"""

from __future__ import annotations

import math
import struct
import threading
from typing import Any

from drivers.base import World
from drivers.canopen_sensor import (
    AI_STATUS_INDEX,
    COB_INVALID,
    PV_TYPES,
    STATUS_NEGATIVE_OVERLOAD,
    STATUS_NOT_VALID,
    STATUS_POSITIVE_OVERLOAD,
    TPDO1_COMM,
    TPDO1_MAP,
)

ABORT_CANNOT_MAP = 0x06040041  # Object cannot be mapped to the PDO
ABORT_PDO_LENGTH = 0x06040042  # PDO length exceeded
ABORT_DEVICE_STATE = 0x08000022  # Data cannot be transferred ... because of the present device state
ABORT_VALUE_RANGE = 0x06090030  # Value range of parameter exceeded


def build_object_dictionary(node_id: int) -> Any:
    """The emulated sensor's object dictionary (one AI channel)."""
    from canopen import ObjectDictionary
    from canopen.objectdictionary import ODRecord, ODVariable
    from canopen.objectdictionary import datatypes as dt

    od = ObjectDictionary()

    def var(name: str, index: int, subindex: int, data_type: int, access: str, default: Any = None,
            mappable: bool = False) -> ODVariable:
        v = ODVariable(name, index, subindex)
        v.data_type, v.access_type, v.default, v.pdo_mappable = data_type, access, default, mappable
        return v

    def record(name: str, index: int, members: list[ODVariable]) -> ODRecord:
        r = ODRecord(name, index)
        for m in members:
            r.add_member(m)
        return r

    od.add_object(var("Device type", 0x1000, 0, dt.UNSIGNED32, "ro", 404))  # low word: profile CiA 404
    od.add_object(var("Error register", 0x1001, 0, dt.UNSIGNED8, "ro", 0, mappable=True))
    od.add_object(var("COB-ID SYNC", 0x1005, 0, dt.UNSIGNED32, "rw", 0x80))
    od.add_object(var("Manufacturer device name", 0x1008, 0, dt.VISIBLE_STRING, "const", "hilbench CiA 404 emu"))
    od.add_object(var("Producer heartbeat time", 0x1017, 0, dt.UNSIGNED16, "rw", 0))
    od.add_object(record("TPDO1 communication parameter", TPDO1_COMM, [
        var("Highest sub-index supported", TPDO1_COMM, 0, dt.UNSIGNED8, "const", 5),
        var("COB-ID used by TPDO", TPDO1_COMM, 1, dt.UNSIGNED32, "rw", 0x180 + node_id),
        var("Transmission type", TPDO1_COMM, 2, dt.UNSIGNED8, "rw", 254),
        var("Inhibit time", TPDO1_COMM, 3, dt.UNSIGNED16, "rw", 0),
        var("Event timer", TPDO1_COMM, 5, dt.UNSIGNED16, "rw", 0),
    ]))
    od.add_object(record("TPDO1 mapping parameter", TPDO1_MAP, [
        var("Number of mapped objects", TPDO1_MAP, 0, dt.UNSIGNED8, "rw", 1),
        *[var(f"Mapped object {k}", TPDO1_MAP, k, dt.UNSIGNED32, "rw", 0x61300120 if k == 1 else 0)
          for k in range(1, 9)],
    ]))
    for index, data_type in ((0x6130, dt.REAL32), (0x7130, dt.INTEGER16), (0x9130, dt.INTEGER32)):
        od.add_object(record("AI input PV", index, [
            var("Number of entries", index, 0, dt.UNSIGNED8, "const", 1),
            var("AI input PV 1", index, 1, data_type, "ro", 0, mappable=True),
        ]))
    od.add_object(record("AI status", AI_STATUS_INDEX, [
        var("Number of entries", AI_STATUS_INDEX, 0, dt.UNSIGNED8, "const", 1),
        var("AI status 1", AI_STATUS_INDEX, 1, dt.UNSIGNED8, "ro", 0, mappable=True),
    ]))
    return od


class CanopenSensorEmulator:
    """A running emulated sensor node; ``url`` names the bus the driver table must use."""

    def __init__(self, settings: dict[str, Any], world: World):
        import canopen

        self.world = world
        self.node_id = int(settings["node_id"])
        self.quantity = str(settings["quantity"])
        self.scale = float(settings["scale"])
        self.offset = float(settings["offset"])
        self.interface = str(settings["interface"])
        self.channel = settings["channel"]
        self.url = f"{self.interface}:{self.channel}"
        self.errors: list[BaseException] = []  # anything that went wrong in the emulator's callbacks
        self.syncs_seen = 0
        self._lock = threading.Lock()
        self._mute_tpdo = False
        self._out_of_range = False
        self._sample: tuple[float, int] | None = None  # (PV, status) frozen at the SYNC being served

        self.network = canopen.Network()
        # The receive thread polls the bus this often; close() waits up to one cycle for it.
        self.network.NOTIFIER_CYCLE = 0.05
        self.network.connect(interface=self.interface, channel=self.channel, bitrate=int(settings["bitrate"]))
        try:
            self.node = canopen.LocalNode(self.node_id, build_object_dictionary(self.node_id))
            self.node.add_read_callback(self._on_read)
            self.node.add_write_callback(self._on_write)
            self.network.add_node(self.node)
            self.network.subscribe(0x80, self._on_sync)
            self.boot()
        except BaseException:
            self.close()
            raise

    # -- NMT ---------------------------------------------------------------------------------------------
    def boot(self) -> None:
        """Power-on: boot-up message (700h + id, 00h), then PRE-OPERATIONAL with the default 1017h."""
        self.node.nmt.send_command(0x81)  # -> INITIALISING: sends the boot-up message
        self.node.nmt.send_command(0x80)  # -> PRE-OPERATIONAL: starts the heartbeat if 1017h != 0

    # -- object access -------------------------------------------------------------------------------------
    def _pv_and_status(self) -> tuple[float, int]:
        """The PV the node would measure now (before type encoding) and its status bits."""
        value = float(self.world.read(self.quantity))
        pv = (value - self.offset) / self.scale
        if self._out_of_range:
            return pv, STATUS_NOT_VALID | STATUS_POSITIVE_OVERLOAD
        return pv, STATUS_NOT_VALID if math.isnan(pv) else 0

    def _encode_pv(self, index: int, pv: float, status: int) -> tuple[float | int, int]:
        """The PV as the object's type holds it; an integer overflow saturates and sets overload."""
        fmt, bits = PV_TYPES[index]
        if fmt == "<f":
            return pv, status
        if math.isnan(pv):
            return 0, status
        top, bottom = 2 ** (bits - 1) - 1, -(2 ** (bits - 1))
        raw = round(pv)
        if raw > top:
            return top, status | STATUS_NOT_VALID | STATUS_POSITIVE_OVERLOAD
        if raw < bottom:
            return bottom, status | STATUS_NOT_VALID | STATUS_NEGATIVE_OVERLOAD
        return raw, status

    def _on_read(self, index: int, subindex: int, od: Any) -> Any:
        if index not in PV_TYPES and index != AI_STATUS_INDEX or subindex != 1:
            return None
        with self._lock:
            sample = self._sample
        pv, status = sample if sample is not None else self._pv_and_status()
        if index == AI_STATUS_INDEX:
            for pv_index in self._mapped_pv_indices():  # an integer PV that saturates adds overload bits
                status |= self._encode_pv(pv_index, pv, status)[1]
            return status
        return self._encode_pv(index, pv, status)[0]

    def _mapped_pv_indices(self) -> list[int]:
        return [entry >> 16 for entry in self._mapping() if entry >> 16 in PV_TYPES]

    def _u32(self, index: int, subindex: int) -> int:
        return struct.unpack("<I", self.node.get_data(index, subindex))[0]

    def _mapping(self) -> list[int]:
        count = self.node.get_data(TPDO1_MAP, 0)[0]
        return [self._u32(TPDO1_MAP, k) for k in range(1, count + 1)]

    def _on_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        """CiA 301 rules for TPDO1: refuse what a real node refuses, with its abort code."""
        from canopen import SdoAbortedError

        if index == TPDO1_MAP:
            pdo_valid = not self._u32(TPDO1_COMM, 1) & COB_INVALID
            if pdo_valid:
                raise SdoAbortedError(ABORT_DEVICE_STATE)
            if subindex == 0:
                count = data[0]
                if count > 8:
                    raise SdoAbortedError(ABORT_VALUE_RANGE)
                bits = sum(self._u32(TPDO1_MAP, k) & 0xFF for k in range(1, count + 1))
                if bits > 64:
                    raise SdoAbortedError(ABORT_PDO_LENGTH)
                return
            if self.node.get_data(TPDO1_MAP, 0)[0] != 0:
                raise SdoAbortedError(ABORT_DEVICE_STATE)
            entry = struct.unpack("<I", data)[0]
            self._check_mappable(entry)
        elif index == TPDO1_COMM and subindex == 2 and 240 < data[0] < 252:  # reserved types
            raise SdoAbortedError(ABORT_VALUE_RANGE)

    def _check_mappable(self, entry: int) -> None:
        from canopen import SdoAbortedError

        index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        if entry == 0:
            return
        try:
            target = self.node._find_object(index, subindex)
        except SdoAbortedError:
            raise SdoAbortedError(ABORT_CANNOT_MAP) from None
        if not target.pdo_mappable or len(target) != bits:
            raise SdoAbortedError(ABORT_CANNOT_MAP)

    # -- SYNC -> TPDO1 -----------------------------------------------------------------------------------
    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        try:
            self.syncs_seen += 1
            if self._mute_tpdo or self.node.nmt.state != "OPERATIONAL":
                return
            cob_id = self._u32(TPDO1_COMM, 1)
            transmission_type = self.node.get_data(TPDO1_COMM, 2)[0]
            if cob_id & COB_INVALID or transmission_type > 240:
                return  # PDO not valid, or event-driven / RTR types: SYNC does not trigger them
            if transmission_type and self.syncs_seen % transmission_type:
                return
            self.network.send_message(cob_id & 0x7FF, self.tpdo_payload())
        except Exception as exc:  # noqa: BLE001 - canopen would only log it; keep it for the tests
            self.errors.append(exc)

    def tpdo_payload(self) -> bytes:
        """TPDO1 data: the mapped objects, in mapping order, as the node encodes them."""
        with self._lock:
            self._sample = self._pv_and_status()
        try:
            return b"".join(self.node.get_data(entry >> 16, (entry >> 8) & 0xFF) for entry in self._mapping())
        finally:
            with self._lock:
                self._sample = None

    # -- fault injection -----------------------------------------------------------------------------------
    def stop_heartbeat(self) -> None:
        """The node goes silent on 700h + id (a cut cable or a dead node) but keeps its state."""
        self.node.nmt.stop_heartbeat()

    def mute_tpdo(self, on: bool = True) -> None:
        """No TPDO after SYNC (the rest of the node keeps working)."""
        self._mute_tpdo = bool(on)

    def out_of_range(self, on: bool = True) -> None:
        """Flag the AI as not valid + positive overload (status 03h)."""
        self._out_of_range = bool(on)

    def emcy(self, code: int, register: int = 0x01, extra: bytes = b"") -> None:
        """Send an emergency message (080h + id): error code, error register, manufacturer bytes."""
        self.node.emcy.send(code, register, extra)

    def reboot(self) -> None:
        """A node reset: boot-up message, PRE-OPERATIONAL, configuration back to the defaults."""
        self.node.nmt.stop_heartbeat()
        self.node.data_store.clear()
        self.boot()

    @property
    def nmt_state(self) -> str:
        return str(self.node.nmt.state)

    def close(self) -> None:
        """Stop the heartbeat and leave the bus (idempotent)."""
        node = getattr(self, "node", None)
        if node is not None:
            node.nmt.stop_heartbeat()
        if self.network.bus is not None:
            self.network.disconnect()


def start_emulator(settings: dict[str, Any], world: World) -> CanopenSensorEmulator:
    """A running emulated CANopen node on a python-can virtual bus, backed by ``world``."""
    from drivers.canopen_sensor import DRIVER

    return CanopenSensorEmulator(DRIVER.complete(settings), world)
