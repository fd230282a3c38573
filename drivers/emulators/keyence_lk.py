"""Emulated Keyence LK-G controller (LK-G3000 ``M0/M1/M2``, LK-G5000 ``MS,nn``) on a pty.

OUT1 (and every OUT of ``MS``) measures ``world.read("output")`` (um), shown in the configured unit
(mm by default) with ``decimals`` digits after the point, in the 8-character measured value format;
a value that does not fit the 7 characters is over range (``+FFFFFFF`` / ``-FFFFFFF``), a non-finite
one is an alarm (``XXXXXXXX``). OUT2 of ``M0`` / ``M2`` reads ``world.read("output2")`` when the
world has it, else repeats OUT1.

``Q0`` enters communication (set-up) mode, ``R0`` returns to measure mode; measured value commands in
set-up mode answer ``ER,<cmd>,01`` (status error), unknown commands ``ER,<cmd>,00``.

Fault injection beyond the base class: :meth:`KeyenceLKEmulator.error_next` (an ``ER`` reply with a
chosen code), :meth:`KeyenceLKEmulator.force` (over range or alarm instead of the world's value).
"""

from __future__ import annotations

import math
from typing import Any

from drivers.base import World
from drivers.emulators.line_server import LineServer
from drivers.keyence_lk import UM_PER_UNIT


class KeyenceLKEmulator(LineServer):
    eol = b"\r"
    name = "keyence-lk"

    def __init__(self, settings: dict[str, Any], world: World):
        super().__init__()
        self.world = world
        self.um_per_unit = UM_PER_UNIT[str(settings["unit"])]
        self.decimals = int(settings["decimals"])
        self.measure_mode = True
        self._error_next: str | None = None
        self._forced: str | None = None
        self._forced_count = 0

    # -- fault injection ------------------------------------------------------------------------------
    def error_next(self, code: str = "00") -> None:
        """The next command is answered ``ER,<command>,<code>``."""
        self._error_next = str(code)

    def force(self, value: str = "+FFFFFFF", count: int = 1) -> None:
        """The next ``count`` measured values read ``value`` (``+FFFFFFF``, ``-FFFFFFF``, ``XXXXXXXX``)."""
        self._forced, self._forced_count = value, int(count)

    # -- the measured value format ----------------------------------------------------------------------
    def format_value(self, um: float) -> str:
        if self._forced_count > 0:
            self._forced_count -= 1
            return str(self._forced)
        if not math.isfinite(um):
            return "XXXXXXXX"
        value = um / self.um_per_unit
        digits = f"{abs(value):0{7}.{self.decimals}f}"
        if len(digits) > 7:  # does not fit the display: over range, signed
            return ("+" if value >= 0 else "-") + "FFFFFFF"
        return ("-" if value < 0 and float(digits) != 0 else "+") + digits

    def _out(self, n: int) -> str:
        channel = "output" if n == 1 else "output2"
        try:
            um = float(self.world.read(channel))
        except (KeyError, ValueError):
            um = float(self.world.read("output"))
        return self.format_value(um)

    # -- commands ---------------------------------------------------------------------------------------
    def handle(self, command: bytes) -> bytes | None:
        text = command.decode("ascii", "replace").strip().upper()  # upper and lower case both accepted
        if not text:
            return None
        head = text.split(",")[0]
        if self._error_next is not None:
            code, self._error_next = self._error_next, None
            return f"ER,{head},{code}\r".encode()
        reply = self._execute(text, head)
        return (reply + "\r").encode("ascii")

    def _execute(self, text: str, head: str) -> str:
        fields = text.split(",")
        if head in ("M0", "M1", "M2", "MS") and not self.measure_mode:
            return f"ER,{head},01"
        if head == "M0":
            return f"M0,{self._out(1)},{self._out(2)}" if len(fields) == 1 else f"ER,{head},21"
        if head in ("M1", "M2"):
            return f"{head},{self._out(int(head[1]))}" if len(fields) == 1 else f"ER,{head},21"
        if head == "MS":
            if len(fields) != 2:
                return f"ER,{head},21"
            if not (fields[1].isdigit() and len(fields[1]) == 2 and 1 <= int(fields[1]) <= 12):
                return f"ER,{head},22"
            return f"MS,{fields[1]},{self._out(1 if fields[1] == '01' else 2)}"
        if head == "Q0":
            self.measure_mode = False
            return "Q0"
        if head == "R0":
            self.measure_mode = True
            return "R0"
        if head.startswith("M") and head[1:].isdigit():
            return f"ER,{head},22"  # M3, M9...: no such OUT
        return f"ER,{head},00"


def start_emulator(settings: dict[str, Any], world: World) -> KeyenceLKEmulator:
    """A running emulated LK-G controller on a pty (``.url``)."""
    from drivers.keyence_lk import DRIVER

    return KeyenceLKEmulator(DRIVER.complete(settings), world).start()
