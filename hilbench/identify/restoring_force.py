"""Identify a restoring-force model (``bouc-wen+restoring-force``) by a bounded simulation-error search.

The model (:mod:`hilbench.models.restoring_force`) has no weight to solve by least squares: its six
physical parameters m, c, k, alpha, gamma, delta are searched together on the free-run error of
the training rows, by scipy's bounded ``least_squares`` over scaled parameters, each of order one:

    m = m0 e^x0,  c = c0 e^x1,  k + alpha = k0 e^x2,  alpha = x3 (k + alpha),
    gamma = x4 / y_s^nu,  delta = x5 / y_s^nu

m0, c0, k0 come from the linear fit (``linear+dynamics``: static gain 1/k0, natural frequency
sqrt(k0/m0), damping c0 / (2 sqrt(k0 m0))), y_s is the largest training |output|. The bounds keep
the search physical: mass a factor 20 either side of the linear fit's, the spring and the
hysteretic element positive and sharing the linear fit's stiffness within a factor 10, the
viscous damping anywhere from 1e-4 to 10 times the linear fit's (hysteresis dissipates too, so the
linear fit's damping over-estimates it), the Bouc-Wen shape |x4|, |x5| <= 20 (the hysteretic
state's slope changes by at most e^20 over the output range). The search starts from the two best
of a small grid of loop shapes (hysteretic share 0.3 and 0.6, x4 in {0.5, 2}, x5 in {-3, -1, 0, 1, 3},
and the linear fit itself), each scored by one simulation.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy import optimize

from hilbench.errors import UserError
from hilbench.models.model import Model, RunData
from hilbench.models.restoring_force import PHYSICAL

#: bounds of the scaled parameters x0..x5 (see the module docstring)
LOWER = np.array([-math.log(20.0), math.log(1e-4), -math.log(10.0), 0.0, -20.0, -20.0])
UPPER = np.array([math.log(20.0), math.log(10.0), math.log(10.0), 0.999, 20.0, 20.0])
#: the start grid: hysteretic share of the stiffness, x4, x5
SHARES = (0.3, 0.6)
GAMMAS = (0.5, 2.0)
DELTAS = (-3.0, -1.0, 0.0, 1.0, 3.0)
#: local searches from the best grid points
LOCAL_STARTS = 2
#: residual (in units of y_s) where the simulation left the finite numbers
DIVERGED = 1e3


class _Search:
    """Scaled parameters <-> the model's physical ones, and the free-run residual of the training rows."""

    def __init__(self, model: Model, runs: list[RunData], masks: list[np.ndarray], m0: float, c0: float,
                 k0: float, y_scale: float):
        self.model, self.runs, self.masks = model, runs, masks
        self.ref = (m0, c0, k0)
        self.y_scale = y_scale
        self.nu = float(model.base.options.get("n", 1.0))
        self.measured = np.concatenate([r.output[m] for r, m in zip(runs, masks)])
        self.evaluations = 0

    def physical(self, x: np.ndarray) -> np.ndarray:
        m0, c0, k0 = self.ref
        total = k0 * math.exp(x[2])
        shape = self.y_scale ** self.nu
        return np.array([m0 * math.exp(x[0]), c0 * math.exp(x[1]), (1.0 - x[3]) * total, x[3] * total,
                         x[4] / shape, x[5] / shape])

    def set(self, x: np.ndarray) -> None:
        self.model.set_shape(self.physical(x))

    def residual(self, x: np.ndarray) -> np.ndarray:
        self.set(x)
        self.evaluations += 1
        simulated = np.concatenate([y[m] for y, m in zip(self.model.simulate_runs(self.runs), self.masks)])
        e = (simulated - self.measured) / self.y_scale
        e[~np.isfinite(e)] = DIVERGED
        return np.clip(e, -DIVERGED, DIVERGED)

    def sse(self, x: np.ndarray) -> float:
        e = self.residual(x)
        return float(e @ e)


def linear_start(runs: list[RunData], masks: list[np.ndarray]) -> tuple[float, float, float]:
    """(m0, c0, k0) of the mass-spring-damper the ``linear+dynamics`` fit describes."""
    from hilbench.identify.separable import fit_model

    linear = Model("linear+dynamics")
    fit_model(linear, runs, masks, local_starts=1)
    assert linear.weights is not None
    # the linear base's weight multiplies the normalised input u / u_scale
    gain = float(linear.weights[linear.weight_names.index("p0*v")]) / float(linear.norm["u_scale"])
    if not gain > 0.0:
        raise UserError(f"the linear fit's static gain is {gain:.4g} output units per input unit; a restoring-force "
                        "model needs the output to move with the drive (a positive gain)",
                        hint="check the sign of the input and output channels")
    dyn = linear.effect("dynamics")
    assert dyn is not None
    wn = 2.0 * math.pi * dyn.param("natural_frequency_hz")
    k0 = 1.0 / gain
    m0 = k0 / wn**2
    return m0, 2.0 * dyn.param("zeta") * wn * m0, k0


def fit_restoring_force(
    model: Model,
    runs: list[RunData],
    train_masks: list[np.ndarray],
    *,
    progress: Callable[[str], None] | None = None,
    max_evaluations: int = 120,
    **_: Any,
) -> Any:
    """Identify ``model`` (a restoring-force structure) on the training rows of ``runs``; sets its
    physical parameters, returns a :class:`hilbench.identify.FitReport`."""
    from hilbench.identify.separable import FitReport, _training_parts

    t0 = time.perf_counter()
    masks = [m & np.isfinite(r.output) for r, m in zip(runs, train_masks)]
    last = max((i for i, m in enumerate(masks) if m.any()), default=-1)
    if last < 0:
        raise UserError("the training set is empty: no samples with a finite output")
    runs, masks = runs[: last + 1], masks[: last + 1]
    model.prepare(_training_parts(model, runs, masks))
    model.weights, model.weight_names = np.zeros(0), []
    m0, c0, k0 = linear_start(runs, masks)
    y_scale = float(max(np.max(np.abs(r.output[m])) for r, m in zip(runs, masks) if m.any())) or 1.0
    search = _Search(model, runs, masks, m0, c0, k0, y_scale)
    if progress is not None:
        progress(f"linear start: m {m0:.4g}, c {c0:.4g}, k {k0:.4g}; searching {len(PHYSICAL)} parameters")
    grid = [np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])]
    grid += [np.array([0.0, 0.0, 0.0, share, g, d]) for share in SHARES for g in GAMMAS for d in DELTAS]
    scored = sorted(((search.sse(x), i) for i, x in enumerate(grid)), key=lambda t: t[0])
    history: list[dict[str, Any]] = []
    best_sse, best_x = scored[0][0], grid[scored[0][1]]
    for start_sse, i in scored[:LOCAL_STARTS]:
        result = optimize.least_squares(search.residual, grid[i], bounds=(LOWER, UPPER), method="trf",
                                        x_scale=1.0, diff_step=1e-6, max_nfev=max_evaluations,
                                        ftol=1e-10, xtol=1e-10, gtol=1e-10)
        sse = float(result.fun @ result.fun)
        history.append({"start_sse": start_sse, "sse": sse, "nfev": int(result.nfev)})
        if progress is not None:
            progress(f"local search {len(history)}: sse {sse:.6g} after {result.nfev} evaluations")
        if sse < best_sse:
            best_sse, best_x = sse, result.x
    search.set(best_x)
    lo, hi = search.physical(LOWER), search.physical(UPPER)
    for p, low, high in zip(model.shape_params(), np.minimum(lo, hi), np.maximum(lo, hi)):
        p.lower, p.upper = float(low), float(high)
    # k and alpha share the searched stiffness: each is bounded by the largest total
    k_top = k0 * math.exp(UPPER[2])
    for p in model.shape_params()[2:4]:
        p.lower, p.upper = 0.0, k_top
    n = int(search.measured.size)
    sse_out = best_sse * y_scale**2
    return FitReport(theta={p.name: p.value for p in model.shape_params()}, sse=sse_out,
                     rmse=math.sqrt(sse_out / n), n_train=n, evaluations=search.evaluations,
                     seconds=time.perf_counter() - t0, starts=len(history), history=history)
