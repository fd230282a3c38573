"""Emulated PI GCS 2.0 piezo controller (E-709 / E-727 class) on a pty, optionally on 127.0.0.1 TCP.

One axis and one piezo channel (ids from the settings), backed by a :class:`~drivers.base.World`:

* ``SVA`` (servo off) -> ``world.command(volts)``; ``VOL?`` answers the last voltage applied;
* ``POS?`` -> ``world.read("output")`` (um);
* ``MOV`` (servo on) runs an integral servo on the world until within ``on_target_um`` (bounded);
* ``WGO`` runs the wave table connected by ``WSL`` through ``world.play(points, servo_rate / WTR)``
  in a worker thread; ``#9`` reports it running until that is done (and, with ``realtime``, until the
  waveform's duration has passed). The data recorder then holds the recorded position (option 2) and
  voltage (option 7) at ``servo_rate / RTR``. Simplification: recording stops with the waveform
  instead of running on until the tables are full (the driver reads only the waveform's samples).

Errors follow GCS: a failing set command sets the error register silently, a failing query gets no
reply; ``ERR?`` returns the code and clears it. :meth:`PIGCSEmulator.fail_next` makes the next command
fail with a chosen code. Everything the base class offers (drop, silence, garbage, disconnect) applies.
"""

from __future__ import annotations

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

PARAM_RECORD_MAX_POINTS = "0x16000200"
PARAM_RECORD_TABLES = "0x16000300"
RECORD_TABLES = 2


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
    if not np.isfinite(value):
        raise GCSFailure(1)
    return value


def _int(token: str) -> int:
    try:
        return int(token, 0)
    except ValueError:
        raise GCSFailure(1) from None


def _pairs(args: list[str]) -> list[tuple[str, str]]:
    if not args or len(args) % 2:
        raise GCSFailure(1)
    return list(zip(args[::2], args[1::2]))


class PIGCSEmulator(LineServer):
    """A running emulated controller; ``url`` (pty) and ``tcp_url`` go into a driver table."""

    name = "pi-gcs"

    def __init__(self, settings: dict[str, Any], world: World):
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
        self.idn = (f"(c)2024 Physik Instrumente (PI) GmbH & Co. KG, {settings['model']}, "
                    "0000000000, hilbench emulator")
        self.on_target_um = 0.01
        self.servo_gain_v_per_um = 0.2  # integral gain per servo cycle of the emulated closed loop
        # device state
        self.error = 0
        self.servo = False
        self.voltage = float(settings["rest_v"])  # last voltage applied (what VOL? reports)
        self.target_um = 0.0
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
        try:
            if self._fail_next is not None:
                code, self._fail_next = self._fail_next, None
                raise GCSFailure(code)
            handler = self.COMMANDS.get(mnemonic)
            if handler is None:
                raise GCSFailure(2)  # unknown command (GCS mnemonics are case-sensitive)
            reply = handler(self, args)
        except GCSFailure as failure:
            self.error = failure.code
            return None  # set commands never reply; a failing query is answered by silence
        if reply is None:
            return None
        lines = reply if isinstance(reply, list) else [reply]
        # GCS multi-line rule: every line but the last ends with a space before LF
        return ("".join(f"{line} \n" for line in lines[:-1]) + f"{lines[-1]}\n").encode("ascii")

    def _single_char(self, code: int) -> bytes | None:
        if code == 0x09:  # #9: wave generator status, hex bit mask
            running = self._wave is not None
            return f"{1 if running else 0:X}\n".encode()
        if code == 0x05:  # #5: motion status, hex bit mask (a MOV here settles before replying)
            return b"0\n"
        if code == 0x18:  # #24: stop all -> generators off, error 10
            self._stop_wave()
            self.error = 10
            return None
        self.error = 2
        return None

    def _axis(self, axis: str) -> None:
        if axis != self.axis:
            raise GCSFailure(15)

    def _busy(self) -> None:
        if self._wave is not None:
            raise GCSFailure(73)

    # -- identification and errors ----------------------------------------------------------------------
    def _idn(self, args: list[str]) -> str:
        return self.idn

    def _err(self, args: list[str]) -> str:
        code, self.error = self.error, 0
        return str(code)

    def _sai(self, args: list[str]) -> str:
        return self.axis

    def _spa_q(self, args: list[str]) -> str:
        if len(args) != 2:
            raise GCSFailure(1)
        item, param = args
        values = {SERVO_UPDATE_TIME_PARAM.lower(): f"{1.0 / self.servo_rate_hz:.6e}",
                  PARAM_RECORD_MAX_POINTS.lower(): str(self.record_points * RECORD_TABLES),
                  PARAM_RECORD_TABLES.lower(): str(RECORD_TABLES)}
        if param.lower() not in values:
            raise GCSFailure(54)
        return f"{item} {param}={values[param.lower()]}"

    # -- servo, open-loop voltage, position ----------------------------------------------------------------
    def _svo(self, args: list[str]) -> None:
        for axis, state in _pairs(args):
            self._axis(axis)
            if state not in ("0", "1"):
                raise GCSFailure(17)
            self.servo = state == "1"
            if self.servo:
                self.target_um = self._position()

    def _svo_q(self, args: list[str]) -> str:
        for axis in args:
            self._axis(axis)
        return f"{self.axis}={int(self.servo)}"

    def _apply(self, volts: float) -> None:
        with self._lock:
            self.world.command(volts)
        self.voltage = volts

    def _sva(self, args: list[str]) -> None:
        for axis, value in _pairs(args):
            self._axis(axis)
            volts = _float(value)
            if self.servo:
                raise GCSFailure(79)
            self._busy()
            if not (self.min_v <= volts <= self.max_v):
                raise GCSFailure(17)
            self._apply(volts)
            self.commanded_v.append(volts)

    def _sva_q(self, args: list[str]) -> str:
        for axis in args:
            self._axis(axis)
        return f"{self.axis}={self.voltage:.6f}"

    def _vol_q(self, args: list[str]) -> str:
        for channel in args:
            if channel != self.channel:
                raise GCSFailure(15)
        return f"{self.channel}={self.voltage:.6f}"

    def _position(self) -> float:
        with self._lock:
            return float(self.world.read("output"))

    def _pos_q(self, args: list[str]) -> str:
        for axis in args:
            self._axis(axis)
        return f"{self.axis}={self._position():.6f}"

    def _mov(self, args: list[str]) -> None:
        for axis, value in _pairs(args):
            self._axis(axis)
            target = _float(value)
            if not self.servo:
                raise GCSFailure(5)
            self._busy()
            self.target_um = target
            # an ideal integral servo on the world, bounded so a target out of reach cannot hang us
            volts = self.voltage
            for _ in range(5000):
                error = target - self._position()
                if abs(error) < self.on_target_um:
                    break
                volts = min(self.max_v, max(self.min_v, volts + self.servo_gain_v_per_um * error))
                self._apply(volts)

    def _mov_q(self, args: list[str]) -> str:
        return f"{self.axis}={self.target_um:.6f}"

    def _ont_q(self, args: list[str]) -> str:
        for axis in args:
            self._axis(axis)
        on = not self.servo or abs(self.target_um - self._position()) < self.on_target_um
        return f"{self.axis}={int(on)}"

    # -- wave generator ---------------------------------------------------------------------------------
    def _wav(self, args: list[str]) -> None:
        # WAV <table> <X|&> PNT <start> <n> <points...>
        if len(args) < 5:
            raise GCSFailure(1)
        table, mode, wave_type = _int(args[0]), args[1], args[2]
        if wave_type != "PNT":
            raise GCSFailure(402)  # SIN_P, LIN, RAMP... are real GCS wave types the emulator lacks
        if mode not in ("X", "&"):
            raise GCSFailure(1)
        self._busy()
        start, count = _int(args[3]), _int(args[4])
        points = [_float(p) for p in args[5:]]
        if count != len(points) or count < 1:
            raise GCSFailure(24)
        current = [] if mode == "X" else self.tables.get(table, [])
        if mode == "&" and table not in self.tables:
            raise GCSFailure(401)
        if start != len(current) + 1:
            raise GCSFailure(17)
        if len(current) + count > self.max_wave_points:
            raise GCSFailure(403)
        if any(not (self.min_v <= p <= self.max_v) for p in points):
            raise GCSFailure(405)
        self.tables[table] = current + points

    def _wav_q(self, args: list[str]) -> list[str]:
        # WAV? <table> 1 -> number of points in the table
        if len(args) != 2 or args[1] != "1":
            raise GCSFailure(1)
        table = _int(args[0])
        return [f"{table} 1={len(self.tables.get(table, []))}"]

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
        # WTR <gen> <rate> <interpolation>
        if len(args) != 3:
            raise GCSFailure(1)
        rate, interpolation = _int(args[1]), _int(args[2])
        if rate < 1 or interpolation not in (0, 1):
            raise GCSFailure(17)
        self.wtr[_int(args[0])] = (rate, interpolation)

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
        # DRC <table> <source> <option>
        if len(args) != 3:
            raise GCSFailure(1)
        table, source, option = _int(args[0]), args[1], _int(args[2])
        if table not in self.drc:
            raise GCSFailure(57)
        if option not in (0, 1, RECORD_OPTION_POSITION, RECORD_OPTION_VOLTAGE):
            raise GCSFailure(58)
        expected = self.channel if option == RECORD_OPTION_VOLTAGE else self.axis
        if option and source != expected:
            raise GCSFailure(59)
        self.drc[table] = (source, option)

    def _drc_q(self, args: list[str]) -> list[str]:
        return [f"{t}={s} {o}" for t, (s, o) in sorted(self.drc.items())]

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
        return [f"{t}={self.records.get(t, np.zeros(0)).size}" for t in tables]

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
        "*IDN?": _idn, "ERR?": _err, "SAI?": _sai, "SPA?": _spa_q,
        "SVO": _svo, "SVO?": _svo_q, "SVA": _sva, "SVA?": _sva_q, "VOL?": _vol_q,
        "POS?": _pos_q, "MOV": _mov, "MOV?": _mov_q, "ONT?": _ont_q,
        "WAV": _wav, "WAV?": _wav_q, "WSL": _wsl, "WSL?": _wsl_q, "WGC": _wgc, "WGC?": _wgc_q,
        "WTR": _wtr, "WTR?": _wtr_q, "WGO": _wgo, "WGO?": _wgo_q,
        "RTR": _rtr, "RTR?": _rtr_q, "TNR?": _tnr_q, "DRC": _drc, "DRC?": _drc_q, "DRT": _drt, "DRT?": _drt_q,
        "DRL?": _drl_q, "DRR?": _drr_q, "HDR?": _hdr_q,
    }

    def close(self, timeout_s: float = 2.0) -> None:
        super().close(timeout_s)
        if self._wave is not None:
            self._wave["thread"].join(timeout_s)


def start_emulator(settings: dict[str, Any], world: World) -> PIGCSEmulator:
    """A running emulated controller on a pty (``.url``), and on 127.0.0.1 TCP if ``tcp_port`` is set."""
    from drivers.pi_gcs import DRIVER

    return PIGCSEmulator(DRIVER.complete(settings), world).start()
