"""Small robust statistics shared by identification, diagnosis and input analysis.

Noise levels are estimated from differences of a signal, robustly (median absolute deviation):
smooth signal content cancels in differences, outliers and steps do not move a median. The k-th
difference of white noise of std sigma has std sqrt(C(2k, k)) sigma (2 for k = 1, 70 for k = 4).
"""

from __future__ import annotations

import math

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
