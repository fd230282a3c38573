"""Feedback designed from the identified loop, and user gains checked against the same loop.

The PID of :mod:`hilbench.online.pid` acts in the output domain (um in, um out): its output is
added to the reference before the inverse. The plant it sees is the *compensated* plant: rig
after inverse model. If the model were exact that is a unit gain; on a rig it is not:

- its **local gain** (how many um the rig moves for one um the inverse was asked for) is the ratio
  of the rig's local slope to the model's, which moves along the loop: at reversals the inverse
  runs at its steepest slope (1/p0), where a small error in p0 is a large error in gain, and where
  the model misses the rig's slope (rate dependence, saturation) the ratio drifts far from 1;
- its **dynamics** are the model's identified linear dynamics and delay (when the model has them),
  one sample of measurement delay (the PID acts on the previous sample's measurement), and
  whatever lag the rig has that the model lacks (amplifier bandwidth, mechanics).

:func:`identify_loop` measures both from the model's training data when the recording is at
hand (the runs named in the model's ``fitted_on``): the model is run on the recorded command,
the unmodelled lag is the time shift that best maps the model's output onto the measured one
(least squares on the model output's derivative), and the local gain range is the 5th-95th
percentile of the measured over the modelled rise on monotone stretches of the model output
(each 2 % of the span and at least 20 noise sigma long), after that shift, widened to at least
0.8-1.25, its lower end at least a tenth of the median; more than a quarter of the stretches
moving against the model is refused. Two measured responses complete the loop where they were
measured (decision 0123, :mod:`hilbench.online.loop_response`): the rig's response over the model's
without its rate terms (a resonance the model lacks; set here), and the compensator's own response to
a correction (simulated by :meth:`hilbench.online.inverse.Compensator.correction_response`, which
sets it). Without the recording it is the model's own loop (unit gain, the model's dynamics and delay) and says so: the
design's 6 dB and 45 deg are then the only allowance for what the model misses, and its crossover
is kept below fs / 100.

:func:`design` picks an integral-only controller (kp = 0: the proportional path would pass the
sensor's noise straight into the command, which on a hysteretic actuator starts a minor loop at
the inverse's steepest slope every few samples) with the largest integral gain whose loop keeps a
gain margin of at least 6 dB and a phase margin of at least 45 deg at every gain of the range,
and whose closed-loop poles lie inside the unit circle at every gain of the range (the unmodelled
lag rounded up to whole samples), crossing over no higher than the training input's excited
bandwidth (:func:`hilbench.diagnosis.input_motion.excited_bandwidth_hz`): above it the rig's
dynamics were never seen, and a lag fitted at the drive rates says nothing of a resonance there.
Below that ceiling the gain is weighed against the errors this model makes on this rig
(:func:`predicted_error`): the training residual (measured - model, sensor noise included) is the
error feed-forward leaves on the training drives, and with the loop closed the measured error is that
residual through the loop's sensitivity S = 1 / (1 + L). An integrator removes the slow part of it and
amplifies what lies near and above the crossover (and feeds the noise back); each run's constant part
it removes from an empty start, so over a run of T s only as far as exp(-ki g t) has decayed
(decision 0122). The design takes the
largest gain whose predicted error, at the worst local gain of the range, is not above
feed-forward's: a reference meets slow errors the training residual lacks (an offset of the starting
state, a drift), and those the integrator removes the better the higher its gain, so the gain is not
lowered further than the training error asks. The same holds for the residual on the rows the fit
held out (the validation rows of each run), the error feed-forward leaves on drives the model was not
fitted on: a gain must not be predicted to raise either (decision 0117). Where every gain raises one
(the residual is the sensor's noise, or lies near every crossover the margins allow), or the gain left
has an integral time longer than the longest training run, the loop is left open (ki = 0) and says so.
:func:`check` evaluates user gains on the same loop and raises
:class:`InstabilityError` when a pole leaves the unit circle at any gain of the range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hilbench.errors import UserError
from hilbench.online.loop_response import MeasuredResponse, response_at, rig_over_model
from hilbench.online.pid import PID

__all__ = [
    "MIN_GAIN_MARGIN_DB",
    "MIN_PHASE_MARGIN_DEG",
    "IdentifiedLoop",
    "InstabilityError",
    "check",
    "design",
    "identify_loop",
    "margins",
    "predicted_error",
    "residual_spectrum",
]

#: design targets over the whole local-gain range
MIN_GAIN_MARGIN_DB = 6.0
MIN_PHASE_MARGIN_DEG = 45.0
#: the local-gain estimate is widened to at least this band around 1 (a fit is never exact)
MIN_GAIN_BAND = (0.8, 1.25)
#: monotone stretches of the model output this fraction of its span long give one local gain
STRETCH_FRACTION = 0.02
GAIN_PERCENTILES = (5.0, 95.0)
#: refused above this fraction of stretches where the rig moves against the model
MAX_NEGATIVE_FRACTION = 0.25
#: the local gain's lower end is at least this fraction of its median
GAIN_FLOOR = 0.1
#: integral gains tried below the margins' ceiling (geometric, down to KI_SPAN below it)
KI_CANDIDATES = 49
KI_SPAN = 1e-4
#: the training residual's power spectrum is kept on this many log-spaced frequency bins
SPECTRUM_BINS = 240
#: without training data the design crosses over at most at fs / this
NO_DATA_BANDWIDTH_DIVISOR = 100.0
#: gains evaluated across the range (geometric)
GAIN_POINTS = 9


class InstabilityError(UserError):
    """A compensator or feedback configuration that cannot be stable; refused before the loop starts."""


@dataclass
class IdentifiedLoop:
    """The loop the output-domain PID closes: ``z^-1 (measurement) z^-d G(z) e^{-s lag}`` times a
    local gain in ``gain_range``. ``b, a``: the model's dynamics (z^-1 polynomials, unit DC
    gain), ``delay_samples`` the model's delay, ``lag_s`` the unmodelled lag (s)."""

    fs: float
    b: np.ndarray
    a: np.ndarray
    delay_samples: int
    lag_s: float
    gain_range: tuple[float, float]
    source: str
    noise_um: float | None = None
    bandwidth_hz: float | None = None
    residual_um: float | None = None  # rms of measured - model over the training runs
    #: the training residual's mean-square power (um^2) per frequency bin: (centre frequencies in Hz,
    #: power per bin); its sum is residual_um^2. None without training data
    residual_spectrum: tuple[np.ndarray, np.ndarray] | None = None
    longest_run_s: float | None = None  # the longest training run (s): the slowest error it resolves
    #: the same for the rows the fit held out (the validation rows of each run), None when it held
    #: none: the error feed-forward leaves on drives the model was not fitted on
    held_out_um: float | None = None
    held_out_spectrum: tuple[np.ndarray, np.ndarray] | None = None
    #: the spectra's constant part run by run ((um^2 of the mean square per run, the run's length in
    #: s), :func:`constant_part`): what an integrator removes of it depends on how long it has. None:
    #: removed whole (a run long against the integral time)
    residual_constant: tuple[np.ndarray, np.ndarray] | None = None
    held_out_constant: tuple[np.ndarray, np.ndarray] | None = None
    #: the rig's response over the model's where the training runs measured it (the lag included),
    #: None where they did not (:mod:`hilbench.online.loop_response`)
    measured: MeasuredResponse | None = None
    #: the compensator's response to a correction (static model output per um added to the target),
    #: set by the compensator that closes this loop; None: taken as one
    compensator: MeasuredResponse | None = None

    @property
    def has_dynamics(self) -> bool:
        return bool(self.b.size > 1 or self.a.size > 1)

    def gains(self) -> np.ndarray:
        lo, hi = self.gain_range
        return np.geomspace(lo, hi, GAIN_POINTS) if hi > lo else np.array([lo])

    def plant_response(self, w: np.ndarray) -> np.ndarray:
        """Unit-gain plant (measurement delay included) at angular frequencies w (rad/s)."""
        zi = np.exp(-1j * w / self.fs)  # z^-1
        g = np.polyval(self.b[::-1], zi) / np.polyval(self.a[::-1], zi)
        g = g * zi ** (1 + self.delay_samples) * np.exp(-1j * w * self.lag_s)
        f = w / (2.0 * np.pi)
        if self.measured is not None:
            # where the runs measured the rig's response over the model's, that response and not
            # the lag alone: a resonance the model lacks is in the loop
            g = g * response_at(self.measured, f, self.lag_s)
        if self.compensator is not None:
            # its phase and its rise, not a fall: a correction the inverse passes only in part at the
            # size of the sensor's noise (a reversal on a hysteresis branch, a dead zone) passes whole
            # once it grows, and the loop must hold then too
            c = response_at(self.compensator, f)
            g = g * c / np.maximum(np.minimum(np.abs(c), 1.0), 1e-12)
        return g

    def integer_plant(self) -> tuple[np.ndarray, np.ndarray]:
        """(b, a) with the model delay and the unmodelled lag rounded up, for the pole check (the
        measurement delay is in :meth:`PID.char_poly`)."""
        extra = self.delay_samples + int(math.ceil(self.lag_s * self.fs - 1e-9))
        return np.concatenate([np.zeros(extra), self.b]), self.a

    def describe(self) -> dict[str, Any]:
        return {"local_gain_range": [float(self.gain_range[0]), float(self.gain_range[1])],
                "model_delay_samples": int(self.delay_samples), "measurement_delay_samples": 1,
                "unmodelled_lag_s": float(self.lag_s), "dynamics": "model" if self.has_dynamics else "none",
                "source": self.source, "noise_um": self.noise_um,
                "identified_up_to_hz": self.bandwidth_hz, "training_error_um": self.residual_um,
                "held_out_error_um": self.held_out_um,
                "rig_over_model": self.measured.describe() if self.measured is not None else None,
                "compensator_response": self.compensator.describe() if self.compensator is not None else None}


# ====================================================================================================
# identification
# ====================================================================================================


def _model_dynamics(model: Any, fs: float) -> tuple[np.ndarray, np.ndarray, int]:
    b, a = np.ones(1), np.ones(1)
    dyn = model.effect("dynamics")
    if dyn is not None:
        b, a = (np.asarray(x, float) for x in dyn.coefficients(fs))
        dc = float(np.sum(b) / np.sum(a))
        if math.isfinite(dc) and dc != 0.0:
            b = b / dc  # the static gain is the hysteresis model's; the loop sees the shape
    delay = model.effect("delay")
    d = int(round(delay.param("seconds") * fs)) if delay is not None else 0
    return b, a, d


def training_runs(model: Any) -> list[tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], float]]:
    """(input, output, aux, fs, n_train) of the runs the model was fitted on, in order, when the
    files are at hand; the first n_train samples trained it (70 % unless the split names runs)."""
    from hilbench.recording.hdf5 import Recording

    runs = []
    info = getattr(model, "info", {}) or {}
    split = str((info.get("fit") or {}).get("split", ""))
    fraction = 0.7 if "first" in split else 1.0
    for entry in info.get("fitted_on", []) or []:
        try:
            run = Recording(entry["file"]).run(entry["run"])
            data = run.data()
        except Exception:  # noqa: BLE001  (a moved or unreadable file: fall back to assumptions)
            continue
        n = int(fraction * data["input"].size)
        aux = {k: np.asarray(v, float) for k, v in data.items() if k not in ("time", "input", "output")}
        runs.append((np.asarray(data["input"], float), np.asarray(data["output"], float), aux,
                     float(run.sample_rate_hz), n))
    return runs


def _lag_and_gains(y_meas: np.ndarray, y_mod: np.ndarray) -> tuple[float, np.ndarray, float] | None:
    """The lag (samples) mapping the model's output onto the measured one, the local gains of the
    monotone stretches (after that shift), and the noise (um rms) of one run."""
    ok = np.isfinite(y_meas) & np.isfinite(y_mod)
    if np.count_nonzero(ok) < 50:
        return None
    y_meas, y_mod = y_meas[ok], y_mod[ok]
    d = np.gradient(y_mod)
    r = y_meas - y_mod
    den = float(np.dot(d, d))
    if den <= 0.0:
        return None
    lag = max(0.0, -float(np.dot(r, d)) / den)  # y(k) ~ y_mod(k - lag)
    for _ in range(3):  # refine: a lag of several samples is not linear in the derivative
        k = np.arange(y_mod.size, dtype=float)
        shifted = np.interp(k - lag, k, y_mod)
        ds = np.gradient(shifted)
        step = -float(np.dot(y_meas - shifted, ds)) / max(float(np.dot(ds, ds)), 1e-300)
        lag = max(0.0, lag + step)
        if abs(step) < 1e-3:
            break
    k = np.arange(y_mod.size, dtype=float)
    shifted = np.interp(k - lag, k, y_mod)
    span = float(np.ptp(shifted))
    noise = float(np.std(np.diff(y_meas - shifted, 2)) / math.sqrt(6.0))
    if span <= 0.0:
        return lag, np.zeros(0), noise
    # a stretch: 2 % of the model's span, and 20 noise sigma on one side at least (the ratio is then
    # good to ~7 %: the measured rise's noise is sqrt(2) sigma)
    step_um = STRETCH_FRACTION * span
    floor_um = 20.0 * noise
    gains = []
    start = 0
    direction = 0.0
    for i in range(1, shifted.size):
        dv = shifted[i] - shifted[i - 1]
        s = 1.0 if dv > 0 else (-1.0 if dv < 0 else 0.0)
        if s != 0.0 and direction != 0.0 and s != direction:
            start = i - 1  # a reversal of the model output: a new stretch starts at the turning point
        if s != 0.0:
            direction = s
        moved = shifted[i] - shifted[start]
        if abs(moved) >= step_um and max(abs(moved), abs(y_meas[i] - y_meas[start])) >= floor_um:
            gains.append((y_meas[i] - y_meas[start]) / moved)
            start = i
    return lag, np.asarray(gains), noise


def _binned_power(r: np.ndarray, run_fs: float, edges_hz: np.ndarray) -> np.ndarray:
    """The sum of squares of ``r`` (um^2) split over the frequency bins ``edges_hz`` (Parseval:
    the bins sum to sum(r^2)); the DC part goes to the first bin."""
    n = r.size
    spec = np.abs(np.fft.rfft(r)) ** 2 / n
    spec[1:(n + 1) // 2] *= 2.0  # both halves of the two-sided spectrum, Nyquist and DC once
    f = np.fft.rfftfreq(n, 1.0 / run_fs)
    k = np.clip(np.searchsorted(edges_hz, f, side="right") - 1, 0, edges_hz.size - 2)
    return np.bincount(k, weights=spec, minlength=edges_hz.size - 1)


def residual_spectrum(residuals: list[tuple[np.ndarray, float]], fs: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The mean-square power (um^2) of the residuals ((samples, their rate in Hz) per run) on one log
    grid of SPECTRUM_BINS bins from the longest run's resolution to the loop's Nyquist frequency ``fs``
    / 2 (a faster run's content above it is folded into the top bin): (bin centres in Hz, power per
    bin, the longest run in s). The bins sum to the residuals' mean square."""
    longest = max(r.size / rfs for r, rfs in residuals)
    edges = np.concatenate([[0.0], np.geomspace(0.5 / longest, 0.5 * fs, SPECTRUM_BINS)])
    power = sum(_binned_power(r, rfs, edges) for r, rfs in residuals) / max(sum(r.size for r, _ in residuals), 1)
    centres = np.concatenate([[0.0], np.sqrt(edges[1:-1] * edges[2:])])
    return centres, np.asarray(power, float), float(longest)


def constant_part(residuals: list[tuple[np.ndarray, float]]) -> tuple[np.ndarray, np.ndarray]:
    """The constant part of each residual ((samples, rate in Hz) per run): its share of the residuals'
    mean square (um^2, n mean^2 over all samples: the spectrum's first bin, run by run) and the run's
    length (s)."""
    total = max(sum(r.size for r, _ in residuals), 1)
    share = np.array([r.size * float(np.mean(r)) ** 2 / total if r.size else 0.0 for r, _ in residuals])
    seconds = np.array([r.size / rfs for r, rfs in residuals], dtype=float)
    return share, seconds


def _remaining_constant(constant: tuple[np.ndarray, np.ndarray], rate_per_s: float) -> float:
    """What an integral loop leaves of each run's constant error over the run (um^2 of the mean square):
    the error decays as exp(-rate t) from the run's start (the integrator starts empty), so over a run
    of T seconds its mean square is a (1 - exp(-2 rate T)) / (2 rate T) share of the constant's."""
    share, seconds = constant
    x = 2.0 * rate_per_s * seconds
    kept = np.where(x > 1e-9, -np.expm1(-x) / np.where(x > 1e-9, x, 1.0), 1.0)
    return float(np.sum(share * kept))


def identify_loop(model: Any, fs: float, *, runs: list | None = None) -> IdentifiedLoop:
    """The loop the output-domain PID closes on a rig at ``fs`` (Hz) for ``model`` (see the module
    docstring). ``runs``: (input, output, aux, fs[, n_train]) tuples in recorded order; default: the
    model's training runs."""
    from hilbench.diagnosis.input_motion import excited_bandwidth_hz
    from hilbench.models import stepping as ST

    b, a, d = _model_dynamics(model, fs)
    runs = training_runs(model) if runs is None else runs
    lags: list[float] = []
    gains: list[np.ndarray] = []
    noises: list[float] = []
    bands: list[float] = []
    squares: list[float] = []
    counts: list[int] = []
    residuals: list[tuple[np.ndarray, float]] = []
    held_out: list[tuple[np.ndarray, float]] = []
    responses: list[tuple[np.ndarray, np.ndarray, float, float]] = []
    used = 0
    compiled: dict[float, Any] = {}
    for run in runs:
        u, y, aux, run_fs = run[:4]
        n_train = run[4] if len(run) > 4 else u.size
        try:
            # one model memory through the runs in order, as the fit ran them: a run starts where
            # the last one left the actuator, not from a virgin state
            if run_fs not in compiled:
                compiled[run_fs] = ST.compile_model(model, run_fs)
            y_mod = compiled[run_fs].block(u, aux or None)
        except Exception:  # noqa: BLE001  (a model that cannot run on the record: not evidence)
            continue
        y_mod = np.asarray(y_mod, float)
        # the rig's response is measured against the model without its rate terms: those are its
        # account of how the loop widens with the drive rate, not of how the rig answers the small,
        # fast corrections of a feedback loop; there the rig answers with its mechanics
        c = compiled[run_fs]
        y_free = (np.asarray(ST.CompiledModel(ST.without_rate_terms(c.I), c.P, c.channels).block(u, aux or None), float)
                  if c.I[ST.I_RATE] != 0 else y_mod)
        rest = y[n_train:] - y_mod[n_train:]
        rest = rest[np.isfinite(rest)]
        u, y, y_mod = u[:n_train], y[:n_train], y_mod[:n_train]
        got = _lag_and_gains(y, y_mod)
        if got is None:
            continue
        lag, g, noise = got
        g = g[np.isfinite(g)]
        if not (math.isfinite(lag) and math.isfinite(noise)):
            continue
        lags.append(lag / run_fs)
        gains.append(g)
        noises.append(noise)
        bands.append(excited_bandwidth_hz(u, run_fs))
        r = (y - y_mod)[np.isfinite(y) & np.isfinite(y_mod)]
        residuals.append((r, float(run_fs)))
        responses.append((y_free[:n_train], y, float(run_fs), noise))
        if rest.size:
            held_out.append((rest, float(run_fs)))
        squares.append(float(np.sum(r * r)))
        counts.append(int(r.size))
        used += 1
    allg = np.concatenate(gains) if gains else np.zeros(0)
    if used == 0 or allg.size < 10:
        # nothing measured: the model's own loop (unit gain, its dynamics and delay); the design's
        # 6 dB and 45 deg are then the only allowance for what the model misses, and it crosses
        # over no higher than fs / 100 (nothing says where the rig's own dynamics start)
        return IdentifiedLoop(fs, b, a, d, 0.0, (1.0, 1.0),
                              "the model only (no training data at hand): unit local gain, no unmodelled lag, "
                              f"crossover at most fs/{NO_DATA_BANDWIDTH_DIVISOR:g}",
                              bandwidth_hz=fs / NO_DATA_BANDWIDTH_DIVISOR)
    lo, hi = (float(np.percentile(allg, p)) for p in GAIN_PERCENTILES)
    negative = float(np.mean(allg <= 0.0))
    median = float(np.median(allg))
    if negative > MAX_NEGATIVE_FRACTION or not median > 0.0:
        raise InstabilityError(
            f"the rig's local gain over the model's ({GAIN_PERCENTILES[0]:g}th-{GAIN_PERCENTILES[1]:g}th percentile "
            f"over the model's training runs) ranges from {lo:.3g} to {hi:.3g}, negative on {100 * negative:.0f} % of "
            "the stretches: there the rig moves against the model, and no output-domain feedback is stable on both "
            "signs", hint="fit a model that follows the rig (hilbench diagnose), then add feedback")
    # a few stretches against the model (at reversals, where a lag is not a pure shift) are not the
    # rig's gain: the lower end only slows an integrator down, it does not destabilise it
    lo = max(lo, GAIN_FLOOR * median)
    lo, hi = min(lo, MIN_GAIN_BAND[0]), max(hi, MIN_GAIN_BAND[1])
    # the largest lag of any training run: the loop must hold at the slowest the rig answered
    lag_s = max(lags)
    centres, power, longest = residual_spectrum(residuals, fs)
    ho_um, ho_spectrum, ho_constant = None, None, None
    if held_out:
        ho_centres, ho_power, _ = residual_spectrum(held_out, fs)
        ho_spectrum = (ho_centres, ho_power)
        ho_um = math.sqrt(float(np.sum(ho_power)))  # the bins sum to the mean square
        ho_constant = constant_part(held_out)
    return IdentifiedLoop(fs, b, a, d, lag_s, (lo, hi), f"training data: {used} run(s), {allg.size} stretches",
                          noise_um=float(np.median(noises)), bandwidth_hz=max(bands) or None,
                          residual_um=math.sqrt(sum(squares) / max(sum(counts), 1)),
                          residual_spectrum=(centres, power), longest_run_s=longest,
                          held_out_um=ho_um, held_out_spectrum=ho_spectrum,
                          residual_constant=constant_part(residuals), held_out_constant=ho_constant,
                          measured=rig_over_model(responses, fs))


# ====================================================================================================
# margins, design, check
# ====================================================================================================


def _controller_response(pid: PID, fs: float, w: np.ndarray) -> np.ndarray:
    T = 1.0 / fs
    tf = pid.tf_s if pid.tf_s is not None else 4.0 * T
    zi = np.exp(-1j * w / fs)
    integ = pid.ki * T / (1.0 - zi)
    deriv = pid.kd * (1.0 - zi) / ((tf + T) - tf * zi)
    return pid.kp + integ + deriv


def _grid(fs: float) -> np.ndarray:
    return 2.0 * np.pi * np.geomspace(1e-5 * fs, 0.5 * fs, 6000)


def margins(pid: PID, loop: IdentifiedLoop) -> dict[str, Any]:
    """Gain margin (dB), phase margin (deg) and crossover (Hz), the worst over the gain range, and
    whether the closed-loop poles stay inside the unit circle at every gain of the range."""
    w = _grid(loop.fs)
    base = _controller_response(pid, loop.fs, w) * loop.plant_response(w)
    gm, pm, fc = math.inf, math.inf, 0.0
    for g in loop.gains():
        L = g * base
        mag = np.abs(L)
        ph = np.unwrap(np.angle(L))
        # phase crossings of -180 - 360 k deg: the gain margin is 1/|L| there
        # (a loop that reaches -180 deg exactly at the Nyquist frequency crosses there)
        turns = np.floor((ph + np.pi * (1 - 1e-9)) / (2 * np.pi))
        for i in np.flatnonzero(np.diff(turns) != 0):
            gm = min(gm, -20.0 * math.log10(max(float(mag[i]), 1e-300)))
        # unit-gain crossings: the phase margin is 180 + phase there (wrapped to (-180, 180])
        for i in np.flatnonzero(np.diff(np.sign(mag - 1.0)) != 0):
            margin = math.degrees((float(ph[i]) + np.pi) % (2 * np.pi))
            margin = margin - 360.0 if margin > 180.0 else margin
            pm = min(pm, margin)
            fc = max(fc, float(w[i]) / (2 * np.pi))
    bi, ai = loop.integer_plant()
    radius = 0.0
    for g in loop.gains():
        radius = max(radius, float(np.max(np.abs(pid.poles(loop.fs, g * bi, ai)), initial=0.0)))
    return {"gain_margin_db": gm, "phase_margin_deg": pm, "crossover_hz": fc, "max_pole_radius": radius,
            "stable": bool(radius < 1.0 - 1e-9)}


def _meets(m: dict[str, Any], loop: IdentifiedLoop) -> bool:
    # above the training's excited bandwidth the rig's dynamics were never seen: no crossover there
    cap = loop.bandwidth_hz if loop.bandwidth_hz else math.inf
    return (m["stable"] and m["gain_margin_db"] >= MIN_GAIN_MARGIN_DB
            and m["phase_margin_deg"] >= MIN_PHASE_MARGIN_DEG and m["crossover_hz"] <= cap)


def predicted_error(pid: PID, loop: IdentifiedLoop, *, held_out: bool = False) -> float | None:
    """The rms error (um) the loop closed with ``pid`` is predicted to leave of the training residual
    (``held_out``: of the residual on the rows the fit held out), at the worst local gain of the
    range: sqrt(sum over frequency of the residual's power times |S|^2), S = 1 / (1 + L) the loop's
    sensitivity. With no controller it is the residual's rms (feed-forward's own error). None
    without that residual."""
    spectrum = loop.held_out_spectrum if held_out else loop.residual_spectrum
    if spectrum is None:
        return None
    constant = loop.held_out_constant if held_out else loop.residual_constant
    f, p = spectrum
    if pid.kp == 0.0 and pid.ki == 0.0 and pid.kd == 0.0:
        return math.sqrt(float(np.sum(p)))
    # an integrator removes a constant error in the end (its response is infinite there), but from an
    # empty start: over a run of T s at a loop rate ki g it leaves a (1 - exp(-2 ki g T)) / (2 ki g T)
    # share of it (a gain whose integral time outlasts the run removes almost nothing)
    dc = f == 0.0
    w = 2.0 * np.pi * f[~dc]
    base = _controller_response(pid, loop.fs, w) * loop.plant_response(w)
    worst = 0.0
    for g in loop.gains():
        s2 = 1.0 / np.abs(1.0 + g * base) ** 2
        if pid.ki <= 0.0:
            left = float(np.sum(p[dc]))
        elif constant is None:
            left = 0.0
        else:
            left = _remaining_constant(constant, pid.ki * g)
        worst = max(worst, float(np.sum(p[~dc] * s2)) + left)
    return math.sqrt(worst)


def design(loop: IdentifiedLoop, *, i_limit: float | None = None) -> tuple[PID, dict[str, Any]]:
    """The integral-only PID (ki in 1/s) meeting the margins over the gain range, lowered until its
    predicted error (:func:`predicted_error`) is not above feed-forward's. The margins give a ceiling
    (bisection in log ki: the loop gain scales with ki, the margins fall with it); below it,
    KI_CANDIDATES gains down to KI_SPAN of the ceiling are tried from the top. Without training data
    the ceiling is the gain; when every gain tried raises the error, ki is 0 (the loop left open)."""
    lo, hi = 1e-6 * loop.fs, 10.0 * loop.fs
    if not _meets(margins(PID(0.0, lo, 0.0, i_limit=i_limit), loop), loop):
        raise InstabilityError(f"no integral gain down to {lo:.3g} 1/s keeps {MIN_GAIN_MARGIN_DB:g} dB and "
                               f"{MIN_PHASE_MARGIN_DEG:g} deg over the local gain range "
                               f"{loop.gain_range[0]:.3g}-{loop.gain_range[1]:.3g}")
    for _ in range(50):
        mid = math.sqrt(lo * hi)
        if _meets(margins(PID(0.0, mid, 0.0, i_limit=i_limit), loop), loop):
            lo = mid
        else:
            hi = mid
        if hi / lo < 1.01:
            break
    ceiling = ki = lo
    m_max = margins(PID(0.0, ceiling, 0.0), loop)
    ff_error = predicted_error(PID(0.0, 0.0, 0.0), loop)
    ff_held = predicted_error(PID(0.0, 0.0, 0.0), loop, held_out=True)
    best = best_held = None
    if ff_error is not None:
        # the largest gain not predicted to raise the training error: what the training drives leave
        # near the crossover sets the ceiling; below it the integrator removes whatever slow error a
        # reference meets (an offset of the starting state, a drift) that the training residual lacks.
        # Nor the error on the rows the fit held out (decision 0117): where the model's error there is
        # the sensor's noise, the training residual's slow part (the runs' starts from rest, errors
        # the held-out rows lack) promised a gain a new reference does not pay for, and the noise
        # fed back near the crossover made it worse
        for k in np.geomspace(ceiling, ceiling * KI_SPAN, KI_CANDIDATES):
            best, ki = predicted_error(PID(0.0, float(k), 0.0), loop), float(k)
            best_held = predicted_error(PID(0.0, float(k), 0.0), loop, held_out=True)
            if best <= ff_error and (ff_held is None or best_held <= ff_held):  # type: ignore[operator]
                break
        else:
            best, best_held, ki = ff_error, ff_held, 0.0
        if loop.longest_run_s and 0.0 < ki * loop.longest_run_s < 1.0:
            # an integral time longer than the longest training run: it removes nothing within a run
            # of that length, and the prediction cannot resolve what it does over a longer one
            best, best_held, ki = ff_error, ff_held, 0.0
    pid = PID(0.0, float(ki), 0.0, i_limit=i_limit, reversal_guard=True)
    m = margins(pid, loop)
    m["ki_max_per_s"] = float(ceiling)
    m["crossover_max_hz"] = m_max["crossover_hz"]
    m["error_limited"] = bool(ki < ceiling)
    m["open"] = bool(ki == 0.0)
    if ff_error is not None and best is not None:
        m["predicted_error_um"] = float(best)
        m["feedforward_error_um"] = float(ff_error)
    if ff_held is not None and best_held is not None:
        m["predicted_held_out_error_um"] = float(best_held)
        m["feedforward_held_out_error_um"] = float(ff_held)
    return pid, m


def check(pid: PID, loop: IdentifiedLoop) -> dict[str, Any]:
    """User gains on the identified loop: the margins; InstabilityError (with the numbers) when a
    closed-loop pole leaves the unit circle at a gain of the range."""
    m = margins(pid, loop)
    if not m["stable"]:
        lo, hi = loop.gain_range
        raise InstabilityError(
            f"PID kp={pid.kp:g}, ki={pid.ki:g} 1/s, kd={pid.kd:g} s (output domain, um/um) destabilise the "
            f"identified loop: closed-loop pole at |z| = {m['max_pole_radius']:.4g} >= 1 over the local gain "
            f"range {lo:.3g}-{hi:.3g} with {'the model' if loop.has_dynamics else 'no'} dynamics, "
            f"{loop.delay_samples + 1} sample(s) of delay (one of measurement) and {loop.lag_s * 1e3:.3g} ms of "
            f"unmodelled lag ({loop.source})",
            hint="omit --kp/--ki/--kd to have the gains designed from the identified loop")
    return m
