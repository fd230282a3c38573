"""PI piezo controllers (E-709 / E-727 class) speaking GCS 2.0 over a serial line or TCP.

The protocol, as PI's GCS manuals and PIPython describe it (see ``tests/drivers/test_pi_gcs.py`` for
the bytes on the wire):

* a command is ASCII ending in LF, e.g. ``SVA 1 12.5\\n``; single-character commands such as ``#9``
  (byte 0x09, wave generator status) and ``#24`` (byte 0x18, stop all) have no LF;
* set commands never reply. Errors are kept in an error register that ``ERR?`` returns and clears
  (``0`` = no error), so the practice is to send ``ERR?`` after every command that can fail. A query
  that fails is answered by an empty line (docs/decisions/0095); this driver then asks ``ERR?`` for
  the reason. Firmware that stays silent instead is handled too: after a silent query the driver asks
  ``ERR?`` before deciding it was a timeout;
* a reply line ending in ``" \\n"`` (space before LF) is continued by the next line; the last line
  ends in a bare LF. Query replies read ``<id>=<value>``, e.g. ``POS? 1`` -> ``1=10.000000``;
* ``DRR?`` answers with a GCS array: ``# key = value`` header lines (``TYPE``, ``SEPARATOR``, ``DIM``,
  ``SAMPLE_TIME``, ``NDATA``, ``NAME0``...) up to ``# END_HEADER``, then one line per sample.

The device is used as an open-loop voltage actuator (``SVA``), a position/voltage sensor (``POS?``,
``VOL?``) and a player: ``play`` uploads a waveform to a wave table (``WAV ... PNT`` in chunks, the
first clearing the table with ``X``, the rest appending with ``&``), connects it to a wave generator
(``WSL``), one cycle (``WGC``), the table rate divider (``WTR``), configures the data recorder
(``RTR``, ``DRC``, ``DRT``; ``WGO`` always triggers recording on these controllers), starts ``WGO``,
polls ``#9`` and reads the recorder back with ``DRR?`` in chunks.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from drivers.base import (
    DeviceError,
    DeviceLost,
    DeviceTimeout,
    DriverSpec,
    Lazy,
    Setting,
    retry,
)
from drivers.serial_link import SerialLink, short

# GCS controller error numbers (PI's GCS error list, as in PIPython's gcserror.py), the ones a
# piezo controller driver meets. Texts are PI's error names in words.
GCS_ERRORS: dict[int, str] = {
    0: "No error",
    1: "Parameter syntax error",
    2: "Unknown command",
    3: "Command length out of limits or command buffer overrun",
    5: "Unallowable move attempted on unreferenced axis, or move attempted with servo off",
    7: "Position out of limits",
    10: "Controller was stopped by command",
    15: "Invalid axis identifier",
    17: "Parameter out of range",
    23: "Illegal axis",
    24: "Incorrect number of parameters",
    25: "Invalid floating point number",
    26: "Parameter missing",
    54: "Unknown parameter",
    57: "Invalid data recorder table",
    58: "Invalid data recorder source option",
    59: "Invalid data recorder source channel",
    73: "Motion commands and wave generator activity are not allowed when wave generator is active",
    77: "Not enough recorded data",
    79: "Open-loop value set when servo is on",
    89: "Command not allowed in current motion mode",
    302: "Voltage out of limits",
    401: "Wave table not defined",
    402: "Wave type not supported",
    403: "Wave length exceeds limit",
    405: "Wave parameter out of range",
    406: "WGO start mode bit not supported",
}

SERVO_UPDATE_TIME_PARAM = "0x0E000200"  # SPA parameter: servo update time in s (E-727 manual: 50 us)
RECORD_OPTION_POSITION = 2  # DRC option "actual position of axis" (PIPython RecordOptions.ACTUAL_POSITION_2)
RECORD_OPTION_VOLTAGE = 7  # DRC option "piezo voltage of output channel" (PIPython PIEZO_VOLTAGE_7)
WGO_START = 1  # WGO start mode: start immediately, synchronised with the servo cycle
WGO_STOP = 0


def gcs_error_text(code: int) -> str:
    return GCS_ERRORS.get(code, "controller error (see the GCS error list of the manual)")


def parse_value(line: str, key: str, what: str, device: str) -> str:
    """The value of a ``<key>=<value>`` reply line, checking the key (guards against a desynced reply)."""
    left, sep, right = line.partition("=")
    if not sep or left.strip().split()[-1:] != [key]:
        raise DeviceError(device, f"unexpected reply to {what}: {short(line)} (expected {key}=<value>)")
    return right.strip()


def parse_float(text: str, what: str, device: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise DeviceError(device, f"unexpected reply to {what}: {short(text)} is not a number") from None


def parse_gcs_array(lines: list[str], what: str, device: str) -> tuple[dict[str, str], np.ndarray]:
    """Header (``# KEY = value``) and data (rows x columns) of a GCS array reply such as ``DRR?``."""
    header: dict[str, str] = {}
    for i, line in enumerate(lines):
        text = line.strip()
        if text.upper().startswith("# END_HEADER"):
            body = lines[i + 1:]
            break
        if not text.startswith("#"):
            raise DeviceError(device, f"unexpected line in the header of {what}: {short(line)}")
        key, sep, value = text.lstrip("#").partition("=")
        if sep:
            header[key.strip().upper()] = value.strip()
    else:
        raise DeviceError(device, f"reply to {what} has no '# END_HEADER' line")
    columns = int(header.get("DIM", "0") or 0)
    separator = chr(int(header.get("SEPARATOR", "32")))
    try:
        rows = [[float(x) for x in line.strip().split(None if separator == " " else separator)] for line in body
                if line.strip()]
        data = np.asarray(rows, dtype=np.float64).reshape(len(rows), -1)
    except ValueError as exc:
        raise DeviceError(device, f"unexpected data in the reply to {what}: {exc}") from None
    if columns and data.shape[1] != columns:
        raise DeviceError(device, f"reply to {what} has {data.shape[1]} columns, header says DIM = {columns}")
    return header, data


class PIGCSController:
    """One PI controller axis: an open-loop voltage actuator, a sensor and a wave-generator player."""

    def __init__(self, settings: dict[str, Any]):
        self.settings = settings
        self.url = str(settings["url"])
        self.axis = str(settings["axis"])
        self.channel = str(settings["channel"])
        self.name = str(settings.get("name") or f"pi-gcs ({self.url})")
        self.rest_v = float(settings["rest_v"])
        self.slew_v_per_s = float(settings["slew_v_per_s"])
        self.min_v = float(settings["min_v"])
        self.max_v = float(settings["max_v"])
        self.attempts = int(settings["attempts"])
        self.backoff_s = float(settings["backoff_s"])
        self.generator = int(settings["wave_generator"])
        self.table = int(settings["wave_table"])
        self.chunk_points = int(settings["wave_chunk_points"])
        self.drr_chunk_points = int(settings["drr_chunk_points"])
        self.max_wave_points = int(settings["max_wave_points"])
        self.link = SerialLink(self.url, device=self.name, baud=int(settings["baud"]),
                               timeout_s=float(settings["timeout_s"]), eol=b"\n")
        try:
            self._idn = self.query("*IDN?")[0].strip()
            self.error_number()  # start from a clean error register
            self.servo_rate_hz = self._servo_rate_hz(float(settings["servo_rate_hz"]))
            self.record_points = self._record_points()
            # write() is SVA: an open-loop command. Switch the servo off once here, so the first
            # write is not refused with error 79.
            self.command(f"SVO {self.axis} 0")
        except BaseException:
            self.link.close()
            raise

    # -- transactions ---------------------------------------------------------------------------------
    def _check_after_silence(self, exc: DeviceTimeout, what: str) -> None:
        """A failing GCS query is answered by silence: ask ERR? before calling it a timeout."""
        self.link.discard_input()
        self.link.write(b"ERR?\n")
        try:
            line = self.link.read_line("ERR?")
        except DeviceTimeout:
            raise exc from None  # silent to ERR? as well: the device does not answer (retried)
        code = self._parse_err(line.decode("ascii", "replace"))
        if code:
            raise self._gcs_error(code, what)
        raise exc

    def _parse_err(self, line: str) -> int:
        try:
            return int(line.strip())
        except ValueError:
            raise DeviceError(self.name, f"unexpected reply to ERR?: {short(line)}") from None

    def _gcs_error(self, code: int, what: str) -> DeviceError:
        return DeviceError(self.name, f"{what} refused: GCS error {code}: {gcs_error_text(code)}")

    def _refused(self, what: str) -> DeviceError:
        """An empty reply: the controller refused the query; ``ERR?`` says why."""
        self.link.write(b"ERR?\n")
        code = self._parse_err(self.link.read_line("ERR?").decode("ascii", "replace"))
        if code:
            return self._gcs_error(code, what)
        return DeviceError(self.name, f"empty reply to {what} (and ERR? reports no error)")

    def _read_reply(self, what: str) -> list[str]:
        """One reply: lines up to the one not ending in a space (GCS continuation rule)."""
        lines: list[str] = []
        while True:
            raw = self.link.read_line(what)
            try:
                line = raw.decode("ascii")
            except UnicodeDecodeError:
                raise DeviceError(self.name, f"garbled reply to {what}: {short(raw)}") from None
            lines.append(line)
            if not line.endswith(" "):
                return lines

    def query(self, *commands: str) -> list[str]:
        """Send query commands in one write; return the first line of each reply (retried on timeout)."""
        what = " / ".join(commands)
        payload = "".join(c + "\n" for c in commands).encode("ascii")

        def attempt() -> list[str]:
            self.link.discard_input()
            self.link.write(payload)
            try:
                replies = [self._read_reply(c)[0] for c in commands]
            except DeviceTimeout as exc:
                self._check_after_silence(exc, what)
                raise
            for c, reply in zip(commands, replies):
                if not reply.strip():
                    raise self._refused(c)
            return replies

        return retry(attempt, device=self.name, what=what, attempts=self.attempts, backoff_s=self.backoff_s)

    def query_lines(self, command: str) -> list[str]:
        """Every line of one (possibly multi-line) reply, retried on timeout."""

        def attempt() -> list[str]:
            self.link.discard_input()
            self.link.write(command.encode("ascii") + (b"" if len(command) == 1 else b"\n"))
            try:
                lines = self._read_reply(command)
            except DeviceTimeout as exc:
                self._check_after_silence(exc, command)
                raise
            if len(lines) == 1 and not lines[0].strip():
                raise self._refused(repr(command) if len(command) == 1 else command)
            return lines

        return retry(attempt, device=self.name, what=command, attempts=self.attempts, backoff_s=self.backoff_s)

    def command(self, *commands: str) -> None:
        """Send set commands, each followed by ERR? (one write); DeviceError with the GCS error number.

        Set commands have no reply, so they are safe to repeat: a timeout on the ERR? answers is
        retried with the whole batch.
        """
        what = " / ".join(commands)
        payload = "".join(f"{c}\nERR?\n" for c in commands).encode("ascii")

        def attempt() -> None:
            self.link.discard_input()
            self.link.write(payload)
            codes = [self._parse_err(self.link.read_line(f"ERR? after {c}").decode("ascii", "replace"))
                     for c in commands]
            for c, code in zip(commands, codes):
                if code:
                    raise self._gcs_error(code, c)

        retry(attempt, device=self.name, what=what, attempts=self.attempts, backoff_s=self.backoff_s)

    def error_number(self) -> int:
        """Read and clear the controller's error register (``ERR?``)."""
        return self._parse_err(self.query("ERR?")[0])

    # -- setup ----------------------------------------------------------------------------------------
    def _servo_rate_hz(self, fallback_hz: float) -> float:
        """Servo update rate: SPA? parameter 0x0E000200 (servo update time), as the E-727 manual does."""
        try:
            line = self.query(f"SPA? {self.axis} {SERVO_UPDATE_TIME_PARAM}")[0]
        except DeviceError as exc:
            if isinstance(exc, (DeviceTimeout, DeviceLost)):
                raise
            return fallback_hz  # parameter unknown on this model (error 54): the configured rate
        seconds = parse_float(line.partition("=")[2], "SPA? servo update time", self.name)
        if not seconds > 0:
            raise DeviceError(self.name, f"servo update time {seconds!r} s is not positive")
        return 1.0 / seconds

    def _record_points(self) -> int:
        """Points per data recorder table: HDR?'s "datapoints per table" line (as PIPython reads it)."""
        for line in self.query_lines("HDR?"):
            if "datapoints per table" in line:
                try:
                    return int(line.split()[0])
                except ValueError:
                    break
        return self.max_wave_points

    # -- device contract ----------------------------------------------------------------------------
    def identity(self) -> str:
        return self._idn

    def capabilities(self) -> dict[str, Any]:
        return {
            "driver": "pi-gcs",
            "idn": self._idn,
            "axes": [self.axis],
            "voltage_channel": self.channel,
            "servo_rate_hz": self.servo_rate_hz,
            "voltage_range_v": [self.min_v, self.max_v],
            "rest_v": self.rest_v,
            "slew_v_per_s": self.slew_v_per_s,
            "max_wave_points": min(self.max_wave_points, self.record_points),
            "record_points_per_table": self.record_points,
            "play_rates": "servo_rate_hz / n for integer n >= 1",
            "channels": {"output": "um (POS?)", "input": "V (VOL?)"},
        }

    def _check_volts(self, volts: float) -> None:
        if not (self.min_v <= volts <= self.max_v):
            raise DeviceError(self.name, f"{volts!r} V is outside the allowed {self.min_v:g}..{self.max_v:g} V")

    def write(self, value: float) -> None:
        """Open-loop output voltage, V (``SVA``)."""
        volts = float(value)
        self._check_volts(volts)
        self.command(f"SVA {self.axis} {volts:.6f}")

    def read(self) -> dict[str, float]:
        """``output``: position, um (``POS?``); ``input``: piezo voltage, V (``VOL?``)."""
        pos, vol = self.query(f"POS? {self.axis}", f"VOL? {self.channel}")
        return {"output": parse_float(parse_value(pos, self.axis, "POS?", self.name), "POS?", self.name),
                "input": parse_float(parse_value(vol, self.channel, "VOL?", self.name), "VOL?", self.name)}

    def generator_running(self) -> bool:
        """``#9``: bit mask (hex) of running wave generators."""
        line = self.query_lines("\x09")[0].strip()
        try:
            mask = int(line, 16)
        except ValueError:
            raise DeviceError(self.name, f"unexpected reply to #9: {short(line)}") from None
        return bool(mask & (1 << (self.generator - 1)))

    def stop(self, success: bool) -> None:
        """End of work. ``success=False`` makes safe: wave generator off, open loop, ramp to ``rest_v``.

        The ramp is a few SVA steps at ``slew_v_per_s`` (a jump to rest can excite the stage), then
        the servo stays off. ``success=True`` only stops the wave generator: after a normal run the
        rig has already brought the actuator to rest through ``write``.
        """
        self.command(f"WGO {self.generator} {WGO_STOP}")
        if success:
            return
        self.command(f"SVO {self.axis} 0")  # SVA is refused while the servo is on (error 79)
        start = parse_float(parse_value(self.query(f"VOL? {self.channel}")[0], self.channel, "VOL?", self.name),
                            "VOL?", self.name)
        span = self.rest_v - start
        duration_s = abs(span) / self.slew_v_per_s if self.slew_v_per_s > 0 else 0.0
        # steps of at most 2 V and ~10 ms each (a single SVA would be a jump whatever the timing),
        # capped at 50 commands so a slow serial line still finishes the ramp promptly
        steps = max(1, min(50, max(math.ceil(abs(span) / 2.0), math.ceil(duration_s / 0.01))))
        for k in range(1, steps + 1):
            if duration_s > 0:
                time.sleep(duration_s / steps)
            self.command(f"SVA {self.axis} {start + span * k / steps:.6f}")

    def play(self, waveform: np.ndarray, rate_hz: float) -> dict[str, np.ndarray]:
        """Run ``waveform`` (V) once at ``rate_hz`` through the wave generator; return what was recorded.

        ``rate_hz`` must be the servo rate divided by an integer (the table rate ``WTR``). Returns
        ``time`` (s), ``input`` (V, recorded piezo voltage) and ``output`` (um, recorded position).
        """
        wave = np.asarray(waveform, dtype=np.float64).ravel()
        n = wave.size
        if n < 2 or not np.all(np.isfinite(wave)):
            raise DeviceError(self.name, "play needs at least 2 finite samples")
        limit = min(self.max_wave_points, self.record_points)
        if n > limit:
            raise DeviceError(self.name, f"waveform has {n} samples; this controller holds at most {limit} "
                                         f"(wave table {self.max_wave_points}, data recorder table {self.record_points})")
        lo, hi = float(wave.min()), float(wave.max())
        if lo < self.min_v or hi > self.max_v:
            raise DeviceError(self.name, f"waveform spans {lo:g}..{hi:g} V, outside {self.min_v:g}..{self.max_v:g} V")
        divider = self.divider_for(rate_hz)

        self.command(f"WGO {self.generator} {WGO_STOP}")
        for start in range(0, n, self.chunk_points):
            chunk = wave[start:start + self.chunk_points]
            points = " ".join(f"{v:.6f}" for v in chunk)
            mode = "X" if start == 0 else "&"  # X clears the table, & appends (PIPython writewavepoints)
            self.command(f"WAV {self.table} {mode} PNT {start + 1} {chunk.size} {points}")
        self.command(f"WSL {self.generator} {self.table}", f"WGC {self.generator} 1",
                     f"WTR {self.generator} {divider} 0",
                     f"RTR {divider}",  # one record per wave point
                     f"DRC 1 {self.axis} {RECORD_OPTION_POSITION}",
                     f"DRC 2 {self.channel} {RECORD_OPTION_VOLTAGE}",
                     "DRT 0 0")  # default trigger: WGO starts the recording anyway on these controllers
        self.command(f"WGO {self.generator} {WGO_START}")

        duration_s = n / (self.servo_rate_hz / divider)
        deadline = time.monotonic() + 2.0 * duration_s + float(self.settings["play_margin_s"])
        poll_s = min(0.05, max(0.002, duration_s / 50))
        while self.generator_running():
            if time.monotonic() > deadline:
                self.command(f"WGO {self.generator} {WGO_STOP}")
                raise DeviceTimeout(self.name, f"wave generator still running {2 * duration_s:.3g} s after a "
                                               f"{duration_s:.3g} s waveform; stopped it")
            time.sleep(poll_s)
        recorded = self.read_recorder(n)
        t = np.arange(n, dtype=np.float64) / (self.servo_rate_hz / divider)
        return {"time": t, "input": recorded[:, 1], "output": recorded[:, 0]}

    def divider_for(self, rate_hz: float) -> int:
        """The integer table rate divider with ``servo_rate_hz / divider == rate_hz``, or DeviceError."""
        ratio = self.servo_rate_hz / float(rate_hz)
        divider = round(ratio)
        if divider < 1 or abs(ratio - divider) > 1e-9 * ratio:
            lower = max(1, math.floor(ratio))
            options = ", ".join(f"{self.servo_rate_hz / d:g} Hz (divider {d})" for d in sorted({lower, lower + 1}))
            raise DeviceError(self.name, f"cannot play at {rate_hz:g} Hz: the wave generator runs at the servo rate "
                                         f"{self.servo_rate_hz:g} Hz divided by an integer; nearest: {options}")
        return int(divider)

    def read_recorder(self, n: int) -> np.ndarray:
        """``n`` samples of record tables 1 (position) and 2 (voltage), read with ``DRR?`` in chunks."""
        blocks = []
        for start in range(1, n + 1, self.drr_chunk_points):
            count = min(self.drr_chunk_points, n - start + 1)
            what = f"DRR? {start} {count} 1 2"
            header, data = parse_gcs_array(self.query_lines(what), what, self.name)
            if data.shape != (count, 2) or int(float(header.get("NDATA", count))) != count:
                raise DeviceError(self.name, f"{what} returned {data.shape[0]} rows x {data.shape[1] if data.ndim > 1 else 0} "
                                             f"(NDATA = {header.get('NDATA')}), expected {count} x 2")
            blocks.append(data)
        return np.concatenate(blocks, axis=0)

    def close(self) -> None:
        self.link.close()

    def __enter__(self) -> PIGCSController:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_device(settings: dict[str, Any]) -> PIGCSController:
    return PIGCSController(DRIVER.complete(settings))


SETTINGS = (
    Setting("url", str, required=True, doc="serial port or pyserial URL: /dev/ttyUSB0, a pty path, socket://host:50000"),
    Setting("name", str, doc="device name in messages (default: pi-gcs (url))"),
    Setting("axis", str, default="1", doc="GCS axis identifier"),
    Setting("channel", str, default="1", doc="piezo output channel (VOL?, data recorder voltage)"),
    Setting("baud", int, default=115200, doc="bit/s (ignored by ptys and sockets)"),
    Setting("timeout_s", float, default=0.5, doc="s to wait for each reply line"),
    Setting("attempts", int, default=3, doc="tries per transaction on timeouts"),
    Setting("backoff_s", float, default=0.02, doc="s before the first retry (doubles each retry)"),
    Setting("rest_v", float, default=0.0, doc="V, where stop(False) ramps to"),
    Setting("slew_v_per_s", float, default=100.0, doc="V/s, ramp rate of stop(False)"),
    Setting("min_v", float, default=-20.0, doc="V, lowest voltage write/play accept"),
    Setting("max_v", float, default=120.0, doc="V, highest voltage write/play accept"),
    Setting("servo_rate_hz", float, default=20000.0,
            doc="Hz; used when SPA? 0x0E000200 is unknown, and by the emulator (E-727: 50 us servo time)"),
    Setting("wave_generator", int, default=1, doc="wave generator id"),
    Setting("wave_table", int, default=1, doc="wave table id"),
    Setting("max_wave_points", int, default=262144, doc="points a wave table holds on this controller"),
    Setting("wave_chunk_points", int, default=100, doc="points per WAV command (controller input buffer limit)"),
    Setting("drr_chunk_points", int, default=4096, doc="points per DRR? query"),
    Setting("play_margin_s", float, default=5.0, doc="s added to twice the waveform duration before play gives up"),
    Setting("record_points", int, default=131072, doc="emulator: points per data recorder table (E-727: 262144 / tables)"),
    Setting("realtime", bool, default=False, doc="emulator: the wave generator takes the waveform's real duration"),
    Setting("tcp_port", int, doc="emulator: also serve GCS on 127.0.0.1:tcp_port (0 = any free port)"),
    Setting("model", str, default="E-727", doc="emulator: model in the *IDN? reply"),
    Setting("servo_bandwidth_hz", float, default=100.0,
            doc="emulator: closed-loop bandwidth of the stage, Hz (a 10 um MOV settles in about 1.4/bandwidth s)"),
    Setting("on_target_um", float, default=0.02, doc="emulator: on-target window of ONT?, um"),
    Setting("travel_min_um", float, default=0.0, doc="emulator: lowest commandable position (TMN?), um"),
    Setting("travel_max_um", float, default=100.0, doc="emulator: highest commandable position (TMX?), um"),
)

DRIVER = DriverSpec(
    name="pi-gcs",
    roles=("actuator", "sensor", "player"),
    settings=SETTINGS,
    open=open_device,
    emulator=Lazy("drivers.emulators.pi_gcs:start_emulator"),
    description="PI piezo controller (E-709/E-727 class), GCS 2.0 over RS-232, USB-serial or TCP",
    transports=("serial", "socket://"),
)
