"""Smoothing and peak location on sampled curves (step responses, frequency responses)."""

from __future__ import annotations

import numpy as np


def quad_vertex(tt: np.ndarray, yy: np.ndarray, want_max: bool) -> tuple[float, float] | None:
    """Least-squares parabola through (tt, yy); its vertex if it is an extremum of the wanted kind
    inside [tt[0], tt[-1]]."""
    if tt.size < 3:
        return None
    tc = tt.mean()
    c2, c1, c0 = np.polyfit(tt - tc, yy, 2)
    if (want_max and c2 >= 0) or (not want_max and c2 <= 0):
        return None
    tv = -c1 / (2 * c2)
    if not (tt[0] - tc <= tv <= tt[-1] - tc):
        return None
    return float(tv + tc), float(c0 - c1**2 / (4 * c2))


def moving_average(x: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average over ``width`` samples, edges by the nearest value."""
    if width <= 1:
        return x
    from scipy.ndimage import uniform_filter1d

    return uniform_filter1d(x, width, mode="nearest")
