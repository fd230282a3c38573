"""Per-sample kernels of the inverse-model compensators (:mod:`hilbench.online.inverse`): numba
functions over explicit state, one kernel for block and step mode.

Kernel layout: ``CI`` (int64 structure), ``CP`` (float64 parameters), ``CX`` (float64 state and
scratch) beside the model's ``I, P, X``. :func:`comp_step` computes the command of one sample (no
memory change but the solver's slope estimate and the feedforward filter), :func:`comp_update`
commits the applied command and the measurement. Both are ``_nrt=False`` and allocate nothing, so
they run inside the fused closed loop of :mod:`hilbench.online.tracking`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from hilbench.models import stepping as ST
from hilbench.models.stepping import model_step as _model_step_inline

# The model's step as a called function, not inlined: inlined, numba typed the whole model (every base
# and effect) again at each call site here; the closed loop's cold compile fell from 97 to 54 s on one
# core with it called, and the fused loop's time per sample did not change (387/391 ns general, 232/235
# ns I-M inverse on piezo-pmpi).
model_step = njit(cache=True, _nrt=False)(_model_step_inline.py_func)
from hilbench.online.oiir import oiir_step_shaped
from hilbench.sim.kernels import sgnpow

# -- kinds -------------------------------------------------------------------------------------------
K_GENERAL = 0
K_PI = 1
K_MPI = 2
K_IM = 3
K_FPMPI = 4
KINDS = {"general": K_GENERAL, "pi": K_PI, "mpi": K_MPI, "im": K_IM, "fpmpi": K_FPMPI}

# -- CI: structure ---------------------------------------------------------------------------------
CI_KIND = 0
CI_NOPS = 1  # operators with a positive (equivalent play) threshold, sorted
CI_PERM = 2  # CI offset: their indices among the model's operators
CI_NPOLY = 3  # polynomial coefficients c_0..c_deg (0 = none)
CI_FF = 4  # order of the dynamics feed-forward filter (0 = none)
CI_PID = 5
CI_ADAPT = 6
CI_MAXIT = 7  # solver iterations per sample
CI_IMIT = 8  # I-M fixed-point passes per sample
CI_NX = 9  # length of the model's X
CI_O_S = 10  # CP offsets: equivalent play thresholds, weights, inverse thresholds, inverse weights
CI_O_P = 11
CI_O_C = 12
CI_O_RH = 13
CI_O_PH = 14
CI_O_POLY = 15
CI_O_FFN = 16  # feed-forward numerator (a / b0), denominator (b / b0), steady-state start
CI_O_FFD = 17
CI_O_FFZI = 18
CI_O_XM = 19  # CX offsets: scratch copy of the model state, feed-forward filter state
CI_O_XFF = 20
CI_M = 21  # OIIR numerator order M
CI_N = 22  # OIIR denominator order N
CI_BIAS = 23  # OIIR has a bias regressor
CI_NT = 24  # fpmpi fast path: terms of the fractional polynomial as a polynomial in t = |v|^(1/q) (0 = off)
CI_O_TK = 25  # CI offset: their integer powers k = q e, ascending
CI_O_TW = 26  # CP offset: their weights
CI_FASTCOMMIT = 27  # 1: the fpmpi commit updates the static model's memory directly (no model_step)
CI_FESHARED = 28  # 1: the identifier's front end has the model's fractional polynomial (and fast commit)
CI_PREVIEW = 29  # 1: the static part's target is CX[S_TARGET], set per sample from the previewed reference
CI_PLAN = 30  # samples of a planned command path (0 = none; hilbench.online.path_plan)
CI_O_PLAN = 31  # CP offset: the plan's commands, stretch lows, stretch highs, slopes, directions, feedback (CI_PLAN each)
CI_PLANAUX = 32  # 1: the planned model reads channels (load, temperature) that move during the run
N_CI = 33

# -- CP: scalars ----------------------------------------------------------------------------------------
C_US = 0  # model input scale (command units per normalised unit)
C_ULO = 1  # command range, command units
C_UHI = 2
C_P0 = 3  # effective linear weight p0 (+ k_e), um per normalised unit
C_PH0 = 4  # 1 / C_P0
C_CONST = 5  # constant of the PI part: offset weight + sum p_i c_i, um
C_KE = 6  # eq. 20 proportional gain, um per normalised unit
C_TOLF = 7  # solver tolerance on the residual
C_TOLU = 8  # solver tolerance on the bracket, command units
C_KP = 9  # PID, output domain: proportional (1), integral per sample (ki T), derivative (s)
C_KIT = 10
C_KD = 11
C_TF = 12  # derivative filter time constant, s
C_T = 13  # sample period, s
C_ILIM = 14  # integrator clamp, um
C_GMIN = 15  # accepted range of the identified gain
C_GMAX = 16
C_WARM = 17  # samples before the identified gain is used
C_SLOPE0 = 18  # initial slope of the residual per command unit
C_SMIN = 19  # smallest slope of the PI part (its first cumulative slope p0 + ...), um per unit
C_PITOL = 20  # relative tolerance of the analytic inverse's check
C_TQ = 21  # fpmpi fast path: q of t = |v|^(1/q)
C_TC0 = 22  # the polynomial's constant (the e = 0 terms)
C_SLO = 23  # the command range in s = sgn(v) |v|^(1/q)
C_SHI = 24
# (25: unused)
C_GUARD = 26  # 1: the feedback's reversal guard (the command moves only the way the reference moves)
C_SIGN = 27  # +1: the static map rises with the command over the bracket; -1: it falls (the general kind)
C_PLANG = 28  # with CI_PLAN: the floor of the slope feedback's correction is divided by, um per command unit
N_CP = 29

# -- CX: state --------------------------------------------------------------------------------------------
S_U = 0  # last command (before the safety path), command units
S_UAPP = 1  # last applied command
S_VPREV = 2  # u_d(k-1) of eq. 13, normalised
S_SLOPE = 3  # solver's slope estimate of the residual
S_PID = 4  # feedback term for the next sample, um
S_I = 5  # integrator, um
S_D = 6  # filtered derivative term, um
S_YPREV = 7  # last measured output, um
S_SAT = 8  # +1 / -1: the last command was limited while the loop wanted more / less
S_GAIN = 9  # identified gain correction (1 = the model is right)
S_BIAS = 10  # identified offset correction, um
S_NOBS = 11  # samples observed by update()
S_EVALS = 12  # residual evaluations so far
S_SATN = 13  # samples whose command was limited
S_STARTED = 14
S_FFSTART = 15
S_HELD = 16  # non-finite references held
S_YMOD = 17  # the static model's output at the last commit, um
S_FIXED = 18  # samples where the analytic inverse was corrected by Newton steps
S_XP = 19  # fpmpi: the operators' input x at the last fast commit, for the input v = S_XP_V
S_XP_V = 20
S_XP_OK = 21  # 1 while S_XP is the model memory's (a fast commit wrote it; precondition clears it)
S_SSOL = 22  # s, x and command of the last Newton solution
S_XSOL = 23
S_USOL = 24
S_SPREV = 25  # s of the applied command S_SPREV_U, and of the two before: the Newton warm start
S_SPREV_U = 26
S_NEWTON = 27  # samples solved by the Newton fast path
S_SPREV2 = 28
S_SPREV3 = 29
S_SHIST = 30  # how many of S_SPREV, S_SPREV2, S_SPREV3 are consecutive Newton solutions
S_RPREV = 31  # the last feed-forward target (the reference, or its preview), um: the reversal guard's direction
S_GUARDN = 32  # samples whose command the reversal guard held
S_TARGET = 33  # with CI_PREVIEW: what the static part must deliver this sample, um (hilbench.online.preview)
S_PLANK = 34  # with CI_PLAN: the planned sample this one is (counted by comp_update)
N_CX = 35


@njit(cache=True, _nrt=False)
def shaped_input(I: np.ndarray, P: np.ndarray, v: float) -> float:
    """The operators' input: the fractional polynomial of 000 eq. 4-5 (fpmpi), else v itself."""
    nin = I[ST.I_NIN]
    if nin == 0:
        return v
    x = 0.0
    for k in range(nin):
        x += P[I[ST.I_INW] + k] * sgnpow(v, P[I[ST.I_INEXP] + k])
    return x


@njit(cache=True, _nrt=False)
def _poly(CI: np.ndarray, CP: np.ndarray, v: float) -> float:
    """The memoryless polynomial sum c_k v^k (Horner), um."""
    n = CI[CI_NPOLY]
    o = CI[CI_O_POLY]
    acc = 0.0
    for k in range(n - 1, -1, -1):
        acc = acc * v + CP[o + k]
    return acc


@njit(cache=True, inline="always", _nrt=False)
def _pi_inverse(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
                z: float) -> float:
    """The inverse PI (own thresholds and weights) at the target z of the play part, from the
    forward operators' current states; returns the operators' input x. Changes no state."""
    n = CI[CI_NOPS]
    o_perm = CI[CI_PERM]
    o_ops = I[ST.I_X_OPS]
    o_p = CI[CI_O_P]
    o_c = CI[CI_O_C]
    o_rh = CI[CI_O_RH]
    o_ph = CI[CI_O_PH]
    p0 = CP[C_P0]
    # the operators' last input (virgin memory: 0, where the operators' states sit) and the play
    # part's value there; the fpmpi fast commit leaves both (its input x and the static model's
    # output, which is the play part plus C_CONST), so neither is evaluated again
    if X[ST.X_STARTED] != 0.0 and CX[S_XP_OK] != 0.0 and CX[S_XP_V] == X[ST.X_V_PREV]:
        xp = CX[S_XP]
        y = CX[S_YMOD] - CP[C_CONST]
    else:
        xp = shaped_input(I, P, X[ST.X_V_PREV]) if X[ST.X_STARTED] != 0.0 else 0.0
        y = p0 * xp
        for j in range(n):
            y += CP[o_p + j] * (X[o_ops + CI[o_perm + j]] - CP[o_c + j])
    x = CP[C_PH0] * z
    sp = 0.0
    spx = 0.0
    for j in range(n):
        pj = CP[o_p + j]
        xj = X[o_ops + CI[o_perm + j]] - CP[o_c + j]
        wh = y - (p0 * (xp - xj) + spx - sp * xj)
        r = CP[o_rh + j]
        wh = min(max(wh, z - r), z + r)
        x += CP[o_ph + j] * wh
        sp += pj
        spx += pj * xj
    return x


@njit(cache=True, inline="always", _nrt=False)
def _pi_forward(CI: np.ndarray, CP: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray, x: float,
                out: np.ndarray) -> None:
    """The play part at input x from the current states (no state change): out = (value, slope)."""
    n = CI[CI_NOPS]
    o_perm = CI[CI_PERM]
    o_ops = I[ST.I_X_OPS]
    o_p = CI[CI_O_P]
    o_c = CI[CI_O_C]
    o_s = CI[CI_O_S]
    val = CP[C_P0] * x
    slope = CP[C_P0]
    for j in range(n):
        s = CP[o_s + j]
        w = X[o_ops + CI[o_perm + j]] - CP[o_c + j]
        pj = CP[o_p + j]
        if w < x - s:
            val += pj * (x - s)
            slope += pj
        elif w > x + s:
            val += pj * (x + s)
            slope += pj
        else:
            val += pj * w
    out[0] = val
    out[1] = slope


@njit(cache=True, inline="always", _nrt=False)
def _pi_value(CI: np.ndarray, CP: np.ndarray, I: np.ndarray, X: np.ndarray, x: float) -> float:
    """The value of :func:`_pi_forward` (the same bits), branch-free: a clamp per operator."""
    n = CI[CI_NOPS]
    o_perm = CI[CI_PERM]
    o_ops = I[ST.I_X_OPS]
    o_p = CI[CI_O_P]
    o_c = CI[CI_O_C]
    o_s = CI[CI_O_S]
    val = CP[C_P0] * x
    for j in range(n):
        s = CP[o_s + j]
        w = X[o_ops + CI[o_perm + j]] - CP[o_c + j]
        val += CP[o_p + j] * min(max(w, x - s), x + s)
    return val


@njit(cache=True, inline="always", _nrt=False)
def _pi_inverse_checked(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray,
                        X: np.ndarray, z: float) -> float:
    """:func:`_pi_inverse`, checked against the forward operators; where the two disagree (operator
    states that no input history from a common start could produce, e.g. virgin M-play operators
    with different eta), Newton steps on the piecewise-linear forward map (bracketed) correct it."""
    x = _pi_inverse(CI, CP, CX, I, P, X, z)
    g = _pi_value(CI, CP, I, X, x) - z
    tol = CP[C_PITOL] * (abs(z) + 1.0)
    if abs(g) <= tol:
        return x
    CX[S_FIXED] += 1.0
    o = CI[CI_O_XM] + CI[CI_NX]
    buf = CX[o : o + 2]
    _pi_forward(CI, CP, I, P, X, x, buf)
    smin = CP[C_SMIN]
    lo = x - abs(g) / smin
    hi = x + abs(g) / smin
    for _ in range(100):
        if g < 0.0:
            lo = max(lo, x)
        else:
            hi = min(hi, x)
        xn = x - g / buf[1]
        if not (lo < xn < hi):
            xn = 0.5 * (lo + hi)
        x = xn
        _pi_forward(CI, CP, I, P, X, x, buf)
        g = buf[0] - z
        if abs(g) <= tol or hi - lo <= 1e-15 * (abs(x) + 1.0):
            break
    return x


@njit(cache=True, _nrt=False)
def _resid(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
           aux: np.ndarray, target: float, u: float, sign: float) -> float:
    """What the solver drives to zero, rising with u (a falling map's residual is negated: ``sign``)."""
    kind = CI[CI_KIND]
    if kind == K_GENERAL:
        o = CI[CI_O_XM]
        nx = CI[CI_NX]
        for i in range(nx):
            CX[o + i] = X[i]
        return sign * (model_step(I, P, CX[o : o + nx], u, aux) - target)
    us = CP[C_US]
    v = u / us
    if kind == K_FPMPI:
        return (shaped_input(I, P, v) - target) * us
    z = target - _poly(CI, CP, v) + CP[C_KE] * v
    return (v - _pi_inverse_checked(CI, CP, CX, I, P, X, z)) * us


@njit(cache=True, _nrt=False)
def _solve(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
           aux: np.ndarray, target: float, x0: float, a: float, b: float, sign: float) -> float:
    """Safeguarded secant/bisection for the rising residual on [a, b], started at x0 (``sign``: the
    map's sense there).

    The bracket narrows with every evaluation; a secant step that leaves it, or that did not halve
    the residual, is replaced by bisection; a domain end is probed before bisecting towards it, and
    a target beyond the reachable range gives that end (the command saturates)."""
    tol_f = CP[C_TOLF]
    tol_x = CP[C_TOLU]
    lo = a
    hi = b
    lo_known = False
    hi_known = False
    x = min(max(x0, a), b)
    fx = _resid(CI, CP, CX, I, P, X, aux, target, x, sign)
    evals = 1
    s = CX[S_SLOPE]
    if not (s > 0.0) or not math.isfinite(s):
        s = CP[C_SLOPE0]
    bisect = False
    sat = 0.0
    for _ in range(CI[CI_MAXIT]):
        if abs(fx) <= tol_f:
            break
        if fx < 0.0:
            lo = x
            lo_known = True
            if x == b:
                sat = 1.0
                break
        else:
            hi = x
            hi_known = True
            if x == a:
                sat = -1.0
                break
        if hi - lo <= tol_x:
            break
        if bisect and lo_known and hi_known:
            xn = 0.5 * (lo + hi)
        else:
            xn = x - fx / s
            if xn <= lo:
                xn = 0.5 * (lo + hi) if lo_known else lo
            elif xn >= hi:
                xn = 0.5 * (lo + hi) if hi_known else hi
        fn = _resid(CI, CP, CX, I, P, X, aux, target, xn, sign)
        evals += 1
        if xn != x:
            sn = (fn - fx) / (xn - x)
            if sn > 0.0 and math.isfinite(sn):
                s = sn
        bisect = abs(fn) > 0.5 * abs(fx)
        x = xn
        fx = fn
    if abs(fx) > tol_f:
        if x == b and fx < 0.0:
            sat = 1.0
        elif x == a and fx > 0.0:
            sat = -1.0
    CX[S_SLOPE] = s
    CX[S_EVALS] += evals
    CX[S_SAT] = sat
    return x


# -- fpmpi fast path: the fractional polynomial as a polynomial in t = |v|^(1/q) ------------------------
#
# The exponents of 000 eq. 5 (0, 1, 2, 1/2, 3, 1/3, 4, 1/4) are multiples of 1/12: with t = |v|^(1/12)
# the polynomial is sum_k w_k t^k (k = 12 e), evaluated with multiplications only (no pow, no
# sqrt), and so is its derivative. Newton's method in s = sgn(v) t, warm-started from the last
# applied command's s, solves it in 1-3 evaluations per sample; whatever Newton cannot do (a step
# out of the command range, a falling or flat part of the polynomial, no convergence in NEWTON_MAX
# steps) goes to the safeguarded solver, which is exact for those cases.
NEWTON_MAX = 6


@njit(cache=True, inline="always", _nrt=False)
def _ipow(t: float, n: int) -> float:
    """t**n for an integer n >= 0 by squaring (multiplications only)."""
    r = 1.0
    b = t
    while n > 0:
        if n & 1:
            r *= b
        b *= b
        n >>= 1
    return r


@njit(cache=True, inline="always", _nrt=False)
def _tpoly(CI: np.ndarray, CP: np.ndarray, t: float) -> tuple[float, float, float]:
    """(sum w_k t^k, sum k w_k t^k, sum k (k - 1) |w_k| t^k) over the terms with k > 0 (t >= 0): the
    second over t is the derivative, the third over t^2 bounds the second derivative's size."""
    nt = CI[CI_NT]
    ok = CI[CI_O_TK]
    ow = CI[CI_O_TW]
    val = 0.0
    der = 0.0
    bound = 0.0
    tp = 1.0
    kp = 0
    for j in range(nt):
        k = CI[ok + j]
        tp = tp * _ipow(t, k - kp)
        kp = k
        wt = CP[ow + j] * tp
        val += wt
        der += k * wt
        bound += (k * (k - 1)) * abs(wt)
    return val, der, bound


@njit(cache=True, inline="always", _nrt=False)
def _fpmpi_newton(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, xt: float) -> float:
    """The command whose shaped input is xt by Newton steps in s (see above); NaN when the fast
    path gives up (the caller then runs the safeguarded solver). Leaves s and x of the solution in
    CX (S_SSOL, S_XSOL) for the commit and the next warm start.

    Warm start: the last solutions extrapolated (quadratic over three consecutive ones, linear over
    two). Stop: the residual within the solver's tolerance, or a Newton step whose remainder
    ``|f(s + d) - xt| <= 1/2 max|f''| d^2`` is bounded below half of it (``k_max |d| <= t / 10``
    bounds ``f''`` on the step by 1.106 times its bound at s); that last point is not evaluated
    again, and its shaped input is taken as xt (within half the tolerance)."""
    us = CP[C_US]
    q = int(CP[C_TQ])
    if CX[S_SPREV_U] == CX[S_UAPP]:
        nh = CX[S_SHIST]
        s1 = CX[S_SPREV]
        if nh >= 3.0:
            s = 3.0 * (s1 - CX[S_SPREV2]) + CX[S_SPREV3]
        elif nh >= 2.0:
            s = 2.0 * s1 - CX[S_SPREV2]
        else:
            s = s1
    else:  # a command the fast path did not see (start, precondition, safety path)
        v = CX[S_UAPP] / us
        s = abs(v) ** (1.0 / q)
        if v < 0.0:
            s = -s
    slo = CP[C_SLO]
    shi = CP[C_SHI]
    s = min(max(s, slo), shi)
    c0 = CP[C_TC0]
    tol = CP[C_TOLF] / us
    kmax = CI[CI[CI_O_TK] + CI[CI_NT] - 1]
    evals = 0
    done = False
    for _ in range(NEWTON_MAX):
        t = abs(s)
        val, der, bound = _tpoly(CI, CP, t)
        evals += 1
        f = (c0 + val if s >= 0.0 else c0 - val) - xt
        if abs(f) <= tol:
            CX[S_XSOL] = f + xt
            done = True
            break
        if not (der > 0.0 and t > 0.0):
            break
        rd = f / der  # the step relative to t
        sn = s - rd * t
        if not (slo <= sn <= shi):
            break
        s = sn
        if kmax * abs(rd) <= 0.1 and 0.553 * bound * rd * rd <= 0.5 * tol:
            CX[S_XSOL] = xt
            done = True
            break
    CX[S_EVALS] += evals
    if not done:
        return math.nan
    CX[S_SSOL] = s
    CX[S_NEWTON] += 1.0
    CX[S_SAT] = 0.0
    v = _ipow(abs(s), q)
    return (v if s >= 0.0 else -v) * us


@njit(cache=True, inline="always", _nrt=False)
def fpmpi_commit(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
                  u: float) -> float:
    """:func:`model_step` of the static fpmpi model (offset, fractional polynomial, operators; the
    structure the constructor checked) for the applied command u, with the shaped input of the
    Newton solution when u is that solution's command. Returns the model output, um."""
    v = u / P[ST.P_USCALE]
    if CX[S_USOL] == u:
        x = CX[S_XSOL]
        # the warm-start history: consecutive solutions only
        continued = CX[S_SPREV_U] == CX[S_UAPP]
        CX[S_SHIST] = min(CX[S_SHIST] + 1.0, 3.0) if continued else 1.0
        CX[S_SPREV3] = CX[S_SPREV2]
        CX[S_SPREV2] = CX[S_SPREV]
        CX[S_SPREV] = CX[S_SSOL]
        CX[S_SPREV_U] = u
    else:
        x = shaped_input(I, P, v)
        CX[S_SHIST] = 0.0
    X[ST.X_V_PREV] = v
    o_r = I[ST.I_R]
    o_eta = I[ST.I_ETA]
    o_ops = I[ST.I_X_OPS]
    ow = I[ST.I_W]
    h = P[ow]
    for i in range(I[ST.I_NOPS]):
        r = P[o_r + i]
        w = min(x + P[o_eta + i] * r, X[o_ops + i])
        w = max(x - r, w)
        X[o_ops + i] = w
        h += w * P[ow + 1 + i]
    X[ST.X_STARTED] = 1.0
    CX[S_XP] = x
    CX[S_XP_V] = v
    CX[S_XP_OK] = 1.0
    return h


@njit(cache=True, _nrt=False)
def _planned_command(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray) -> tuple[float, float, float]:
    """A planned path's command for this sample, the map's sense there and the plan's direction:
    feed-forward replays the plan; feedback adds its correction (um) over the model's slope along
    the plan (floored: a flat spot gets less gain, never more), kept inside the stretch around the
    planned command where one output has one command (:mod:`hilbench.online.path_plan`). Its own
    function: written inside comp_step it made the fused loop's every other kind 1.6x slower."""
    n = CI[CI_PLAN]
    k = min(int(CX[S_PLANK]), n - 1)
    o = CI[CI_O_PLAN]
    u = CP[o + k]
    g = CP[o + 3 * n + k]
    way = CP[o + 4 * n + k]
    sign = 1.0 if g > 0.0 else (-1.0 if g < 0.0 else way)
    CX[S_SAT] = 0.0
    if CI[CI_PID] != 0 and CP[o + 5 * n + k] != 0.0:
        u += CX[S_PID] / (sign * max(abs(g), CP[C_PLANG]))
        if u > CP[o + 2 * n + k]:
            u = CP[o + 2 * n + k]
            CX[S_SAT] = 1.0
        elif u < CP[o + n + k]:
            u = CP[o + n + k]
            CX[S_SAT] = -1.0
    return u, sign, way


@njit(cache=True, _nrt=False)
def _planned_solve(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
                   aux: np.ndarray, target: float, u: float, sign: float) -> float:
    """A planned path under channels that move during the run: the plan was made at the values read
    before it, so this sample's command is solved for the target at the channels' values now, inside
    the plan's stretch around its command (where one output has one command), started at the plan's
    command (with feedback's correction where the plan lets it act)."""
    n = CI[CI_PLAN]
    k = min(int(CX[S_PLANK]), n - 1)
    o = CI[CI_O_PLAN]
    if CI[CI_PID] != 0 and CP[o + 5 * n + k] == 0.0:
        target -= CX[S_PID]  # feedback does not act here (path_plan.feedback_samples)
    lo = CP[o + n + k]
    hi = CP[o + 2 * n + k]
    return _solve(CI, CP, CX, I, P, X, aux, target, min(max(u, lo), hi), lo, hi, sign)


@njit(cache=True, _nrt=False)
def comp_step(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
              y_d: float, aux: np.ndarray) -> float:
    """The command for the desired output y_d (um) of this sample; call :func:`comp_update` with
    what was applied. A non-finite y_d holds the last command."""
    if not math.isfinite(y_d):
        CX[S_HELD] += 1.0
        return CX[S_U]
    target = y_d
    if CI[CI_PREVIEW] != 0:  # dynamics and delay inverted over the whole reference, before the run
        target = CX[S_TARGET]
    # the direction the command follows (the reversal guard's): the feed-forward target's
    heading = target
    # -- feed-forward of the dynamics' inverse (minimum-phase part only) ------------------------------
    nf = CI[CI_FF]
    if nf > 0:
        on = CI[CI_O_FFN]
        od = CI[CI_O_FFD]
        oz = CI[CI_O_XFF]
        if CX[S_FFSTART] == 0.0:
            for i in range(nf):
                CX[oz + i] = CP[CI[CI_O_FFZI] + i] * y_d
            CX[S_FFSTART] = 1.0
        yf = CP[on] * y_d + CX[oz]
        for i in range(nf - 1):
            CX[oz + i] = CP[on + i + 1] * y_d + CX[oz + i + 1] - CP[od + i + 1] * yf
        CX[oz + nf - 1] = CP[on + nf] * y_d - CP[od + nf] * yf
        target = yf
        heading = y_d
    # -- feedback and the identified correction -------------------------------------------------------------
    if CI[CI_PID] != 0:
        target += CX[S_PID]
    if CI[CI_ADAPT] != 0:
        target = (target - CX[S_BIAS]) / CX[S_GAIN]
    kind = CI[CI_KIND]
    us = CP[C_US]
    a = CP[C_ULO]
    b = CP[C_UHI]
    sign = CP[C_SIGN]
    way_planned = 0.0
    if CI[CI_PLAN] > 0:
        u, sign, way_planned = _planned_command(CI, CP, CX)
        if CI[CI_PLANAUX] != 0:
            u = _planned_solve(CI, CP, CX, I, P, X, aux, target, u, sign)
    elif kind == K_GENERAL:
        u = _solve(CI, CP, CX, I, P, X, aux, target, CX[S_UAPP], a, b, sign)
    else:
        z = target - CP[C_CONST]
        if kind == K_PI:
            u = _pi_inverse_checked(CI, CP, CX, I, P, X, z) * us
        elif kind == K_FPMPI:
            xt = _pi_inverse_checked(CI, CP, CX, I, P, X, z)
            u = _fpmpi_newton(CI, CP, CX, xt) if CI[CI_NT] > 0 else math.nan
            if not math.isnan(u):
                CX[S_USOL] = min(max(u, a), b)
            else:
                u = _solve(CI, CP, CX, I, P, X, aux, xt, CX[S_UAPP], a, b, 1.0)
                CX[S_USOL] = math.nan
        elif kind == K_IM:
            v = CX[S_VPREV]
            ke = CP[C_KE]
            for _ in range(CI[CI_IMIT]):
                v = _pi_inverse_checked(CI, CP, CX, I, P, X, z - _poly(CI, CP, v) + ke * v)
                v = min(max(v, a / us), b / us)
            u = v * us
        else:
            u = _solve(CI, CP, CX, I, P, X, aux, z, CX[S_UAPP], a, b, 1.0)
        if kind != K_FPMPI and kind != K_MPI:
            CX[S_SAT] = 1.0 if u > b else (-1.0 if u < a else 0.0)
    u = min(max(u, a), b)
    # the reversal guard: the command may speed up, slow down or stop, but not reverse while its
    # target moves the other way. On a hysteretic actuator each reversal starts a minor loop at the
    # inverse's steepest slope (1/p0), where the compensated gain is least known; the sensor's noise
    # fed back would add one every few samples, and a rig whose gain follows the drive rate reads
    # them as a kHz drive (decision 0080). Feed-forward alone keeps it too: a solve's wobble within
    # its tolerance where the target turns (flat to 1e-9 um at 50 kHz) is such a reversal, and a model
    # that counts its drive frequency between turning points read it as 25 kHz and solved at the
    # rail. A held command is a limit for the conditional integration (S_SAT), so the integrator
    # does not wind against it.
    if CP[C_GUARD] != 0.0:
        rp = CX[S_RPREV]
        if rp == rp and CX[S_STARTED] != 0.0:
            up = CX[S_UAPP]
            # the way the command follows the reference (a plan's own direction: it turns early)
            way = way_planned if way_planned != 0.0 else sign * (heading - rp)
            held = 0.0
            if way > 0.0 and u < up:
                held = -1.0
            elif way < 0.0 and u > up:
                held = 1.0
            if held != 0.0:
                u = up
                CX[S_GUARDN] += 1.0
                if CI[CI_PID] != 0:
                    CX[S_SAT] = held
        CX[S_RPREV] = heading
    CX[S_U] = u
    CX[S_VPREV] = u / us
    return u


@njit(cache=True, _nrt=False)
def _planned_commit(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray) -> tuple[float, bool]:
    """A planned path at the commit: the map's sense at this sample, whether the plan lets feedback
    act here (:func:`hilbench.online.path_plan.feedback_samples`); counts the sample."""
    n = CI[CI_PLAN]
    k = min(int(CX[S_PLANK]), n - 1)
    o = CI[CI_O_PLAN]
    g = CP[o + 3 * n + k]
    sign = 1.0 if g > 0.0 else (-1.0 if g < 0.0 else CP[o + 4 * n + k])
    CX[S_PLANK] += 1.0
    return sign, CP[o + 5 * n + k] != 0.0


@njit(cache=True, _nrt=False)
def comp_update(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
                oa: Any, y_d: float, u_applied: float, y_meas: float, aux: np.ndarray) -> None:
    """Commit the applied command to the model's memory; take the measured output (um) into the
    identifier and the feedback for the next sample (NaN: nothing measured)."""
    if not math.isfinite(u_applied):
        u_applied = CX[S_UAPP]
    if CI[CI_FASTCOMMIT] != 0:
        CX[S_YMOD] = fpmpi_commit(CI, CP, CX, I, P, X, u_applied)
    else:
        CX[S_YMOD] = model_step(I, P, X, u_applied, aux)
    if u_applied != CX[S_U]:
        CX[S_SAT] = 1.0 if CX[S_U] > u_applied else -1.0
    if CX[S_SAT] != 0.0:
        CX[S_SATN] += 1.0
    CX[S_UAPP] = u_applied
    CX[S_VPREV] = u_applied / CP[C_US]
    CX[S_STARTED] = 1.0
    sign = CP[C_SIGN]
    fb_here = True
    if CI[CI_PLAN] > 0:
        sign, fb_here = _planned_commit(CI, CP, CX)
    if not math.isfinite(y_meas):
        return
    CX[S_NOBS] += 1.0
    if CI[CI_ADAPT] != 0:
        # the front end's shaped input: the commit's, when it is the same polynomial of the same u
        x = CX[S_XP] if CI[CI_FESHARED] != 0 else math.nan
        oiir_step_shaped(u_applied, x, y_meas, oa[0], oa[1], oa[2], oa[3], oa[4], oa[5], oa[6], oa[7], oa[8],
                         oa[9], oa[10], oa[11], oa[12], oa[13], oa[14], oa[15], oa[16])
        theta = oa[12]
        m1 = CI[CI_M] + 1
        nq = CI[CI_N]
        sp = 0.0
        for i in range(m1):
            sp += theta[i]
        sq = 0.0
        for j in range(nq):
            sq += theta[m1 + j]
        den = 1.0 - sq
        if CX[S_NOBS] >= CP[C_WARM] and abs(den) > 1e-9:
            gain = sp / den
            bias = theta[m1 + nq] / den if CI[CI_BIAS] != 0 else 0.0
            if gain >= CP[C_GMIN] and gain <= CP[C_GMAX] and math.isfinite(bias):
                CX[S_GAIN] = gain
                CX[S_BIAS] = bias
    if CI[CI_PID] != 0 and math.isfinite(y_d):
        e = y_d - y_meas
        # conditional integration: not while the command is limited in the direction e pushes (the
        # output's direction is the command's times the map's sense)
        if fb_here and not (CX[S_SAT] * sign * e > 0.0):
            i = CX[S_I] + CP[C_KIT] * e
            lim = CP[C_ILIM]
            CX[S_I] = min(max(i, -lim), lim)
        dy = 0.0 if CX[S_NOBS] <= 1.0 else y_meas - CX[S_YPREV]
        tf = CP[C_TF]
        T = CP[C_T]
        CX[S_D] = (tf * CX[S_D] - CP[C_KD] * dy) / (tf + T)
        CX[S_PID] = CP[C_KP] * e + CX[S_I] + CX[S_D]
    CX[S_YPREV] = y_meas


@njit(cache=True, _nrt=False)
def comp_block(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
               oa: Any, y_d: np.ndarray, aux: np.ndarray, out: np.ndarray, targets: np.ndarray) -> None:
    """Open loop (feed-forward only): the commands for y_d, each committed as applied, (n,) ->
    out; ``aux`` is (n, channels); ``targets`` (n,) the previewed targets (read with CI_PREVIEW)."""
    for k in range(y_d.shape[0]):
        CX[S_TARGET] = targets[k]
        u = comp_step(CI, CP, CX, I, P, X, y_d[k], aux[k])
        comp_update(CI, CP, CX, I, P, X, oa, y_d[k], u, math.nan, aux[k])
        out[k] = u



@njit(cache=True, _nrt=False)
def comp_block_corrected(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray,
                         X: np.ndarray, oa: Any, targets: np.ndarray, corrections: np.ndarray, aux: np.ndarray,
                         out: np.ndarray) -> None:
    """Open loop with a given output-domain correction (um) in the PID's place each sample: the
    static part's ``targets`` (n,) plus ``corrections`` (n,) -> commands ``out``, each committed as
    applied. With CI_PID and CI_PREVIEW set: how the compensator answers what a feedback loop adds."""
    for k in range(targets.shape[0]):
        CX[S_TARGET] = targets[k]
        CX[S_PID] = corrections[k]
        u = comp_step(CI, CP, CX, I, P, X, targets[k], aux[k])
        comp_update(CI, CP, CX, I, P, X, oa, targets[k], u, math.nan, aux[k])
        out[k] = u


@njit(cache=True, _nrt=False)
def tpoly_call(CI: np.ndarray, CP: np.ndarray, t: float) -> tuple[float, float, float]:
    return _tpoly(CI, CP, t)


@njit(cache=True, _nrt=False)
def model_step_call(I: np.ndarray, P: np.ndarray, X: np.ndarray, u: float, aux: np.ndarray) -> float:
    return model_step(I, P, X, u, aux)
