"""CANopen measuring devices (CiA 301 communication, CiA 404 profile): displacement or temperature.

What the driver does with the sensor, in the order of the manual:

1. NMT "enter pre-operational" (``80 id`` on COB-ID 000h), so the PDO may be reconfigured.
2. SDO expedited downloads (COB-ID 600h + id, answered on 580h + id):

   * 1017h:00 producer heartbeat time (UNSIGNED16, ms);
   * 1800h:01 TPDO1 COB-ID with bit 31 set: the PDO is invalid while its mapping changes;
   * 1A00h:00 = 0, then 1A00h:01 = the process value (``index << 16 | subindex << 8 | bits``), and
     1A00h:02 = the AI status byte (6150h, 8 bits) when mapped, then 1A00h:00 = number of entries;
   * 1800h:02 transmission type 1 (synchronous, cyclic: one TPDO after every SYNC);
   * 1800h:01 = 180h + id: the PDO is valid again.

3. NMT "start remote node" (``01 id``); the heartbeat (700h + id, one byte: 05h operational) follows.

``read()`` sends a SYNC (COB-ID 080h, no data) and waits (bounded) for the TPDO1 it triggers:
the process value (little endian; 6130h REAL32, 7130h INTEGER16 or 9130h INTEGER32 per CiA 404)
then the status byte. Value = ``offset + scale * PV`` in the configured unit (``output`` um or
``temperature`` degC). Status bits 0 (not valid), 1 (positive overload) or 2 (negative overload)
make the value NaN.

A heartbeat consumer thread marks the node lost when no heartbeat arrives within
``heartbeat_consumer_ms``; the next call raises :class:`DeviceLost` naming the node. Errors in
the receive callbacks and the supervisor are stored and re-raised on the next call, never dropped.
An EMCY (080h + id) with a non-zero error code is raised once as :class:`DeviceError`.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

from drivers.base import (
    DeviceError,
    DeviceLost,
    DeviceTimeout,
    DriverSpec,
    Lazy,
    Setting,
    retry,
)

# CiA 404 process value objects: index -> (struct format, bits). 6xxxh REAL32, 7xxxh INTEGER16,
# 9xxxh INTEGER32 are the profile's variants of the same "AI input PV".
PV_TYPES: dict[int, tuple[str, int]] = {0x6130: ("<f", 32), 0x7130: ("<h", 16), 0x9130: ("<i", 32)}
AI_STATUS_INDEX = 0x6150  # UNSIGNED8 per channel
STATUS_NOT_VALID, STATUS_POSITIVE_OVERLOAD, STATUS_NEGATIVE_OVERLOAD = 0x01, 0x02, 0x04
NMT_STATES = {0x00: "BOOT-UP", 0x04: "STOPPED", 0x05: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}
NMT_START, NMT_PRE_OPERATIONAL = 0x01, 0x80
TPDO1_COMM, TPDO1_MAP = 0x1800, 0x1A00
COB_INVALID = 0x80000000  # bit 31 of a PDO COB-ID: PDO does not exist / not valid
QUANTITIES = {"output": "um", "temperature": "degC"}


def bus_options(interface: str, port: int) -> dict[str, Any]:
    """Extra python-can bus arguments: the UDP port of a ``udp_multicast`` bus (0: python-can's default).

    On Linux a multicast socket receives every group joined on its port (``IP_MULTICAST_ALL``), so
    two udp_multicast buses are kept apart by their port, not by their group address (channel)."""
    if port and interface != "udp_multicast":
        raise ValueError(f"port = {port}: only the udp_multicast interface has a port (interface is {interface!r})")
    return {"port": port} if port else {}


def mapping_entry(index: int, subindex: int, bits: int) -> int:
    """A PDO mapping entry (CiA 301): index in bits 31..16, subindex 15..8, length in bits 7..0."""
    return (index << 16) | (subindex << 8) | bits


class CanopenSensor:
    """One CANopen sensor node: configured over SDO, read with SYNC -> TPDO1, watched by heartbeat."""

    def __init__(self, settings: dict[str, Any]):
        import canopen

        self.settings = dict(settings)
        self.node_id = int(settings["node_id"])
        self.quantity = str(settings["quantity"])
        self.name = f"canopen-sensor node {self.node_id} on {settings['interface']}:{settings['channel']}"
        if self.quantity not in QUANTITIES:
            raise DeviceError(self.name, f"quantity must be one of {', '.join(QUANTITIES)}, got {self.quantity!r}")
        self.pv_index = int(settings["pv_index"])
        if self.pv_index not in PV_TYPES:
            raise DeviceError(self.name, f"pv_index 0x{self.pv_index:04X} is not a CiA 404 AI PV "
                                         f"({', '.join(f'0x{i:04X}' for i in PV_TYPES)})")
        self.pv_subindex = int(settings["pv_subindex"])
        self.status_index = int(settings["status_index"])  # 0: status not mapped
        self.status_subindex = int(settings["status_subindex"])
        self.scale = float(settings["scale"])
        self.offset = float(settings["offset"])
        self.heartbeat_ms = int(settings["heartbeat_ms"])
        self.consumer_s = float(settings["heartbeat_consumer_ms"]) / 1000.0
        self.timeout_s = float(settings["timeout_s"])
        self.attempts = int(settings["attempts"])
        self.tpdo_cob = 0x180 + self.node_id
        if not 1 <= self.node_id <= 127:
            raise DeviceError(self.name, f"node_id must be 1..127, got {self.node_id}")
        if not 0 < self.heartbeat_ms < self.consumer_s * 1000:
            raise DeviceError(self.name, f"heartbeat_consumer_ms ({self.consumer_s * 1000:.0f}) must exceed "
                                         f"heartbeat_ms ({self.heartbeat_ms}) > 0")

        self._cond = threading.Condition()
        self._tpdo: bytes | None = None
        self._tpdo_count = 0
        self._last_heartbeat: float | None = None  # time.monotonic() of the last heartbeat
        self._nmt_state: int | None = None
        self._lost: str | None = None
        self._errors: list[BaseException] = []  # from callbacks and the supervisor, re-raised by calls
        self._emcy: list[tuple[int, int, bytes]] = []  # (error code, error register, manufacturer bytes)
        self._closed = threading.Event()
        self._configured = False

        self.network = canopen.Network()
        # The receive thread polls the bus this often; close() waits up to one cycle for it.
        self.network.NOTIFIER_CYCLE = 0.05
        try:
            options = bus_options(str(settings["interface"]), int(settings.get("port") or 0))
        except ValueError as exc:
            raise DeviceError(self.name, str(exc)) from None
        self.network.connect(interface=str(settings["interface"]), channel=settings["channel"],
                             bitrate=int(settings["bitrate"]), **options)
        try:
            self.node = canopen.RemoteNode(self.node_id, canopen.ObjectDictionary())
            self.network.add_node(self.node)
            # canopen's own heartbeat and EMCY handlers would run first and, on a malformed frame,
            # raise and so skip ours (canopen stops at the first failing callback and only logs it).
            self.network.unsubscribe(0x700 + self.node_id, self.node.nmt.on_heartbeat)
            self.network.unsubscribe(0x080 + self.node_id, self.node.emcy.on_emcy)
            self.node.sdo.RESPONSE_TIMEOUT = self.timeout_s
            self.network.subscribe(self.tpdo_cob, self._guarded(self._on_tpdo))
            self.network.subscribe(0x700 + self.node_id, self._guarded(self._on_heartbeat))
            self.network.subscribe(0x080 + self.node_id, self._guarded(self._on_emcy))
            self._supervisor = threading.Thread(target=self._supervise, name=f"heartbeat-consumer-{self.node_id}",
                                                daemon=True)
            self._supervisor.start()
            self.configure()
        except BaseException:
            self.close()
            raise

    # -- receive side: never silent --------------------------------------------------------------------
    def _guarded(self, callback: Callable[[int, bytes, float], None]) -> Callable[[int, bytes, float], None]:
        """canopen logs and drops callback exceptions; keep them to raise on the next call instead."""

        def run(can_id: int, data: bytes, timestamp: float) -> None:
            try:
                callback(can_id, bytes(data), timestamp)
            except Exception as exc:  # noqa: BLE001 - stored, re-raised by the next call
                with self._cond:
                    self._errors.append(exc)
                    self._cond.notify_all()

        return run

    def _on_tpdo(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self._cond:
            self._tpdo = data
            self._tpdo_count += 1
            self._cond.notify_all()

    def _on_heartbeat(self, can_id: int, data: bytes, timestamp: float) -> None:
        if not data:
            raise DeviceError(self.name, "empty heartbeat frame")
        state = data[0] & 0x7F  # bit 7 is the node guarding toggle bit, not part of the state
        with self._cond:
            self._last_heartbeat = time.monotonic()
            self._nmt_state = state
            if state == 0x00 and self._configured and self._lost is None:
                # A boot-up after configuration: the node reset and forgot its PDO configuration.
                self._lost = "the node rebooted (boot-up message) and lost its configuration"
            self._cond.notify_all()

    def _on_emcy(self, can_id: int, data: bytes, timestamp: float) -> None:
        code, register = struct.unpack_from("<HB", data.ljust(3, b"\0"))
        with self._cond:
            self._emcy.append((code, register, data[3:8]))

    def _supervise(self) -> None:
        """Heartbeat consumer: mark the node lost once no heartbeat came for the consumer time.

        A wake-up that comes late by more than a period means this process was stalled (a busy host,
        a long compile holding the interpreter): heartbeats received meanwhile may still wait in the
        receive thread's queue, so the verdict waits one more period for them to be processed rather
        than call a node lost that only the host failed to listen to."""
        period = max(0.005, self.consumer_s / 4)
        previous = time.monotonic()
        while not self._closed.wait(period):
            now = time.monotonic()
            stalled = now - previous > 2.0 * period
            previous = now
            if stalled:
                continue
            try:
                with self._cond:
                    last = self._last_heartbeat
                    if last is None or self._lost is not None:
                        continue  # not started yet (configure() waits for the first one) or already lost
                    silent = time.monotonic() - last
                    if silent > self.consumer_s:
                        self._lost = (f"no heartbeat for {silent * 1000:.0f} ms "
                                      f"(consumer time {self.consumer_s * 1000:.0f} ms)")
                        self._cond.notify_all()
            except Exception as exc:  # noqa: BLE001 - stored, re-raised by the next call
                with self._cond:
                    self._errors.append(exc)

    def _check(self) -> None:
        """Raise what the background side found: a notifier failure, a callback error, a lost node."""
        try:
            self.network.check()
        except Exception as exc:
            raise DeviceLost(self.name, f"CAN receive thread stopped: {exc}") from exc
        with self._cond:
            if self._errors:
                exc = self._errors.pop(0)
                if isinstance(exc, DeviceError):
                    raise exc
                raise DeviceError(self.name, f"receive error: {type(exc).__name__}: {exc}") from exc
            if self._lost is not None:
                raise DeviceLost(self.name, self._lost)
            if self._emcy:
                code, register, extra = self._emcy.pop(0)
                if code != 0:  # 0000h: error reset / no error
                    raise DeviceError(self.name, f"EMCY error code 0x{code:04X}, error register 0x{register:02X}, "
                                                 f"manufacturer data {extra.hex(' ') or '-'}")

    # -- SDO ---------------------------------------------------------------------------------------------
    def sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        """One expedited SDO download; aborts -> DeviceError, no answer -> retried, then DeviceTimeout."""
        from canopen import SdoAbortedError, SdoCommunicationError

        what = f"SDO write {index:04X}h:{subindex:02X} = {data[::-1].hex().upper()}h"

        def once() -> None:
            self._check()
            try:
                self.node.sdo.download(index, subindex, data)
            except SdoAbortedError as exc:
                raise DeviceError(self.name, f"{what} aborted: {exc}") from exc
            except SdoCommunicationError as exc:
                raise DeviceTimeout(self.name, f"{what}: {exc}") from exc

        retry(once, device=self.name, what=what, attempts=self.attempts)

    def configure(self) -> None:
        """Heartbeat, TPDO1 mapping and synchronous transmission over SDO, then NMT start."""
        pv_bits = PV_TYPES[self.pv_index][1]
        self.network.send_message(0x000, [NMT_PRE_OPERATIONAL, self.node_id])
        self.sdo_write(0x1017, 0x00, struct.pack("<H", self.heartbeat_ms))
        self.sdo_write(TPDO1_COMM, 0x01, struct.pack("<I", COB_INVALID | self.tpdo_cob))
        self.sdo_write(TPDO1_MAP, 0x00, bytes([0]))
        entries = [mapping_entry(self.pv_index, self.pv_subindex, pv_bits)]
        if self.status_index:
            entries.append(mapping_entry(self.status_index, self.status_subindex, 8))
        for k, entry in enumerate(entries, start=1):
            self.sdo_write(TPDO1_MAP, k, struct.pack("<I", entry))
        self.sdo_write(TPDO1_MAP, 0x00, bytes([len(entries)]))
        self.sdo_write(TPDO1_COMM, 0x02, bytes([1]))  # synchronous, cyclic every SYNC
        self.sdo_write(TPDO1_COMM, 0x01, struct.pack("<I", self.tpdo_cob))
        self.network.send_message(0x000, [NMT_START, self.node_id])
        self._wait_operational()
        self._configured = True

    def _wait_operational(self) -> None:
        """Wait (bounded) for a heartbeat saying OPERATIONAL: it proves heartbeat and NMT start work."""
        limit = max(self.consumer_s, self.timeout_s) + self.heartbeat_ms / 1000.0
        deadline = time.monotonic() + limit
        with self._cond:
            while self._nmt_state != 0x05:
                left = deadline - time.monotonic()
                if left <= 0:
                    seen = NMT_STATES.get(self._nmt_state, "no heartbeat") if self._nmt_state is not None \
                        else "no heartbeat"
                    raise DeviceLost(self.name, f"not OPERATIONAL {limit * 1000:.0f} ms after NMT start ({seen})")
                self._cond.wait(left)

    # -- sensor --------------------------------------------------------------------------------------------
    def read_raw(self) -> tuple[float, int | None]:
        """SYNC -> TPDO1: the process value as sent and the status byte (None when not mapped)."""

        def once() -> bytes:
            self._check()
            with self._cond:
                seen = self._tpdo_count
            self.network.sync.transmit()
            deadline = time.monotonic() + self.timeout_s
            with self._cond:
                while self._tpdo_count == seen:
                    if self._errors or self._lost is not None:
                        break
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise DeviceTimeout(self.name, f"no TPDO1 (COB-ID {self.tpdo_cob:03X}h) "
                                                       f"within {self.timeout_s} s of SYNC")
                    self._cond.wait(left)
                data = self._tpdo
            self._check()  # a loss noticed while waiting wins over a stale frame
            assert data is not None
            return data

        data = retry(once, device=self.name, what="read (SYNC -> TPDO1)", attempts=self.attempts)
        fmt, bits = PV_TYPES[self.pv_index]
        need = bits // 8 + (1 if self.status_index else 0)
        if len(data) < need:
            raise DeviceError(self.name, f"TPDO1 has {len(data)} bytes ({data.hex(' ')}), expected {need}")
        (pv,) = struct.unpack_from(fmt, data)
        status = data[bits // 8] if self.status_index else None
        return float(pv), status

    def read(self) -> dict[str, float]:
        """``{quantity: offset + scale * PV}``; NaN when the status flags not valid / overload."""
        pv, status = self.read_raw()
        bad = status is not None and status & (STATUS_NOT_VALID | STATUS_POSITIVE_OVERLOAD | STATUS_NEGATIVE_OVERLOAD)
        value = math.nan if bad or math.isnan(pv) else self.offset + self.scale * pv
        return {self.quantity: value}

    # -- description ---------------------------------------------------------------------------------------
    def identity(self) -> str:
        return f"CANopen CiA 404 sensor, node {self.node_id}, {self.settings['interface']}:{self.settings['channel']}"

    def capabilities(self) -> dict[str, Any]:
        return {"quantity": self.quantity, "unit": QUANTITIES[self.quantity], "pv_object": f"{self.pv_index:04X}h:"
                f"{self.pv_subindex:02X}", "status_mapped": bool(self.status_index), "scale": self.scale,
                "offset": self.offset, "heartbeat_ms": self.heartbeat_ms,
                "heartbeat_consumer_ms": self.consumer_s * 1000, "transmission_type": 1}

    def close(self) -> None:
        """Stop the heartbeat consumer and leave the bus (idempotent)."""
        self._closed.set()
        supervisor = getattr(self, "_supervisor", None)
        if supervisor is not None and supervisor.is_alive():
            supervisor.join(1.0)
        if self.network.bus is not None:
            self.network.disconnect()


def open_device(settings: dict[str, Any]) -> CanopenSensor:
    return CanopenSensor(DRIVER.complete(settings))


SETTINGS = (
    Setting("interface", str, default="virtual", doc="python-can interface (virtual, socketcan, pcan, udp_multicast, ...)"),
    Setting("channel", str, default="hilbench", doc="python-can channel (virtual: any shared name; socketcan: can0; udp_multicast: a group address)"),
    Setting("bitrate", int, default=500000, doc="bit/s"),
    Setting("port", int, default=0, doc="udp_multicast interface only: UDP port (0 = python-can's default 43113)"),
    Setting("node_id", int, required=True, doc="CANopen node id, 1..127"),
    Setting("quantity", str, default="output", doc="'output' (displacement, um) or 'temperature' (degC)"),
    Setting("pv_index", int, default=0x6130, doc="CiA 404 AI PV object: 0x6130 REAL32, 0x7130 INTEGER16, 0x9130 INTEGER32"),
    Setting("pv_subindex", int, default=1, doc="AI channel (subindex) of the PV object"),
    Setting("status_index", int, default=AI_STATUS_INDEX, doc="AI status object mapped after the PV (0x6150); 0 = none"),
    Setting("status_subindex", int, default=1, doc="AI channel (subindex) of the status object"),
    Setting("scale", float, default=1.0, doc="physical unit per PV unit"),
    Setting("offset", float, default=0.0, doc="physical value at PV = 0"),
    Setting("heartbeat_ms", int, default=50, doc="producer heartbeat time written to 0x1017, ms"),
    Setting("heartbeat_consumer_ms", int, default=150, doc="node lost after this long without a heartbeat, ms"),
    Setting("timeout_s", float, default=0.1, doc="SDO answer and TPDO-after-SYNC timeout, s"),
    Setting("attempts", int, default=3, doc="tries per SDO write or SYNC when answers time out"),
)

DRIVER = DriverSpec(
    name="canopen-sensor",
    roles=("sensor",),
    settings=SETTINGS,
    open=open_device,
    emulator=Lazy("drivers.emulators.canopen_sensor:start_emulator"),
    description="CANopen CiA 404 measuring device (displacement or temperature): SDO-configured TPDO1 "
                "on SYNC, heartbeat supervised",
    transports=("python-can",),
)
