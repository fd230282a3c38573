"""A CiA 301 CANopen slave on a python-can bus: NMT, SDO server, heartbeat, SYNC -> TPDO1, EMCY.

Written on raw python-can frames (not canopen's ``LocalNode``, which answers SDO in every NMT state,
checks write access only at the end of a segmented download and cannot reset communication), so an
emulated device behaves as the standard says. What it does, with the source of each fact (CiA 301's
own text was not at hand, so no section numbers: the facts come from CiA's public pages,
CANopenNode's ``301/`` sources and vendor manuals quoting the standard):

* NMT state machine (CANopenNode ``301/CO_NMT_Heartbeat.h``, CiA's "Network management" page):
  power-on and both resets send the boot-up message (700h + id, one byte 00h) and enter
  PRE-OPERATIONAL. Commands on COB-ID 000h, two data bytes (command specifier, node id; id 0 = every
  node): 01h start (-> OPERATIONAL), 02h stop (-> STOPPED), 80h enter PRE-OPERATIONAL, 81h reset
  node (objects 2000h-9FFFh and then 1000h-1FFFh back to their defaults), 82h reset communication
  (1000h-1FFFh only). Which services each state serves (CiA's page; vendor manuals printing CiA 301's
  table "NMT states and communication objects", e.g. Gefran RK-5-C 6.3): SDO, SYNC and EMCY in
  PRE-OPERATIONAL and OPERATIONAL, PDO only in OPERATIONAL, in STOPPED only NMT and the heartbeat.
  A request the state does not serve gets no answer at all (as CANopenNode's SDO server).
* Heartbeat (CANopenNode ``CO_NMT_internalState_t``): every 1017h ms (0 = off) one byte on
  700h + id: 04h STOPPED, 05h OPERATIONAL, 7Fh PRE-OPERATIONAL. A write of 1017h restarts the
  producer at once.
* SDO server on 600h + id, answers on 580h + id, 8-byte frames only (shorter ones are ignored, as
  CANopenNode does): expedited and segmented upload and download (CANopenNode ``CO_SDOserver.c``,
  canopen ``sdo/server.py``), block transfer refused with 0504 0001. Abort codes (CiA 301 table
  "SDO abort codes" as printed in CANopenNode ``CO_SDOserver.h``) in :data:`ABORT`.
* SYNC (COB-ID in 1005h, default 080h) -> TPDO1 (1800h/1A00h): transmission type 0..240 sends
  after every n-th SYNC (0: every SYNC, as an acyclic PDO whose data always changed), 241..251
  reserved (CANopenNode ``CO_PDO.c``), 252..255 never on SYNC. Mapping rules as vendor manuals quote
  CiA 301 (Applied Motion ST10 CANopen manual "0x1600~0x1603", Bonfiglioli CM-CAN "Mapping
  Sequence"): PDO invalid (1800h:01 bit 31) and 1A00h:00 = 0 before an entry changes, entries naming
  an object that does not exist or cannot be mapped -> 0602 0000 / 0604 0041, more than 64 bits ->
  0604 0042 (CANopenNode); a PDO without mapped objects cannot be made valid (CANopenNode).
* EMCY on 1014h (080h + id): error code (UNSIGNED16), error register 1001h, five manufacturer bytes
  (canopen ``emcy.py``); not sent in STOPPED (CiA's page).

Not verified against the text of CiA 301 (it is not public; taken from the implementations named):
the abort for a mapping change while the PDO is valid (0800 0022 here, CANopenNode answers
0601 0000); 0607 0012/0607 0013 for too long/too short data (CANopenNode; canopen's LocalNode
answers 0607 0010 for both); that an SDO request arriving during a segmented transfer starts a new
transfer rather than aborting the old one; 0609 0030 for a 1005h write that sets bit 30 (this node
cannot produce SYNC).
"""

from __future__ import annotations

import contextlib
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can

#: SDO abort codes used here (CiA 301 table "SDO abort codes").
ABORT = {
    "toggle": 0x05030000,  # Toggle bit not alternated
    "command": 0x05040001,  # Client/server command specifier not valid or unknown
    "unsupported": 0x06010000,  # Unsupported access to an object
    "write_only": 0x06010001,  # Attempt to read a write only object
    "read_only": 0x06010002,  # Attempt to write a read only object
    "no_object": 0x06020000,  # Object does not exist in the object dictionary
    "cannot_map": 0x06040041,  # Object cannot be mapped to the PDO
    "pdo_length": 0x06040042,  # The number and length of the objects to be mapped would exceed PDO length
    "length": 0x06070010,  # Data type does not match, length of service parameter does not match
    "too_long": 0x06070012,  # Data type does not match, length of service parameter too high
    "too_short": 0x06070013,  # Data type does not match, length of service parameter too low
    "no_subindex": 0x06090011,  # Sub-index does not exist
    "value_range": 0x06090030,  # Invalid value for parameter (download only) / value range exceeded
    "cannot_store": 0x08000020,  # Data cannot be transferred or stored to the application
    "device_state": 0x08000022,  # ... because of the present device state
}

#: Heartbeat state byte per NMT state (CANopenNode ``CO_NMT_internalState_t``, vendor manuals).
STATE_BYTE = {"INITIALISING": 0x00, "STOPPED": 0x04, "OPERATIONAL": 0x05, "PRE-OPERATIONAL": 0x7F}
NMT_COMMANDS = {0x01: "start", 0x02: "stop", 0x80: "pre-operational", 0x81: "reset node", 0x82: "reset communication"}
COB_INVALID = 0x80000000  # bit 31 of a PDO COB-ID: the PDO does not exist / is not valid
TPDO1_COMM, TPDO1_MAP = 0x1800, 0x1A00
VISIBLE_STRING = "str"


class SdoAbort(Exception):
    """An SDO request refused with a CiA 301 abort code."""

    def __init__(self, code: int):
        super().__init__(f"SDO abort 0x{code:08X}")
        self.code = code


@dataclass
class Entry:
    """One object dictionary entry (index, subindex) as CiA 301 describes it."""

    name: str
    fmt: str  # struct format character of the value (little endian), or VISIBLE_STRING
    access: str  # "ro", "wo", "rw" or "const"
    default: Any
    mappable: bool = False
    #: value range check of a download: False -> abort 0609 0030
    valid: Callable[[Any], bool] | None = None

    @property
    def size(self) -> int | None:
        """Bytes of a fixed-size type; None for a string."""
        return None if self.fmt == VISIBLE_STRING else struct.calcsize("<" + self.fmt)

    def encode(self, value: Any) -> bytes:
        return str(value).encode("ascii") if self.fmt == VISIBLE_STRING else struct.pack("<" + self.fmt, value)

    def decode(self, raw: bytes) -> Any:
        return raw.decode("ascii", "replace") if self.fmt == VISIBLE_STRING else struct.unpack("<" + self.fmt, raw)[0]


def record(name: str, members: dict[int, Entry]) -> dict[int, Entry]:
    """A RECORD/ARRAY object: sub-index 0 (highest sub-index supported, const) plus its members."""
    return {0: Entry(f"{name}: highest sub-index supported", "B", "const", max(members)), **members}


@dataclass
class _Transfer:
    """A segmented SDO transfer in progress."""

    upload: bool
    index: int
    subindex: int
    data: bytearray = field(default_factory=bytearray)
    toggle: int = 0
    size: int | None = None  # a download's indicated size


class CanopenSlave:
    """A CiA 301 slave with one TPDO, serving ``objects`` on ``bus``; ``close()`` stops it.

    ``live(index, subindex)`` gives the value of an entry measured now (None: use the stored one);
    ``sampling()`` is entered once per TPDO, so every mapped object of one PDO is of one sample.
    """

    def __init__(self, bus: can.BusABC, node_id: int, objects: dict[int, dict[int, Entry]], *,
                 live: Callable[[int, int], Any] | None = None,
                 sampling: Callable[[], contextlib.AbstractContextManager[Any]] | None = None):
        if not 1 <= node_id <= 127:
            raise ValueError(f"node_id = {node_id}: expected 1..127")
        self.bus, self.node_id, self.objects = bus, node_id, objects
        self._live = live or (lambda index, subindex: None)
        self._sampling = sampling or contextlib.nullcontext
        self.values: dict[tuple[int, int], Any] = {}
        self.state = "INITIALISING"
        self.errors: list[BaseException] = []  # what went wrong in the receive/heartbeat threads
        self.syncs_seen = 0
        self.mute_tpdo = False  # fault injection: SYNC answered by nothing
        self._transfer: _Transfer | None = None
        self._last_mux = (0, 0)
        self._lock = threading.RLock()
        self._heartbeat_on = True
        self._heartbeat_changed = threading.Event()
        self._closed = threading.Event()
        self._reset(application=True)
        self._notifier = can.Notifier(bus, [self._on_message], timeout=0.05)
        self._heartbeat = threading.Thread(target=self._produce_heartbeat, name=f"canopen-heartbeat-{node_id}",
                                           daemon=True)
        self._heartbeat.start()
        self.boot()

    # -- object access -------------------------------------------------------------------------------
    def entry(self, index: int, subindex: int) -> Entry:
        if index not in self.objects:
            raise SdoAbort(ABORT["no_object"])
        if subindex not in self.objects[index]:
            raise SdoAbort(ABORT["no_subindex"])
        return self.objects[index][subindex]

    def get(self, index: int, subindex: int) -> Any:
        """The entry's value now: measured (``live``) or stored."""
        live = self._live(index, subindex)
        return self.values[index, subindex] if live is None else live

    def set(self, index: int, subindex: int, value: Any) -> None:
        """Set a value from inside the device (no access check), e.g. the error register."""
        self.entry(index, subindex)
        with self._lock:
            self.values[index, subindex] = value

    def _reset(self, application: bool) -> None:
        """Reset communication (1000h-1FFFh) and, for a node reset, the application (2000h-9FFFh)."""
        with self._lock:
            for index, members in self.objects.items():
                if 0x1000 <= index <= 0x1FFF or application and 0x2000 <= index <= 0x9FFF:
                    for subindex, entry in members.items():
                        self.values[index, subindex] = entry.default
            self._transfer = None
            self.syncs_seen = 0

    # -- NMT -------------------------------------------------------------------------------------------
    def boot(self, application: bool = False) -> None:
        """INITIALISING (-> defaults), boot-up message, then PRE-OPERATIONAL (CiA 301 NMT state machine)."""
        with self._lock:
            self.state = "INITIALISING"
            self._reset(application)
            self._send(0x700 + self.node_id, bytes([STATE_BYTE["INITIALISING"]]))
            self.state = "PRE-OPERATIONAL"
            self._heartbeat_on = True
        self._heartbeat_changed.set()

    def _on_nmt(self, data: bytes) -> None:
        if len(data) != 2 or data[1] not in (0, self.node_id) or data[0] not in NMT_COMMANDS:
            return
        command = NMT_COMMANDS[data[0]]
        if command in ("reset node", "reset communication"):
            self.boot(application=command == "reset node")
            return
        with self._lock:
            self.state = {"start": "OPERATIONAL", "stop": "STOPPED", "pre-operational": "PRE-OPERATIONAL"}[command]
            if self.state == "OPERATIONAL":
                self.syncs_seen = 0

    def _produce_heartbeat(self) -> None:
        """One state byte on 700h + id every 1017h ms; restarted at once when 1017h changes."""
        next_at = time.monotonic()
        while not self._closed.is_set():
            with self._lock:
                period_ms = self.values[0x1017, 0]
                on = self._heartbeat_on
            if self._heartbeat_changed.is_set():
                self._heartbeat_changed.clear()
                next_at = time.monotonic() + period_ms / 1000.0
            if not period_ms or not on:
                self._heartbeat_changed.wait(0.5)
                continue
            wait = next_at - time.monotonic()
            if wait > 0:
                self._heartbeat_changed.wait(wait)
                continue
            try:
                with self._lock:
                    state = self.state
                self._send(0x700 + self.node_id, bytes([STATE_BYTE[state]]))
            except Exception as exc:  # noqa: BLE001 - kept for the caller, never silent
                self.errors.append(exc)
            next_at += period_ms / 1000.0
            if next_at < time.monotonic():  # a stalled host: no burst of late heartbeats
                next_at = time.monotonic() + period_ms / 1000.0

    def stop_heartbeat(self) -> None:
        """Fault injection: the heartbeat stops, the node keeps its state and answers."""
        with self._lock:
            self._heartbeat_on = False
        self._heartbeat_changed.set()

    # -- receive side ----------------------------------------------------------------------------------
    def _on_message(self, msg: can.Message) -> None:
        if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
            return
        try:
            cob_id, data = msg.arbitration_id, bytes(msg.data)
            if cob_id == 0x000:
                self._on_nmt(data)
            elif cob_id == self.values[0x1005, 0] & 0x7FF:
                self._on_sync()
            elif cob_id == 0x600 + self.node_id and len(data) == 8 and self.state in ("PRE-OPERATIONAL", "OPERATIONAL"):
                self._on_sdo(data)
        except Exception as exc:  # noqa: BLE001 - kept for the caller, never silent
            self.errors.append(exc)

    def _send(self, cob_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    # -- SDO server ------------------------------------------------------------------------------------
    def _on_sdo(self, data: bytes) -> None:
        ccs = data[0] >> 5
        with self._lock:
            mux = (int.from_bytes(data[1:3], "little"), data[3]) if ccs in (1, 2, 5, 6) else self._last_mux
            try:
                if ccs == 4:  # the client aborts: drop the transfer, no answer
                    self._transfer = None
                    return
                handler = {1: self._initiate_download, 0: self._download_segment, 2: self._initiate_upload,
                           3: self._upload_segment}.get(ccs)
                if handler is None:  # 5, 6 block transfer (not supported), 7 unknown
                    raise SdoAbort(ABORT["command"])
                self._last_mux = mux
                self._sdo_reply(handler(data, *mux))
            except SdoAbort as abort:
                self._transfer = None
                self._sdo_reply(bytes([0x80]) + mux[0].to_bytes(2, "little") + bytes([mux[1]])
                                + abort.code.to_bytes(4, "little"))

    def _sdo_reply(self, data: bytes) -> None:
        self._send(0x580 + self.node_id, data.ljust(8, b"\0"))

    @staticmethod
    def _head(command: int, index: int, subindex: int) -> bytes:
        return bytes([command]) + index.to_bytes(2, "little") + bytes([subindex])

    def _initiate_upload(self, data: bytes, index: int, subindex: int) -> bytes:
        entry = self.entry(index, subindex)
        if entry.access == "wo":
            raise SdoAbort(ABORT["write_only"])
        raw = entry.encode(self.get(index, subindex))
        if len(raw) <= 4:  # expedited, size indicated: n = bytes of d without data
            return self._head(0x43 | (4 - len(raw)) << 2, index, subindex) + raw
        self._transfer = _Transfer(True, index, subindex, bytearray(raw))
        return self._head(0x41, index, subindex) + len(raw).to_bytes(4, "little")

    def _upload_segment(self, data: bytes, index: int, subindex: int) -> bytes:
        transfer = self._transfer
        if transfer is None or not transfer.upload:
            raise SdoAbort(ABORT["command"])
        if data[0] & 0x10 != transfer.toggle:
            raise SdoAbort(ABORT["toggle"])
        chunk, transfer.data = bytes(transfer.data[:7]), transfer.data[7:]
        last = not transfer.data
        reply = bytes([transfer.toggle | (7 - len(chunk)) << 1 | last]) + chunk
        transfer.toggle ^= 0x10
        if last:
            self._transfer = None
        return reply

    def _initiate_download(self, data: bytes, index: int, subindex: int) -> bytes:
        entry = self.entry(index, subindex)
        if entry.access in ("ro", "const"):
            raise SdoAbort(ABORT["read_only"])
        expedited, size_indicated = data[0] & 0x02, data[0] & 0x01
        if expedited:
            size = 4 - (data[0] >> 2 & 0x03) if size_indicated else min(entry.size or 4, 4)
            self._write(entry, index, subindex, data[4:4 + size])
            self._transfer = None
        else:
            size = int.from_bytes(data[4:8], "little") if size_indicated else None
            if size is not None and entry.size is not None and size != entry.size:
                raise SdoAbort(ABORT["too_long"] if size > entry.size else ABORT["too_short"])
            self._transfer = _Transfer(False, index, subindex, size=size)
        return self._head(0x60, index, subindex)

    def _download_segment(self, data: bytes, index: int, subindex: int) -> bytes:
        transfer = self._transfer
        if transfer is None or transfer.upload:
            raise SdoAbort(ABORT["command"])
        toggle = data[0] & 0x10
        if toggle != transfer.toggle:
            raise SdoAbort(ABORT["toggle"])
        transfer.data += data[1:8 - (data[0] >> 1 & 0x07)]
        transfer.toggle ^= 0x10
        if data[0] & 0x01:  # c: no more segments
            self._transfer = None
            if transfer.size is not None and transfer.size != len(transfer.data):
                raise SdoAbort(ABORT["too_long"] if len(transfer.data) > transfer.size else ABORT["too_short"])
            self._write(self.entry(index, subindex), index, subindex, bytes(transfer.data))
        return bytes([0x20 | toggle])

    def _write(self, entry: Entry, index: int, subindex: int, raw: bytes) -> None:
        """Check and store a download: length, value range, the CiA 301 rules of 1005h and TPDO1."""
        if entry.size is not None and len(raw) != entry.size:
            raise SdoAbort(ABORT["too_long"] if len(raw) > entry.size else ABORT["too_short"])
        value = entry.decode(raw)
        if entry.valid is not None and not entry.valid(value):
            raise SdoAbort(ABORT["value_range"])
        if index == 0x1005 and value & 0x7FFFF800:  # bit 30: generate SYNC; bits 11..29 must be 0
            raise SdoAbort(ABORT["value_range"])
        if index == TPDO1_COMM:
            self._check_tpdo_comm(subindex, value)
        elif index == TPDO1_MAP:
            self._check_tpdo_map(subindex, value)
        self.values[index, subindex] = value
        if index == 0x1017:
            self._heartbeat_changed.set()

    def _pdo_valid(self) -> bool:
        return not self.values[TPDO1_COMM, 1] & COB_INVALID

    def _check_tpdo_comm(self, subindex: int, value: int) -> None:
        if subindex == 1:
            valid = not value & COB_INVALID
            same_id = value & 0x7FF == self.values[TPDO1_COMM, 1] & 0x7FF
            if value & 0x3FFFF800 or valid and (self._pdo_valid() and not same_id or not self.values[TPDO1_MAP, 0]):
                raise SdoAbort(ABORT["value_range"])
        # 241..251: reserved transmission types; the inhibit time changes only while the PDO is invalid
        elif subindex == 2 and 241 <= value <= 251 or subindex == 3 and self._pdo_valid():
            raise SdoAbort(ABORT["value_range"])

    def _check_tpdo_map(self, subindex: int, value: int) -> None:
        if self._pdo_valid():
            raise SdoAbort(ABORT["device_state"])
        if subindex == 0:
            if value > max(self.objects[TPDO1_MAP]):
                raise SdoAbort(ABORT["pdo_length"])
            if sum(self.values[TPDO1_MAP, k] & 0xFF for k in range(1, value + 1)) > 64:
                raise SdoAbort(ABORT["pdo_length"])
            return
        if self.values[TPDO1_MAP, 0] != 0:  # entries change only while the mapping is disabled
            raise SdoAbort(ABORT["device_state"])
        if value == 0:
            return
        index, sub, bits = value >> 16, value >> 8 & 0xFF, value & 0xFF
        target = self.entry(index, sub)  # 0602 0000 / 0609 0011 when it does not exist
        if not target.mappable or target.size is None or target.size * 8 != bits:
            raise SdoAbort(ABORT["cannot_map"])

    # -- SYNC -> TPDO1 ---------------------------------------------------------------------------------
    def _on_sync(self) -> None:
        with self._lock:
            if self.state not in ("PRE-OPERATIONAL", "OPERATIONAL"):
                return
            self.syncs_seen += 1
            transmission_type = self.values[TPDO1_COMM, 2]
            if (self.state != "OPERATIONAL" or self.mute_tpdo or not self._pdo_valid() or transmission_type > 240
                    or transmission_type and self.syncs_seen % transmission_type):
                return
            cob_id = self.values[TPDO1_COMM, 1] & 0x7FF
            payload = self.tpdo_payload()
        self._send(cob_id, payload)

    def mapping(self) -> list[tuple[int, int, int]]:
        """TPDO1's mapped objects as (index, subindex, bits), in order."""
        return [(v >> 16, v >> 8 & 0xFF, v & 0xFF)
                for v in (self.values[TPDO1_MAP, k] for k in range(1, self.values[TPDO1_MAP, 0] + 1))]

    def tpdo_payload(self) -> bytes:
        """TPDO1 data: the mapped objects, in mapping order, all of one sample."""
        with self._sampling():
            return b"".join(self.entry(i, s).encode(self.get(i, s)) for i, s, _ in self.mapping())

    # -- EMCY ------------------------------------------------------------------------------------------
    def emcy(self, code: int, register: int, extra: bytes = b"") -> None:
        """An emergency message (1014h COB-ID): error code, error register (also set in 1001h), 5 bytes."""
        with self._lock:
            self.values[0x1001, 0] = register
            if self.state == "STOPPED":
                return
            cob_id = self.values[0x1014, 0] & 0x7FF
        self._send(cob_id, struct.pack("<HB", code, register) + extra[:5].ljust(5, b"\0"))

    # -- life ------------------------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the heartbeat and the receive thread (idempotent); the bus stays with its owner."""
        self._closed.set()
        self._heartbeat_changed.set()
        if self._heartbeat.is_alive():
            self._heartbeat.join(1.0)
        self._notifier.stop(timeout=1.0)


def communication_objects(node_id: int, *, device_type: int, name: str, identity: tuple[int, int, int, int],
                          software_version: str) -> dict[int, dict[int, Entry]]:
    """The CiA 301 communication objects of a one-TPDO slave (TPDO1 mapping left to the profile)."""
    u8, u16, u32 = "B", "H", "I"
    vendor, product, revision, serial = identity
    return {
        0x1000: {0: Entry("Device type", u32, "ro", device_type)},
        0x1001: {0: Entry("Error register", u8, "ro", 0, mappable=True)},
        0x1005: {0: Entry("COB-ID SYNC", u32, "rw", 0x80)},
        0x1008: {0: Entry("Manufacturer device name", VISIBLE_STRING, "const", name)},
        0x100A: {0: Entry("Manufacturer software version", VISIBLE_STRING, "const", software_version)},
        0x1014: {0: Entry("COB-ID EMCY", u32, "ro", 0x80 + node_id)},
        0x1017: {0: Entry("Producer heartbeat time", u16, "rw", 0)},
        0x1018: record("Identity object", {1: Entry("Vendor-ID", u32, "ro", vendor),
                                           2: Entry("Product code", u32, "ro", product),
                                           3: Entry("Revision number", u32, "ro", revision),
                                           4: Entry("Serial number", u32, "ro", serial)}),
        TPDO1_COMM: record("TPDO1 communication parameter", {
            1: Entry("COB-ID used by TPDO", u32, "rw", 0x180 + node_id),
            2: Entry("Transmission type", u8, "rw", 254),
            3: Entry("Inhibit time", u16, "rw", 0),
            5: Entry("Event timer", u16, "rw", 0),
        }),
    }
