"""Keyence LK-G laser displacement sensors (LK-G3000 / LK-G5000 controllers) over RS-232C.

The protocol, from the LK-G Series user manual (chapter 5 "RS-232C", LK-G-M-NO5-E) and, for the
LK-G5000, from independent clients of it (docs/decisions/0098); ``tests/drivers/test_keyence_lk.py``
shows the bytes and ``tests/drivers/test_keyence_lk_conformance.py`` walks the command lists:

* 115200 (or 57600/38400/19200/9600) bit/s, 8 data bits, no parity, 1 stop bit, no flow control;
  every command and reply ends in CR. Send the next command only after the reply to the last one.
* measured value output: ``M0`` (OUT1 and OUT2), ``M1`` / ``M2`` (one OUT) on the LK-G3000; ``MS,<nn>``
  (OUT nn, two digits) on the LK-G5000. The reply repeats the command as its header:
  ``M1,+01.2345``, ``M0,+01.2345,-00.0120``, ``MS,01,+01.2345``.
* a measured value is 8 characters: a sign, then 7 characters right-aligned with the decimal point
  where the display has it (``+01.2345``, ``-00.0120``, ``+1234.56``). ``+FFFFFFF`` / ``-FFFFFFF`` mean
  over range (positive / negative), ``XXXXXXXX`` no valid value (alarm, e.g. too little light).
* an error reply is ``ER,<command>,<code>``. LK-G3000 (manual 5-5): 00 command error, 01 status
  error, 20 command length error, 21 parameter count error, 22 invalid parameter error, 88 timeout
  error, 99 other errors. LK-G5000 (two clients' tables; its manual was not at hand): 50, 51, 60,
  61, 62 in the same order, 88, 99.
* measuring needs general mode; ``Q0`` enters communication mode (settings), ``R0`` returns. ``R0``
  in general mode is refused with a status error, so on open the driver sends ``R0`` and takes
  either answer: a controller left in communication mode (by a set-up tool, a crashed script)
  measures again. The mode change may take 600 ms plus 750 ms per head expansion unit (a client's
  note, unverified), hence its own timeout ``mode_timeout_s``.

The displayed unit is set on the controller (mm for most heads); ``unit`` tells the driver which, and
``read()`` returns um. Over range and alarm values come back as NaN, so a sensor interlock trips on
them; :attr:`KeyenceLK.last_status` says which it was.
"""

from __future__ import annotations

import math
import re
from typing import Any

from drivers.base import (
    DEFAULT_BACKOFF_S,
    DeviceError,
    DriverSpec,
    Lazy,
    Setting,
    retry,
)
from drivers.serial_link import SerialLink, short

_MEANINGS = ("command error (unknown command)",
             "status error (not allowed in the current state, e.g. communication/set-up mode: send R0)",
             "command length error", "parameter count error", "invalid parameter error",
             "timeout error", "other error")
# protocol -> error code -> meaning
ERROR_CODES: dict[str, dict[str, str]] = {
    "M": dict(zip(("00", "01", "20", "21", "22", "88", "99"), _MEANINGS)),  # LK-G3000, manual 5-5
    "MS": dict(zip(("50", "51", "60", "61", "62", "88", "99"), _MEANINGS)),  # LK-G5000, clients' tables
}
STATUS_ERROR = {"M": "01", "MS": "51"}
UM_PER_UNIT = {"mm": 1000.0, "um": 1.0}
VALUE = re.compile(r"^[+-](?=[0-9.]*[0-9])[0-9.]{7}$")  # sign + 7 characters, digits and one point
OVER_RANGE = {"+FFFFFFF": "over_range_positive", "-FFFFFFF": "over_range_negative"}
ALARM = "XXXXXXXX"


class Refused(DeviceError):
    """The controller answered ``ER,<command>,<code>``."""

    def __init__(self, device: str, message: str, code: str):
        super().__init__(device, message)
        self.code = code


def parse_measured_value(field: str) -> tuple[float, str]:
    """(value in the controller's unit or NaN, status) of one 8-character measured value field."""
    if field in OVER_RANGE:
        return math.nan, OVER_RANGE[field]
    if field == ALARM:
        return math.nan, "alarm"
    if not VALUE.match(field) or field.count(".") > 1:
        raise ValueError(f"not a measured value: {field!r}")
    return float(field), "ok"


class KeyenceLK:
    """One OUT of an LK-G controller, read as a displacement in um."""

    def __init__(self, settings: dict[str, Any]):
        self.settings = settings
        self.url = str(settings["url"])
        self.out = int(settings["out"])
        self.protocol = str(settings["protocol"])
        self.unit = str(settings["unit"])
        self.channel = str(settings["channel"])
        self.name = str(settings.get("name") or f"keyence-lk ({self.url})")
        self.attempts = int(settings["attempts"])
        self.backoff_s = float(settings["backoff_s"])
        if self.unit not in UM_PER_UNIT:
            raise DeviceError(self.name, f"unit {self.unit!r} is not one of {', '.join(UM_PER_UNIT)}")
        if self.protocol == "M":  # LK-G3000: M1 / M2
            if self.out not in (1, 2):
                raise DeviceError(self.name, f"out {self.out} does not exist on an LK-G3000 (1 or 2)")
            self.command_text = f"M{self.out}"
            self.header = [self.command_text]
        elif self.protocol == "MS":  # LK-G5000: MS,01 .. MS,12
            if not 1 <= self.out <= 12:
                raise DeviceError(self.name, f"out {self.out} does not exist on an LK-G5000 (1..12)")
            self.command_text = f"MS,{self.out:02d}"
            self.header = ["MS", f"{self.out:02d}"]
        else:
            raise DeviceError(self.name, f"protocol {self.protocol!r} is not 'M' (LK-G3000) or 'MS' (LK-G5000)")
        self.error_codes = ERROR_CODES[self.protocol]
        self.last_status = "none"
        self.link = SerialLink(self.url, device=self.name, baud=int(settings["baud"]),
                               timeout_s=float(settings["timeout_s"]), eol=b"\r")
        if settings["general_mode_on_open"]:
            try:
                self.general_mode(float(settings["mode_timeout_s"]))
            except BaseException:
                self.link.close()
                raise

    def general_mode(self, timeout_s: float) -> None:
        """Leave communication mode if the controller is in it (``R0``; in general mode already, the
        controller refuses it with a status error, which is as good)."""
        try:
            fields = self.transact("R0", timeout_s=timeout_s)
        except Refused as exc:
            if exc.code != STATUS_ERROR[self.protocol]:
                raise
            return
        if fields != ["R0"]:
            raise DeviceError(self.name, f"unexpected reply to R0: {short(','.join(fields))}")

    def transact(self, command: str, timeout_s: float | None = None) -> list[str]:
        """Send one command, return the reply's comma-separated fields; ER replies -> DeviceError."""

        def attempt() -> list[str]:
            self.link.discard_input()  # a late reply to a timed-out command must not answer this one
            self.link.write(command.encode("ascii") + b"\r")
            raw = self.link.read_line(command, timeout_s)
            try:
                text = raw.decode("ascii")
            except UnicodeDecodeError:
                raise DeviceError(self.name, f"garbled reply to {command}: {short(raw)}") from None
            fields = text.split(",")
            if fields[0] == "ER":
                code = fields[2] if len(fields) > 2 else "?"
                raise Refused(self.name, f"{command} refused: ER code {code}: "
                                         f"{self.error_codes.get(code, 'unknown error code')} (reply {text!r})", code)
            return fields

        return retry(attempt, device=self.name, what=command, attempts=self.attempts, backoff_s=self.backoff_s)

    def read_raw(self) -> tuple[float, str]:
        """(value in the controller's unit or NaN, status) of the configured OUT."""
        fields = self.transact(self.command_text)
        head = fields[: len(self.header)]
        if head != self.header or len(fields) != len(self.header) + 1:
            raise DeviceError(self.name, f"unexpected reply to {self.command_text}: {short(','.join(fields))}")
        try:
            return parse_measured_value(fields[-1])
        except ValueError:
            raise DeviceError(self.name, f"unexpected reply to {self.command_text}: {short(','.join(fields))}") from None

    def read(self) -> dict[str, float]:
        """The displacement in um (NaN when over range or in alarm; see ``last_status``)."""
        value, self.last_status = self.read_raw()
        return {self.channel: value * UM_PER_UNIT[self.unit]}

    def identity(self) -> str:
        # The LK-G command set has no identification query; say what was configured.
        return f"Keyence {self.settings['model']} OUT{self.out} at {self.url}"

    def capabilities(self) -> dict[str, Any]:
        return {
            "driver": "keyence-lk",
            "model": self.settings["model"],
            "out": self.out,
            "command": self.command_text,
            "channels": {self.channel: "um"},
            "controller_unit": self.unit,
            "um_per_controller_unit": UM_PER_UNIT[self.unit],
            "out_of_range": "NaN (+FFFFFFF / -FFFFFFF over range, XXXXXXXX alarm); last_status tells which",
        }

    def close(self) -> None:
        self.link.close()

    def __enter__(self) -> KeyenceLK:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_device(settings: dict[str, Any]) -> KeyenceLK:
    return KeyenceLK(DRIVER.complete(settings))


SETTINGS = (
    Setting("url", str, required=True, doc="serial port or pyserial URL: /dev/ttyUSB0, a pty path, socket://host:port"),
    Setting("name", str, doc="device name in messages (default: keyence-lk (url))"),
    Setting("out", int, default=1, doc="OUT number to read (LK-G3000: 1 or 2; LK-G5000: 1..12)"),
    Setting("protocol", str, default="M", doc="'M' (LK-G3000: M1/M2) or 'MS' (LK-G5000: MS,01)"),
    Setting("unit", str, default="mm", doc="unit the controller displays: 'mm' or 'um'"),
    Setting("channel", str, default="output", doc="channel name read() returns"),
    Setting("model", str, default="LK-G3000", doc="controller model, for identity()"),
    Setting("baud", int, default=115200, doc="bit/s as set on the controller (115200, 57600, 38400, 19200, 9600)"),
    Setting("timeout_s", float, default=0.2, doc="s to wait for a reply"),
    Setting("attempts", int, default=3, doc="tries per command on timeouts"),
    Setting("backoff_s", float, default=DEFAULT_BACKOFF_S, doc="s before the first retry (doubles each retry)"),
    Setting("general_mode_on_open", bool, default=True,
            doc="send R0 on open, so a controller left in communication mode measures again"),
    Setting("mode_timeout_s", float, default=3.0, doc="s to wait for the reply to R0 (a mode change is slow)"),
    Setting("decimals", int, default=4, doc="emulator: digits after the decimal point (display setting)"),
)

DRIVER = DriverSpec(
    name="keyence-lk",
    roles=("sensor",),
    settings=SETTINGS,
    open=open_device,
    emulator=Lazy("drivers.emulators.keyence_lk:start_emulator"),
    description="Keyence LK-G laser displacement sensor (LK-G3000/LK-G5000) over RS-232C",
    transports=("serial", "socket://"),
)
