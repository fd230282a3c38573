"""The sensor's noise floor, from the measured output itself (not from a model's residual).

The diagnosis asks whether a model's validation error is above what the sensor's noise leaves
unexplainable (``error_above_noise``, the wrong-base check). That floor is the sensor's: estimating
it from the residual ``e = model - measured`` counts every fast model error (a delay, a resonance,
rate effects at high drive rates, a fast signal sampled fast) as noise, and overestimated it ~3x
on such data, blocking true findings. Here it is estimated from the measured output ``y`` alone,
by several estimators that each see the white sensor noise plus some signal content:

* ``differences``: the k-th differences of ``y`` (k = 1..4) cancel polynomial trends of degree
  < k; the std of white noise's k-th difference is sqrt(C(2k, k)) sigma. Each order's robust std
  (MAD; pooled over the contiguous segments of every run) is one estimate; steps and corners are
  sparse and do not move a median.
* ``spectrum``: fast periodic drives leave signal in every difference, but only at their harmonics:
  the Hann-windowed periodogram of 1024-sample windows over the upper half of the band (fs/4 to
  fs/2), its lower quartile (harmonic lines only raise bins; for white noise a bin is exponential
  with mean sigma^2, so the quartile is ln(4/3) sigma^2) per window, the median over windows
  (windows with a step are the minority).
* ``holds``: where the input holds still (after NOISE_HOLD_SETTLE_S for ringing to settle) the output's
  second differences: only the noise moves (creep drifts slowly and cancels).
* ``quantisation``: a quantised output (every sample on a grid of step q) with little noise has
  differences of exactly 0 or +-q, where a median says nothing; its floor is the rms of the
  rounding error, q / sqrt(12), and estimates are taken from a trimmed std there instead.

Signal content only ever inflates these estimates, so the floor is the smallest of them that rests
on enough samples (MIN_SAMPLES), and never below the quantisation floor. The residual-based
estimate of earlier versions is kept in ``estimates["residual"]`` for comparison only.

Units: the output's unit (um).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hilbench.diagnosis import thresholds as T
from hilbench.identify.statistics import difference_noise_std, robust_std

ORDERS = T.NOISE_DIFFERENCE_ORDERS
MIN_SAMPLES = T.NOISE_MIN_SAMPLES
#: periodogram windows, samples (shorter segments use the longest power of two that fits, >= 128)
WINDOW = 1024
#: quantile of the top-band periodogram bins taken per window, and its value for white noise
#: (exponential bins of mean sigma^2: -ln(1 - q) sigma^2)
BAND_QUANTILE = 0.25
#: a trimmed std keeps the central fraction of the samples; for a normal distribution its variance
#: is this fraction of the full one (1 - 2 z phi(z) / (1 - 2 Phi(-z)), z = 1.645)
TRIM_KEEP = 0.9
_TRIM_VARIANCE = 0.6236


#: Sensor estimates whose variance is within this ratio of the floor's agree with it: their spread
#: is how well the floor is known (:meth:`NoiseFloor.variance_uncertainty`). Beyond, an estimate
#: holds signal content (decision 0044).
AGREEING_VARIANCE_RATIO = 2.0


class NoiseFloor(float):
    """The noise floor (a float, output unit) with ``estimates``: every estimate by name, what it
    rests on, and ``chosen``, the estimate taken."""

    estimates: dict[str, Any]

    def __new__(cls, value: float, estimates: dict[str, Any] | None = None) -> NoiseFloor:
        obj = super().__new__(cls, value)
        obj.estimates = dict(estimates or {})
        return obj

    def __reduce__(self) -> tuple[Any, ...]:
        return (NoiseFloor, (float(self), self.estimates))

    def variance_uncertainty(self) -> float:
        """How uncertain the floor's variance is, as a fraction of it: the spread of the sensor
        estimates (differences, spectrum, holds) that agree with the floor, (largest / smallest)^2 - 1
        over those within AGREEING_VARIANCE_RATIO of it in variance. Signal content only inflates an
        estimate: one far above the floor measured the signal (first differences of a 10 kHz record
        of a fast drive: 46x the spectrum's), not the floor's uncertainty. inf when fewer than two
        estimates agree."""
        floor = float(self)
        vals = [float(v) for k, v in self.estimates.items()
                if (k.startswith("differences_") or k in ("spectrum", "holds"))
                and isinstance(v, (int, float)) and math.isfinite(v) and v > 0]
        vals = [v for v in vals if floor > 0 and (v / floor) ** 2 <= AGREEING_VARIANCE_RATIO]
        if len(vals) < 2:
            return math.inf
        return (max(vals) / min(vals)) ** 2 - 1.0


def residual_noise_floor(e: np.ndarray, run: np.ndarray) -> float:
    """The old estimate: noise std from sample-to-sample differences of the residual (MAD), output
    unit. Model error that changes fast inflates it; kept for comparison."""
    d = np.concatenate([np.diff(e[run == k]) for k in np.unique(run)]) if e.size else np.zeros(0)
    if d.size < 3:
        return 0.0
    return difference_noise_std(d)


def segments(run: np.ndarray, t: np.ndarray) -> list[np.ndarray]:
    """Index arrays of the contiguous stretches of rows: one run, no gap in time (validation rows
    of a run are contiguous; a masked sample splits)."""
    out = []
    for k in np.unique(run):
        idx = np.flatnonzero(run == k)
        if idx.size < 2:
            continue
        dt = np.diff(t[idx])
        step = float(np.median(dt)) if dt.size else 0.0
        cuts = np.flatnonzero(dt > 1.5 * step) + 1 if step > 0 else np.zeros(0, int)
        out += [s for s in np.split(idx, cuts) if s.size >= 2]
    return out


def quantum(y: np.ndarray) -> float:
    """The grid step of a quantised signal (0 when it is not quantised): the smallest nonzero step
    between samples, when at least 99 % of the samples lie on that grid (and it is not a
    floating-point rounding step)."""
    y = y[np.isfinite(y)]
    if y.size < 10:
        return 0.0
    d = np.abs(np.diff(y))
    scale = float(np.max(np.abs(y))) or 1.0
    nz = d[d > 1e-9 * scale]
    if nz.size == 0:
        return 0.0
    q = float(nz.min())
    x = (y - y[0]) / q
    on_grid = np.abs(x - np.round(x)) < 1e-3
    return q if on_grid.mean() >= 0.99 else 0.0


def trimmed_std(x: np.ndarray) -> float:
    """Std of a normal sample from its central TRIM_KEEP (by rank: ties on a grid are cut cleanly)."""
    x = np.sort(x[np.isfinite(x)])
    if x.size < 10:
        return 0.0
    cut = int(round(0.5 * (1 - TRIM_KEEP) * x.size))
    core = x[cut: x.size - cut]
    return float(np.sqrt(np.mean((core - np.mean(core)) ** 2) / _TRIM_VARIANCE))


def _scale(x: np.ndarray, quantised: bool) -> float:
    return trimmed_std(x) if quantised else robust_std(x)


def difference_estimates(ys: list[np.ndarray], quantised: bool) -> dict[int, tuple[float, int]]:
    """order -> (noise std from the pooled ``order``-th differences of every segment, samples)."""
    out = {}
    for k in ORDERS:
        d = [np.diff(y, k) for y in ys if y.size > k]
        if not d:
            continue
        d = np.concatenate(d)
        out[k] = (_scale(d, quantised) / math.sqrt(math.comb(2 * k, k)), int(d.size))
    return out


def spectrum_estimate(ys: list[np.ndarray]) -> tuple[float, int]:
    """(noise std from the upper half of the band, samples used): module docstring."""
    per_window, used = [], 0
    for y in ys:
        n = y.size
        if n < 128:
            continue
        L = min(WINDOW, 1 << int(math.log2(n)))
        w = np.hanning(L)
        norm = float(np.sum(w**2))
        lo_bin = L // 4 + 1  # fs/4 (bins are fs/L apart); Nyquist's bin left out
        starts = range(0, n - L + 1, L // 2)
        for s in starts:
            x = y[s: s + L]
            x = x - np.polyval(np.polyfit(np.arange(L), x, 1), np.arange(L))
            p = np.abs(np.fft.rfft(w * x)[lo_bin: L // 2]) ** 2 / norm
            per_window.append(np.quantile(p, BAND_QUANTILE) / -math.log(1.0 - BAND_QUANTILE))
        used += n
    if not per_window:
        return float("nan"), 0
    return float(math.sqrt(np.median(per_window))), used


def hold_estimate(ys: list[np.ndarray], quantised: bool) -> tuple[float, int]:
    """(noise std from the second differences of the output along settled holds, samples)."""
    d = [np.diff(y, 2) for y in ys if y.size > 8]
    if not d:
        return float("nan"), 0
    d = np.concatenate(d)
    return _scale(d, quantised) / math.sqrt(6.0), int(d.size)


def sensor_noise(y: np.ndarray, run: np.ndarray, t: np.ndarray, held: np.ndarray | None = None,
                 since: np.ndarray | None = None) -> NoiseFloor:
    """The sensor's noise std from the measured output ``y`` (rows of runs ``run`` at times ``t``,
    s), with the input holding still where ``held`` (and ``since`` s since it last moved): module
    docstring. Output unit."""
    finite = np.isfinite(y)
    segs = [s[finite[s]] for s in segments(run, t)]
    segs = [s for s in segs if s.size >= 2]
    ys = [y[s] for s in segs]
    q = max((quantum(v) for v in ys), default=0.0)
    quantised = q > 0
    est: dict[str, Any] = {}
    candidates: dict[str, float] = {}
    for k, (v, n) in difference_estimates(ys, quantised).items():
        est[f"differences_{k}"] = v
        if n >= MIN_SAMPLES:
            candidates[f"differences_{k}"] = v
    v, n = spectrum_estimate(ys)
    if n:
        est["spectrum"] = v
        if n >= MIN_SAMPLES and math.isfinite(v):
            candidates["spectrum"] = v
    if held is not None:
        settled = held & (since > T.NOISE_HOLD_SETTLE_S) if since is not None else held
        hold_segs = []
        for s in segs:
            m = settled[s]
            edges = np.flatnonzero(np.diff(m.astype(np.int8)) != 0) + 1
            hold_segs += [y[p] for p in np.split(s, edges) if p.size > 8 and settled[p[0]]]
        v, n = hold_estimate(hold_segs, quantised)
        if n:
            est["holds"] = v
            est["hold_samples"] = n
            if n >= MIN_SAMPLES and math.isfinite(v):
                candidates["holds"] = v
    floor = q / math.sqrt(12.0)
    if quantised:
        est["quantum"] = q
        est["quantisation"] = floor
    chosen = min(candidates, key=candidates.get) if candidates else None
    value = candidates[chosen] if chosen else 0.0
    if floor > value:
        value, chosen = floor, "quantisation"
    est["chosen"] = chosen
    return NoiseFloor(value, est)
