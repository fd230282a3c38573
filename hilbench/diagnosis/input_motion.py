"""How the input moves: rate, direction, holds, reversals and drive frequencies of one run.

Used by the diagnosis to locate errors (rising / falling / turning / hold), to decide what the data
can test (several drive frequencies? steps? holds long enough for creep?) and to group runs by drive
rate. A measured input is noisy, so "holding still" means staying inside a dead band set by the
input's own noise (:func:`hold_band`), not bit-for-bit constancy.

Units: input in the command unit (V or A), rates in input units per s, times in s, frequencies in Hz.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numba import njit

from hilbench.identify.statistics import difference_noise_std

#: a measured input holds still inside this many noise stds, capped at this fraction of its span
HOLD_NOISE_SIGMAS = 5.0
HOLD_MAX_SPAN = 0.01
#: a jump larger than this fraction of the span within one sample counts as a step
STEP_FRACTION = 0.05
#: samples (or input fraction of the span) around a reversal that count as "turning"
TURNING_SAMPLES = 5
TURNING_SPAN = 0.02
#: The input "excites" a frequency where its power spectral density stands this far above the
#: input's own noise floor (20 dB) and above EXCITED_RELATIVE of its strongest component (-60 dB:
#: a harmonic of 0.1 % of the drive's amplitude; behind a resonance of Q ~ 10 that is a ringing of
#: 1 % of the output's, well above a sensor's noise). A sharp triangle's harmonics fall as 1/k^2 in
#: amplitude and reach ~30x its drive frequency; a sine's end at its own frequency.
EXCITED_OVER_NOISE = 100.0
EXCITED_RELATIVE = 1e-6
#: A half cycle counts as a loop at its rate when it spans at least this fraction of the input span:
#: a reversal in the jitter of a hold or a noise drive's ripple draws no loop a rate term could fit.
LOOP_MIN_SPAN = 0.1
#: A rate is present in the loops when at least this many half cycles (two full loops) run at it or
#: beyond it: three loops of a 9 Hz triangle before minutes at 0.7 Hz are a second rate a rate term
#: is fitted on, though they fill a few percent of the time.
LOOP_HALF_CYCLES = 4


def input_noise(u: np.ndarray) -> float:
    """Noise std of a measured input (command unit), from its fourth differences (robust: MAD).

    Fourth differences cancel ramps and parabolas and are tiny on smooth drives (A (w dt)^4 for a
    sine: 0.02 V for 90 V at 20 Hz sampled at 1 kHz), so a digital command gives ~0 and a measured
    voltage its (white) sensor noise: the fourth difference of white noise has std sqrt(70) sigma."""
    if u.size < 9:
        return 0.0
    return difference_noise_std(np.diff(u, 4), order=4)


@njit(cache=True)
def _held(u: np.ndarray, band: float) -> np.ndarray:
    """True where the input stays within ``band`` of the value it last moved to (a dead band)."""
    out = np.zeros(u.shape[0], np.bool_)
    held = u[0] if u.shape[0] else 0.0
    for i in range(1, u.shape[0]):
        if abs(u[i] - held) > band:
            held = u[i]
        else:
            out[i] = True
    return out


def hold_band(u: np.ndarray, span: float) -> float:
    """The dead band within which the input counts as holding still: HOLD_NOISE_SIGMAS input-noise
    stds, at least 1e-6 and at most HOLD_MAX_SPAN of the input span (a noisy drive must not turn
    into holds)."""
    floor = 1e-6 * max(span, 1e-12)
    return float(min(max(HOLD_NOISE_SIGMAS * input_noise(u), floor), max(HOLD_MAX_SPAN * span, floor)))


def _forward_fill(x: np.ndarray) -> np.ndarray:
    """Each zero replaced by the last nonzero value before it (zero before the first)."""
    idx = np.where(x != 0.0, np.arange(x.size), 0)
    np.maximum.accumulate(idx, out=idx)
    return x[idx]


def _run_length(still: np.ndarray) -> np.ndarray:
    """How many samples in a row, up to and including each one, are still (0 where moving)."""
    count = np.cumsum(still)
    reset = np.where(~still, count, 0)
    np.maximum.accumulate(reset, out=reset)
    return count - reset


def motion(u: np.ndarray, fs: float, span: float) -> dict[str, np.ndarray]:
    """Rate ``du`` (input unit/s), ``direction`` (rising / falling / turning / hold), ``since`` (s
    the input has held still), ``flips`` (reversal indices) and ``still`` of one run, all rows.

    ``span`` is the input span the turning band is measured against (of all runs compared)."""
    n = u.size
    du = np.gradient(u) * fs if n > 1 else np.zeros(n)
    still = _held(np.ascontiguousarray(u, dtype=np.float64), hold_band(u, span))
    sign = np.sign(du)
    sign[still] = 0.0
    filled = _forward_fill(sign)
    flips = np.flatnonzero((filled[1:] * filled[:-1]) < 0) + 1
    direction = np.where(sign > 0, "rising", np.where(sign < 0, "falling", "hold")).astype(object)
    if flips.size:
        idx = np.arange(n)
        pos = np.searchsorted(flips, idx)
        near = np.zeros(n, bool)
        for cand in (np.clip(pos - 1, 0, flips.size - 1), np.clip(pos, 0, flips.size - 1)):
            f = flips[cand]
            near |= (np.abs(idx - f) <= TURNING_SAMPLES) | (np.abs(u - u[np.maximum(f - 1, 0)]) <= TURNING_SPAN * span)
        direction[near & (sign != 0)] = "turning"
    # a sharp corner has zero central-difference rate without holding still
    direction[(sign == 0) & ~still & (np.abs(np.diff(u, prepend=u[:1])) > 0)] = "turning"
    since = _run_length(still) / fs
    return {"du": du, "direction": direction, "since": since, "flips": flips, "still": still}


def excited_bandwidth_hz(u: np.ndarray, fs: float) -> float:
    """The highest frequency (Hz) the input excites (module constants EXCITED_*): Welch's power
    spectral density against the median of its top quarter band (the white noise of a measured input,
    or the quantisation of a digital one) and against its peak. 0 for too short a record."""
    from scipy import signal

    u = u[np.isfinite(u)]
    if u.size < 64:
        return 0.0
    f, p = signal.welch(u - float(np.mean(u)), fs, nperseg=min(u.size, 4096))
    top = p[f >= 0.375 * fs]
    floor = float(np.median(top)) if top.size else 0.0
    level = max(EXCITED_OVER_NOISE * floor, EXCITED_RELATIVE * float(p.max()))
    above = np.flatnonzero(p > level)
    return float(f[above[-1]]) if above.size else 0.0


def half_cycle_frequencies(flips: np.ndarray, fs: float) -> np.ndarray:
    """Drive frequency (Hz) of every half cycle between consecutive reversals."""
    return fs / (2.0 * np.diff(flips)) if flips.size >= 2 else np.zeros(0)


def loop_spread(f: np.ndarray, amplitude: np.ndarray, span: float) -> float:
    """Spread of drive frequencies counted in loops: the LOOP_HALF_CYCLES-th fastest over the
    LOOP_HALF_CYCLES-th slowest frequency of the half cycles spanning LOOP_MIN_SPAN of the input
    span (1 when fewer than two such sets exist)."""
    f = np.sort(f[amplitude >= LOOP_MIN_SPAN * span])
    k = LOOP_HALF_CYCLES
    return float(f[-k] / f[k - 1]) if f.size >= 2 * k else 1.0


def rate_spread(f: np.ndarray, amplitude: np.ndarray, span: float) -> float:
    """Spread of drive rates: of the half cycles spanning LOOP_MIN_SPAN of the input span, the 90th
    over the 10th percentile over time of their mean rates (swing x 2 f, input unit per s), or the
    LOOP_HALF_CYCLES-th fastest over the LOOP_HALF_CYCLES-th slowest (a few loops at a second rate),
    the larger; 1 when fewer than three such half cycles. One frequency at several amplitudes drives
    several rates: what a velocity damping is a function of (decision 0064)."""
    keep = (amplitude >= LOOP_MIN_SPAN * span) & (f > 0)
    rates, durations = 2.0 * f[keep] * amplitude[keep], 0.5 / f[keep]
    if rates.size < 3:
        return 1.0
    p10, p90 = (_weighted_percentile(rates, durations, q) for q in (10, 90))
    k = LOOP_HALF_CYCLES
    ordered = np.sort(rates)
    loops = float(ordered[-k] / ordered[k - 1]) if rates.size >= 2 * k and ordered[k - 1] > 0 else 1.0
    return max(p90 / p10 if p10 > 0 else 1.0, loops)


def excursion_rates(u: np.ndarray, fs: float, span: float, still: np.ndarray) -> np.ndarray:
    """Mean rates (input unit per s) of the input's monotone excursions spanning LOOP_MIN_SPAN of
    ``span``: the stretches between holds (``still``) and reversals over which it moves one way.
    A half cycle of a sine is one (its rate about swing x 2 f), a step is one (its swing over its
    slew), a staircase is one per step."""
    du = np.diff(u)
    sign = np.sign(du)
    sign[still[1:]] = 0.0
    rates = []
    start = 0
    for k in range(1, sign.size + 1):
        if k == sign.size or sign[k] != sign[start]:
            if sign[start] != 0.0:
                swing = abs(float(u[k] - u[start]))
                if swing >= LOOP_MIN_SPAN * span:
                    rates.append(swing * fs / (k - start))
            start = k
    return np.asarray(rates, dtype=float)


def step_rate_ratio(excursions: np.ndarray, f: np.ndarray, amplitude: np.ndarray, span: float) -> float:
    """How much faster than any part of the loops the fastest excursion moves: its mean rate over
    pi/2 x the fastest loop's mean rate (swing x 2 f, of the half cycles spanning LOOP_MIN_SPAN of
    ``span``). pi/2 is a sine's peak rate over its mean, so no stretch of a loop reaches a ratio
    above 1; a step slewed in a few samples beside slow loops reaches tens. 1 without both."""
    keep = (amplitude >= LOOP_MIN_SPAN * span) & (f > 0)
    if not keep.any() or not excursions.size:
        return 1.0
    loops = float(np.max(2.0 * f[keep] * amplitude[keep]))
    return max(1.0, float(np.max(excursions)) / (0.5 * np.pi * loops)) if loops > 0 else 1.0


def _weighted_percentile(x: np.ndarray, weights: np.ndarray, q: float) -> float:
    """The ``q``-th percentile of ``x``, each value counted with its weight."""
    order = np.argsort(x)
    w = np.cumsum(weights[order])
    return float(x[order][min(int(np.searchsorted(w, q / 100.0 * w[-1])), x.size - 1)])


def _time_percentile(f: np.ndarray, q: float) -> float:
    """The ``q``-th percentile of half-cycle frequencies, each weighted by its duration 1/(2f)."""
    return _weighted_percentile(f, 1.0 / f, q)


def drive_frequencies(f: np.ndarray, amplitude: np.ndarray, span: float) -> list[float]:
    """The range (Hz) of the input's drive frequencies, counted as :func:`loop_spread` and the
    spread count them: the 10th and 90th percentiles over time of the half-cycle frequencies,
    widened to the LOOP_HALF_CYCLES-th slowest and fastest half cycle spanning LOOP_MIN_SPAN of the
    span (a few loops at a second rate are a rate, decision 0040). One short reversal is no drive
    rate: a slewed jump from a hold to where a triangle starts (for example 0.087 A in 4
    samples at 5 kHz) is a half cycle of 625 Hz, and a 3.6 Hz drive read as reaching 625 Hz asked of
    its training content 3.1 kHz to be predicted (decision 0078). Empty when there are no reversals."""
    if not f.size:
        return []
    lo, hi = _time_percentile(f, 10), _time_percentile(f, 90)
    loops = np.sort(f[amplitude >= LOOP_MIN_SPAN * span])
    k = LOOP_HALF_CYCLES
    if loops.size >= k:
        lo, hi = min(lo, float(loops[k - 1])), max(hi, float(loops[-k]))
    return [float(lo), float(hi)]


def excitation_summary(inputs: Sequence[np.ndarray], fs: float, span: float | None = None) -> dict[str, Any]:
    """What a set of input records can excite: spread of drive frequencies (90th / 10th percentile
    over time of the half-cycle frequencies, or :func:`loop_spread` counted in loops, the larger), the
    half cycles spanning LOOP_MIN_SPAN of the input span (``loops``), the spread of their mean rates
    (:func:`rate_spread`), how much faster than the loops its steps move (:func:`step_rate_ratio`),
    their range (Hz), the longest hold (s), the number of steps and of reversals, and the highest
    frequency the input excites (Hz, :func:`excited_bandwidth_hz`)."""
    us = [u for u in inputs if u.size]
    if span is None:
        span = max(float(np.ptp(np.concatenate(us))), 1e-12) if us else 1.0
    freqs, amplitudes, plateau_s, jumps, excited, excursions = [], [], 0.0, 0, 0.0, []
    for u in us:
        excited = max(excited, excited_bandwidth_hz(u, fs))
        m = motion(u, fs, span)
        excursions.append(excursion_rates(u, fs, span, m["still"]))
        freqs.append(half_cycle_frequencies(m["flips"], fs))
        turns = u[np.maximum(m["flips"] - 1, 0)]  # the input where each reversal turns
        amplitudes.append(np.abs(np.diff(turns)) if turns.size >= 2 else np.zeros(0))
        plateau_s = max(plateau_s, float(m["since"].max()))
        jumps += int(np.count_nonzero(np.abs(np.diff(u)) > STEP_FRACTION * span))
    f = np.concatenate(freqs) if freqs else np.zeros(0)
    # percentiles over time: 3 s at 1 Hz weigh as much as 3 s at 9 Hz, so the short reversals of a
    # noisy stretch do not make a spread; but a few full loops at a second rate are a second rate
    # however short they are (decision 0040), so counted in loops too
    spread = float(_time_percentile(f, 90) / max(_time_percentile(f, 10), 1e-12)) if f.size >= 3 else 1.0
    amplitude = np.concatenate(amplitudes) if amplitudes else np.zeros(0)
    spread = max(spread, loop_spread(f, amplitude, span))
    steps = step_rate_ratio(np.concatenate(excursions) if excursions else np.zeros(0), f, amplitude, span)
    return {"frequency_spread": spread, "rate_spread": rate_spread(f, amplitude, span), "step_rate_ratio": steps,
            "loops": int(np.count_nonzero(amplitude >= LOOP_MIN_SPAN * span)), "frequencies_hz": drive_frequencies(f, amplitude, span),
            "median_frequency_hz": float(np.median(f)) if f.size else float("nan"),
            "longest_hold_s": plateau_s, "steps": jumps, "reversals": int(f.size), "excited_hz": excited}


__all__ = ["excitation_summary", "excited_bandwidth_hz", "excursion_rates", "step_rate_ratio", "half_cycle_frequencies", "hold_band", "input_noise", "motion",
           "rate_spread"]
