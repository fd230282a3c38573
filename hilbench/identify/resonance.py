"""Where a lightly damped resonance rings: peaks of a residual's spectrum (peak picking, as in
experimental modal analysis), used as starting points of the natural-frequency search.

A resonance well above the drive, rung by a triangle's corners or a step, adds decaying
oscillations at its damped frequency to the output. A model without it leaves them in the
residual, where they form a peak of width ~2 zeta f_n in the spectrum. The least-squares search
over (f_n, zeta) sees that peak only from starts within about zeta f_n of it (the fit error is flat
elsewhere, the basin narrow for zeta of a few per cent), so a coarse scan over five decades of f_n
misses it; read off the spectrum, it is one evaluation away (docs/decisions/0023).
"""

from __future__ import annotations

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
#: ... each with these damping ratios (a light resonance rings long enough to form a peak; the
#: local search refines zeta from the nearest).
START_DAMPING = (0.03, 0.1, 0.3)
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
    return [float(freqs[peaks[i]]) for i in order]
