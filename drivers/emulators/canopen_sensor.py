"""Emulator of a CANopen CiA 404 measuring device: one analogue input on a CiA 301 slave.

The communication side (NMT, SDO, heartbeat, SYNC -> TPDO1, EMCY) is :mod:`.canopen_node`; this
module adds the CiA 404 object dictionary and the measurement behind it:

* 1000h device type 0002_0194h: profile 404 (0194h) in the low word, "analogue input block"
  (0002h) in the additional information (CiA 404 as quoted by Axiomatic's AX030301/AX030541
  manuals, section 3.2.1 "Object 1000h");
* 6130h / 7130h / 9130h AI input PV, one channel (sub-index 1), REAL32 / INTEGER16 / INTEGER32,
  ro, mappable (7130h INTEGER16: Axiomatic AX030301 3.3.10-13; 6130h REAL32 and 9130h INTEGER32
  follow the profile's 6xxxh/7xxxh/9xxxh variants of one object, not verified in a manual);
* 6150h AI status, UNSIGNED8, ro, mappable: bit 0 not valid, bit 1 positive overload, bit 2
  negative overload, never 1 and 2 together (esd CAN-CBX-Pt100 manual 8.10.9 "AI Status (6150h)");
* 61A0h AI filter type, UNSIGNED8, rw: 0 none, 1 moving average, 2 repeating average; 61A1h AI
  filter constant, UNSIGNED8, rw, default 1 (Axiomatic AX030301 3.3.17-18). Moving average:
  ``y = y + (x - y) / constant``; repeating average: the mean of ``constant`` samples, published
  every ``constant``-th sample. Both advance once per measurement: each TPDO after SYNC and each SDO
  upload of a PV (the vendor samples every 10 ms on its own clock, which this emulator has not). A
  constant of 0 is refused (0609 0030): the manual gives the range UNSIGNED8, but 0 divides by zero.

Application objects (61A0h, 61A1h) go back to their defaults on NMT reset node, not on reset
communication (CiA's "Network management" page: reset application covers 2000h-9FFFh).

Process values come from ``world.read(quantity)`` converted back through the driver table's
``scale``/``offset`` (PV = (value - offset) / scale). An integer PV that does not fit its type is
saturated and flagged in the status byte (not valid + positive/negative overload).

Transport: any python-can interface; ``udp_multicast`` (with ``port``) reaches other processes on
this machine, which ``hilbench emulate`` uses so a config can be swept from another shell.

Fault injection for tests: :meth:`stop_heartbeat` (a lost node), :meth:`out_of_range` (status
03h), :meth:`mute_tpdo` (no TPDO after SYNC), :meth:`emcy` (an emergency message), :meth:`reboot`
(a power cycle: boot-up, PRE-OPERATIONAL, defaults).
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Iterator
from typing import Any

import can

from drivers.base import World
from drivers.canopen_sensor import (
    AI_STATUS_INDEX,
    PV_TYPES,
    STATUS_NEGATIVE_OVERLOAD,
    STATUS_NOT_VALID,
    STATUS_POSITIVE_OVERLOAD,
    TPDO1_MAP,
    bus_options,
)
from drivers.emulators.canopen_node import (
    CanopenSlave,
    Entry,
    communication_objects,
    record,
)

DEVICE_TYPE = 0x0002_0194  # additional information 0002h (analogue input block), profile 404
FILTER_TYPE_INDEX, FILTER_CONSTANT_INDEX = 0x61A0, 0x61A1
FILTER_NONE, FILTER_MOVING, FILTER_REPEATING = 0, 1, 2
PV_FORMATS = {0x6130: "f", 0x7130: "h", 0x9130: "i"}
DEVICE_NAME = "hilbench CiA 404 AI emulator"  # 28 characters: read by segmented SDO upload
#: vendor-ID 0: hilbench has no vendor-ID assigned by CiA; product code 404, revision 1.0, serial 1
IDENTITY = (0x00000000, 404, 0x00010000, 1)


def build_object_dictionary(node_id: int) -> dict[int, dict[int, Entry]]:
    """The emulated sensor's object dictionary (one AI channel), CiA 301 + CiA 404."""
    objects = communication_objects(node_id, device_type=DEVICE_TYPE, name=DEVICE_NAME, identity=IDENTITY,
                                    software_version="hilbench emulator 1")
    objects[TPDO1_MAP] = {0: Entry("TPDO1: number of mapped objects", "B", "rw", 1),
                          **{k: Entry(f"TPDO1 mapped object {k}", "I", "rw", 0x61300120 if k == 1 else 0)
                             for k in range(1, 9)}}
    for index, fmt in PV_FORMATS.items():
        objects[index] = record("AI input PV", {1: Entry("AI input PV 1", fmt, "ro", 0, mappable=True)})
    objects[AI_STATUS_INDEX] = record("AI status", {1: Entry("AI status 1", "B", "ro", 0, mappable=True)})
    objects[FILTER_TYPE_INDEX] = record("AI filter type", {
        1: Entry("AI filter type 1", "B", "rw", FILTER_NONE, valid=lambda v: v <= FILTER_REPEATING)})
    objects[FILTER_CONSTANT_INDEX] = record("AI filter constant", {
        1: Entry("AI filter constant 1", "B", "rw", 1, valid=lambda v: v >= 1)})
    return objects


class CanopenSensorEmulator:
    """A running emulated sensor node; ``url`` names the bus the driver table must use."""

    def __init__(self, settings: dict[str, Any], world: World):
        self.world = world
        self.node_id = int(settings["node_id"])
        self.quantity = str(settings["quantity"])
        self.scale = float(settings["scale"])
        self.offset = float(settings["offset"])
        self.interface = str(settings["interface"])
        self.channel = settings["channel"]
        self.port = int(settings.get("port") or 0)
        self.url = f"{self.interface}:{self.channel}" + (f" port {self.port}" if self.port else "")
        self._lock = threading.Lock()
        self._out_of_range = False
        self._sample: tuple[float, int] | None = None  # (PV, status) of the TPDO being packed
        self._last: tuple[float, int] | None = None  # the last measurement
        self._filtered: float | None = None  # moving average / published repeating average
        self._window: list[float] = []  # repeating average: samples since the last publication

        self.bus = can.Bus(interface=self.interface, channel=self.channel, bitrate=int(settings["bitrate"]),
                           **bus_options(self.interface, self.port))
        try:
            self.node = CanopenSlave(self.bus, self.node_id, build_object_dictionary(self.node_id),
                                     live=self._live, sampling=self._sampling)
        except BaseException:
            self.bus.shutdown()
            raise

    # -- measurement -------------------------------------------------------------------------------------
    def _measure(self) -> tuple[float, int]:
        """Take one sample: the PV after the 61A0h filter, and its status bits (before type encoding)."""
        value = float(self.world.read(self.quantity))
        pv = (value - self.offset) / self.scale
        status = STATUS_NOT_VALID | STATUS_POSITIVE_OVERLOAD if self._out_of_range else 0
        if math.isnan(pv):
            self._filtered, self._window = None, []
            sample = (pv, status | STATUS_NOT_VALID)
        else:
            sample = (self._filter(pv), status)
        self._last = sample
        return sample

    def _filter(self, pv: float) -> float:
        kind, constant = self.node.get(FILTER_TYPE_INDEX, 1), self.node.get(FILTER_CONSTANT_INDEX, 1)
        if kind == FILTER_MOVING:
            self._filtered = pv if self._filtered is None else self._filtered + (pv - self._filtered) / constant
            return self._filtered
        if kind == FILTER_REPEATING:
            self._window.append(pv)
            if len(self._window) >= constant or self._filtered is None:
                self._filtered = sum(self._window) / len(self._window)
                self._window = []
            return self._filtered
        self._filtered, self._window = None, []
        return pv

    @contextlib.contextmanager
    def _sampling(self) -> Iterator[None]:
        """One measurement for every object of one TPDO."""
        with self._lock:
            self._sample = self._measure()
        try:
            yield
        finally:
            with self._lock:
                self._sample = None

    def _live(self, index: int, subindex: int) -> Any:
        if index not in PV_TYPES and index != AI_STATUS_INDEX or subindex != 1:
            return None
        with self._lock:
            sample = self._sample
            if sample is None:  # an SDO upload: a PV takes a sample, the status reports the last one
                sample = self._measure() if index in PV_TYPES or self._last is None else self._last
        pv, status = sample
        if index == AI_STATUS_INDEX:
            for pv_index in self._mapped_pv_indices():  # an integer PV that saturates adds overload bits
                status |= self._encode_pv(pv_index, pv, status)[1]
            return status
        return self._encode_pv(index, pv, status)[0]

    @staticmethod
    def _encode_pv(index: int, pv: float, status: int) -> tuple[float | int, int]:
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

    def _mapped_pv_indices(self) -> list[int]:
        return [index for index, _, _ in self.node.mapping() if index in PV_TYPES]

    def tpdo_payload(self) -> bytes:
        """TPDO1 data as the node would send it after a SYNC now."""
        return self.node.tpdo_payload()

    # -- fault injection -----------------------------------------------------------------------------------
    def stop_heartbeat(self) -> None:
        """The node goes silent on 700h + id (a cut cable or a dead node) but keeps its state."""
        self.node.stop_heartbeat()

    def mute_tpdo(self, on: bool = True) -> None:
        """No TPDO after SYNC (the rest of the node keeps working)."""
        self.node.mute_tpdo = bool(on)

    def out_of_range(self, on: bool = True) -> None:
        """Flag the AI as not valid + positive overload (status 03h)."""
        self._out_of_range = bool(on)

    def emcy(self, code: int, register: int = 0x01, extra: bytes = b"") -> None:
        """Send an emergency message (080h + id): error code, error register (also in 1001h), 5 bytes."""
        self.node.emcy(code, register, extra)

    def reboot(self) -> None:
        """A power cycle: boot-up message, PRE-OPERATIONAL, every object back to its default."""
        self.node.boot(application=True)

    @property
    def nmt_state(self) -> str:
        return self.node.state

    @property
    def errors(self) -> list[BaseException]:
        return self.node.errors

    @property
    def syncs_seen(self) -> int:
        return self.node.syncs_seen

    def close(self) -> None:
        """Stop the node and leave the bus (idempotent)."""
        node = getattr(self, "node", None)
        if node is not None:
            node.close()
        self.bus.shutdown()


def start_emulator(settings: dict[str, Any], world: World) -> CanopenSensorEmulator:
    """A running emulated CANopen node on the configured python-can bus, backed by ``world``."""
    from drivers.canopen_sensor import DRIVER

    return CanopenSensorEmulator(DRIVER.complete(settings), world)
