"""Paper 000's online identifier: FPMPI front end + online IIR filter (OIIR) identified by RLS.

Per sample k (one numba step function, :func:`oiir_step`; :func:`oiir_block` loops over it, so
block mode and step mode give identical results):

1. FPMPI front end (000 eq. 1-5), parameters fixed by an offline fit: the normalised input
   ``v = u / u_scale`` is shaped by the fractional polynomial ``x = sum_i w_P,i sgn(v)|v|^e_i``
   (eq. 4-5: e = 0, 1, 2, 1/2, 3, 1/3, 4, 1/4), then drives one-sided play operators
   (eq. 1, ``hilbench.sim.kernels.mplay_block`` with eta = 0, the operator of the plant and of
   :class:`hilbench.models.Model`), and ``u_r = offset + sum_i w_H,i H_ri[x]`` (eq. 2, 4).
2. Regressor shift (eq. 11, measured outputs):
   ``phi(k) = [u_r(k), ..., u_r(k-M), y(k-1), ..., y(k-N)]``,
   weights ``w = [p_0, ..., p_M, q_1, ..., q_N]`` (eq. 9), i.e.
   ``y_m(k) = sum_{i=0..M} p_i u_r(k-i) + sum_{j=1..N} q_j y(k-j)`` (eq. 6:
   ``G = P(z^-1) / (1 - Q(z^-1))``). Index choices, as printed in eq. 6, 8, 9, 11: the numerator
   starts at lag 0 (u_r(k) enters the prediction of y(k): a direct feed-through term p_0, which the
   identifier sets near zero when the plant has a delay), M is the numerator order and N the
   denominator order (000 sec. 4.1 uses M = 3, N = 5: p_0..p_3 and q_1..q_5 as in Fig. 10c-d), so
   there are K = M + N + 1 weights. The paper calls eq. 10 the "output error" and eq. 7 the
   "equation error"; it is the other way round in the usual terms: eq. 10/11, implemented here,
   regress on measured outputs (equation error), which keeps the least-squares problem quadratic.
   ``bias=True`` appends a constant regressor 1 (not in the paper): an output offset, e.g. a load's
   compliance or a thermal strain, then need not be explained through the loop gain.
3. RLS update (eq. 12-13) by :func:`hilbench.online.rls.rls_step` (directional forgetting,
   symmetric covariance update, trace cap, NaN and outlier guards): the returned a-priori
   prediction ``w(k-1)' phi(k)`` is the online model output y_m(k) whose error 000 eq. 18 measures.
4. The measured y(k) enters the output history, except when the RLS skipped it (non-finite, or
   a gross error beyond ``reject_k`` robust standard deviations: a sensor spike): then its
   prediction goes in, so a spike does not poison the next N regressors. A Huber-weighted sample
   (between ``outlier_k`` and ``reject_k``) keeps its measured value in the history: such errors
   are mostly the plant (the front end's mismatch where the input turns, a load landing), and
   replacing them by clipped values gives the next N predictions wrong lags (on the simulated
   load scenario of 000 that tripled the online error, 0.24 -> 0.78 % re_N2, measured with the
   offline Hammerstein fit's FPMPI as front end).

5. The guard (decision 0082), in the same kernel: after each RLS update the poles of 1 - Q are kept
   within ``pole_radius`` (0.999; Schur-Cohn test, radial contraction with the numerator moved to
   its least-squares best, :func:`project_poles`) in the *filter*, a copy of theta that predicts
   (``OIIR.filter_weights``, recorded as the weights), while the RLS keeps its own least-squares
   theta; so the filter's free run over skipped samples is bounded; a run of ``diverge_after`` gross errors (or non-finite weights) resets P to delta I and
   puts the measurements back into the lags; a prediction beyond the outputs seen, widened by their
   span, is held at that bound. Counted: ``poles_projected``, ``divergence_resets``,
   ``predictions_bounded``.

A non-finite input sample is replaced by the previous input (the actuator holds its last command)
and counted; the operators never see NaN. The regressor history starts in steady state at the
first sample (all u_r lags = u_r(0), all y lags = y(0)), as ``lfilter_zi`` starts a filter, for
the predictions of the first max(M, N) samples only: the RLS is updated from the first sample
whose regressor holds measured data alone.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from hilbench.online import rls as R
from hilbench.sim.kernels import sgnpow

__all__ = ["OIIR", "FPMPIFrontEnd", "oiir_step", "oiir_step_shaped", "oiir_block", "re_n2_pct", "re_ninf_pct", "persistence",
           "offline_hammerstein", "OFFLINE_SPEC"]

# -- front-end scalar parameters (fe) -----------------------------------------------------------
F_U_SCALE = 0  # command units per normalised unit (v = u / u_scale)
F_OFFSET = 1  # constant term of u_r
F_U_LO = 2  # the polynomial's input is held within [F_U_LO, F_U_HI], command units (default: +-inf)
F_U_HI = 3
N_FE = 4

# -- OIIR scalars (xs): state, the guard's settings, and the guard's work area -------------------
X_STARTED = 0
X_U_PREV = 1  # last finite input, command units
X_INPUT_HELD = 2  # non-finite inputs replaced by the previous one (count)
X_FILLED = 3  # samples seen, up to max(M, N): the regressor holds only measured data after that
X_PROJECTED = 4  # updates whose denominator had a pole beyond the admissible radius: projected (count)
X_DIVERGED = 5  # divergence resets: P = delta I, scale re-learnt, measured output back in the lags (count)
X_SKIP_RUN = 6  # consecutive samples skipped as gross errors (with a finite measurement)
X_POLE_RADIUS = 7  # setting: every pole of 1 - Q(z^-1) is kept at |z| <= this (< 1)
X_DIVERGE_AFTER = 8  # setting: this many consecutive gross errors mean the identifier lost the plant
X_Y_LO = 9  # lowest measured output taken into the lags so far, um (+inf before the first)
X_Y_HI = 10  # highest, um (-inf before the first)
X_BOUNDED = 11  # predictions held at the bound of the outputs seen (count)
X_BOUND_ON = 12  # setting: 1 holds predictions within the bound, 0 does not (tests: the unguarded filter)
X_DROP_RUN = 13  # consecutive samples without a finite measurement
X_WORK = 14  # work area of the stability guard (:func:`work_size`): no allocation per sample
N_XS = X_WORK  # scalars before the work area; the array has N_XS + work_size(N) entries


def work_size(N: int) -> int:
    """Scratch values the stability guard needs for denominator order N: the Schur-Cohn step-down
    (2 (N + 1)) and the projection's solve (2 N + N^2)."""
    return 2 * (N + 1) + 2 * N + N * N


@njit(cache=True, inline="always")
def filter_at(nd: int) -> int:
    """Where in ``xs`` the filter's weights start (after the work area of order nd): the weights
    that predict, the estimator's own theta projected into the admissible region."""
    return X_WORK + 2 * (nd + 1) + 2 * nd + nd * nd

#: default bound of the OIIR's pole radius: the slowest admissible mode decays by 1/e in 1000 samples
#: (0.2 s at 5 kHz); anything slower is a drift the equation-error fit invents from lags that barely
#: move (data sampled far faster than the dynamics), and a pole at or beyond 1 makes the filter's
#: free run (over skipped samples) grow without bound. Decision 0082.
POLE_RADIUS = 0.999

# -- OIIR integer layout (dims) -------------------------------------------------------------------
D_M = 0  # numerator order M: u_r(k) .. u_r(k-M)
D_N = 1  # denominator order N: y(k-1) .. y(k-N)
D_BIAS = 2  # 1: a constant regressor is appended


@njit(cache=True, inline="always", error_model="numpy")
def fpmpi_shape(u: float, fe: np.ndarray, exps: np.ndarray, w_p: np.ndarray) -> float:
    """The front end's shaped input x = sum_i w_P,i sgn(v)|v|^e_i, v = u / u_scale (000 eq. 4-5).

    u is first held within [F_U_LO, F_U_HI] (by default +-inf: min/max return u itself, bit for
    bit): a front end given the inputs it was fitted on does not extrapolate its polynomial."""
    v = min(max(u, fe[F_U_LO]), fe[F_U_HI]) / fe[F_U_SCALE]
    x = 0.0
    for i in range(exps.shape[0]):
        x += w_p[i] * sgnpow(v, exps[i])
    return x


@njit(cache=True, inline="always", error_model="numpy")
def fpmpi_operators(
    x: float, fe: np.ndarray, r: np.ndarray, eta: np.ndarray, w_h: np.ndarray, ops: np.ndarray, xbuf: np.ndarray,
    opbuf: np.ndarray,
) -> float:
    """The front end's operators on the shaped input x: u_r; operator states ``ops`` updated. The
    arithmetic of ``hilbench.sim.kernels.mplay_block`` on a one-sample block, written out here so
    that it inlines (a call per sample costs more than the ten operators)."""
    xbuf[0] = x
    ur = fe[F_OFFSET]
    for i in range(r.shape[0]):
        w = min(x + eta[i] * r[i], ops[i])
        w = max(x - r[i], w)
        ops[i] = w
        opbuf[0, i] = w
        ur += w_h[i] * w
    return ur


@njit(cache=True, inline="always", error_model="numpy")
def fpmpi_step(
    u: float, fe: np.ndarray, exps: np.ndarray, w_p: np.ndarray, r: np.ndarray, eta: np.ndarray, w_h: np.ndarray,
    ops: np.ndarray, xbuf: np.ndarray, opbuf: np.ndarray,
) -> float:
    """FPMPI output u_r for one input sample u (command units); operator states ``ops`` updated.

    ``xbuf`` (1,) and ``opbuf`` (1, n_ops) receive the shaped input and the operator outputs.
    """
    return fpmpi_operators(fpmpi_shape(u, fe, exps, w_p), fe, r, eta, w_h, ops, xbuf, opbuf)


@njit(cache=True, inline="always", error_model="numpy")
def poles_within(theta: np.ndarray, m1: int, nd: int, radius: float, work: np.ndarray, w0: int) -> bool:
    """Whether every pole of ``1 - Q(z^-1) = 1 - sum_j q_j z^-j`` (q_j = theta[m1 + j - 1]) lies
    strictly inside the circle |z| < radius, without computing the roots.

    Schur-Cohn (Jury) test by the Levinson step-down recursion: the monic polynomial with
    coefficients ``a_j = -q_j / radius^j`` (its poles are those of 1 - Q divided by ``radius``) is
    stable iff every reflection coefficient ``k_m = a_m^(m)`` of the step-down
    ``a_j^(m-1) = (a_j^(m) - k_m a_(m-j)^(m)) / (1 - k_m^2)`` has |k_m| < 1. O(N^2) flops, no
    allocation (``work[w0 : w0 + 2 (nd + 1)]`` is scratch), exact up to rounding; a NaN fails.
    """
    a = w0  # a_j at work[a + j]
    b = w0 + nd + 1  # the step-down's next row
    f = 1.0
    inv_r = 1.0 / radius
    for j in range(1, nd + 1):
        f *= inv_r
        work[a + j] = -theta[m1 + j - 1] * f
    for m in range(nd, 0, -1):
        k = work[a + m]
        if not abs(k) < 1.0:
            return False
        inv_d = 1.0 / (1.0 - k * k)
        for j in range(1, m):
            work[b + j] = (work[a + j] - k * work[a + m - j]) * inv_d
        for j in range(1, m):
            work[a + j] = work[b + j]
    return True


@njit(cache=True, inline="always", error_model="numpy")
def project_poles(theta: np.ndarray, P: np.ndarray, m1: int, nd: int, radius: float, work: np.ndarray,
                  w0: int) -> None:
    """Bring every pole of 1 - Q within ``radius``: the denominator contracted radially, the other
    weights moved to the least-squares best for it.

    Denominator: ``q_j -> q_j s^j`` moves every pole p_i to s p_i (1 - sum q_j s^j z^-j =
    prod (1 - s p_i z^-1)), so the angles and relative damping are kept and only the slowest modes
    are pulled in. ``s`` is the largest in [0, 1] that passes :func:`poles_within`, by bisection (a
    contraction is monotone in s; s = 0 always passes): 40 halvings of the Schur-Cohn test, only on
    the samples whose update left the admissible region.

    The rest: RLS's theta minimises the weighted squared error, whose Hessian is P^-1; the best
    weights with q fixed at the contracted q' are ``theta + P[:, q] P_qq^-1 (q' - q)`` (the minimum
    of (theta - theta_LS)' P^-1 (theta - theta_LS) over the other weights). Contracting q alone (a
    Euclidean projection) leaves an estimate the next RLS updates fight: on the simulated gmm rig
    the numerator then ran away to 1e6 within ten samples of the start. P_qq (N x N) is factored
    by Cholesky in ``work``; if it is not positive definite only q is contracted. P is not changed.
    Scratch: ``work[w0 : w0 + 2 (nd + 1) + 2 nd + nd^2]``.
    """
    lo = 0.0
    hi = 1.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if poles_within(theta, m1, nd, radius / mid, work, w0):
            lo = mid
        else:
            hi = mid
    dq = w0 + 2 * (nd + 1)  # q' - q
    x = dq + nd  # P_qq^-1 (q' - q)
    L = x + nd  # Cholesky factor of P_qq, row-major
    f = 1.0
    for j in range(nd):
        f *= lo
        work[dq + j] = theta[m1 + j] * f - theta[m1 + j]
    ok = True
    for i in range(nd):
        for j in range(i + 1):
            acc = P[m1 + i, m1 + j]
            for k in range(j):
                acc -= work[L + i * nd + k] * work[L + j * nd + k]
            if i == j:
                if not acc > 0.0:
                    ok = False
                    break
                work[L + i * nd + i] = math.sqrt(acc)
            else:
                work[L + i * nd + j] = acc / work[L + j * nd + j]
        if not ok:
            break
    if ok:
        for i in range(nd):  # forward: L z = dq
            acc = work[dq + i]
            for k in range(i):
                acc -= work[L + i * nd + k] * work[x + k]
            work[x + i] = acc / work[L + i * nd + i]
        for i in range(nd - 1, -1, -1):  # backward: L' x = z
            acc = work[x + i]
            for k in range(i + 1, nd):
                acc -= work[L + k * nd + i] * work[x + k]
            work[x + i] = acc / work[L + i * nd + i]
        for i in range(theta.shape[0]):
            if i < m1 or i >= m1 + nd:
                acc = 0.0
                for j in range(nd):
                    acc += P[i, m1 + j] * work[x + j]
                theta[i] += acc
    f = 1.0
    for j in range(nd):  # q' exactly as tested (not q + P_qq x, which carries rounding)
        f *= lo
        theta[m1 + j] *= f


@njit(cache=True, inline="always", error_model="numpy")
def oiir_step(
    u: float, y: float,
    fe: np.ndarray, exps: np.ndarray, w_p: np.ndarray, r: np.ndarray, eta: np.ndarray, w_h: np.ndarray,
    ops: np.ndarray, xbuf: np.ndarray, opbuf: np.ndarray, dims: np.ndarray, xs: np.ndarray, phi: np.ndarray,
    theta: np.ndarray, P: np.ndarray, g: np.ndarray, cfg: np.ndarray, st: np.ndarray,
) -> float:
    """One sample of the identifier: returns the online model output y_m(k) (a-priori), um."""
    return oiir_step_shaped(u, math.nan, y, fe, exps, w_p, r, eta, w_h, ops, xbuf, opbuf, dims, xs, phi, theta, P,
                            g, cfg, st)


@njit(cache=True, inline="always", error_model="numpy")
def oiir_step_shaped(
    u: float, x: float, y: float,
    fe: np.ndarray, exps: np.ndarray, w_p: np.ndarray, r: np.ndarray, eta: np.ndarray, w_h: np.ndarray,
    ops: np.ndarray, xbuf: np.ndarray, opbuf: np.ndarray, dims: np.ndarray, xs: np.ndarray, phi: np.ndarray,
    theta: np.ndarray, P: np.ndarray, g: np.ndarray, cfg: np.ndarray, st: np.ndarray,
) -> float:
    """:func:`oiir_step` with the front end's shaped input x of u given (NaN: computed here). For a
    caller that has already evaluated the same fractional polynomial at u (the fpmpi compensator
    of the same model); x must be that polynomial's value at this u, to rounding."""
    if not math.isfinite(u):
        u = xs[X_U_PREV]
        xs[X_INPUT_HELD] += 1.0
        x = math.nan
    xs[X_U_PREV] = u
    if math.isnan(x):
        x = fpmpi_shape(u, fe, exps, w_p)
    ur = fpmpi_operators(x, fe, r, eta, w_h, ops, xbuf, opbuf)
    m1 = dims[D_M] + 1
    nd = dims[D_N]
    n_w = theta.shape[0]
    f0 = filter_at(nd)
    if xs[X_STARTED] == 0.0:
        xs[X_STARTED] = 1.0
        y0 = y if math.isfinite(y) else 0.0
        for i in range(m1):
            phi[i] = ur
        for j in range(nd):
            phi[m1 + j] = y0
        if dims[D_BIAS] != 0:
            phi[m1 + nd] = 1.0
        xs[X_Y_LO] = math.inf
        xs[X_Y_HI] = -math.inf
    # u_r lags: shift right, newest first (the y lags were shifted after the previous sample)
    for i in range(m1 - 1, 0, -1):
        phi[i] = phi[i - 1]
    phi[0] = ur
    if math.isfinite(y):
        if xs[X_DROP_RUN] >= xs[X_DIVERGE_AFTER]:
            # The sensor is back after a dropout longer than a spike: the output lags hold the
            # filter's own free run, so they are refilled with measurements before it learns again,
            # as at the start (learning from them set a 2nd-order ARX back by ~1e4 samples).
            xs[X_FILLED] = 0.0
        xs[X_DROP_RUN] = 0.0
    else:
        xs[X_DROP_RUN] += 1.0
    if xs[X_FILLED] < max(m1 - 1, nd):
        # Lags from before the first sample are guesses: predict, but keep them out of the fit
        # (a handful of wrong rows bias a noise-free, ill-conditioned least squares visibly).
        xs[X_FILLED] += 1.0
        y_m = 0.0
        for i in range(n_w):
            y_m += xs[f0 + i] * phi[i]
        y_in = y if math.isfinite(y) else y_m
    else:
        # the filter's a-priori prediction: the weights of sample k-1, within the admissible region
        y_m = 0.0
        for i in range(n_w):
            y_m += xs[f0 + i] * phi[i]
        R.rls_step(phi, y, theta, P, g, cfg, st)  # the estimator's own, unconstrained prediction unused
        status = st[R.ST_STATUS]
        y_in = y_m if (status == R.NONFINITE or status == R.OUTLIER_SKIPPED) else y
        if status == R.NONFINITE and math.isfinite(y):
            # not learnt from (the prediction or the regressor is not finite), but the measurement
            # is good: it goes into the lags, so that a non-finite history ends here
            y_in = y
        # -- guard 1: a stable filter. A skipped measurement puts the prediction into the output
        # lags, so the OIIR then runs free on its own denominator; with a pole on or outside the
        # unit circle that free run grows without bound, every later error is "gross", every later
        # sample is skipped, and the predictions reach inf (the dSPACE 20 Hz capture did this).
        # The filter is the estimate, projected when its poles leave the region; the estimator keeps
        # its own theta, the least-squares solution its P belongs to (projecting theta itself made
        # the next updates start from a point that is no least-squares solution: with lambda = 1 it
        # never quite returns; 000's 1 Hz scenario: 0.151 -> 0.199 % re_N2).
        for i in range(n_w):
            xs[f0 + i] = theta[i]
        if nd > 0 and not poles_within(theta, m1, nd, xs[X_POLE_RADIUS], xs, X_WORK):
            project_poles(xs[f0:f0 + n_w], P, m1, nd, xs[X_POLE_RADIUS], xs, X_WORK)
            xs[X_PROJECTED] += 1.0
        # -- guard 2: divergence. Gross errors are sensor spikes only while they are short; a run of
        # them longer than the regressor's memory means the identifier has lost the plant (its lags
        # are all its own predictions by then). So do non-finite weights (an overflowing error).
        if status == R.OUTLIER_SKIPPED:
            xs[X_SKIP_RUN] += 1.0
        else:
            xs[X_SKIP_RUN] = 0.0
        finite = True
        for i in range(n_w):
            finite = finite and math.isfinite(theta[i]) and math.isfinite(xs[f0 + i])
        if xs[X_SKIP_RUN] >= xs[X_DIVERGE_AFTER] or not finite:
            if not finite:
                for i in range(n_w):
                    theta[i] = 0.0
                    xs[f0 + i] = 0.0
            delta = cfg[R.C_DELTA]
            for i in range(n_w):
                for j in range(n_w):
                    P[i, j] = 0.0
                P[i, i] = delta
            st[R.ST_RESETS] += 1.0
            st[R.ST_WARM] = 0.0  # the error scale is learnt afresh: the old one judged the lost plant
            st[R.ST_SCALE] = 0.0
            xs[X_DIVERGED] += 1.0
            xs[X_SKIP_RUN] = 0.0
            xs[X_FILLED] = 0.0  # the lags are predictions: refilled with measurements before learning
            if math.isfinite(y):
                y_in = y  # the measurement back into the lags: the free run ends here
    # -- guard 3: a bounded prediction. The outputs seen so far span [lo, hi]; a prediction beyond
    # them by more than their own span is known to be wrong before y(k) arrives (a front end far
    # outside its fitted input range: the piezo stack's u_r reached 3e9 um for a 40 um stroke), so
    # it is held at that bound (counted). Any drive that moves the output on from where it has been
    # widens the bound as fast as it moves (the span grows with it), so a right prediction is never
    # held after the first sample of motion. The held value is also what a skipped sample puts into
    # the lags, so the filter's free run stays within the bound too.
    lo = xs[X_Y_LO]
    hi = xs[X_Y_HI]
    if hi >= lo and xs[X_BOUND_ON] != 0.0:
        span = hi - lo
        if not y_m <= hi + span:  # also NaN
            y_m = hi + span if y_m > hi else lo - span if y_m < lo else phi[m1] if nd > 0 else lo
            xs[X_BOUNDED] += 1.0
        elif y_m < lo - span:
            y_m = lo - span
            xs[X_BOUNDED] += 1.0
    measured = math.isfinite(y) and y_in == y
    if not measured:
        y_in = y_m  # the prediction, held within the bound
    if not math.isfinite(y_in):  # no prediction either (nothing seen yet, non-finite input lags)
        y_in = phi[m1] if nd > 0 else 0.0
    if measured:
        xs[X_Y_LO] = min(lo, y)
        xs[X_Y_HI] = max(hi, y)
    for j in range(nd - 1, 0, -1):
        phi[m1 + j] = phi[m1 + j - 1]
    if nd > 0:
        phi[m1] = y_in
    return y_m


@njit(cache=True, error_model="numpy", _nrt=False)
def oiir_block(
    u: np.ndarray, y: np.ndarray,
    fe: np.ndarray, exps: np.ndarray, w_p: np.ndarray, r: np.ndarray, eta: np.ndarray, w_h: np.ndarray,
    ops: np.ndarray, xbuf: np.ndarray, opbuf: np.ndarray, dims: np.ndarray, xs: np.ndarray, phi: np.ndarray,
    theta: np.ndarray, P: np.ndarray, g: np.ndarray, cfg: np.ndarray, st: np.ndarray,
    y_m: np.ndarray, u_r: np.ndarray, theta_hist: np.ndarray, decimate: int,
) -> int:
    """:func:`oiir_step` over a block; y_m, u_r (n,) outputs; theta after every ``decimate``-th
    sample into ``theta_hist`` until full. Returns the history rows written."""
    rows = 0
    max_rows = theta_hist.shape[0] if decimate > 0 else 0
    countdown = decimate  # no integer division per sample
    for k in range(u.shape[0]):
        y_m[k] = oiir_step(u[k], y[k], fe, exps, w_p, r, eta, w_h, ops, xbuf, opbuf, dims, xs, phi,
                           theta, P, g, cfg, st)
        u_r[k] = phi[0]
        if rows < max_rows:
            countdown -= 1
            if countdown == 0:
                countdown = decimate
                f0 = filter_at(dims[D_N])
                for i in range(theta.shape[0]):
                    theta_hist[rows, i] = xs[f0 + i]  # the filter's weights (= theta inside the region)
                rows += 1
    return rows


class FPMPIFrontEnd:
    """The rate-independent part of 000 (eq. 1-5) with fixed parameters, as kernel arrays.

    ``exponents`` and ``w_p`` define the fractional polynomial of v = u / u_scale; ``thresholds``
    (in units of the polynomial's output) and ``w_h`` the one-sided play operators; ``offset`` is
    the constant term. Output u_r in the output unit of the offline fit (um). ``input_range``
    (command units, default none): the input is held within it before the polynomial, e.g. the
    range the front end was fitted on, beyond which its polynomial (up to u^4) is an arbitrary
    extrapolation (the dSPACE 100 Hz capture, fitted on -90..-36 V: u_r fell to -13 um at 18 V
    while the output rose to 0.6 um); the OIIR then explains the rest from its output lags.
    """

    def __init__(self, u_scale: float, exponents: np.ndarray, w_p: np.ndarray, thresholds: np.ndarray,
                 w_h: np.ndarray, offset: float = 0.0, input_range: tuple[float, float] | None = None):
        self.exps = np.ascontiguousarray(exponents, dtype=np.float64)
        self.w_p = np.ascontiguousarray(w_p, dtype=np.float64)
        self.r = np.ascontiguousarray(thresholds, dtype=np.float64)
        self.w_h = np.ascontiguousarray(w_h, dtype=np.float64)
        if self.exps.shape != self.w_p.shape:
            raise ValueError(f"exponents {self.exps.shape} and w_p {self.w_p.shape} differ in length")
        if self.r.shape != self.w_h.shape or self.r.ndim != 1 or self.r.size < 1:
            raise ValueError(f"thresholds {self.r.shape} and w_h {self.w_h.shape}: expected equal, >= 1 operator")
        if np.any(self.r < 0):
            raise ValueError("thresholds must be >= 0")
        if not u_scale > 0:
            raise ValueError(f"u_scale={u_scale}: expected > 0")
        lo, hi = (-math.inf, math.inf) if input_range is None else (float(input_range[0]), float(input_range[1]))
        if not lo <= hi:
            raise ValueError(f"input_range={input_range}: expected lo <= hi")
        self.fe = np.array([float(u_scale), float(offset), lo, hi])
        self.eta = np.zeros(self.r.shape[0])  # one-sided play (000 eq. 1)

    @classmethod
    def from_model(cls, model: Any, input_range: tuple[float, float] | None = None) -> FPMPIFrontEnd:
        """From a fitted :class:`hilbench.models.Model` whose base is ``fpmpi`` (``input_range``: see
        the class).

        Effects without columns (``dynamics``, ``delay``) are ignored: the OIIR replaces the
        offline dynamics. Effects that add columns (asymmetry, aux channels, ...) are refused.
        """
        base = model.base
        if base.name != "fpmpi":
            raise ValueError(f"model base is {base.name!r}; the OIIR front end needs an 'fpmpi' model")
        if model.weights is None:
            raise ValueError("the model has no weights yet: fit it first")
        n_ops = int(base.constants["n"])
        if len(model.weights) != n_ops + 1:
            extra = [e.name for e in model.effects if e.name not in ("dynamics", "delay")]
            raise ValueError(f"model {model.spec!r} has {len(model.weights)} weights, the FPMPI front end "
                             f"{n_ops + 1}; effects with columns ({', '.join(extra)}) are not supported")
        if "shaped_max" not in base.constants:
            raise ValueError("the fpmpi model is not finalised (no 'shaped_max'): fit it first")
        params = iter(base.params)
        exps = np.asarray(base.constants["exponents"], float)
        w_p = np.array([1.0 if e == 1.0 else next(params).value for e in exps])
        span = float(base.constants["shaped_max"]) or 1.0
        r = np.arange(n_ops) / n_ops * span  # as FPMPI.columns
        w = np.asarray(model.weights, float)
        return cls(float(model.norm["u_scale"]), exps, w_p, r, w[1:], offset=float(w[0]), input_range=input_range)

    def unbounded(self) -> FPMPIFrontEnd:
        """The same front end without an input range (the offline model's own static part)."""
        out = FPMPIFrontEnd(float(self.fe[F_U_SCALE]), self.exps, self.w_p, self.r, self.w_h,
                            offset=float(self.fe[F_OFFSET]))
        return out

    def new_state(self) -> dict[str, np.ndarray]:
        n = self.r.shape[0]
        return {"ops": np.zeros(n), "xbuf": np.zeros(1), "opbuf": np.zeros((1, n))}

    def simulate(self, u: np.ndarray, state: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """u_r for a block of inputs (fresh operators unless ``state`` is given)."""
        s = self.new_state() if state is None else state
        out = np.empty(len(u))
        _fpmpi_block(np.ascontiguousarray(u, dtype=np.float64), self.fe, self.exps, self.w_p, self.r, self.eta,
                     self.w_h, s["ops"], s["xbuf"], s["opbuf"], out)
        return out


@njit(cache=True, error_model="numpy", _nrt=False)
def _fpmpi_block(u, fe, exps, w_p, r, eta, w_h, ops, xbuf, opbuf, out) -> None:
    for k in range(u.shape[0]):
        out[k] = fpmpi_step(u[k], fe, exps, w_p, r, eta, w_h, ops, xbuf, opbuf)


class OIIR:
    """Online identifier of 000 (Fig. 6): FPMPI front end + OIIR weights by RLS every sample.

    ``front_end``: an :class:`FPMPIFrontEnd` (or use :meth:`from_model`). ``M``, ``N``: numerator
    and denominator orders (000: 3 and 5). ``bias``: append a constant regressor. ``theta0``:
    initial weights [p_0..p_M, q_1..q_N(, bias)] (default 0). Remaining keywords go to the RLS
    (:func:`hilbench.online.rls.make_config`): ``lam`` (000 uses 1), ``delta`` (000: 1e5),
    ``forgetting``, ``outlier``, ...

    The guard (decision 0082; None / False switch a part off, for tests): ``pole_radius`` (default
    0.999) bounds the poles of 1 - Q after every update; ``diverge_after`` (default "auto":
    max(20, 2 max(M, N)) samples) gross errors in a row reset P to delta I and put the measurement
    back into the lags; ``bound_predictions`` holds a prediction within the outputs seen widened by
    their span.
    """

    def __init__(self, front_end: FPMPIFrontEnd, M: int = 3, N: int = 5, *, bias: bool = False,
                 theta0: np.ndarray | None = None, delta: float = 1.0e5, pole_radius: float | None = POLE_RADIUS,
                 diverge_after: int | str | None = "auto", bound_predictions: bool = True, **rls_options: Any):
        if M < 0 or N < 0:
            raise ValueError(f"orders M={M}, N={N}: expected >= 0")
        self.front_end = front_end
        self.M, self.N, self.bias = int(M), int(N), bool(bias)
        self.n_weights = self.M + 1 + self.N + (1 if bias else 0)
        self.dims = np.array([self.M, self.N, 1 if bias else 0], dtype=np.int64)
        self.cfg = R.make_config(self.n_weights, delta=delta, **rls_options)
        # None switches a guard off: for tests that show what it prevents, not for use
        if pole_radius is not None and not 0.0 < pole_radius < 1.0:
            raise ValueError(f"pole_radius={pole_radius}: expected 0 < pole_radius < 1 (a stable filter)")
        self.pole_radius = math.inf if pole_radius is None else float(pole_radius)
        # Spikes last a sample or a few; twice the regressor's memory of gross errors in a row is a
        # lost plant, not a sensor (and never fewer than 20 samples).
        if diverge_after is not None and diverge_after != "auto" and not int(diverge_after) >= 1:
            raise ValueError(f"diverge_after={diverge_after}: expected >= 1 sample")
        self.diverge_after = (max(20, 2 * max(self.M, self.N)) if diverge_after == "auto" else
                              math.inf if diverge_after is None else int(diverge_after))
        self.bound_predictions = bool(bound_predictions)
        self._theta0 = theta0
        self.reset()

    @classmethod
    def from_model(cls, model: Any, M: int = 3, N: int = 5, **options: Any) -> OIIR:
        """Front end from a fitted ``fpmpi`` :class:`hilbench.models.Model` (see FPMPIFrontEnd)."""
        return cls(FPMPIFrontEnd.from_model(model), M, N, **options)

    @property
    def weight_names(self) -> list[str]:
        names = [f"p{i}" for i in range(self.M + 1)] + [f"q{j}" for j in range(1, self.N + 1)]
        return names + (["bias"] if self.bias else [])

    def reset(self) -> None:
        """Fresh operators, empty history, theta0, P0 = delta I."""
        fs = self.front_end.new_state()
        self.ops, self.xbuf, self.opbuf = fs["ops"], fs["xbuf"], fs["opbuf"]
        self.xs = np.zeros(N_XS + work_size(self.N) + self.n_weights)
        if self._theta0 is not None:  # the filter starts at theta0 too (projected at the first update)
            self.xs[N_XS + work_size(self.N):] = np.asarray(self._theta0, dtype=np.float64).reshape(self.n_weights)
        self.xs[X_POLE_RADIUS] = self.pole_radius
        self.xs[X_DIVERGE_AFTER] = float(self.diverge_after)
        self.xs[X_BOUND_ON] = 1.0 if self.bound_predictions else 0.0
        self.phi = np.zeros(self.n_weights)
        s = R.new_state(self.n_weights, float(self.cfg[R.C_DELTA]), self._theta0)
        self.theta, self.P, self.g, self.st = s["theta"], s["P"], s["g"], s["st"]

    def kernel_args(self) -> tuple:
        """The arrays of :func:`oiir_step` after its (u, y) arguments, in order: the front end's
        parameters, the operator and regressor state, the RLS state and settings (for compiled
        loops that call the step themselves)."""
        f = self.front_end
        return (f.fe, f.exps, f.w_p, f.r, f.eta, f.w_h, self.ops, self.xbuf, self.opbuf, self.dims, self.xs,
                self.phi, self.theta, self.P, self.g, self.cfg, self.st)

    def step(self, u: float, y: float) -> float:
        """Step mode: input u (command units) and measured output y (um) of sample k; returns the
        online model output y_m(k) predicted before y(k) was used."""
        return oiir_step(float(u), float(y), *self.kernel_args())

    def run(self, u: np.ndarray, y: np.ndarray, decimate: int = 1) -> dict[str, np.ndarray]:
        """Block mode. Returns ``y_m`` (online model output), ``u_r`` (FPMPI output) and
        ``weights`` (theta after every ``decimate``-th sample, rows x K; 000 Fig. 10c-d)."""
        u = np.ascontiguousarray(u, dtype=np.float64).reshape(-1)
        y = np.ascontiguousarray(y, dtype=np.float64).reshape(-1)
        if u.shape != y.shape:
            raise ValueError(f"u {u.shape} and y {y.shape} differ")
        n = u.shape[0]
        y_m = np.empty(n)
        u_r = np.empty(n)
        hist = np.empty((n // decimate if decimate > 0 else 0, self.n_weights))
        oiir_block(u, y, *self.kernel_args(), y_m, u_r, hist, int(decimate))
        return {"y_m": y_m, "u_r": u_r, "weights": hist}

    def counters(self) -> dict[str, Any]:
        """The RLS counters (``covariance_resets`` counts every reset of P, divergence ones too),
        the inputs held, the stability projections and the divergence resets."""
        return {**R.counters(self.st), "input_held": int(self.xs[X_INPUT_HELD]),
                "poles_projected": int(self.xs[X_PROJECTED]), "divergence_resets": int(self.xs[X_DIVERGED]),
                "predictions_bounded": int(self.xs[X_BOUNDED])}

    @property
    def filter_weights(self) -> np.ndarray:
        """The weights that predict: the estimate theta, projected when its poles leave the
        admissible region (a view into the state)."""
        return self.xs[N_XS + work_size(self.N):]

    def poles(self, theta: np.ndarray | None = None) -> np.ndarray:
        """Poles of the OIIR's denominator 1 - Q(z^-1), of the filter's weights by default (np.roots:
        for reports, not per sample)."""
        t = self.filter_weights if theta is None else theta
        q = np.asarray(t[self.M + 1 : self.M + 1 + self.N], float)
        return np.roots(np.concatenate([[1.0], -q])) if q.size else np.zeros(0, complex)

    def transfer_function(self) -> tuple[np.ndarray, np.ndarray]:
        """The filter's weights as (b, a) in scipy.signal.lfilter convention: G = P / (1 - Q)."""
        w = self.filter_weights
        b = w[: self.M + 1].copy()
        a = np.concatenate([[1.0], -w[self.M + 1 : self.M + 1 + self.N]])
        return b, a

    def static_gain(self, theta: np.ndarray | None = None) -> float:
        """DC gain of the OIIR, sum p / (1 - sum q): um of output per um of u_r (the filter's
        weights by default)."""
        t = self.filter_weights if theta is None else theta
        return float(np.sum(t[: self.M + 1]) / (1.0 - np.sum(t[self.M + 1 : self.M + 1 + self.N])))


def re_n2_pct(y: np.ndarray, y_m: np.ndarray) -> float:
    """000 eq. 18: ||y - y_m||_2 / ||y||_2 x 100 % (non-finite samples left out)."""
    ok = np.isfinite(y) & np.isfinite(y_m)
    return float(100.0 * np.linalg.norm(y[ok] - y_m[ok]) / np.linalg.norm(y[ok]))


def re_ninf_pct(y: np.ndarray, y_m: np.ndarray) -> float:
    """000 eq. 18: ||y - y_m||_inf / ||y||_inf x 100 % (non-finite samples left out)."""
    ok = np.isfinite(y) & np.isfinite(y_m)
    return float(100.0 * np.max(np.abs(y[ok] - y_m[ok])) / np.max(np.abs(y[ok])))


def persistence(y: np.ndarray) -> np.ndarray:
    """The naive one-step-ahead predictor y(k-1) of y(k) (NaN at k = 0): what the measured output
    lags of eq. 11 give for free, the baseline any one-step-ahead error must be read against."""
    y = np.asarray(y, dtype=np.float64)
    out = np.empty_like(y)
    if y.size:
        out[0] = np.nan
        out[1:] = y[:-1]
    return out


#: paper 000's offline Hammerstein model (sec. 4.1, eq. 15): FPMPI, then linear dynamics with a delay
OFFLINE_SPEC = "fpmpi+dynamics+delay"


def offline_hammerstein(
    runs: list[Any], train_masks: list[np.ndarray], *, dynamics_masks: list[np.ndarray] | None = None,
    hysteresis: Any = None, global_starts: int = 16, local_starts: int = 2, progress: Any = None,
) -> tuple[Any, Any]:
    """Paper 000's offline model, identified once on the training rows and then held.

    As 000 sec. 4.1 (and tests/models/test_paper_reproductions.py): first the rate-independent
    FPMPI (spec ``fpmpi``: the fractional polynomial's weights by a bounded global + local search,
    the play weights by least squares), unless ``hysteresis`` (a fitted ``fpmpi`` model) is given;
    then ``fpmpi+dynamics+delay`` started from it (second-order dynamics with unit static gain and
    a delay: the structure of eq. 15), all on free-run simulation error. ``runs``:
    :class:`hilbench.models.RunData` in recorded order (memory chained as recorded); ``train_masks``
    the rows each run trains with; ``dynamics_masks`` other rows for the second stage (000 takes the
    FPMPI from a slow ramped sine, the dynamics from band-limited noise). Returns
    ``(hysteresis, hammerstein)``.
    """
    from hilbench.identify import fit_model
    from hilbench.models import Model

    channels = ["input", "output"]
    if hysteresis is None:
        hysteresis = Model("fpmpi", channels=channels)
        fit_model(hysteresis, runs, train_masks, global_starts=global_starts, local_starts=local_starts,
                  progress=progress)
    elif hysteresis.base.name != "fpmpi":
        raise ValueError(f"model base is {hysteresis.base.name!r}; the offline Hammerstein model of 000 needs 'fpmpi'")
    model = Model(OFFLINE_SPEC, channels=channels)
    fit_model(model, runs, train_masks if dynamics_masks is None else dynamics_masks, global_starts=0, local_starts=1,
              start_from=hysteresis, progress=progress)
    return hysteresis, model
