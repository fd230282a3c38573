"""The closed loop: reference -> compensator -> rig safety path -> plant -> feedback, at the fixed rate.

On a simulated rig the whole loop is ONE fused numba loop per block (:func:`closed_loop_block`):
per sample the compensator's command (:func:`hilbench.online.inverse_kernels.comp_step`), the rig's safety
path with :func:`hilbench.rig.safety.command_path` semantics (NaN holds the last applied value,
clamp to ``[min, max]``, slew limit ``max_rate / fs``), the plant
(:func:`hilbench.sim.kernels.plant_step_flat`) and the commit of the applied command and the
measurement (:func:`hilbench.online.inverse_kernels.comp_update`: model memory, PID, OIIR identifier). It
is compiled with ``_nrt=False`` (it allocates nothing; see :mod:`hilbench.models.stepping`), so the
inlined steps (the plant's, the compensator's commit with the identifier) and the called
compensator step (itself ``_nrt=False``) pay no reference counting. Both loops use numpy's error
model: under Python's, every division of the inlined code tests its divisor for zero to raise
ZeroDivisionError (12 % of the loop's time); here a zero divisor gives inf or NaN, which the
safety path holds (NaN) or clamps (inf) like any other bad command. The loop runs in lock-step, so its ``lateness`` channel is 0.

A rig of per-sample devices runs the runner's fixed-rate loop (:mod:`hilbench.runners.fixed_rate`,
the one every experiment on a real rig runs) with the compensator as its law
(:class:`CompensatorLaw`): interlocks, watchdog, Ctrl-C held off to a safe point (the run recorded
``aborted``, :class:`~hilbench.errors.RunStopped`), the recording streamed and closed with its status,
the lateness of each sample recorded and summarised (``TrackResult.loop``).

The plant's sensor noise and temperature/load trajectories are drawn from the plant's own seeded
streams in the order its block mode draws them, so a tracking run is reproducible.

:func:`track` is the Python entry: it builds the compensator for the rig's limits, brings the rig
and the compensator's memory to the same state (a full-range cycle, then a ramp to the first
command), runs the loop, writes a recording (the rig's channels plus ``reference`` um, ``error``
um = reference - output, ``command`` before the safety path, ``lateness`` s) and returns the metric
keys of :mod:`hilbench.identify.metrics` (read at call time) of the output against the reference.

Before anything moves, :func:`track` refuses (:class:`UserError`) a reference that leaves the
reachable output range of the compensator (:mod:`hilbench.online.operating_range`: the static map's
major loop over the model's operating range, within the output sensor's measurable ``range`` when
the rig gives one), naming the range and the first sample outside it;
``allow_clip=True`` (CLI ``--allow-clip``) runs it clipped to that range instead, and the run's
``reference_clipped`` attribute (JSON: ``reference_clipped``) says how many samples were clipped and
the reference's original range; the ``reference`` channel holds what the loop was asked to track.
Where the model's loop turns over in its fitted range and the reference leaves the monotone part's
reach, the commands are a path planned over the whole reference (:mod:`hilbench.online.path_plan`,
decision 0118) after the full-range cycle and an approach; a reference the model itself cannot
follow on any such path is refused too.
Every run reports its health (:mod:`hilbench.online.health`: samples at a limit, slew-limited
samples, error against the model's own): ``TrackResult.health``, the JSON's ``health`` object and
the run's ``health`` attribute.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit

from hilbench.errors import UserError
from hilbench.online.health import model_validation_metric, run_health
from hilbench.online.inverse import PID, Compensator
from hilbench.online.inverse_kernels import S_TARGET, comp_step, comp_update
from hilbench.online.operating_range import FALL_TOLERANCE
from hilbench.rig.safety import ramp
from hilbench.sim import kernels as K

__all__ = ["track", "TrackResult", "closed_loop_block", "loop_step", "reference_signal", "SimulatedLoop"]


# The compensator's step is called, not inlined: inlined, numba typed and SSA-rebuilt its body (every
# inverse kind) again inside this loop, and a first `track` compiled 138 s (102 s now, same machine);
# the loop's time per sample did not change (583/569 ns best chunk, 610/623 median, timed alternately
# on bench_closed_loop's chain). Its commit stays inlined: it hands on the identifier's 17 arrays,
# and with it called too the loop lost 66 ns per sample (637/571 ns).
_comp_update = njit(cache=True, inline="always", _nrt=False)(comp_update.py_func)


@njit(cache=True, inline="always", _nrt=False)
def _safety(x: float, lo: float, hi: float, max_step: float, last: np.ndarray) -> float:
    """:func:`hilbench.rig.safety.command_path` for one sample (the same arithmetic)."""
    prev = last[0]
    if x != x:
        x = prev
    c = min(max(x, lo), hi)
    c = min(max(c, prev - max_step), prev + max_step)
    last[0] = c
    return c


@njit(cache=True, _nrt=False, error_model="numpy")
def loop_step(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
              oa: Any, F: np.ndarray, L: np.ndarray, B: np.ndarray, pos: int, lims: np.ndarray,
              last: np.ndarray, r: float, aux: np.ndarray, rec: np.ndarray) -> float:
    """One sample of the closed loop on a simulated plant; returns the measured output (um).

    ``lims`` = (lo, hi, max_step); ``last`` (1,) the last applied command (the rig's safety state);
    ``B`` the plant's per-sample noise/temperature/load, column ``pos``; ``rec`` receives
    (command, applied)."""
    u = comp_step(CI, CP, CX, I, P, X, r, aux)
    c = _safety(u, lims[0], lims[1], lims[2], last)
    y = K.plant_step_flat(F, L, B, pos, c)
    _comp_update(CI, CP, CX, I, P, X, oa, r, c, y, aux)
    rec[0] = u
    rec[1] = c
    return y


@njit(cache=True, _nrt=False, error_model="numpy")
def closed_loop_block(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
                      oa: Any, F: np.ndarray, L: np.ndarray, B: np.ndarray, lims: np.ndarray, last: np.ndarray,
                      ref: np.ndarray, aux: np.ndarray, out_cmd: np.ndarray, out_applied: np.ndarray,
                      out_y: np.ndarray, targets: np.ndarray) -> int:
    """n = len(ref) samples of the fused loop (see :func:`loop_step`); returns how many commands the
    safety path changed (as :func:`command_path` counts them). ``targets``: the previewed targets of
    the static part (read when the compensator previews, :meth:`Compensator.enable_preview`)."""
    changed = 0
    lo = lims[0]
    hi = lims[1]
    ms = lims[2]
    # the plant's arrays as views taken once (per sample they would cost ~35 ns, see plant_views)
    V = K.plant_views(F, L)
    o = K.plant_out_offset(L)
    for k in range(ref.shape[0]):
        r = ref[k]
        CX[S_TARGET] = targets[k]
        u = comp_step(CI, CP, CX, I, P, X, r, aux[k])
        c = _safety(u, lo, hi, ms, last)
        if c != u:
            changed += 1
        y, y_true, drive = K.plant_step_views(c, B[K.B_TEMPERATURE, k], B[K.B_LOAD, k], B[K.B_NOISE, k], V)
        F[o] = y_true
        F[o + 1] = drive
        _comp_update(CI, CP, CX, I, P, X, oa, r, c, y, aux[k])
        out_cmd[k] = u
        out_applied[k] = c
        out_y[k] = y
    return changed


# ====================================================================================================
# the plant's per-sample inputs, drawn as its block mode draws them
# ====================================================================================================


class SimulatedLoop:
    """The fused loop on a simulated plant (:class:`hilbench.sim.plant.Plant`) and a compensator.

    ``inputs(n)`` prepares the next n samples' noise and trajectories from the plant's streams
    (the order :meth:`Plant.simulate` uses), with the measured aux channels the compensator reads.
    """

    def __init__(self, plant: Any, comp: Compensator, lo: float, hi: float, max_step: float, last: np.ndarray):
        self.plant = plant
        self.comp = comp
        self.lims = np.array([lo, hi, max_step])
        self.last = last
        for c in comp.channels:
            if c not in plant.sensors:
                raise UserError(f"the model reads channel {c!r}, which the rig does not measure",
                                hint="fit a model without it, or add the sensor to the rig")

    def inputs(self, n: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        p = self.plant
        B, aux_noise = p.draw_inputs(n)
        aux: dict[str, np.ndarray] = {}
        for channel, row in (("temperature", K.B_TEMPERATURE), ("load", K.B_LOAD)):
            if channel in p.sensors and channel in p.tables:
                aux[channel] = p.read_aux(channel, B[row], aux_noise.get(channel))
        return B, aux

    def run(self, ref: np.ndarray, targets: np.ndarray | None = None) -> dict[str, Any]:
        n = ref.shape[0]
        B, aux = self.inputs(n)
        c = self.comp
        F, L = self.plant.step_arrays()
        cmd, applied, y = np.empty(n), np.empty(n), np.empty(n)
        r = np.ascontiguousarray(ref, dtype=np.float64)
        t = r if targets is None else np.ascontiguousarray(targets, dtype=np.float64)
        changed = closed_loop_block(c.CI, c.CP, c.CX, c.I, c.P, c.X, c.oiir_arrays(), F, L, B, self.lims,
                                    self.last, r, c.aux_matrix(aux, n), cmd, applied, y, t)
        self.plant.samples += n
        return {"command": cmd, "input": applied, "output": y, "aux": aux, "changed": changed}


# ====================================================================================================
# references
# ====================================================================================================


def reference_signal(spec: Any, sample_rate_hz: float) -> tuple[np.ndarray, Any]:
    """A reference (um at the rig's rate) from an array, an excitation, the compact form
    ``KIND:key=value,...`` or ``FILE.h5:RUN`` (that run's output channel). Returns (values, description)."""
    if isinstance(spec, np.ndarray) or isinstance(spec, (list, tuple)):
        values = np.asarray(spec, dtype=np.float64)
        return values, {"kind": "array", "samples": int(values.size)}
    if hasattr(spec, "generate"):
        return spec.generate(sample_rate_hz), spec.describe()
    text = str(spec)
    head, sep, run_name = text.rpartition(":")
    if sep and head.lower().endswith((".h5", ".hdf5")):
        from hilbench.recording.hdf5 import Recording

        run = Recording(head).run(run_name)
        y = run.channel("output")
        fs = run.sample_rate_hz
        if abs(fs - sample_rate_hz) > 1e-9 * sample_rate_hz:
            t_old = np.arange(y.size) / fs
            t_new = np.arange(int(math.floor(t_old[-1] * sample_rate_hz)) + 1) / sample_rate_hz
            y = np.interp(t_new, t_old, y)
        if not np.all(np.isfinite(y)):
            raise UserError(f"run {run.name} has non-finite output samples; a reference must be finite",
                            where=text)
        return y, {"kind": "recording", "file": head, "run": run.name, "units": run.units.get("output", "um")}
    from hilbench.excitation.plan import plan_from_compact

    runs = plan_from_compact([text])
    if len(runs) != 1:
        raise UserError("the reference must be one signal (no '|' sweeps)", where=f"--reference {text!r}")
    exc = runs[0].excitation
    return exc.generate(sample_rate_hz), exc.describe()


# ====================================================================================================
# track
# ====================================================================================================


@dataclass
class TrackResult:
    metrics: dict[str, float]
    time: np.ndarray
    reference: np.ndarray
    command: np.ndarray
    input: np.ndarray
    output: np.ndarray
    compensator: dict[str, Any]
    file: str | None = None
    group: str | None = None
    limited: int = 0
    aux: dict[str, np.ndarray] = field(default_factory=dict)
    seconds: float = 0.0
    approach_from: float = 0.0  # the applied command just before the first sample (of the pre-actuation)
    health: dict[str, Any] = field(default_factory=dict)
    reference_clipped: dict[str, Any] | None = None
    loop: dict[str, Any] | None = None  # a run on devices: the fixed-rate loop's lateness figures
    #: the samples run before the reference's first one (the dynamics' stable inversion, recorded at
    #: the run's start): ``input``, ``command``, ``output``, ``reference`` and ``aux:<channel>``
    preactuation: dict[str, np.ndarray] = field(default_factory=dict)
    #: the commands applied before the run (not recorded): from the one the rig held when ``track`` was
    #: called (at rest) through the precondition, the approach and the hold at the first command, as
    #: the compensator's model memory was given them; a replay of the model starts there
    approach: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def error(self) -> np.ndarray:
        return self.reference - self.output

    @property
    def preactuation_samples(self) -> int:
        """Samples of pre-actuation the run started with (recorded before the reference's first)."""
        return int(self.preactuation["input"].size) if "input" in self.preactuation else 0

    def __repr__(self) -> str:
        return (f"TrackResult({self.time.size} samples, erms {self.metrics.get('erms_pct', float('nan')):.3g} %, "
                f"max error {self.metrics.get('max_abs_error', float('nan')):.4g} um"
                + (f", run {self.group} of {self.file}" if self.file else "") + ")")

    def to_json(self) -> dict[str, Any]:
        return {"metrics": self.metrics, "file": self.file, "run": self.group, "samples": int(self.time.size),
                "commands_limited_by_safety_path": self.limited, "compensator": self.compensator,
                "loop_seconds": self.seconds, "health": self.health,
                "preactuation_samples": self.preactuation_samples,
                **({"loop": self.loop} if self.loop else {}),
                **({"reference_clipped": self.reference_clipped} if self.reference_clipped else {})}


def tracking_metrics(reference: np.ndarray, output: np.ndarray) -> dict[str, float]:
    """The metric keys of :mod:`hilbench.identify.metrics`, read at call time (errors in um,
    ``*_pct`` against the reference)."""
    from hilbench.identify import metrics as M

    values = M.metrics(reference, output)
    return {k: float(values[k]) for k in M.METRIC_KEYS if k in values}


def _open_rig(rig: Any) -> Any:
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig

    if isinstance(rig, Rig):
        return rig
    return Rig(load_rig(rig))


def _drive(rig: Any, comp: Compensator, target: float, hold: int = 0) -> None:
    """Move the rig to ``target`` at its slew limit through its safety path (unrecorded), hold it there
    ``hold`` samples, and feed the same applied commands to the compensator's model memory."""
    _play(rig, comp, np.concatenate([ramp(rig.last_applied, target, rig.max_step), np.full(max(hold, 0), target)]))


def _play(rig: Any, comp: Compensator, commands: np.ndarray) -> None:
    """Apply ``commands`` (unrecorded) through the rig's safety path and feed what was applied to the
    compensator's model memory."""
    if commands.shape[0] == 0:
        return
    applied = rig.apply(np.ascontiguousarray(commands, dtype=np.float64))
    measured = rig.measure(applied)
    comp.precondition(applied, {k: v for k, v in measured.items() if k in comp.channels})


def _needs_plan(ref: np.ndarray, comp: Compensator) -> bool:
    """Whether the reference needs a planned path: the static map turns over in its fitted range (the
    general inverse on its monotone part, or on none) and the reference leaves that part's reach by
    more than the model's validation rmse."""
    r = comp.range
    if comp.kind != "general" or r.rising:
        return False
    if not r.invertible:
        return True
    finite = ref[np.isfinite(ref)]
    if finite.size == 0:
        return False
    tolerance = _reach_tolerance(comp, *r.output)
    return bool(float(np.min(finite)) < r.output[0] - tolerance or float(np.max(finite)) > r.output[1] + tolerance)


def _reach_tolerance(comp: Compensator, lo: float, hi: float) -> float:
    """How far (um) a reference may leave the reach ``[lo, hi]`` and still run as asked: the model's
    validation rmse (the recorded extremes are read with the sensor's noise and the loop's overshoot),
    never more than the share of the span a branch may fall (:data:`FALL_TOLERANCE`): a poor model's
    error says nothing about where the rig turns."""
    return min(model_validation_metric(comp.model, "rmse")[0] or 0.0, FALL_TOLERANCE * (hi - lo))


def _refuse_a_missed_plan(comp: Compensator, error: np.ndarray, fs: float, allow_clip: bool) -> None:
    """Refuse (before the rig moves) a planned path along which the model itself misses the reference
    by more rms than its validation rmse: the reference asks for what no path through the model's
    loop gives, and the run would track at least that much worse than the model can (``allow_clip``
    runs it, said in the notes). Where the rms holds, the largest miss is in the notes."""
    val = model_validation_metric(comp.model, "rmse")[0] or 0.0
    miss = np.abs(error)
    rms = float(np.sqrt(np.mean(error ** 2))) if error.size else 0.0
    if rms <= val:
        return
    worst = int(np.argmax(miss))
    line = (f"no command path through the loop of {comp.model.spec!r} follows this reference: planned over the "
            f"fitted [{comp.range.fitted[0]:.4g}, {comp.range.fitted[1]:.4g}] {comp.unit}, the model misses it by "
            f"{rms:.3g} um rms, more than its validation rmse {val:.3g} um, and by {miss[worst]:.3g} um at sample "
            f"{worst} (t = {worst / fs:.6g} s)").replace("  ", " ")
    if not allow_clip:
        raise UserError(line, hint="slow the reference or keep it inside the loop, or --allow-clip to run it anyway")
    comp.notes.append(line + " (--allow-clip: run anyway)")


#: the hold before a run: windows of this many seconds (at least SETTLE_MIN_WINDOW samples) ...
SETTLE_WINDOW_S = 0.002
SETTLE_MIN_WINDOW = 16
#: ... until two windows' means differ by at most this many standard errors of the sensor's noise
SETTLE_NOISE_SIGMAS = 4.0
#: ... or by this fraction of the reference's span (a creeping actuator never stops)
SETTLE_SPAN_FRACTION = 1e-3
#: ... and at most this long (s); a rig still moving then is run anyway and said so
SETTLE_MOST_S = 1.0
#: the first command is re-aimed when the model's memory moved it by what, at the model's mean slope,
#: is more than this share of the reference's span (finer re-aims chase the minor loops they make)
SETTLE_REAIM_FRACTION = 0.01


def _hold_until_settled(rig: Any, comp: Compensator, reference0: float, aux0: dict[str, float] | None,
                        at_least: int, span: float) -> tuple[float, int, str]:
    """Hold the rig at the command for the run's first reference sample until its *measured* output has
    settled, and return (that command, samples held, a note when it had not settled).

    The model's own settling time (``at_least`` samples) is a lower bound only: the rig's dynamics may
    be slower or more resonant than the model's (a static model has none). Held there, a model with
    memory (creep, temperature) keeps moving, so the command for the first sample is asked again after
    every window and the rig moved to it when it changed: the run starts where the model, in its state
    at that moment, puts the first sample. Settled: two consecutive windows at one command whose means
    differ by at most SETTLE_NOISE_SIGMAS standard errors of the sensor's noise (estimated from
    sample-to-sample differences, blind to a slow drift) or SETTLE_SPAN_FRACTION of the reference's span,
    and whose rms about their mean is at most twice the noise plus that tolerance (no ringing left)."""
    fs = rig.sample_rate_hz
    window = max(SETTLE_MIN_WINDOW, int(math.ceil(SETTLE_WINDOW_S * fs)))
    most = max(int(SETTLE_MOST_S * fs), at_least + 2 * window)
    slope = abs(comp.range.slope) or 1.0  # um per command unit
    command = comp.peek(reference0, aux0)
    _drive(rig, comp, command, hold=max(at_least, 0))
    held = max(at_least, 0)
    previous: float | None = None
    while held < most:
        aimed = comp.peek(reference0, aux0)
        if abs(aimed - command) * slope > SETTLE_REAIM_FRACTION * span:
            command, previous = aimed, None
            _drive(rig, comp, command)
        applied = rig.apply(np.full(window, command))
        measured = rig.measure(applied)
        comp.precondition(applied, {k: v for k, v in measured.items() if k in comp.channels})
        held += window
        y = np.asarray(measured.get("output", np.zeros(window)), dtype=np.float64)
        if not np.all(np.isfinite(y)):
            return command, held, "the output read non-finite values while held before the run"
        d = np.abs(np.diff(y))
        noise = float(np.median(d)) / (0.6745 * math.sqrt(2.0)) if d.size else 0.0
        mean = float(np.mean(y))
        tol = max(SETTLE_NOISE_SIGMAS * noise * math.sqrt(2.0 / window), SETTLE_SPAN_FRACTION * span)
        rms = float(np.sqrt(np.mean((y - mean) ** 2)))
        if previous is not None and abs(mean - previous) <= tol and rms <= 2.0 * noise + tol:
            return command, held, ""
        previous = mean
    return command, held, (f"the output was still moving after {held / fs:.3g} s held at the first command "
                           f"({command:.6g} {rig.actuator.unit}); the run started from that transient")


def track(
    rig: Any,
    model: Any,
    reference: Any,
    *,
    feedback: PID | bool | None = None,
    online: dict[str, Any] | bool | None = None,
    output: str | Path | None = None,
    label: str = "track",
    method: str = "auto",
    gain: float | str | None = "auto",
    iterations: int = 1,
    precondition: bool = True,
    chunk_samples: int = 65536,
    allow_clip: bool = False,
    check_rate: bool = False,
    preview: bool = True,
) -> TrackResult:
    """Track ``reference`` (um) on ``rig`` with the inverse of ``model`` (a fitted
    :class:`~hilbench.models.Model` or its JSON file); see the module docstring.

    ``feedback``: True (gains designed from the identified loop) or a :class:`PID` (checked on
    it); ``online``: True or OIIR options for the adaptive compensator (fpmpi models). ``precondition``: before the run, a full-range cycle
    (up to the top of the range the model was fitted on, then to the first command) wipes the
    actuator's memory so that the model's memory can match it. Writes a
    run to ``output`` (appended when it exists) when given. ``allow_clip``: run a reference that
    leaves the reachable output range clipped to it (else it is refused before the rig moves).
    ``check_rate``: on per-sample devices, paced, the devices' round trips are timed first and a rate
    they cannot hold is refused before the rig moves (:mod:`hilbench.runners.rate_check`).
    ``preview``: the model's dynamics and delay are inverted over the whole reference before the run
    (:meth:`Compensator.enable_preview`); False leaves them to the causal pre-filter and feedback.
    """
    from hilbench.models import Model

    if not hasattr(model, "weights"):
        model = Model.load(model)
    rig = _open_rig(rig)
    fs = rig.sample_rate_hz
    ref, described = reference_signal(reference, fs)
    if ref.size == 0:
        raise UserError("the reference is empty")
    act = rig.actuator
    span = float(np.ptp(ref[np.isfinite(ref)])) if np.any(np.isfinite(ref)) else 1.0
    comp = Compensator(model, fs, (act.min, act.max), method=method, gain=gain, iterations=iterations,
                       feedback=feedback, online=online, reference_span=max(span, 1e-9), unit=act.unit,
                       plannable=preview and not online, aux_values=_aux_now(rig, model))
    # the model's memory starts where the actuator has been: at the command it holds now (at rest
    # before a run), settled there, as the fit's runs started from rest. Started at the approach's first
    # command instead, it took a one-sample jump to the top of the range for a long hold there: with a
    # creep bank of time constants up to 29 s, the inverse then missed by an offset decaying over the
    # run (randomized rig 228: 2.7 % against the model's own 0.42 %)
    _play(rig, comp, np.array([rig.last_applied]))
    # a map that turns over in its fitted range: the monotone part serves a reference inside its reach;
    # one beyond it runs on a path planned over the whole fitted range (hilbench.online.path_plan)
    planned = _needs_plan(ref, comp) and preview and not online
    if planned:
        comp.range.plan_over_fitted()
    sensor = rig.config.sensor("output") if hasattr(rig, "config") else None
    ref, clipped = _reachable(ref, comp, fs, allow_clip, getattr(sensor, "range", None))
    lead = 0
    if preview:
        pre, targets = comp.enable_preview(ref)
        if pre.size:
            # the pre-actuation runs as the run's first samples, the reference held at its first value:
            # the same loop and pacing carry it into the run without a gap; the figures leave it out
            lead = int(pre.size)
            ref = np.concatenate([np.full(lead, ref[0]), ref])
            targets = np.concatenate([pre, targets])
    else:
        targets = ref
    comp.lead = lead
    lead_in = np.zeros(0)
    approach = np.zeros(0)
    if planned:
        a, b = comp.range.fitted
        lead_in = np.concatenate([ramp(rig.last_applied, a, rig.max_step), ramp(a, b, rig.max_step)])
        aux_plan = _first_aux(rig, comp) if comp.channels else None
        approach, error = comp.plan_path(targets, rig.max_step, aux_plan, lead_in)
        _refuse_a_missed_plan(comp, error, fs, allow_clip)
    comp.CX[S_TARGET] = targets[0]  # what the first command (peeked below) is for
    plant = getattr(rig.lockstep, "plant", None)
    on_devices = plant is None or not hasattr(plant, "step_arrays")
    played = False
    if on_devices:
        from hilbench.online.tracking_devices import plays_waveform, refuse_per_sample_law_on_player

        refuse_per_sample_law_on_player(rig, comp)
        played = plays_waveform(rig, comp)  # the device plays the run: no per-sample round trips to time
    trips = None
    if on_devices and check_rate and rig.pace and not played:
        from hilbench.runners.rate_check import require_rate

        trips = require_rate(rig).describe()
    if planned:
        # the full-range cycle the path was planned after, then its approach: the very commands planned
        _play(rig, comp, np.concatenate([lead_in, approach]))
    elif precondition:
        # up to the top of the range the model was fitted on (and the rig allows): every operator
        # that the model knows switches, so model and actuator memories agree; then down to the start
        if comp.range.sub_range:
            # a map monotone only on part of its fitted range: a full cycle over that part puts the
            # model and the actuator on the loop the operating range was traced on
            _drive(rig, comp, comp.range.command[0])
            _drive(rig, comp, comp.range.command[1])
        else:
            _drive(rig, comp, comp.range.fitted[1])
    aux0 = _first_aux(rig, comp) if comp.channels else None
    # held at the first command until the rig has settled: a run that starts while the approach still
    # rings (or creeps) tracks from a transient the model's memory does not hold
    _, comp.held_before_run, comp.settle_note = _hold_until_settled(
        rig, comp, float(ref[0]) if np.isfinite(ref[0]) else 0.0, aux0, comp.settling_samples(), span)
    if on_devices:
        from hilbench.online.tracking_devices import track_on_devices

        return track_on_devices(rig, comp, ref, described, clipped, output, label, aux0, trips, targets)
    # Lock-step simulation: the fused loop, on the rig's own safety state.
    rig.lockstep.start_run()
    approach_from = rig.last_applied
    started = time.perf_counter()
    n = ref.size
    cmd, applied, y = np.empty(n), np.empty(n), np.empty(n)
    aux_rec: dict[str, list[np.ndarray]] = {}
    limited = 0
    loop = SimulatedLoop(plant, comp, act.min, act.max, rig.max_step, rig.safety_state)
    for start in range(0, n, chunk_samples):
        stop = min(n, start + chunk_samples)
        out = loop.run(ref[start:stop], targets[start:stop])
        cmd[start:stop], applied[start:stop], y[start:stop] = out["command"], out["input"], out["output"]
        for k, v in out["aux"].items():
            aux_rec.setdefault(k, []).append(v)
        limited += out["changed"]
    rig.clamped_samples += limited
    seconds = time.perf_counter() - started
    aux = {k: np.concatenate(v) for k, v in aux_rec.items()}
    result = _result(rig, comp, ref, cmd, applied, y, aux, described, clipped)
    result.limited, result.seconds, result.approach_from = limited, seconds, approach_from
    if output is not None:
        result.file, result.group = _write(rig, result, (ref, cmd, applied, y, aux), output, label)
    return result


def _result(rig: Any, comp: Compensator, ref: np.ndarray, cmd: np.ndarray, applied: np.ndarray, y: np.ndarray,
            aux: dict[str, np.ndarray], described: dict[str, Any], clipped: dict[str, Any] | None) -> TrackResult:
    """The run's figures: metrics of the output against the reference, the compensator's counters,
    the run's health. The arrays are the whole run as the rig ran it; its first ``comp.lead`` samples
    (the pre-actuation) go to ``preactuation`` and stay out of the figures."""
    act = rig.actuator
    lead = min(comp.lead, ref.size)
    pre = {"input": applied[:lead], "command": cmd[:lead], "output": y[:lead], "reference": ref[:lead],
           **{f"aux:{k}": v[:lead] for k, v in aux.items()}}
    ref, cmd, applied, y = ref[lead:], cmd[lead:], applied[lead:], y[lead:]
    aux = {k: v[lead:] for k, v in aux.items()}
    result = TrackResult(tracking_metrics(ref, y), np.arange(ref.size) / rig.sample_rate_hz, ref, cmd, applied, y,
                         comp.describe(), aux=aux)
    result.approach = np.concatenate(comp.preconditioned) if comp.preconditioned else np.zeros(0)
    result.compensator["counters"] = comp.counters()
    result.compensator["reference"] = described
    result.health = run_health(cmd, applied, comp.bracket, (act.min, act.max),
                               result.metrics.get("erms_pct", math.nan), comp.model, _span(ref))
    result.reference_clipped = clipped
    result.preactuation = pre
    return result


def _span(reference: np.ndarray) -> float | None:
    """The reference's peak-to-peak (um): what the tracking ``erms_pct`` is a share of."""
    finite = reference[np.isfinite(reference)]
    return float(np.ptp(finite)) if finite.size else None


def _finish_attrs(result: TrackResult) -> dict[str, Any]:
    """What a tracking run's recording keeps besides its samples."""
    extra = {"compensator": json.dumps(result.compensator, default=str), "metrics": json.dumps(result.metrics),
             "health": json.dumps(result.health, default=str), "degraded": bool(result.health.get("degraded", False))}
    if result.reference_clipped is not None:
        extra["reference_clipped"] = json.dumps(result.reference_clipped)
    # the run's first samples are the pre-actuation (reference held at its first value), not in the figures
    extra["preactuation_samples"] = result.preactuation_samples
    return extra


def _reachable(ref: np.ndarray, comp: Compensator, fs: float, allow_clip: bool,
               measurable: list[float] | None = None) -> tuple[np.ndarray, dict[str, Any] | None]:
    """The reference checked against the compensator's reachable output range (within the output
    sensor's measurable ``range``, um, when the rig gives one: beyond it no output is measured, and
    the model's extrapolation towards the rig's limits is not believed past it): refused when it
    leaves it, or (``allow_clip``) clipped to it, with what was clipped."""
    lo, hi = comp.range.output
    within = ""
    if measurable is not None and (measurable[0] > lo or measurable[1] < hi):
        lo, hi = max(lo, float(measurable[0])), min(hi, float(measurable[1]))
        within = f", within the output sensor's range [{measurable[0]:.4g}, {measurable[1]:.4g}] um"
        comp.notes.append(f"reachable output within the output sensor's range: [{lo:.4g}, {hi:.4g}] um")
        if not hi > lo:
            raise UserError(f"the output sensor's range [{measurable[0]:.4g}, {measurable[1]:.4g}] um and what "
                            f"{comp.model.spec!r} reaches, [{comp.range.output[0]:.4g}, {comp.range.output[1]:.4g}] um, "
                            "do not overlap")
    finite = np.isfinite(ref)
    outside = finite & ((ref < lo) | (ref > hi))
    if not np.any(outside):
        return ref, None
    # the reach is the model's static loop, known only as well as the model: a reference just beyond
    # it runs as asked, and says so; the rig may well reach it
    tolerance = _reach_tolerance(comp, lo, hi)
    beyond = float(np.max(np.maximum(ref[outside] - hi, lo - ref[outside])))
    measured_there = measurable is None or (float(np.min(ref[finite])) >= float(measurable[0])
                                            and float(np.max(ref[finite])) <= float(measurable[1]))
    if beyond <= tolerance and measured_there:
        comp.notes.append(f"{int(np.count_nonzero(outside))} reference samples leave the model's reach "
                          f"[{lo:.4g}, {hi:.4g}] um by at most {beyond:.3g} um, within its validation rmse "
                          f"{tolerance:.3g} um: run as asked (the command saturates at the operating range's end there)")
        return ref, None
    k = int(np.argmax(outside))
    count = int(np.count_nonzero(outside))
    span = comp.range.command
    where = (f"the reachable output range of {comp.model.spec!r} on this rig is [{lo:.4g}, {hi:.4g}] um "
             f"(its static map over [{span[0]:.4g}, {span[1]:.4g}] {comp.unit}{within})").replace(" ,", ",").replace(" )", ")")
    if comp.range.sub_range:
        r = comp.range
        fl, fh = r.fitted
        way = "falls" if r.direction > 0 else "rises"
        where += (f", the part of the fitted [{fl:.4g}, {fh:.4g}] {comp.unit} where one output has one command "
                  f"(elsewhere the loop turns over: its {r.fall_branch} branch {way} back by {r.fall_um:.3g} um "
                  f"from {r.fall_from[0]:.4g} to {r.fall_to[0]:.4g} {comp.unit})").replace("  ", " ")
    if not allow_clip:
        raise UserError(f"the reference leaves what the actuator can reach: {where}; sample {k} (t = {k / fs:.6g} s) "
                        f"asks for {ref[k]:.4g} um ({count} of {ref.size} samples outside)",
                        hint="scale the reference into the range, or --allow-clip to run it clipped")
    clipped = np.where(finite, np.clip(ref, lo, hi), ref)
    info = {"samples": count, "share_pct": 100.0 * count / ref.size, "first_index": k, "first_time_s": k / fs,
            "reachable_um": [lo, hi],
            "original_range_um": [float(np.min(ref[finite])), float(np.max(ref[finite]))]}
    comp.notes.append(f"reference clipped to the reachable [{lo:.4g}, {hi:.4g}] um: {count} of {ref.size} samples "
                      f"(--allow-clip)")
    return clipped, info


def _held_sample(rig: Any) -> dict[str, np.ndarray]:
    """Every channel the rig reads over one unrecorded sample held at the last command."""
    return rig.measure(rig.apply(np.full(1, rig.last_applied)))


def _aux_now(rig: Any, model: Any) -> dict[str, float] | None:
    """The model's aux channels as the rig reads them now, before anything moves: what the reachable
    range is judged at. None for a model without aux channels; a channel the rig does not read is left
    out (the range takes the model's reference)."""
    wanted = list(model.aux_channels)
    if not wanted:
        return None
    measured = _held_sample(rig)
    return {k: float(measured[k][0]) for k in wanted if k in measured}


def _first_aux(rig: Any, comp: Compensator) -> dict[str, float]:
    """The aux channels' current readings (for the first command), also preconditioning the compensator's
    aux pre-filters on them."""
    measured = _held_sample(rig)
    comp.precondition(np.full(1, rig.last_applied), {k: v for k, v in measured.items() if k in comp.channels})
    return {k: float(measured[k][0]) for k in comp.channels}


def _write(rig: Any, result: TrackResult, whole: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]],
           output: str | Path, label: str) -> tuple[str, str]:
    """A lock-step run, recorded when it is done (the fused loop runs in one go): the channels a run on
    devices records (``lateness`` 0: a lock-step simulation is never late), over the ``whole`` run
    (reference, command, input, output, aux) with its pre-actuation, as a run on devices records it."""
    from hilbench.recording.hdf5 import RecordingWriter
    from hilbench.runners.fixed_rate import lateness_channel, tracking_channels

    writer = RecordingWriter(output)
    channels = [c for c in rig.channels() if c.name in ("time", "input", "output") or c.name in result.aux]
    channels += [lateness_channel(), *tracking_channels(rig.actuator.unit)]
    run = writer.begin_run(label, channels, experiment="track", excitation=result.compensator.get("reference", {}),
                           sample_rate_hz=rig.sample_rate_hz, rig_toml=rig.config.text, devices=rig.devices(),
                           extra_attrs={"compensator": json.dumps(result.compensator, default=str), "mode": "lockstep"})
    ref, cmd, applied, y, aux = whole
    data = {"time": np.arange(ref.size) / rig.sample_rate_hz, "input": applied, "output": y, "reference": ref,
            "error": ref - y, "command": cmd, "lateness": np.zeros(ref.size), **aux}
    try:
        run.append({c.name: data[c.name] for c in channels})
    except BaseException as exc:
        run.finish("failed", repr(exc))
        raise
    run.finish("complete", extra_attrs=_finish_attrs(result))
    return str(output), run.group_name


def plot_tracking(result: TrackResult, path: str | Path, title: str = "") -> Path:
    """Three panels: reference and output over time, the error over time, desired vs actual
    (matplotlib, Agg backend); the metrics in the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    m = result.metrics
    mean_key = next((k for k in ("mean_abs_error", "mad") if k in m), None)
    max_key = next((k for k in ("max_abs_error", "mae") if k in m), None)
    summary = f"MRE {m.get('mre_pct', float('nan')):.3g} %"
    if max_key:
        summary += f", max |e| {m[max_key]:.3g} um"
    if mean_key:
        summary += f", mean |e| {m[mean_key]:.3g} um"
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ax = axes[0]
    ax.plot(result.time, result.reference, label="reference", lw=1.2)
    ax.plot(result.time, result.output, label="output", lw=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("displacement (um)")
    ax.set_title("tracking")
    ax.legend(loc="best")
    ax = axes[1]
    ax.plot(result.time, result.error, lw=0.7, color="C3")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("error: reference - output (um)")
    ax.set_title("error")
    ax = axes[2]
    ax.plot(result.reference, result.output, lw=0.7)
    lo, hi = float(np.nanmin(result.reference)), float(np.nanmax(result.reference))
    ax.plot([lo, hi], [lo, hi], "k--", lw=0.6)
    ax.set_xlabel("desired (um)")
    ax.set_ylabel("actual (um)")
    ax.set_title("desired vs actual")
    fig.suptitle(f"{title + ': ' if title else ''}{result.compensator.get('method', '')} inverse of "
                 f"{result.compensator.get('model', '')} - {summary}")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
