"""Loop measures of periodic input-output data: branch gap (loop width), asymmetry, peak-to-peak.

Used by tests and reports to state, with numbers, what a hysteresis loop looks like.
"""

from __future__ import annotations

import numpy as np


def last_cycles(x: np.ndarray, samples_per_cycle: int, cycles: int = 1) -> slice:
    """The slice of the last ``cycles`` whole cycles."""
    n = samples_per_cycle * cycles
    return slice(max(0, x.shape[0] - n), x.shape[0])


def branches(u: np.ndarray, y: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rising and falling branches of a loop interpolated on an input grid."""
    du = np.gradient(u)
    out = []
    for mask in (du > 0, du < 0):
        order = np.argsort(u[mask])
        out.append(np.interp(grid, u[mask][order], y[mask][order]))
    return out[0], out[1]


def loop_measures(u: np.ndarray, y: np.ndarray, points: int = 201) -> dict[str, float]:
    """Measures of one (or a few) closed loops of output y against input u.

    width: largest vertical gap between the falling and rising branch, whichever lies above
    (output unit; loops of a sign-inverting actuator run the other way round);
    asymmetry: largest departure from central symmetry about the loop centre, i.e.
    max |(y_rise(u) - y_c) + (y_fall(2 u_c - u) - y_c)| (output unit, 0 for a PI loop);
    p2p: peak-to-peak output.
    """
    lo, hi = float(u.min()), float(u.max())
    margin = 0.02 * (hi - lo)
    grid = np.linspace(lo + margin, hi - margin, points)
    rise, fall = branches(u, y, grid)
    centre = 0.5 * (np.interp(0.5 * (lo + hi), grid, rise) + np.interp(0.5 * (lo + hi), grid, fall))
    asymmetry = np.max(np.abs((rise - centre) + (fall[::-1] - centre)))
    return {
        "width": float(np.max(np.abs(fall - rise))),
        "asymmetry": float(asymmetry),
        "p2p": float(np.ptp(y)),
        "relative_width": float(np.max(np.abs(fall - rise)) / np.ptp(y)) if np.ptp(y) > 0 else 0.0,
    }
