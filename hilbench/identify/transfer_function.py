"""The discrete transfer function of paper 000 eq. 15, fitted to input-output data.

``G(z) = z^-d sum_{j=1..nb} b_j z^-j / (1 + sum_{i=1..na} a_i z^-i)``, by equation-error (ARX) least
squares and Steiglitz-McBride iterations refined to the output-error (simulation-error) optimum, kept
stable; :func:`search_delay` tries d = 0..max_delay. Conventions follow scipy.signal: ``b`` and ``a`` in
powers of z^-1 for ``lfilter(b, a, u)``. Eq. 15 sums the numerator from j = 1, so d = 0 already means one
sample between input and output (a zero-order-hold sampled plant); d counts samples on top of that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize
from scipy import signal as sps

from hilbench.errors import UserError
from hilbench.identify.array_checks import (
    as_1d,
    require_finite,
    require_positive,
    same_length,
)
from hilbench.identify.metrics import metrics


# ------------------------------------------------------------------------------------------------
# discrete transfer function (000 eq. 15): ARX start, output-error refinement
# ------------------------------------------------------------------------------------------------
def stabilize(a: np.ndarray, radius: float = 0.999) -> np.ndarray:
    """Reflect poles outside the unit circle to 1/conj(p) (same magnitude response shape), pull
    poles on it inside to ``radius``; ``a`` = [1, a_1, ...]."""
    if a.size <= 1:
        return a
    poles = np.roots(a)
    mag = np.abs(poles)
    if np.all(mag < radius):
        return a
    fixed = np.where(mag > 1, 1 / np.conj(poles), poles)
    mag = np.abs(fixed)
    fixed = np.where(mag > radius, fixed * (radius / np.maximum(mag, 1e-300)), fixed)
    return np.real(np.poly(fixed))


@dataclass
class DiscreteTF:
    """``G(z) = z^-d (b_1 z^-1 + ... + b_nb z^-nb) / (1 + a_1 z^-1 + ... + a_na z^-na)`` (000 eq. 15)
    from input (A or V) to output (um) at ``sample_rate_hz``, with the operating point
    (``u_ref``: input at which the model rests at output ``y_ref``).

    metrics: hilbench metric keys (rmse in um, re_n2_pct, ...) of the free-run simulation against
    the data the fit saw; arx_metrics: the same for the equation-error (ARX) estimate. re_n2_pct is
    relative to ||y|| including the operating point's offset (hilbench.identify.metrics), so it is small
    around a large offset; erms_pct (relative to the output's span) is the fairer figure there.
    """

    b: np.ndarray  # b_1..b_nb
    a: np.ndarray  # [1, a_1..a_na]
    delay: int
    sample_rate_hz: float
    method: str
    u_ref: float = 0.0
    y_ref: float = 0.0
    metrics: dict[str, float] = field(default_factory=dict)
    arx_metrics: dict[str, float] = field(default_factory=dict)
    arx_b: np.ndarray | None = None
    arx_a: np.ndarray | None = None
    delay_rmse: dict[int, float] = field(default_factory=dict)  # filled by search_delay
    nfev: int = 0

    @property
    def numerator(self) -> np.ndarray:
        """Full numerator in powers of z^-1 for ``lfilter``: d + 1 leading zeros, then b."""
        return np.concatenate([np.zeros(self.delay + 1), self.b])

    @property
    def poles(self) -> np.ndarray:
        return np.roots(self.a) if self.a.size > 1 else np.zeros(0, complex)

    @property
    def zeros(self) -> np.ndarray:
        return np.roots(self.b) if np.count_nonzero(self.b) > 0 and self.b.size > 1 else np.zeros(0, complex)

    @property
    def dc_gain(self) -> float:
        """Static gain G(1), output unit per input unit (um/A)."""
        return float(np.sum(self.b) / np.sum(self.a))

    @property
    def stable(self) -> bool:
        return bool(np.all(np.abs(self.poles) < 1))

    @property
    def rmse(self) -> float:
        return float(self.metrics.get("rmse", math.nan))

    def continuous_poles(self) -> np.ndarray:
        """Poles mapped to the s-plane, s = fs ln(z) (rad/s); NaN for poles at z <= 0 on the real axis."""
        z = self.poles.astype(complex)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = self.sample_rate_hz * np.log(z)
        bad = (np.abs(z.imag) < 1e-12) & (z.real <= 0)
        return np.where(bad, np.nan + 0j, s)

    def natural_frequencies_hz(self) -> np.ndarray:
        """|s| / 2 pi (Hz) of each pole pair (upper half plane) and real pole, ascending."""
        s = self.continuous_poles()
        s = s[np.isfinite(s) & (s.imag >= -1e-9)]
        return np.sort(np.abs(s)) / (2 * math.pi)

    def damping_ratios(self) -> np.ndarray:
        """-Re(s) / |s| of the poles in :meth:`natural_frequencies_hz` order."""
        s = self.continuous_poles()
        s = s[np.isfinite(s) & (s.imag >= -1e-9)]
        s = s[np.argsort(np.abs(s))]
        return -s.real / np.abs(s)

    def simulate(self, u: np.ndarray) -> np.ndarray:
        """Free-run output (um) for input u, starting at rest at u[0]."""
        u = as_1d(u, "u")
        if u.size == 0:
            return u.copy()
        y_rest = self.y_ref + self.dc_gain * (u[0] - self.u_ref)
        return sps.lfilter(self.numerator, self.a, u - u[0]) + y_rest

    def freqresp(self, frequency_hz: np.ndarray) -> np.ndarray:
        """Complex G(e^(j 2 pi f / fs)) at the frequencies (Hz)."""
        _, h = sps.freqz(self.numerator, self.a, worN=np.asarray(frequency_hz, float), fs=self.sample_rate_hz)
        return h

    def to_table(self) -> dict[str, Any]:
        """A rig-config ``[plant.dynamics]`` table that :func:`hilbench.sim.dynamics.discretize_dynamics`
        accepts: ``{"kind": "discrete", "b": [...], "a": [...]}`` (b with the delay's leading zeros)."""
        return {"kind": "discrete", "b": [float(x) for x in self.numerator], "a": [float(x) for x in self.a]}

    def to_dict(self) -> dict[str, Any]:
        return {
            "structure": "000 eq. 15", "method": self.method, "delay": self.delay, "nb": int(self.b.size),
            "na": int(self.a.size - 1), "b": self.b.tolist(), "a": self.a.tolist(),
            "sample_rate_hz": self.sample_rate_hz, "u_ref": self.u_ref, "y_ref": self.y_ref,
            "dc_gain": self.dc_gain, "poles": [[float(p.real), float(p.imag)] for p in self.poles],
            "natural_frequencies_hz": self.natural_frequencies_hz().tolist(),
            "metrics": self.metrics, "arx_metrics": self.arx_metrics,
            "delay_rmse": {str(k): v for k, v in self.delay_rmse.items()},
        }


def _lagged(x: np.ndarray, lag: int) -> np.ndarray:
    out = np.zeros_like(x)
    if lag < x.size:
        out[lag:] = x[: x.size - lag]
    return out


def _arx(ud: np.ndarray, yd: np.ndarray, nb: int, na: int, delay: int, n0: int) -> tuple[np.ndarray, np.ndarray]:
    """Equation-error least squares with an output offset: y[n] + sum a_i y[n-i] =
    sum b_j u[n-d-j] + c."""
    cols = [-_lagged(yd, i) for i in range(1, na + 1)]
    cols += [_lagged(ud, delay + j) for j in range(1, nb + 1)]
    cols.append(np.ones_like(yd))
    A = np.column_stack(cols)[n0:]
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    theta, *_ = np.linalg.lstsq(A / scale, yd[n0:], rcond=None)
    theta = theta / scale
    a = np.concatenate([[1.0], theta[:na]])
    return theta[na:na + nb], a


def _simulate(b: np.ndarray, a: np.ndarray, delay: int, ud: np.ndarray) -> np.ndarray:
    return sps.lfilter(np.concatenate([np.zeros(delay + 1), b]), a, ud)


def _steiglitz_mcbride(ud: np.ndarray, yd: np.ndarray, nb: int, na: int, delay: int, n0: int,
                       a: np.ndarray, iterations: int = 15) -> tuple[np.ndarray, np.ndarray]:
    """Steiglitz-McBride iterations: ARX on u and y prefiltered by 1/A of the previous estimate.
    Its fixed point is close to the output-error optimum for white output noise, so it is a far
    better start for the (multimodal) output-error search than plain ARX at low signal-to-noise."""
    b = np.zeros(nb)
    for _ in range(iterations):
        uf = sps.lfilter([1.0], a, ud)
        yf = sps.lfilter([1.0], a, yd)
        b_new, a_new = _arx(uf, yf, nb, na, delay, n0)
        a_new = stabilize(a_new)
        done = np.allclose(a_new, a, rtol=0, atol=1e-10)
        a, b = a_new, b_new
        if done:
            break
    return b, a


def fit_transfer_function(
    u: np.ndarray,
    y: np.ndarray,
    fs: float,
    *,
    nb: int,
    na: int,
    delay: int = 0,
    method: str = "oe",
    max_nfev: int = 200,
) -> DiscreteTF:
    """Fit paper 000 eq. 15, ``G(z) = z^-d sum_{j=1..nb} b_j z^-j / (1 + sum_{i=1..na} a_i z^-i)``,
    from input u (A or V) to output y (um) sampled at fs (Hz).

    The model starts at rest at u[0] (input deviations u - u[0]) and an output offset is estimated
    with it, so data around an operating point need no detrending (but let the rig settle before
    recording: a start-up transient is not in the model). ``method="arx"``: equation-error least
    squares (fast, biased by output noise). ``method="oe"`` (default, like MATLAB ``oe``/``tfest``):
    the better of the ARX and the Steiglitz-McBride estimates refined by
    ``scipy.optimize.least_squares`` (Levenberg-Marquardt, analytic sensitivities) on the free-run
    simulation error (``lfilter``); poles leaving the unit circle are reflected inside, so the
    estimate stays stable. Reports rmse (um) and re_n2_pct (000 eq. 18) of the simulation.
    """
    u = as_1d(u, "u")
    y = as_1d(y, "y")
    n = same_length(u=u, y=y)
    fs = require_positive(fs, "fs")
    if method not in ("oe", "arx"):
        raise UserError(f"method = {method!r}: expected 'oe' (output error) or 'arx' (equation error)")
    for name, v, lo in (("nb", nb, 1), ("na", na, 0), ("delay", delay, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise UserError(f"{name} = {v!r}: expected an integer >= {lo}")
    nb, na, delay = int(nb), int(na), int(delay)
    n0 = max(na, delay + nb)
    n_par = na + nb + 1
    if n - n0 < 10 * n_par:
        raise UserError(f"too few samples for a transfer function with nb = {nb}, na = {na}, d = {delay}: "
                        f"{n} (need at least {n0 + 10 * n_par})")
    require_finite(u, "u")
    require_finite(y, "y")
    if np.ptp(u) == 0:
        raise UserError("u is constant: no excitation to fit a transfer function to")
    u_ref = float(u[0])
    ud = u - u_ref
    y_mean = float(np.mean(y))
    y_scale = float(np.std(y)) or 1.0
    yd = (y - y_mean) / y_scale  # work in normalised units; back to um at the end
    rows = slice(n0, n)

    def simulate(b: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, float]:
        """Free-run output with the least-squares output offset c (normalised units)."""
        sim = _simulate(b, a, delay, ud)
        c = float(np.mean(yd[rows] - sim[rows]))
        return sim + c, c

    def sse(b: np.ndarray, a: np.ndarray) -> float:
        r = (simulate(b, a)[0] - yd)[rows]
        return float(r @ r) if np.all(np.isfinite(r)) else math.inf

    b_arx, a_arx = _arx(ud, yd, nb, na, delay, n0)
    a_arx = stabilize(a_arx)
    b_fit, a_fit, nfev = b_arx, a_arx, 0

    if method == "oe":
        starts = [(b_arx, a_arx)]
        if na > 0:
            starts.append(_steiglitz_mcbride(ud, yd, nb, na, delay, n0, a_arx))
        b_start, a_start = min(starts, key=lambda ba: sse(*ba))

        def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return x[na:], stabilize(np.concatenate([[1.0], x[:na]]))

        def residual(x: np.ndarray) -> np.ndarray:
            r = (simulate(*unpack(x))[0] - yd)[rows]
            return r if np.all(np.isfinite(r)) else np.full(r.shape, 1e6)

        def jac(x: np.ndarray) -> np.ndarray:
            b, a = unpack(x)
            sim = _simulate(b, a, delay, ud)
            fu = sps.lfilter([1.0], a, ud)
            fy = sps.lfilter([1.0], a, sim)
            cols = [-_lagged(fy, i) for i in range(1, na + 1)] + [_lagged(fu, delay + j) for j in range(1, nb + 1)]
            J = np.column_stack(cols)[rows]
            return np.nan_to_num(J - J.mean(axis=0))  # the offset is re-estimated for every model

        x0 = np.concatenate([a_start[1:], b_start])
        res = optimize.least_squares(residual, x0, jac=jac, method="lm", x_scale="jac",
                                     ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=max_nfev)
        b_oe, a_oe = unpack(res.x)
        nfev = int(res.nfev)
        b_fit, a_fit = min([(b_start, a_start), (b_oe, a_oe)], key=lambda ba: sse(*ba))

    sim_fit, c_fit = simulate(b_fit, a_fit)
    sim_arx, _ = simulate(b_arx, a_arx)
    return DiscreteTF(
        b=np.asarray(b_fit * y_scale, float), a=np.asarray(a_fit, float), delay=delay, sample_rate_hz=fs,
        method=method, u_ref=u_ref, y_ref=float(c_fit * y_scale + y_mean),
        metrics=metrics(y[rows], (sim_fit * y_scale + y_mean)[rows]),
        arx_metrics=metrics(y[rows], (sim_arx * y_scale + y_mean)[rows]),
        arx_b=np.asarray(b_arx * y_scale, float), arx_a=np.asarray(a_arx, float), nfev=nfev,
    )


def search_delay(
    u: np.ndarray,
    y: np.ndarray,
    fs: float,
    *,
    nb: int,
    na: int,
    max_delay: int = 10,
    method: str = "oe",
    rel_tol: float = 0.0,
) -> DiscreteTF:
    """Fit eq. 15 for d = 0..max_delay (samples) and keep the best by simulation rmse.

    ``rel_tol`` > 0 prefers a longer delay whose rmse is within that relative margin of the best
    (a shorter d only matches it by zeroing its leading numerator coefficients when nb is larger
    than needed). Slow plants sampled fast show little rmse difference between neighbouring d: the
    zeros absorb a sample of delay; every d's rmse is kept in ``delay_rmse`` to judge by."""
    if not isinstance(max_delay, (int, np.integer)) or max_delay < 0:
        raise UserError(f"max_delay = {max_delay!r}: expected an integer >= 0")
    fits = {d: fit_transfer_function(u, y, fs, nb=nb, na=na, delay=d, method=method) for d in range(int(max_delay) + 1)}
    scores = {d: f.rmse for d, f in fits.items()}
    best = min(scores.values())
    chosen = max(d for d, s in scores.items() if s <= best * (1 + rel_tol))
    result = fits[chosen]
    result.delay_rmse = scores
    return result
