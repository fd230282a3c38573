"""Where a lightly damped resonance rings: peaks of a residual's spectrum (peak picking, as in
experimental modal analysis), used as starting points of the natural-frequency search.

A resonance well above the drive, rung by a triangle's corners or a step, adds decaying
oscillations at its damped frequency to the output. A model without it leaves them in the
residual, where they form a peak of width ~2 zeta f_n in the spectrum. The least-squares search
over (f_n, zeta) sees that peak only from starts within about zeta f_n of it (the fit error is flat
elsewhere, the basin narrow for zeta of a few per cent), so a coarse scan over five decades of f_n
misses it; read off the spectrum, it is one evaluation away (docs/decisions/0023).

The damping is searched on a log scale down to the lightest a record resolves: a resonance at
Nyquist whose decay time 1 / (zeta w_n) equals the longest stretch (any lighter one is an undecaying
line over the record). Each peak starts the search at damping ratios half a decade apart from 0.3
down to that floor; a floor of 0.02 (before decision 0105) held a piezo-like resonance of zeta 0.006
at 0.02, whose model ringing died three times too fast.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

#: Welch segment length bounds (samples): at least this many for a usable resolution ...
MIN_SEGMENT = 128
#: ... at most this many (at 2 kHz: 0.25 Hz bins, finer than any peak of zeta >= 0.001 at 10 Hz) ...
MAX_SEGMENT = 8192
#: ... and the longest stretch of residual holds at least this many segments (Welch averages them:
#: with 50 % overlap about twice as many, so the peak stands above the spectrum's scatter).
SEGMENTS_PER_STRETCH = 4
#: Starts of the natural-frequency search: this many of the most prominent peaks (the ringing
#: need not be the most prominent: base-model error leaves lines at the drive's harmonics) ...
RESONANCE_PEAKS = 6
#: ... each with damping ratios from this one down by half decades to the lightest the record
#: resolves (:func:`lightest_damping`); the local search refines zeta from the nearest.
HEAVIEST_START_DAMPING = 0.3
#: Peaks closer to 0 Hz than this many bins are the residual's slow drift, not a ringing.
MIN_PEAK_BINS = 3


def contiguous_stretches(residual: np.ndarray, rows: np.ndarray) -> list[np.ndarray]:
    """The residual split where its row numbers ``rows`` (increasing) jump: contiguous stretches."""
    if residual.size == 0:
        return []
    cuts = np.flatnonzero(np.diff(rows) != 1) + 1
    return [part for part in np.split(residual, cuts) if part.size]


def residual_spectrum(stretches: Sequence[np.ndarray], fs: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Welch power spectral density (unit^2/Hz) averaged over the stretches long enough for one
    segment, weighted by their segments; (frequencies Hz, psd), or None when none is long enough."""
    from scipy import signal

    longest = max((s.size for s in stretches), default=0)
    if longest < MIN_SEGMENT:
        return None
    nperseg = int(2 ** np.floor(np.log2(max(MIN_SEGMENT, min(MAX_SEGMENT, longest // SEGMENTS_PER_STRETCH)))))
    total, weight, freqs = None, 0.0, None
    for s in stretches:
        if s.size < nperseg:
            continue
        freqs, psd = signal.welch(s - np.mean(s), fs=fs, nperseg=nperseg, detrend="linear")
        n = s.size / nperseg
        total = psd * n if total is None else total + psd * n
        weight += n
    if total is None or freqs is None:
        return None
    return freqs, total / weight


def ringing_frequencies(stretches: Sequence[np.ndarray], fs: float, count: int = 6) -> list[float]:
    """Up to ``count`` frequencies (Hz) of the most prominent peaks of the residual's spectrum,
    most prominent first (prominence in decades of power density over the surrounding valleys);
    none closer to 0 Hz than MIN_PEAK_BINS bins (slow drift)."""
    from scipy import signal

    spectrum = residual_spectrum(stretches, fs)
    if spectrum is None:
        return []
    freqs, psd = spectrum
    floor = np.max(psd) * 1e-12 if np.max(psd) > 0 else 1e-300
    level = np.log10(np.maximum(psd, floor))
    peaks, props = signal.find_peaks(level, prominence=0.0)
    keep = peaks >= MIN_PEAK_BINS
    peaks, prominence = peaks[keep], props["prominences"][keep]
    order = np.argsort(-prominence)[:count]
    return [_interpolated(freqs, level, int(peaks[i])) for i in order]


def _interpolated(freqs: np.ndarray, level: np.ndarray, k: int) -> float:
    """The frequency of the peak at bin ``k`` between bins: the vertex of the parabola through the
    log power of bins k-1, k, k+1 (a sharp resonance's basin in f_n, ~zeta f_n wide, can be
    narrower than a bin)."""
    if k <= 0 or k >= level.size - 1:
        return float(freqs[k])
    a, b, c = level[k - 1], level[k], level[k + 1]
    curvature = a - 2.0 * b + c
    shift = 0.5 * (a - c) / curvature if curvature < 0 else 0.0
    return float(freqs[k] + max(-0.5, min(0.5, shift)) * (freqs[1] - freqs[0]))


def lightest_damping(longest_samples: int) -> float:
    """The lightest damping ratio a record whose longest contiguous stretch has ``longest_samples``
    samples resolves: a resonance at Nyquist (the fastest a sampled record shows ringing) with this
    damping decays by 1/e over the stretch, 1 / (zeta 2 pi (fs / 2)) = N / fs; any lighter one looks
    the same, an undecaying line. Equally, its half-power width 2 zeta f_n is one frequency bin
    fs / N of the stretch's spectrum."""
    return 1.0 / (math.pi * max(int(longest_samples), 1))


def start_dampings(lower: float, upper: float) -> list[float]:
    """Damping ratios of the starts at each ringing: HEAVIEST_START_DAMPING and down by half decades
    to ``lower`` (the lightest resolvable), clipped to [lower, upper]; lightest first."""
    heaviest = min(max(HEAVIEST_START_DAMPING, lower), upper)
    steps = max(math.floor(2.0 * math.log10(heaviest / lower) + 1e-9), 0)
    return sorted({heaviest * 10.0 ** (-k / 2.0) for k in range(steps + 1)})
