"""Emulated Keyence LK-G controller on a pty: the LK-G3000 (``protocol = "M"``) or the LK-G5000 (``"MS"``).

What the emulated controller answers, and where each fact comes from (docs/decisions/0098; the
conformance test ``tests/drivers/test_keyence_lk_conformance.py`` walks both command lists):

* Format (LK-G Series user manual LK-G-M-NO5-E, 5-5 "Outline of the command format" and 5-6
  "Measurement value format"): CR ends every command and reply; upper and lower case are accepted;
  the reply repeats the main command (and identifiers) as its header; a refusal is
  ``ER,<main command>,<code>``; a measured value is a sign and 7 right-aligned characters,
  ``+FFFFFFF`` / ``-FFFFFFF`` over range, ``XXXXXXXX`` no valid value.
* Error codes: LK-G3000 00 command, 01 status, 20 length, 21 parameter count, 22 invalid parameter,
  88 timeout, 99 other (manual 5-5). LK-G5000 50, 51, 60, 61, 62, 88, 99 in the same order: from two
  independent clients' tables (theion-batteries/firm_keyence_rs232, a C# KeyenceSILib client); the
  LK-G5000 manual itself was not among the stored pages.
* Modes: general (measure) mode takes the measurement control commands, communication mode (``Q0``)
  only ``SW``/``SR`` settings and ``R0``; the measurement stops in communication mode. ``Q0`` in
  communication mode and ``R0`` in general mode are refused with a status error: three clients
  expect that (LSST's ts5_dlog ignores ER only for Q0/R0, a Japanese LK-G5000 client sends R0 "even
  if it errs", ISIS's keylkg emulator).
* LK-G3000 mnemonics, from DESY cmstkmodlab's LK-G3000 driver (replies it checks) and ISIS's keylkg
  IOC emulator: ``M0``/``M1``/``M2``; ``V<n>`` auto-zero ON and ``W<n>`` OFF (reply ``V<n>``/``W<n>``;
  n = 0 both OUTs); ``VR,<n>`` reset (``VR``); ``KL,<0|1>`` panel lock (``KL``); ``PW,<n>`` program
  change (``PW``), ``PR`` program check (``PR,<n>``); ``DO,<n>``/``DQ,<n>`` statistics (reply format
  unknown: refused as not executable); ``AS``/``AP``/``AQ`` storage start/stop/initialize, ``AO,<n>``
  output, ``AN`` status; ``SW,CA,<0-5>`` sampling cycle 20/50/100/200/500/1000 us (``SW,CA``) and
  ``SR,CA``; ``SW,HA``/``HB``/``HE``/``OC`` exist but are not modelled (refused as not executable).
  The LK-G3000's timing ON/OFF and light waveform mnemonics were not found: unknown here (``00``).
* LK-G5000 mnemonics, from clients and Keyence's LkIF2.h command order: ``MS,<nn>`` (OUT 01-12),
  ``MM,<12 x 0/1, OUT1 first>``, ``MA``; ``VS,<nn>``/``WS,<nn>`` auto-zero ON/OFF single (a Japanese
  client); ``KL``, ``PW``/``PR``; ``AS``/``AP``/``AQ``/``AO,<nn>``/``AN`` (LSST, C#, Japanese
  clients); ``SW,CA,<0-8>`` sampling 2.55/5/10/20/50/100/200/500/1000 us, ``SW,CF,<7 digits>,<2
  digits>`` data storage count and cycle. Inferred, not verified: ``VM``/``VA``/``WM``/``WA`` (the
  multiple/all forms by the ``MS``/``MM``/``MA`` pattern), timing ``TS``/``TM``/``TA`` ON and
  ``US``/``UM``/``UA`` OFF, reset ``RS``/``RM``/``RA``, and ``OI`` as the "minimum display unit"
  setting id (its place in LkIF2.h's order between ``OH`` and ``OJ``; codes 0-6 = 0.01/0.001/0.0001/
  0.00001 mm, 0.1/0.01/0.001 um from LkIF2.h).

The plant behind it: OUT1 measures ``world.read("output")`` (um), OUT2 and up ``world.read("output2")``
when the world has it, else OUT1's value. Auto-zero ON makes the present value the zero of that OUT
until auto-zero OFF; timing ON holds the present value until timing OFF; reset re-takes a held value
(a live OUT is unchanged). Data storage records one value per active OUT every serving tick (about
20 ms, not the sampling cycle) up to the configured count, then stops by itself. The LK-G3000 has 2
OUTs; the emulated LK-G5000 reports max(2, ``out``) OUTs in ``MA``/``AN``.

Fault injection beyond the base class: :meth:`KeyenceLKEmulator.error_next` (an ``ER`` reply with a
chosen code), :meth:`KeyenceLKEmulator.force` (over range or alarm instead of the world's value).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NoReturn

from drivers.base import World
from drivers.emulators.line_server import LineServer
from drivers.keyence_lk import UM_PER_UNIT

Handler = Callable[[list[str]], str]


@dataclass(frozen=True)
class Model:
    name: str
    outs: int  # OUT numbers a command may name
    codes: dict[str, str]  # kind of refusal -> error code
    sampling_us: tuple[float, ...]  # SW,CA code -> sampling cycle (us)
    default_sampling: int


LK_G3000 = Model("LK-G3000", 2, {"command": "00", "status": "01", "length": "20", "count": "21",
                                 "parameter": "22", "timeout": "88", "other": "99"},
                 (20, 50, 100, 200, 500, 1000), 0)
LK_G5000 = Model("LK-G5000", 12, {"command": "50", "status": "51", "length": "60", "count": "61",
                                  "parameter": "62", "timeout": "88", "other": "99"},
                 (2.55, 5, 10, 20, 50, 100, 200, 500, 1000), 5)
# LkIF2.h "Set Minimum Display Unit": code -> (unit, digits after the point)
DISPLAY_UNITS = (("mm", 2), ("mm", 3), ("mm", 4), ("mm", 5), ("um", 1), ("um", 2), ("um", 3))
# Setting ids clients use that this emulator does not model: refused as not executable (status error).
UNMODELLED_SETTINGS = {
    LK_G3000.name: {"HA", "HB", "HE", "OC", "OF"},
    LK_G5000.name: {"LM", "HA", "HB", "HC", "HE", "HF", "HG", "HH", "HI", "HJ", "OA", "OB", "OC", "OD",
                    "OE", "OF", "OG", "OH", "OJ", "OK", "CB", "CD", "CE", "CG", "CH", "EE", "EF", "EG", "EH"},
}
STORAGE_MAX = 1_200_000  # LK-G5000 data storage points (the C# client's limit)


class Refused(Exception):
    """A command the controller refuses; ``kind`` is a key of :attr:`Model.codes`."""

    def __init__(self, kind: str):
        super().__init__(kind)
        self.kind = kind


def count(fields: list[str], n: int) -> None:
    if len(fields) != n:
        raise Refused("count")


def choice(field: str, n: int) -> int:
    """A decimal parameter in 0..n-1."""
    if not field.isdigit() or not 0 <= int(field) < n:
        raise Refused("parameter")
    return int(field)


class KeyenceLKEmulator(LineServer):
    eol = b"\r"
    name = "keyence-lk"

    def __init__(self, settings: dict[str, Any], world: World):
        super().__init__()
        self.world = world
        self.model = LK_G5000 if str(settings["protocol"]).upper() == "MS" else LK_G3000
        self.unit = str(settings["unit"])
        self.decimals = int(settings["decimals"])
        self.active_outs = 2 if self.model is LK_G3000 else max(2, min(12, int(settings["out"])))
        self.general_mode = True
        self.zero_um: dict[int, float] = {}  # auto-zero ON: the raw value that reads as zero
        self.held_um: dict[int, float] = {}  # timing ON: the raw value held
        self.panel_locked = False
        self.program = 0
        self.sampling = self.model.default_sampling
        self.storage_points = 1000
        self.storage_cycle = 0
        self.storing = False
        self.stored: dict[int, list[str]] = {n: [] for n in range(1, self.active_outs + 1)}
        self._error_next: str | None = None
        self._forced: str | None = None
        self._forced_count = 0
        self._commands = self._lk_g5000() if self.model is LK_G5000 else self._lk_g3000()

    # -- fault injection ------------------------------------------------------------------------------
    def error_next(self, code: str = "00") -> None:
        """The next command is answered ``ER,<command>,<code>``."""
        self._error_next = str(code)

    def force(self, value: str = "+FFFFFFF", count: int = 1) -> None:
        """The next ``count`` measured values read ``value`` (``+FFFFFFF``, ``-FFFFFFF``, ``XXXXXXXX``)."""
        self._forced, self._forced_count = value, int(count)

    # -- the plant and the measured value format ----------------------------------------------------------
    def format_value(self, um: float) -> str:
        if self._forced_count > 0:
            self._forced_count -= 1
            return str(self._forced)
        if not math.isfinite(um):
            return "XXXXXXXX"
        value = um / UM_PER_UNIT[self.unit]
        digits = f"{abs(value):07.{self.decimals}f}"
        if len(digits) > 7:  # does not fit the display: over range, signed
            return ("+" if value >= 0 else "-") + "FFFFFFF"
        return ("-" if value < 0 and float(digits) != 0 else "+") + digits

    def raw_um(self, n: int) -> float:
        """What OUT n sees before auto-zero (um): the world, or the value timing holds."""
        if n in self.held_um:
            return self.held_um[n]
        try:
            return float(self.world.read("output" if n == 1 else "output2"))
        except (KeyError, ValueError):
            return float(self.world.read("output"))

    def value(self, n: int) -> str:
        return self.format_value(self.raw_um(n) - self.zero_um.get(n, 0.0))

    # -- serving --------------------------------------------------------------------------------------
    def handle(self, command: bytes) -> bytes | None:
        text = command.decode("ascii", "replace").strip().upper()  # upper and lower case both accepted
        if not text:
            return None
        head, *params = text.split(",")
        if self._error_next is not None:
            code, self._error_next = self._error_next, None
            return f"ER,{head},{code}\r".encode()
        try:
            reply = self._execute(head, params)
        except Refused as refusal:
            reply = f"ER,{head},{self.model.codes[refusal.kind]}"
        return (reply + "\r").encode("ascii")

    def _execute(self, head: str, params: list[str]) -> str:
        if self.model is LK_G3000 and head[:1] == "M" and head[1:].isdigit() and head not in self._commands:
            raise Refused("parameter")  # M3, M9: the OUT digit is the parameter of M
        if head not in self._commands:
            raise Refused("command")
        handler, mode = self._commands[head]
        if mode != ("general" if self.general_mode else "communication"):
            raise Refused("status")
        return handler(params)

    def idle(self) -> None:
        if not (self.storing and self.general_mode):
            return
        for n, data in self.stored.items():
            data.append(self.value(n))
        if len(self.stored[1]) >= self.storage_points:
            self.storing = False  # full: the controller stops storing by itself

    # -- command tables -------------------------------------------------------------------------------
    def _common(self) -> dict[str, tuple[Handler, str]]:
        return {
            "Q0": (self._q0, "general"),
            "R0": (self._r0, "communication"),
            "KL": (self._panel_lock, "general"),
            "PW": (self._program_change, "general"),
            "PR": (self._program_check, "general"),
            "AS": (self._storage("AS", start=True), "general"),
            "AP": (self._storage("AP", start=False), "general"),
            "AQ": (self._storage_init, "general"),
            "AN": (self._storage_status, "general"),
            "AO": (self._storage_output, "general"),
            "SW": (self._setting_write, "communication"),
            "SR": (self._setting_read, "communication"),
        }

    def _lk_g3000(self) -> dict[str, tuple[Handler, str]]:
        table = self._common()
        for n in (0, 1, 2):
            table[f"M{n}"] = (self._g3000_measure(n), "general")
            table[f"V{n}"] = (self._g3000_zero(n, on=True), "general")
            table[f"W{n}"] = (self._g3000_zero(n, on=False), "general")
        table["VR"] = (self._g3000_reset, "general")
        table["DO"] = (self._not_executable, "general")  # statistics output: reply format unknown
        table["DQ"] = (self._not_executable, "general")  # statistics clear
        return table

    def _lk_g5000(self) -> dict[str, tuple[Handler, str]]:
        table = self._common()
        table["MS"] = (self._ms, "general")
        table["MM"] = (self._mm, "general")
        table["MA"] = (self._ma, "general")
        for letter, action in (("T", self._timing_on), ("U", self._timing_off), ("V", self._zero_on),
                               ("W", self._zero_off), ("R", self._reset)):
            table[letter + "S"] = (self._single(letter + "S", action), "general")
            table[letter + "M"] = (self._multiple(letter + "M", action), "general")
            table[letter + "A"] = (self._all(letter + "A", action), "general")
        return table

    # -- mode change ----------------------------------------------------------------------------------
    def _q0(self, params: list[str]) -> str:
        count(params, 0)
        self.general_mode = False
        self.storing = False  # the measurement stops in communication mode
        return "Q0"

    def _r0(self, params: list[str]) -> str:
        count(params, 0)
        self.general_mode = True
        return "R0"

    # -- measurement control: LK-G3000 --------------------------------------------------------------------
    def _g3000_outs(self, n: int) -> list[int]:
        return [1, 2] if n == 0 else [n]

    def _g3000_measure(self, n: int) -> Handler:
        def measure(params: list[str]) -> str:
            count(params, 0)
            return ",".join([f"M{n}", *(self.value(k) for k in self._g3000_outs(n))])
        return measure

    def _g3000_zero(self, n: int, *, on: bool) -> Handler:
        def zero(params: list[str]) -> str:
            count(params, 0)
            for k in self._g3000_outs(n):
                (self._zero_on if on else self._zero_off)(k)
            return f"{'V' if on else 'W'}{n}"
        return zero

    def _g3000_reset(self, params: list[str]) -> str:
        count(params, 1)
        for k in self._g3000_outs(choice(params[0], 3)):
            self._reset(k)
        return "VR"

    # -- measurement control: LK-G5000 ----------------------------------------------------------------------
    def _out(self, field: str) -> int:
        """A two-digit OUT number 01..12."""
        if len(field) != 2 or not field.isdigit() or not 1 <= int(field) <= self.model.outs:
            raise Refused("parameter")
        return int(field)

    def _bits(self, field: str) -> list[int]:
        """12 characters 0/1, OUT1 first; at least one OUT."""
        if len(field) != 12 or set(field) - {"0", "1"} or "1" not in field:
            raise Refused("parameter")
        return [k + 1 for k, bit in enumerate(field) if bit == "1"]

    def _ms(self, params: list[str]) -> str:
        count(params, 1)
        return f"MS,{params[0]},{self.value(self._out(params[0]))}"

    def _mm(self, params: list[str]) -> str:
        count(params, 1)
        return ",".join(["MM", params[0], *(self.value(k) for k in self._bits(params[0]))])

    def _ma(self, params: list[str]) -> str:
        count(params, 0)
        return ",".join(["MA", *(self.value(k) for k in range(1, self.active_outs + 1))])

    def _single(self, head: str, action: Callable[[int], None]) -> Handler:
        def single(params: list[str]) -> str:
            count(params, 1)
            action(self._out(params[0]))
            return head
        return single

    def _multiple(self, head: str, action: Callable[[int], None]) -> Handler:
        def multiple(params: list[str]) -> str:
            count(params, 1)
            for k in self._bits(params[0]):
                action(k)
            return head
        return multiple

    def _all(self, head: str, action: Callable[[int], None]) -> Handler:
        def every(params: list[str]) -> str:
            count(params, 0)
            for k in range(1, self.active_outs + 1):
                action(k)
            return head
        return every

    # -- the actions on one OUT ---------------------------------------------------------------------------
    def _zero_on(self, n: int) -> None:
        self.zero_um.pop(n, None)
        self.zero_um[n] = self.raw_um(n)

    def _zero_off(self, n: int) -> None:
        self.zero_um.pop(n, None)

    def _timing_on(self, n: int) -> None:
        self.held_um.pop(n, None)
        self.held_um[n] = self.raw_um(n)

    def _timing_off(self, n: int) -> None:
        self.held_um.pop(n, None)

    def _reset(self, n: int) -> None:
        if n in self.held_um:
            self._timing_on(n)  # the hold is taken again at the present value

    # -- panel lock, program, statistics ------------------------------------------------------------------
    def _panel_lock(self, params: list[str]) -> str:
        count(params, 1)
        self.panel_locked = bool(choice(params[0], 2))
        return "KL"

    def _program_change(self, params: list[str]) -> str:
        count(params, 1)
        self.program = choice(params[0], 8)
        return "PW"

    def _program_check(self, params: list[str]) -> str:
        count(params, 0)
        return f"PR,{self.program}"

    def _not_executable(self, params: list[str]) -> str:
        raise Refused("status")

    # -- data storage ---------------------------------------------------------------------------------
    def _storage(self, head: str, *, start: bool) -> Handler:
        def storage(params: list[str]) -> str:
            count(params, 0)
            self.storing = start
            return head
        return storage

    def _storage_init(self, params: list[str]) -> str:
        count(params, 0)
        self.storing = False
        for data in self.stored.values():
            data.clear()
        return "AQ"

    def _storage_status(self, params: list[str]) -> str:
        count(params, 0)
        counts = (f"{len(data):07d}" for data in self.stored.values())
        return ",".join(["AN", "1" if self.storing else "0", *counts])

    def _storage_output(self, params: list[str]) -> str:
        count(params, 1)
        n = choice(params[0], 3) if self.model is LK_G3000 else self._out(params[0])
        if n not in self.stored:
            raise Refused("parameter")
        return ",".join(["AO", *self.stored[n]])

    # -- settings (communication mode) ------------------------------------------------------------------
    def _setting_write(self, params: list[str]) -> str:
        if not params:
            raise Refused("count")
        ident, values = params[0], params[1:]
        if ident == "CA":
            count(values, 1)
            self.sampling = choice(values[0], len(self.model.sampling_us))
        elif ident == "CF" and self.model is LK_G5000:
            count(values, 2)
            if len(values[0]) != 7 or not values[0].isdigit() or not 1 <= int(values[0]) <= STORAGE_MAX:
                raise Refused("parameter")
            self.storage_points, self.storage_cycle = int(values[0]), choice(values[1], 11)
        elif ident == "OI" and self.model is LK_G5000:
            count(values, 2)
            self._out(values[0])
            self.unit, self.decimals = DISPLAY_UNITS[choice(values[1], len(DISPLAY_UNITS))]
        else:
            self._unmodelled(ident)
        return f"SW,{ident}"

    def _setting_read(self, params: list[str]) -> str:
        if not params:
            raise Refused("count")
        ident, values = params[0], params[1:]
        if ident == "CA":
            count(values, 0)
            return f"SR,CA,{self.sampling}"
        if ident == "CF" and self.model is LK_G5000:
            count(values, 0)
            return f"SR,CF,{self.storage_points:07d},{self.storage_cycle:02d}"
        if ident == "OI" and self.model is LK_G5000:
            count(values, 1)
            self._out(values[0])
            if (self.unit, self.decimals) not in DISPLAY_UNITS:
                raise Refused("other")  # a display the LK-G5000 cannot show
            return f"SR,OI,{values[0]},{DISPLAY_UNITS.index((self.unit, self.decimals))}"
        self._unmodelled(ident)

    def _unmodelled(self, ident: str) -> NoReturn:
        raise Refused("status" if ident in UNMODELLED_SETTINGS[self.model.name] else "parameter")


def start_emulator(settings: dict[str, Any], world: World) -> KeyenceLKEmulator:
    """A running emulated LK-G controller on a pty (``.url``)."""
    from drivers.keyence_lk import DRIVER

    return KeyenceLKEmulator(DRIVER.complete(settings), world).start()
