"""Small robust statistics shared by identification, diagnosis and input analysis.

Noise levels are estimated from differences of a signal, robustly (median absolute deviation):
smooth signal content cancels in differences, outliers and steps do not move a median. The k-th
difference of white noise of std sigma has std sqrt(C(2k, k)) sigma (2 for k = 1, 70 for k = 4).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

#: MAD of a normal distribution times this is its standard deviation
MAD_TO_STD = 1.4826


def robust_std(x: np.ndarray) -> float:
    """Standard deviation from the median absolute deviation, finite samples only; 0 for < 2 samples."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if x.size < 2:
        return 0.0
    return float(MAD_TO_STD * np.median(np.abs(x - np.median(x))))


def difference_noise_std(differences: np.ndarray, order: int = 1) -> float:
    """White-noise std behind ``differences`` (the ``order``-th differences of a signal), robustly."""
    return robust_std(differences) / math.sqrt(math.comb(2 * order, order))


def aux_variation(runs: Sequence[np.ndarray]) -> float:
    """How far an auxiliary channel moves beyond its noise: the range of its moving average (1 % of
    each run) over its sample-to-sample noise std. Pure noise gives well under 1 (the average
    removes it); a 1.5 degC drift under 0.15 degC of noise gives 10."""
    smooth, diffs, quantum = [], [], math.inf
    for a in runs:
        a = a[np.isfinite(a)]
        if a.size < 3:
            continue
        k = max(1, a.size // 100)
        smooth.append(np.convolve(a, np.ones(k) / k, mode="valid"))
        d = np.diff(a)
        diffs.append(d)
        nz = np.abs(d[d != 0])
        if nz.size:
            quantum = min(quantum, float(nz.min()))
    if not smooth:
        return 0.0
    d = np.concatenate(diffs)
    noise = difference_noise_std(d)
    if math.isfinite(quantum):
        noise = max(noise, quantum / math.sqrt(12.0))  # a quantised, mostly constant channel
    s = np.concatenate(smooth)
    return float(np.ptp(s) / max(noise, 1e-12 * max(float(np.abs(s).max()), 1.0)))
