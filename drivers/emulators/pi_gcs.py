"""Emulated PI GCS 2.0 piezo controller (E-709 / E-727 class) on a pty, optionally on 127.0.0.1 TCP.

What it follows, by section of the E-727 user manual (E727T0005, "GCS Commands") and the GCS 2.0
command descriptions PI's manuals share (e.g. MS249E, chapter 8):

* "GCS Syntax for Syntax Version 2.0": a command is a 3-character mnemonic (``CMD``, query ``CMD?``),
  ``*IDN?``, or a single character written ``#n`` (byte n, no LF); the mnemonic is not
  case-sensitive; arguments are separated by spaces, a line ends with LF. A reply of several lines
  ends every line but the last with a space before the LF.
* Set commands never reply. A command that cannot be executed sets the error register; ``ERR?``
  returns the code and resets it to 0 ("Error Codes": 1 parameter syntax, 2 unknown command, 5 move
  with servo off, 7 position out of limits, 10 stopped by command, 15 invalid axis identifier, 17
  parameter out of range, ...).
* A query that cannot be executed is answered by an empty line (LF) with the error register set, so
  a client that waits for the reply of every query (PI's own GCS library does) is not left to time
  out and reads the real code with the ``ERR?`` it sends next. See docs/decisions/0095.
* ``CSV?`` answers ``2.0``; ``HLP?`` lists the commands this controller knows, one per line between
  a title line and ``end of help``; ``#7`` answers the byte 0xB1 (ready); ``SPA?`` takes the
  parameter id in hexadecimal (``0x0E000200``) or decimal (``234881536``) and echoes it as sent.
* Wave generator ("Wave Generator", "WAV"): ``WAV <table> <X|&|+> <type> ...`` with the types
  ``PNT`` (points), ``SIN_P`` (one period of an inverted cosine), ``LIN`` (a line with smoothed
  start and end) and ``RAMP`` (up to a centre point and back, smoothed corners); ``X`` clears the
  table, ``&`` appends, ``+`` adds the segment to what the table holds. ``WSL``, ``WGC``, ``WTR``,
  ``WGO`` run it; ``#9`` reports the running generators.
* Data recorder: ``DRC {<table> <source> <option>}`` (several tables in one command), ``RTR``,
  ``DRT``, ``DRL?``, ``DRR?`` (a GCS array with its header), ``HDR?``, ``TNR?``.
* Closed loop: ``SVO``, ``MOV``, ``MVR``, ``ONT?``, ``TMN?``/``TMX?``, ``STP``/``HLT``/``#24``. The
  servo is modelled at the stage: the position follows the target as a critically damped second-order
  loop of bandwidth ``servo_bandwidth_hz``, in wall-clock time, so a move takes the settling time a
  stage takes and ``ONT?`` turns 1 once the position is within ``on_target_um`` of the target. A
  target outside ``travel_min_um..travel_max_um`` is refused with error 7. (A servo run through the
  world's hysteresis, as before, could not reach every target: a magnetostrictive plant's butterfly
  loop changes the sign of its gain, and the integrator wound up to the voltage limit.)

Backed by a :class:`~drivers.base.World`: ``SVA`` (servo off) -> ``world.command(volts)``, ``POS?``
(servo off) -> ``world.read("output")``, ``WGO`` -> ``world.play(points, servo_rate / WTR)`` in a
worker thread; the data recorder then holds the recorded position (option 2) and voltage (option 7)
at ``servo_rate / RTR``. Simplification: recording stops with the waveform instead of running on
until the tables are full. :meth:`PIGCSEmulator.fail_next` makes the next command fail with a chosen
code; everything the base class offers (drop, silence, garbage, disconnect) applies.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any, ClassVar

import numpy as np

from drivers.base import World
from drivers.emulators.line_server import LineServer
from drivers.pi_gcs import (
    RECORD_OPTION_POSITION,
    RECORD_OPTION_VOLTAGE,
    SERVO_UPDATE_TIME_PARAM,
)

PARAM_RECORD_MAX_POINTS = 0x16000200
PARAM_RECORD_TABLES = 0x16000300
RECORD_TABLES = 2
READY = b"\xb1\n"  # #7 "controller ready": byte 0xB1 (0xB0 = not ready), as PI's library reads it
SYNTAX_VERSION = "2.0"


class GCSFailure(Exception):
    """A command the controller refuses: sets the error register."""

    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


def _float(token: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise GCSFailure(1) from None  # parameter syntax error
    if not math.isfinite(value):
        raise GCSFailure(1)
    return value


def _int(token: str) -> int:
    """An integer argument, decimal or 0x-hexadecimal (parameter ids come in both)."""
    try:
        return int(token, 0)
    except ValueError:
        try:
            return int(token, 10)  # "010": base 0 refuses leading zeros, GCS does not
        except ValueError:
            raise GCSFailure(1) from None


def _pairs(args: list[str]) -> list[tuple[str, str]]:
    if not args or len(args) % 2:
        raise GCSFailure(1)
    return list(zip(args[::2], args[1::2]))


def smooth_ramp(n: int, speed_up_down: int) -> np.ndarray:
    """``n`` points rising from 0 to 1 (first and last included) with a trapezoidal speed profile.

    The speed grows linearly over ``speed_up_down`` points, stays constant, and falls again over the
    last ``speed_up_down`` points ("SpeedUpDown" of the LIN and RAMP wave types), so the curve starts
    and ends without a jump in speed.
    """
    if n <= 1:
        return np.ones(max(n, 0))
    t = np.arange(n, dtype=np.float64) / (n - 1)
    a = min(0.5, max(0.0, speed_up_down / (n - 1)))
    if a == 0.0:
        return t
    v = 1.0 / (1.0 - a)  # peak speed so that the area under the trapezoid is 1
    out = np.where(t < a, 0.5 * v / a * t**2,
                   np.where(t > 1.0 - a, 1.0 - 0.5 * v / a * (1.0 - t) ** 2, v * (t - 0.5 * a)))
    return out


def wave_segment(wave_type: str, params: list[float]) -> np.ndarray:
    """The points of one WAV segment of an analytic type (manual, "WAV"), or GCSFailure.

    ``SIN_P <SegLength> <Amp> <Offset> <WaveLength> <StartPoint> <CurveCenterPoint>``: one period of
    an inverted cosine, rising from Offset to Offset+Amp at CurveCenterPoint and back by WaveLength.
    ``LIN <SegLength> <Amp> <Offset> <WaveLength> <StartPoint> <SpeedUpDown>``: Offset to
    Offset+Amp over WaveLength points, then held there. ``RAMP <SegLength> <Amp> <Offset>
    <WaveLength> <StartPoint> <SpeedUpDown> <CurveCenterPoint>``: up to Offset+Amp at
    CurveCenterPoint and down to Offset by WaveLength. Before StartPoint the segment is Offset.
    """
    counts = {"SIN_P": 6, "LIN": 6, "RAMP": 7}
    if len(params) != counts[wave_type]:
        raise GCSFailure(1)
    seg_length, amp, offset, wave_length, start = params[:5]
    ints = [seg_length, wave_length, start] + ([params[5]] if wave_type != "SIN_P" else [])
    if wave_type in ("SIN_P", "RAMP"):
        ints.append(params[-1])
    if any(x != int(x) for x in ints):
        raise GCSFailure(1)
    seg, length, first = int(seg_length), int(wave_length), int(start)
    if seg < 1 or length < 1 or first < 0 or first + length > seg:
        raise GCSFailure(405)  # wave parameter out of range
    out = np.full(seg, offset, dtype=np.float64)
    if wave_type == "SIN_P":
        centre = int(params[5])
        if not 0 < centre < length:
            raise GCSFailure(405)
        i = np.arange(length, dtype=np.float64)
        up = 0.5 * (1.0 - np.cos(np.pi * i / centre))
        down = 0.5 * (1.0 + np.cos(np.pi * (i - centre) / (length - centre)))
        out[first:first + length] = offset + amp * np.where(i < centre, up, down)
    elif wave_type == "LIN":
        speed = int(params[5])
        if speed < 0 or 2 * speed > length:
            raise GCSFailure(405)
        out[first:first + length] = offset + amp * smooth_ramp(length, speed)
        out[first + length:] = offset + amp  # a line ends where it got to
    else:  # RAMP
        speed, centre = int(params[5]), int(params[6])
        if not 0 < centre < length or speed < 0 or 2 * speed > min(centre, length - centre):
            raise GCSFailure(405)
        shape = np.concatenate([smooth_ramp(centre + 1, speed)[:-1], 1.0 - smooth_ramp(length - centre + 1, speed)[:-1]])
        out[first:first + length] = offset + amp * shape
    return out


class StageServo:
    """The closed-loop stage: a critically damped second-order loop of bandwidth ``bandwidth_hz``.

    The error ``e = position - target`` obeys ``e'' + 2 w e' + w^2 e = 0`` (w = 2 pi bandwidth), so
    from ``e0`` and speed ``v0`` at the start of a move ``e(t) = (e0 + (v0 + w e0) t) exp(-w t)``:
    no overshoot (the position never leaves the span between start and target, hence never the
    travel range), settled to within ``window`` after :meth:`settling_time_s`.
    """

    def __init__(self, bandwidth_hz: float, window_um: float):
        self.w = 2.0 * math.pi * float(bandwidth_hz)
        self.window_um = float(window_um)
        self.target = 0.0
        self._t0 = time.monotonic()
        self._e0 = 0.0
        self._v0 = 0.0

    def start(self, position: float) -> None:
        """Servo switched on: the target is where the stage is (the manual: SVO sets MOV? to POS?)."""
        self.target, self._e0, self._v0, self._t0 = position, 0.0, 0.0, time.monotonic()

    def state(self, now: float | None = None) -> tuple[float, float]:
        """Position (um) and speed (um/s) now."""
        t = max(0.0, (time.monotonic() if now is None else now) - self._t0)
        decay = math.exp(-self.w * t)
        a = self._v0 + self.w * self._e0
        e = (self._e0 + a * t) * decay
        v = (self._v0 - self.w * a * t) * decay
        return self.target + e, v

    def move(self, target: float) -> None:
        now = time.monotonic()
        position, speed = self.state(now)
        self.target, self._e0, self._v0, self._t0 = float(target), position - float(target), speed, now

    def halt(self) -> None:
        """Stop where the stage is now (STP, HLT, #24)."""
        position, _ = self.state()
        self.start(position)

    def on_target(self) -> bool:
        position, _ = self.state()
        return abs(position - self.target) <= self.window_um

    def settling_time_s(self, step_um: float) -> float:
        """Time a move of ``step_um`` from rest takes to stay within the on-target window."""
        ratio = self.window_um / max(abs(step_um), 1e-300)
        if ratio >= 1.0:
            return 0.0
        x = 1.0  # solve (1 + x) exp(-x) = ratio for x = w t by Newton from the right of the maximum
        for _ in range(100):
            f = (1.0 + x) * math.exp(-x) - ratio
            x -= f / (-x * math.exp(-x))
        return x / self.w


# The commands of the E-727 the manual lists ("Command Overview"), with what HLP? says of each. The
# ones this emulator implements are in PIGCSEmulator.COMMANDS; HLP? lists only those.
HELP: dict[str, str] = {
    "#5": "Request Motion Status", "#7": "Request Controller Ready Status",
    "#9": "Get Wave Generator Status", "#24": "Stop All Axes", "*IDN?": "Get Device Identification",
    "CSV?": "Get Current Syntax Version", "DRC": "{<RecTableID> <Source> <RecOption>} Set Data Recorder Configuration",
    "DRC?": "[{<RecTableID>}] Get Data Recorder Configuration", "DRL?": "[{<RecTableID>}] Get Number Of Recorded Points",
    "DRR?": "[<StartPoint> [<NumberOfPoints> [{<RecTableID>}]]] Get Recorded Data Values",
    "DRT": "<RecTableID> <TriggerSource> <Value> Set Data Recorder Trigger Source",
    "DRT?": "[{<RecTableID>}] Get Data Recorder Trigger Source", "ERR?": "Get Error Number",
    "HDR?": "Get All Data Recorder Options", "HLP?": "Get List Of Available Commands",
    "HLT": "[{<AxisID>}] Halt Motion Smoothly", "MOV": "{<AxisID> <Position>} Set Target Position",
    "MOV?": "[{<AxisID>}] Get Target Position", "MVR": "{<AxisID> <Distance>} Set Target Relative To Current Target",
    "ONT?": "[{<AxisID>}] Get On Target State", "POS?": "[{<AxisID>}] Get Real Position",
    "RTR": "<RecordTableRate> Set Record Table Rate", "RTR?": "Get Record Table Rate",
    "SAI?": "[ALL] Get List Of Current Axis Identifiers", "SPA?": "[{<ItemID> <PamID>}] Get Volatile Memory Parameters",
    "STP": "Stop All Axes", "SVA": "{<AxisID> <Amplitude>} Set Open-Loop Axis Value",
    "SVA?": "[{<AxisID>}] Get Open-Loop Axis Value", "SVO": "{<AxisID> <ServoState>} Set Servo Mode",
    "SVO?": "[{<AxisID>}] Get Servo Mode", "SVR": "{<AxisID> <Amplitude>} Set Relative Open-Loop Axis Value",
    "TMN?": "[{<AxisID>}] Get Minimum Commandable Position", "TMX?": "[{<AxisID>}] Get Maximum Commandable Position",
    "TNR?": "Get Number Of Record Tables", "VOL?": "[{<OutputSignalChannel>}] Get Voltage Of Output Signal Channel",
    "WAV": "<WaveTableID> <AppendWave> <WaveType> <WaveTypeParameters> Set Waveform Definition",
    "WAV?": "<WaveTableID> <WaveParameterID> Get Waveform Definition", "WCL": "{<WaveTableID>} Clear Wave Table Data",
    "WGC": "{<WaveGenID> <Cycles>} Set Number Of Wave Generator Cycles",
    "WGC?": "[{<WaveGenID>}] Get Number Of Wave Generator Cycles", "WGO": "{<WaveGenID> <StartMode>} Set Wave Generator Start/Stop Mode",
    "WGO?": "[{<WaveGenID>}] Get Wave Generator Start/Stop Mode", "WSL": "{<WaveGenID> <WaveTableID>} Set Connection Of Wave Table To Wave Generator",
    "WSL?": "[{<WaveGenID>}] Get Connection Of Wave Table To Wave Generator",
    "WTR": "{<WaveGenID> <WaveTableRate> <InterpolationType>} Set Wave Generator Table Rate",
    "WTR?": "[{<WaveGenID>}] Get Wave Generator Table Rate",
}


def check_settings(settings: dict[str, Any]) -> None:
    """ValueError naming the key and value of an emulator setting that cannot work."""
    for key in ("servo_bandwidth_hz", "on_target_um", "servo_rate_hz"):
        value = float(settings[key])
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{key} = {settings[key]!r}: expected a number > 0")
    if not float(settings["travel_min_um"]) < float(settings["travel_max_um"]):
        raise ValueError(f"travel_min_um = {settings['travel_min_um']!r} must be below "
                         f"travel_max_um = {settings['travel_max_um']!r}")
    if not float(settings["min_v"]) < float(settings["max_v"]):
        raise ValueError(f"min_v = {settings['min_v']!r} must be below max_v = {settings['max_v']!r}")


class PIGCSEmulator(LineServer):
    """A running emulated controller; ``url`` (pty) and ``tcp_url`` go into a driver table."""

    name = "pi-gcs"

    def __init__(self, settings: dict[str, Any], world: World):
        check_settings(settings)  # before a pty or a port is taken
        tcp_port = settings.get("tcp_port")
        super().__init__(tcp_port=None if tcp_port is None else int(tcp_port))
        self.world = world
        self.axis = str(settings["axis"])
        self.channel = str(settings["channel"])
        self.servo_rate_hz = float(settings["servo_rate_hz"])
        self.min_v = float(settings["min_v"])
        self.max_v = float(settings["max_v"])
        self.max_wave_points = int(settings["max_wave_points"])
        self.record_points = int(settings["record_points"])
        self.realtime = bool(settings["realtime"])
        self.travel_um = (float(settings["travel_min_um"]), float(settings["travel_max_um"]))
        self.idn = (f"(c)2024 Physik Instrumente (PI) GmbH & Co. KG, {settings['model']}, "
                    "0000000000, hilbench emulator")
        self.stage = StageServo(float(settings["servo_bandwidth_hz"]), float(settings["on_target_um"]))
        # device state
        self.error = 0
        self.servo = False
        self.voltage = float(settings["rest_v"])  # last voltage applied (what VOL? reports)
        self.tables: dict[int, list[float]] = {}
        self.wsl: dict[int, int] = {}
        self.wgc: dict[int, int] = {}
        self.wtr: dict[int, tuple[int, int]] = {}
        self.wgo: dict[int, int] = {}
        self.rtr = 1
        self.drc: dict[int, tuple[str, int]] = {1: (self.axis, RECORD_OPTION_POSITION), 2: (self.channel, 0)}
        self.drt: dict[int, int] = {1: 0, 2: 0}
        self.records: dict[int, np.ndarray] = {1: np.zeros(0), 2: np.zeros(0)}
        self.commanded_v: list[float] = []  # every SVA value, for tests (was the actuator brought to rest?)
        self._fail_next: int | None = None
        self._wave: dict[str, Any] | None = None  # the running generator: thread, result, end time
        self._lock = threading.Lock()  # guards the world while a waveform plays in the worker thread

    # -- fault injection specific to GCS -----------------------------------------------------------------
    def fail_next(self, code: int) -> None:
        """The next command (set or query) fails with GCS error ``code``."""
        self._fail_next = int(code)

    @property
    def last_commanded_v(self) -> float | None:
        return self.commanded_v[-1] if self.commanded_v else None

    # -- framing: single-character commands (#5, #7, #9, #24) have no LF ----------------------------------
    def split(self, data: bytes) -> tuple[list[bytes], bytes]:
        commands: list[bytes] = []
        start = 0
        for i, byte in enumerate(data):
            if byte == 0x0A:
                commands.append(data[start:i])
                start = i + 1
            elif byte < 0x20 and byte != 0x0D and i == start:
                commands.append(data[i:i + 1])
                start = i + 1
        return commands, data[start:]

    # -- dispatch ---------------------------------------------------------------------------------------
    def handle(self, command: bytes) -> bytes | None:
        self._collect_wave()
        if len(command) == 1 and command[0] < 0x20:
            return self._single_char(command[0])
        text = command.decode("ascii", "replace").strip()
        if not text:
            return None
        mnemonic, *args = text.split()
        mnemonic = mnemonic.upper()  # "The command mnemonic is not case-sensitive" (GCS syntax 2.0)
        try:
            if self._fail_next is not None:
                code, self._fail_next = self._fail_next, None
                raise GCSFailure(code)
            handler = self.COMMANDS.get(mnemonic)
            if handler is None:
                raise GCSFailure(2)  # unknown command
            reply = handler(self, args)
        except GCSFailure as failure:
            self.error = failure.code
            # a set command stays silent; a query still ends its reply (an empty line), so the
            # client reads the error with its next ERR? instead of waiting for a timeout
            return b"\n" if mnemonic.endswith("?") else None
        if reply is None:
            return None
        lines = reply if isinstance(reply, list) else [reply]
        # GCS multi-line rule: every line but the last ends with a space before LF
        return ("".join(f"{line} \n" for line in lines[:-1]) + f"{lines[-1]}\n").encode("ascii")

    def _single_char(self, code: int) -> bytes | None:
        if code == 0x09:  # #9: wave generator status, hex bit mask
            running = self._wave is not None
            return f"{1 if running else 0:X}\n".encode()
        if code == 0x05:  # #5: motion status, hex bit mask of moving axes
            moving = self.servo and not self.stage.on_target()
            return f"{1 if moving else 0:X}\n".encode()
        if code == 0x07:  # #7: controller ready (no command is ever pending here)
            return READY
        if code == 0x18:  # #24: stop all -> generators off, motion halted, error 10
            self._stop_wave()
            self.stage.halt()
            self.error = 10
            return None
        self.error = 2
        return None

    def _axis(self, axis: str) -> None:
        if axis != self.axis:
            raise GCSFailure(15)

    def _axes(self, args: list[str]) -> None:
        for axis in args:
            self._axis(axis)

    def _busy(self) -> None:
        if self._wave is not None:
            raise GCSFailure(73)

    # -- identification, syntax, errors, parameters -------------------------------------------------------
    def _idn(self, args: list[str]) -> str:
        return self.idn

    def _csv(self, args: list[str]) -> str:
        if args:
            raise GCSFailure(1)
        return SYNTAX_VERSION

    def _hlp(self, args: list[str]) -> list[str]:
        # PI's library drops the first and the last line and takes the first word of the others
        return (["The following commands are valid:"]
                + [f"{name} {HELP[name]}" for name in self.HELP_ORDER]
                + ["end of help"])

    def _err(self, args: list[str]) -> str:
        code, self.error = self.error, 0
        return str(code)

    def _sai(self, args: list[str]) -> str:
        return self.axis

    def _parameters(self) -> dict[int, tuple[str, str]]:
        """SPA? parameters: id -> (item, value)."""
        return {int(SERVO_UPDATE_TIME_PARAM, 16): (self.axis, f"{1.0 / self.servo_rate_hz:.6e}"),
                PARAM_RECORD_MAX_POINTS: (self.axis, str(self.record_points * RECORD_TABLES)),
                PARAM_RECORD_TABLES: (self.axis, str(RECORD_TABLES))}

    def _spa_q(self, args: list[str]) -> list[str]:
        # SPA? [{<ItemID> <PamID>}]: the id in hexadecimal or decimal; the reply echoes it as sent
        known = self._parameters()
        if not args:
            return [f"{item} 0x{pid:08X}={value}" for pid, (item, value) in sorted(known.items())]
        lines = []
        for item, param in _pairs(args):
            self._axis(item)
            pid = _int(param)
            if pid not in known:
                raise GCSFailure(54)  # unknown parameter
            lines.append(f"{item} {param}={known[pid][1]}")
        return lines

    # -- servo, open-loop voltage, position ----------------------------------------------------------------
    def _svo(self, args: list[str]) -> None:
        for axis, state in _pairs(args):
            self._axis(axis)
            if state not in ("0", "1"):
                raise GCSFailure(17)
            on = state == "1"
            if on and not self.servo:
                self.stage.start(self._world_position())
            self.servo = on

    def _svo_q(self, args: list[str]) -> str:
        self._axes(args)
        return f"{self.axis}={int(self.servo)}"

    def _apply(self, volts: float) -> None:
        with self._lock:
            self.world.command(volts)
        self.voltage = volts

    def _sva(self, args: list[str], relative: bool = False) -> None:
        for axis, value in _pairs(args):
            self._axis(axis)
            volts = _float(value) + (self.voltage if relative else 0.0)
            if self.servo:
                raise GCSFailure(79)
            self._busy()
            if not (self.min_v <= volts <= self.max_v):
                raise GCSFailure(17)
            self._apply(volts)
            self.commanded_v.append(volts)

    def _svr(self, args: list[str]) -> None:
        self._sva(args, relative=True)

    def _sva_q(self, args: list[str]) -> str:
        self._axes(args)
        return f"{self.axis}={self.voltage:.6f}"

    def _vol_q(self, args: list[str]) -> str:
        for channel in args:
            if channel != self.channel:
                raise GCSFailure(15)
        return f"{self.channel}={self.voltage:.6f}"

    def _world_position(self) -> float:
        with self._lock:
            return float(self.world.read("output"))

    def _position(self) -> float:
        """Closed loop: where the stage's servo has brought it; open loop: the world's output."""
        return self.stage.state()[0] if self.servo else self._world_position()

    def _pos_q(self, args: list[str]) -> str:
        self._axes(args)
        return f"{self.axis}={self._position():.6f}"

    def _mov(self, args: list[str], relative: bool = False) -> None:
        pairs = _pairs(args)
        for axis, value in pairs:  # the whole command is checked before anything moves
            self._axis(axis)
            target = _float(value) + (self.stage.target if relative else 0.0)
            if not self.servo:
                raise GCSFailure(5)  # move attempted with servo off
            self._busy()
            if not (self.travel_um[0] <= target <= self.travel_um[1]):
                raise GCSFailure(7)  # position out of limits (TMN?..TMX?)
        for _axis, value in pairs:
            self.stage.move(_float(value) + (self.stage.target if relative else 0.0))

    def _mvr(self, args: list[str]) -> None:
        self._mov(args, relative=True)

    def _mov_q(self, args: list[str]) -> str:
        self._axes(args)
        return f"{self.axis}={self.stage.target:.6f}"

    def _ont_q(self, args: list[str]) -> str:
        self._axes(args)
        on = not self.servo or self.stage.on_target()
        return f"{self.axis}={int(on)}"

    def _tmn_q(self, args: list[str]) -> str:
        self._axes(args)
        return f"{self.axis}={self.travel_um[0]:.6f}"

    def _tmx_q(self, args: list[str]) -> str:
        self._axes(args)
        return f"{self.axis}={self.travel_um[1]:.6f}"

    def _stp(self, args: list[str]) -> None:
        self._stop_wave()
        self.stage.halt()
        self.error = 10  # "controller was stopped by command", as STP and #24 report

    def _hlt(self, args: list[str]) -> None:
        self._axes(args)
        self.stage.halt()

    # -- wave generator ---------------------------------------------------------------------------------
    def _wav(self, args: list[str]) -> None:
        # WAV <WaveTableID> <AppendWave> <WaveType> <WaveTypeParameters>
        if len(args) < 4:
            raise GCSFailure(1)
        table, mode, wave_type = _int(args[0]), args[1].upper(), args[2].upper()
        if mode not in ("X", "&", "+"):
            raise GCSFailure(1)
        self._busy()
        current = self.tables.get(table)
        if mode != "X" and current is None:
            raise GCSFailure(401)  # wave table not defined
        current = [] if mode == "X" or current is None else current
        if wave_type == "PNT":
            # PNT <StartPoint> <NumberOfPoints> <Point>...: StartPoint counts from 1 within the segment
            if len(args) < 6:
                raise GCSFailure(1)
            start, count = _int(args[3]), _int(args[4])
            points = [_float(p) for p in args[5:]]
            if count != len(points) or count < 1:
                raise GCSFailure(1)
            if start != (len(current) + 1 if mode == "&" else 1):
                raise GCSFailure(17)  # a new table starts at point 1; appended points continue it
            segment = np.asarray(points, dtype=np.float64)
        elif wave_type in ("SIN_P", "LIN", "RAMP"):
            segment = wave_segment(wave_type, [_float(p) for p in args[3:]])
        else:
            raise GCSFailure(402)  # wave type not supported (SIN, POL, ...)
        if mode == "+":
            if segment.size > len(current):
                raise GCSFailure(403)
            combined = np.asarray(current, dtype=np.float64)
            combined[:segment.size] += segment
            new = combined.tolist()
        else:
            new = current + segment.tolist()
        if len(new) > self.max_wave_points:
            raise GCSFailure(403)  # wave length exceeds limit
        if any(not (self.min_v <= p <= self.max_v) for p in new):
            raise GCSFailure(405)  # points beyond the output range
        self.tables[table] = new

    def _wav_q(self, args: list[str]) -> list[str]:
        # WAV? <table> 1 -> number of points in the table
        if len(args) != 2 or args[1] != "1":
            raise GCSFailure(1)
        table = _int(args[0])
        return [f"{table} 1={len(self.tables.get(table, []))}"]

    def _wcl(self, args: list[str]) -> None:
        self._busy()
        for table in args:
            self.tables.pop(_int(table), None)

    def _wsl(self, args: list[str]) -> None:
        for gen, table in _pairs(args):
            self._busy()
            self.wsl[_int(gen)] = _int(table)

    def _wsl_q(self, args: list[str]) -> list[str]:
        return [f"{g}={t}" for g, t in sorted(self.wsl.items())] or ["1=0"]

    def _wgc(self, args: list[str]) -> None:
        for gen, cycles in _pairs(args):
            n = _int(cycles)
            if n < 0:
                raise GCSFailure(17)
            self.wgc[_int(gen)] = n

    def _wgc_q(self, args: list[str]) -> list[str]:
        return [f"{g}={c}" for g, c in sorted(self.wgc.items())] or ["1=0"]

    def _wtr(self, args: list[str]) -> None:
        # WTR {<WaveGenID> <WaveTableRate> <InterpolationType>}
        if not args or len(args) % 3:
            raise GCSFailure(1)
        for k in range(0, len(args), 3):
            rate, interpolation = _int(args[k + 1]), _int(args[k + 2])
            if rate < 1 or interpolation not in (0, 1):
                raise GCSFailure(17)
            self.wtr[_int(args[k])] = (rate, interpolation)

    def _wtr_q(self, args: list[str]) -> list[str]:
        return [f"{g}={r} {i}" for g, (r, i) in sorted(self.wtr.items())] or ["1=1 0"]

    def _wgo(self, args: list[str]) -> None:
        for gen_text, mode_text in _pairs(args):
            gen, mode = _int(gen_text), _int(mode_text)
            if mode == 0:
                self._stop_wave()
                self.wgo[gen] = 0
                continue
            if mode != 1:
                raise GCSFailure(406)  # only "start immediately" is emulated
            if self.servo:
                raise GCSFailure(89)  # closed-loop playback is not emulated
            self._busy()
            table = self.tables.get(self.wsl.get(gen, 0))
            if not table:
                raise GCSFailure(401)
            cycles = self.wgc.get(gen, 0)
            if cycles < 1:
                raise GCSFailure(17)  # WGC 0 = run forever: a test must not start that
            self.wgo[gen] = mode
            self._start_wave(np.tile(np.asarray(table, dtype=np.float64), cycles), self.wtr.get(gen, (1, 0))[0])

    def _wgo_q(self, args: list[str]) -> list[str]:
        return [f"{g}={m}" for g, m in sorted(self.wgo.items())] or ["1=0"]

    def _start_wave(self, points: np.ndarray, divider: int) -> None:
        rate_hz = self.servo_rate_hz / divider
        state: dict[str, Any] = {"points": points, "divider": divider, "result": None, "error": None,
                                 "ends": time.monotonic() + (points.size / rate_hz if self.realtime else 0.0)}

        def play() -> None:
            try:
                with self._lock:
                    state["result"] = self.world.play(points, rate_hz)
            except BaseException as exc:  # noqa: BLE001 - reported through the error register
                state["error"] = exc

        state["thread"] = threading.Thread(target=play, name="pi-gcs-wave", daemon=True)
        self.records = {1: np.zeros(0), 2: np.zeros(0)}
        self._wave = state
        state["thread"].start()

    def _stop_wave(self) -> None:
        if self._wave is not None:
            self._wave["thread"].join(10.0)
            self._wave = None

    def _collect_wave(self) -> None:
        """Finish a played waveform: fill the data recorder once world.play is done (and time is up)."""
        wave = self._wave
        if wave is None or wave["thread"].is_alive() or time.monotonic() < wave["ends"]:
            return
        self._wave = None
        if wave["error"] is not None or wave["result"] is None:
            self.error = 555 if wave["error"] is not None else 0
            return
        points, divider = wave["points"], wave["divider"]
        output = np.asarray(wave["result"]["output"], dtype=np.float64)
        applied = np.asarray(wave["result"].get("input", points), dtype=np.float64)
        # one record every RTR servo cycles; the wave advances one point every WTR cycles
        n_records = min(self.record_points, points.size * divider // self.rtr)
        index = (np.arange(n_records) * self.rtr) // divider
        sources = {RECORD_OPTION_POSITION: output, RECORD_OPTION_VOLTAGE: applied}
        for table, (_source, option) in self.drc.items():
            series = sources.get(option)
            self.records[table] = series[index] if series is not None else np.zeros(0)
        self.voltage = float(points[-1])
        self.commanded_v.append(self.voltage)

    def idle(self) -> None:
        self._collect_wave()

    # -- data recorder ----------------------------------------------------------------------------------
    def _rtr(self, args: list[str]) -> None:
        if len(args) != 1:
            raise GCSFailure(1)
        rate = _int(args[0])
        if rate < 1:
            raise GCSFailure(17)
        self.rtr = rate

    def _rtr_q(self, args: list[str]) -> str:
        return str(self.rtr)

    def _tnr_q(self, args: list[str]) -> str:
        return str(RECORD_TABLES)

    def _drc(self, args: list[str]) -> None:
        # DRC {<RecTableID> <Source> <RecOption>}: one or more tables in one command, all checked
        # before any is changed
        if not args or len(args) % 3:
            raise GCSFailure(1)
        changes = {}
        for k in range(0, len(args), 3):
            table, source, option = _int(args[k]), args[k + 1], _int(args[k + 2])
            if table not in self.drc:
                raise GCSFailure(57)
            if option not in (0, 1, RECORD_OPTION_POSITION, RECORD_OPTION_VOLTAGE):
                raise GCSFailure(58)
            expected = self.channel if option == RECORD_OPTION_VOLTAGE else self.axis
            if option and source != expected:
                raise GCSFailure(59)
            changes[table] = (source, option)
        self.drc.update(changes)

    def _drc_q(self, args: list[str]) -> list[str]:
        tables = [_int(a) for a in args] or sorted(self.drc)
        if any(t not in self.drc for t in tables):
            raise GCSFailure(57)
        return [f"{t}={self.drc[t][0]} {self.drc[t][1]}" for t in tables]

    def _drt(self, args: list[str]) -> None:
        if len(args) < 2:
            raise GCSFailure(1)
        table, trigger = _int(args[0]), _int(args[1])
        if trigger not in (0, 1, 2, 4):
            raise GCSFailure(17)
        for t in (self.drt if table == 0 else [table]):
            if t not in self.drt:
                raise GCSFailure(57)
            self.drt[t] = trigger

    def _drt_q(self, args: list[str]) -> list[str]:
        return [f"{t}={g}" for t, g in sorted(self.drt.items())]

    def _drl_q(self, args: list[str]) -> list[str]:
        tables = [_int(a) for a in args] or sorted(self.records)
        if any(t not in self.records for t in tables):
            raise GCSFailure(57)
        return [f"{t}={self.records[t].size}" for t in tables]

    def _drr_q(self, args: list[str]) -> list[str]:
        # DRR? [<start> <n> [<table>...]], start counts from 1
        tables = [_int(a) for a in args[2:]] or [t for t, (_s, o) in sorted(self.drc.items()) if o]
        if any(t not in self.drc for t in tables):
            raise GCSFailure(57)
        length = min(self.records[t].size for t in tables)
        start = _int(args[0]) if args else 1
        count = _int(args[1]) if len(args) > 1 else length - start + 1
        if start < 1 or count < 1:
            raise GCSFailure(17)
        if start - 1 + count > length:
            raise GCSFailure(77)  # not enough recorded data
        names = {RECORD_OPTION_POSITION: "Actual Position of axis", RECORD_OPTION_VOLTAGE: "Voltage of output channel"}
        header = ["# TYPE = 1", "# SEPARATOR = 32", f"# DIM = {len(tables)}",
                  f"# SAMPLE_TIME = {self.rtr / self.servo_rate_hz:.6e}", f"# NDATA = {count}"]
        for k, t in enumerate(tables):
            source, option = self.drc[t]
            header.append(f"# NAME{k} = {names.get(option, 'Option ' + str(option))} {source}")
        header.append("# END_HEADER")
        columns = np.column_stack([self.records[t][start - 1:start - 1 + count] for t in tables])
        rows = [" ".join(f"{v:.6f}" for v in row) for row in columns]
        return header + rows

    def _hdr_q(self, args: list[str]) -> list[str]:
        return ["#RecordOptions", "0=Nothing is recorded", "1=Commanded Position of axis",
                f"{RECORD_OPTION_POSITION}=Actual Position of axis",
                f"{RECORD_OPTION_VOLTAGE}=Voltage of output channel",
                "#TriggerOptions", "0=Default setting", "1=Any command changing position",
                "2=Next command, resets trigger", "4=Trigger immediately",
                "#Additional information", f"{self.record_points * RECORD_TABLES} datapoints in total",
                f"{self.record_points} datapoints per table"]

    COMMANDS: ClassVar[dict[str, Any]] = {
        "*IDN?": _idn, "CSV?": _csv, "HLP?": _hlp, "ERR?": _err, "SAI?": _sai, "SPA?": _spa_q,
        "SVO": _svo, "SVO?": _svo_q, "SVA": _sva, "SVR": _svr, "SVA?": _sva_q, "VOL?": _vol_q,
        "POS?": _pos_q, "MOV": _mov, "MVR": _mvr, "MOV?": _mov_q, "ONT?": _ont_q, "TMN?": _tmn_q,
        "TMX?": _tmx_q, "STP": _stp, "HLT": _hlt,
        "WAV": _wav, "WAV?": _wav_q, "WCL": _wcl, "WSL": _wsl, "WSL?": _wsl_q, "WGC": _wgc, "WGC?": _wgc_q,
        "WTR": _wtr, "WTR?": _wtr_q, "WGO": _wgo, "WGO?": _wgo_q,
        "RTR": _rtr, "RTR?": _rtr_q, "TNR?": _tnr_q, "DRC": _drc, "DRC?": _drc_q, "DRT": _drt, "DRT?": _drt_q,
        "DRL?": _drl_q, "DRR?": _drr_q, "HDR?": _hdr_q,
    }
    # what HLP? lists: the single-character commands and every mnemonic above, in the manual's order
    HELP_ORDER: ClassVar[list[str]] = ["#5", "#7", "#9", "#24"] + sorted(COMMANDS, key=lambda c: (c != "*IDN?", c))

    def close(self, timeout_s: float = 2.0) -> None:
        super().close(timeout_s)
        if self._wave is not None:
            self._wave["thread"].join(timeout_s)


def start_emulator(settings: dict[str, Any], world: World) -> PIGCSEmulator:
    """A running emulated controller on a pty (``.url``), and on 127.0.0.1 TCP if ``tcp_port`` is set."""
    from drivers.pi_gcs import DRIVER

    return PIGCSEmulator(DRIVER.complete(settings), world).start()
