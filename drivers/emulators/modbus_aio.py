"""Emulator of the Modbus analog I/O module: a real pymodbus server on 127.0.0.1.

Modbus TCP for a ``tcp://`` driver table; for a serial (RTU) one, RTU frames (with CRC) over a
loopback socket that the driver opens as the serial URL ``socket://127.0.0.1:PORT``. The function
layer (which functions, which exception for what) is :mod:`drivers.emulators.modbus_server`'s.

The module emulated, when the driver table's registers fit it (AO register 10 or 11, AI registers
0..5, as the defaults and the templates have them): the ADAM-6024 as the ADAM-6000 Series User
Manual (Edition 9) has it.

* Appendix B.2.4, "ADAM-6024 12-ch Universal I/O Module" (0-based protocol address = Modicon
  number - 1 in its table):

  ====================  ==========  =================  =========
  table                 Modicon     what               attribute
  ====================  ==========  =================  =========
  0X (coils)            00001-2     DI0, DI1           Read
  0X (coils)            00017-18    DO0, DO1           R/W
  4X (registers)        40001-6     AI0..AI5 value     Read
  4X (registers)        40011-12    AO0, AO1 value     R/W
  4X (registers)        40021-26    AI0..AI5 status    Read
  ====================  ==========  =================  =========

* Section 6.3.2 / B.1.2, "Modbus Function Code Introductions": functions 01, 02, 03, 04, 05, 06,
  08, 15, 16; every other function is answered 01 ILLEGAL FUNCTION. 03 and 04 both read the 4X
  table (the manual: "the function code 03 or 04 is used to read ...", its 04 example reads
  40001-40002); 01 and 02 both read the 0X table (its 02 example is sent as function 01). 05
  takes FF00 (on), 0000 (off) and FFFF ("release the force"); 08 echoes its request.

Not in the manual, so chosen here and to be checked on a real module: an address outside the
table (the gaps 00003-00016, 40007-40010, 40013-40020, beyond 00018 and 40026) and a write to a
Read address answer 02 ILLEGAL DATA ADDRESS; an AO value outside the configured AO count range
answers 03 ILLEGAL DATA VALUE and leaves the AO as it was; 05 with FFFF changes nothing; another
unit id answers 0B; the AI status value is 0 normal, 1 over high, 2 over low (the manual's remark
"Bit Value 0: normal, 1: over high, 2: over low, 0: invalid calibration" leaves open whether these
are values or bit numbers); inputs not wired to the plant read 0 V, DIs read off.

A driver table whose registers do not fit the ADAM-6024 is emulated as a module with exactly those
registers (the AO register read/write, the AI registers read only, functions 03, 04, 06, 16).

Behind the registers, the :class:`~drivers.base.World`:

* a write to the AO register -> counts -> volts -> amps (through the amplifier gain) ->
  ``world.command(amps)``;
* a read of the AI registers -> ``world.read("current")`` / ``world.read("output")`` -> volts ->
  counts.

Fault injection for tests: :meth:`drop_replies` (no reply: the client times out),
:meth:`exception_next` (an exception response to the next request), :meth:`garbage_replies`
(bytes that are not Modbus instead of replies), :meth:`out_of_range` (AI counts outside the
configured range) and :meth:`disconnect` (server shutdown: connections close). Every frame sent
and received is kept in :attr:`frames`, so a test can show the bytes on the wire.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from drivers.base import World
from drivers.emulators.modbus_server import (
    ILLEGAL_DATA_ADDRESS,
    ILLEGAL_DATA_VALUE,
    ModbusServerThread,
    Refused,
)
from drivers.modbus_aio import ai_registers, ai_scale, ao_scale, parse_url


@dataclass(frozen=True)
class Area:
    """One row of a module's Modbus table: ``count`` addresses from ``first`` (0-based)."""

    table: str  # "0X" (bits: functions 01, 02, 05, 15) or "4X" (registers: 03, 04, 06, 16)
    first: int
    count: int
    kind: str  # "DI", "DO", "AI", "AO", "AI status"
    writable: bool


ADAM_6024_MAP = (  # ADAM-6000 Series User Manual, Appendix B.2.4
    Area("0X", 0, 2, "DI", False),
    Area("0X", 16, 2, "DO", True),
    Area("4X", 0, 6, "AI", False),
    Area("4X", 10, 2, "AO", True),
    Area("4X", 20, 6, "AI status", False),
)
ADAM_6024_FUNCTIONS = frozenset({1, 2, 3, 4, 5, 6, 8, 15, 16})  # manual section 6.3.2, Table 6-1
RELEASE_FORCE = 0xFFFF  # function 05: "a value of FF FF hex requests it to release the force"
GENERIC_FUNCTIONS = frozenset({3, 4, 6, 16})
TABLE_OF_FUNCTION = {1: "0X", 2: "0X", 5: "0X", 15: "0X", 3: "4X", 4: "4X", 6: "4X", 16: "4X"}
AI_STATUS_NORMAL, AI_STATUS_OVER_HIGH, AI_STATUS_OVER_LOW = 0, 1, 2


def fits_adam_6024(settings: dict[str, Any]) -> bool:
    """Do the driver table's registers lie where the ADAM-6024 has its AO and AIs?"""
    return int(settings["ao_register"]) in (10, 11) and all(0 <= r <= 5 for r in ai_registers(settings).values())


class ModbusAIOEmulator:
    """A running emulated analog I/O module; ``url`` is what the driver table's ``url`` should be."""

    def __init__(self, settings: dict[str, Any], world: World, *, start_timeout_s: float = 5.0):
        self.world = world
        self.unit_id = int(settings["unit_id"])
        self.ao_register = int(settings["ao_register"])
        self.ai_regs = ai_registers(settings)
        self.ao = ao_scale(settings)
        self.ai = ai_scale(settings)
        self.gain_a_per_v = float(settings["amplifier_gain_a_per_v"])
        self.monitor_v_per_a = float(settings["current_monitor_v_per_a"])
        self.output_um_per_v = float(settings["output_um_per_v"])
        self.output_offset_um = float(settings["output_offset_um"])

        if fits_adam_6024(settings):
            self.model = "ADAM-6024"
            self.areas: tuple[Area, ...] = ADAM_6024_MAP
            self.functions = ADAM_6024_FUNCTIONS
            self.coil_values_without_effect = frozenset({RELEASE_FORCE})
        else:
            self.model = "generic"
            self.areas = (Area("4X", self.ao_register, 1, "AO", True),
                          *(Area("4X", reg, 1, "AI", False) for reg in sorted(set(self.ai_regs.values()))))
            self.functions = GENERIC_FUNCTIONS
            self.coil_values_without_effect = frozenset()
        # What every address holds: (table, address) -> Area, and the stored values of DIs, DOs, AOs.
        self._where = {(a.table, a.first + k): a for a in self.areas for k in range(a.count)}
        self._stored: dict[tuple[str, int], int] = {key: 0 for key, a in self._where.items()
                                                    if a.kind in ("DI", "DO", "AO")}
        self._channel_at = {reg: name for name, reg in self.ai_regs.items()}
        self._ai_first = min(a.first for a in self.areas if a.kind == "AI") if self.ai_regs else 0
        self._status_first = next((a.first for a in self.areas if a.kind == "AI status"), None)

        # What the tests look at: every AO value written (A), and the frames on the wire.
        self.ao_writes: list[float] = []
        self.frames: list[tuple[str, bytes]] = []  # ("rx" | "tx", the ADU: MBAP + PDU, or RTU frame)
        self._lock = threading.Lock()  # the World is called from the server thread only, under it
        self._drop = 0
        self._garbage: tuple[int, bytes] = (0, b"")  # how many replies to replace, and by what
        self._exception: int | None = None
        self._out_of_range = False

        url = str(settings.get("url", ""))
        # A tcp:// config gets Modbus TCP on its own port (so a real-rig config can be dry-run); a
        # serial (RTU) config gets RTU frames over a loopback socket, reached as socket://host:port.
        self.rtu = not url.startswith("tcp://")
        port = 0 if self.rtu else parse_url(url)[2]
        self._server = ModbusServerThread(self, rtu=self.rtu, port=port, trace=self._trace,
                                          start_timeout_s=start_timeout_s)
        self._thread = self._server.thread
        self.port = self._server.port
        self.url = f"{'socket' if self.rtu else 'tcp'}://127.0.0.1:{self.port}"

    # -- the module's registers (called by the function layer, in the server thread) -------------------
    def admit(self, function: int) -> None:
        with self._lock:
            if self._exception is not None:
                code, self._exception = self._exception, None
                raise Refused(code)

    def _areas(self, function: int, address: int, count: int, writing: bool) -> list[Area]:
        """The table's rows at ``address``..``address + count - 1``; Refused(02) if one is not there
        (or, ``writing``, is read only)."""
        table = TABLE_OF_FUNCTION[function]
        areas = []
        for k in range(count):
            area = self._where.get((table, address + k))
            if area is None or (writing and not area.writable):
                raise Refused(ILLEGAL_DATA_ADDRESS)
            areas.append(area)
        return areas

    def read(self, function: int, address: int, count: int) -> list[int] | list[bool]:
        areas = self._areas(function, address, count, writing=False)
        with self._lock:
            if TABLE_OF_FUNCTION[function] == "0X":
                return [bool(self._stored[("0X", address + k)]) for k in range(count)]
            return [self._register(area.kind, address + k) for k, area in enumerate(areas)]

    def write(self, function: int, address: int, values: Sequence[int] | Sequence[bool]) -> None:
        areas = self._areas(function, address, max(len(values), 1), writing=True)
        if not values:  # 05 with FFFF, "release the force": nothing to change on this module
            return
        table = TABLE_OF_FUNCTION[function]
        if table == "4X" and any(a.kind == "AO" and not self.ao.counts_min <= int(v) <= self.ao.counts_max
                                 for a, v in zip(areas, values)):
            raise Refused(ILLEGAL_DATA_VALUE)
        with self._lock:
            for k, value in enumerate(values):
                self._stored[(table, address + k)] = int(value)
                if table == "4X" and address + k == self.ao_register:
                    amps = self.ao.to_volts(int(value)) * self.gain_a_per_v
                    self.ao_writes.append(amps)
                    self.world.command(amps)

    def _register(self, kind: str, address: int) -> int:
        if kind == "AI":
            return self._ai(address)[0]
        if kind == "AI status":
            assert self._status_first is not None
            return self._ai(self._ai_first + address - self._status_first)[1]
        return self._stored[("4X", address)]

    def _ai(self, address: int) -> tuple[int, int]:
        """AI counts at ``address`` and its status; an AI not wired to the plant reads 0 V."""
        channel = self._channel_at.get(address)
        if channel is None:
            return self.ai.to_counts(0.0)[0], AI_STATUS_NORMAL
        if self._out_of_range:
            return min(self.ai.counts_max + 1, 0xFFFF), AI_STATUS_OVER_HIGH
        value = float(self.world.read(channel))
        if channel == "current":
            volts = value * self.monitor_v_per_a
        else:
            volts = (value - self.output_offset_um) / self.output_um_per_v
        counts, _ = self.ai.to_counts(volts)  # a real ADC saturates at its range ends
        status = (AI_STATUS_OVER_HIGH if volts > self.ai.volts_max
                  else AI_STATUS_OVER_LOW if volts < self.ai.volts_min else AI_STATUS_NORMAL)
        return counts, status

    def _trace(self, sending: bool, data: bytes) -> bytes:
        with self._lock:
            if sending and self._drop > 0:
                self._drop -= 1
                return b""  # nothing goes on the wire: the client sees no reply
            if sending and self._garbage[0] > 0:
                data = self._garbage[1]
                self._garbage = (self._garbage[0] - 1, data)
            self.frames.append(("tx" if sending else "rx", bytes(data)))
        return data

    # -- fault injection -----------------------------------------------------------------------------
    def drop_replies(self, n: int) -> None:
        """Send no reply to the next ``n`` requests (the request is still executed)."""
        with self._lock:
            self._drop = int(n)

    def exception_next(self, code: int) -> None:
        """Answer the next request with Modbus exception ``code`` (e.g. 4 SERVER DEVICE FAILURE)."""
        with self._lock:
            self._exception = int(code)

    def garbage_replies(self, n: int, data: bytes = b"HTTP/1.1 400 Bad Request\r\n\r\n") -> None:
        """Send ``data`` (not a Modbus frame) instead of the next ``n`` replies; the requests are executed."""
        with self._lock:
            self._garbage = (int(n), bytes(data))

    def out_of_range(self, on: bool = True) -> None:
        """AI reads return counts above the configured count range (an over-range input)."""
        with self._lock:
            self._out_of_range = bool(on)

    @property
    def last_ao(self) -> float | None:
        """The last AO value written, A (None before any write)."""
        with self._lock:
            return self.ao_writes[-1] if self.ao_writes else None

    def disconnect(self, timeout_s: float = 2.0) -> None:
        """Shut the server down: open connections close and new ones are refused."""
        self._server.shutdown(timeout_s)

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the server and its thread (idempotent)."""
        self._server.close(timeout_s)


def start_emulator(settings: dict[str, Any], world: World) -> ModbusAIOEmulator:
    """A running Modbus server on 127.0.0.1 (``.url``) backed by ``world``."""
    from drivers.modbus_aio import DRIVER

    return ModbusAIOEmulator(DRIVER.complete(settings), world)
