"""Compensators: inverse models as numba step functions over explicit state (block and step mode).

A compensator turns a desired displacement ``y_d`` (um) into the command ``u`` (V or A) that makes
the actuator produce it. It keeps its own copy of the fitted model's forward memory (the flat
arrays of :func:`hilbench.models.stepping.compile_model`) and, after the rig's safety path, commits
the command that was *really applied* to it, so the inverse's memory always matches what the
actuator went through (a clamped or slew-limited command does not desynchronise it).

Kinds (chosen from the model spec by :class:`Compensator`, ``method="auto"``):

``pi``       classical inverse Prandtl-Ishlinskii (004 eq. 14-15): the inverse is itself a PI on
             ``y`` with its own thresholds ``r'_i = p0 s_i + sum_{j<i} p_j (s_i - s_j)`` and weights
             ``p'_0 = 1/p0``, ``p'_i = -p_i / ((p0 + sum_{j<=i} p_j)(p0 + sum_{j<i} p_j))``. It is the
             exact inverse of a PI whose cumulative slopes are positive (weights >= 0, p0 > 0).
             M-play operators (eta != 1, ``pmpi``; one-sided play, ``pi1``/``fpmpi``) are written
             exactly as play operators: ``max(v - r, min(v + eta r, w))`` is the play of threshold
             ``s = (1 + eta) r / 2`` on ``v`` plus the constant ``c = (eta - 1) r / 2``, so the
             inverse is exact for any eta (004 eq. 14 reuses eta with the play's thresholds, which is
             exact only for eta = 1). The inverse operators' states are not integrated separately:
             they are read off the forward operators' states every sample,
             ``w'_i = Y - p0 (x - x_i) - sum_{j<i} p_j (x_j - x_i)`` (sorted thresholds), which is
             what they would be after the same history, so the compensator commits applied
             commands to one memory only. Each result is checked against the forward operators
             (one O(n) evaluation); operator states that no common history produces (virgin M-play
             operators with different eta) are corrected by bracketed Newton steps on the
             piecewise-linear forward map (counted as ``analytic_inverse_corrected``).
``mpi``      PI part inverted analytically, the memoryless polynomial (002's cubic, 004's P, the
             ``asymmetry`` effect) by a safeguarded secant/bisection solve per sample of the fixed
             point ``v = Gamma^-1[y - P(v) + k_e v]`` (exact inverse).
``im``       004's iterative inverse-model (I-M) compensator, eq. 13: ``u_d(k) = Gamma^-1[y_d(k) -
             P(u_d(k-1))]`` (``iterations`` fixed-point passes per sample, 1 as in the paper). The
             small-gain condition eq. 16, ``p0 > max |P'(u)|`` over the actuator's range, is checked;
             when it fails, eq. 20's proportional gain ``k_e`` moves ``k_e u`` from the polynomial
             to the PI part (``gain="auto"`` picks one, a number sets it; ``gain=None`` refuses).
``fpmpi``    000's FPMPI: the one-sided play part is inverted analytically (it acts on the shaped
             input ``x``), then the fractional polynomial ``x(v) = sum w_i sgn(v)|v|^e_i`` is
             solved. When the exponents are multiples of 1/q (000's are of 1/12), it is a
             polynomial in ``s = sgn(v)|v|^(1/q)`` (multiplications only), solved by Newton steps
             warm-started from the last solutions extrapolated (about 2 evaluations per sample;
             counter ``newton_samples``); a step that leaves the command range or meets a falling
             part of the polynomial hands the sample to the safeguarded solver below. The commit
             then updates the static model's operators directly with that shaped input (checked
             against ``model_step`` when the compensator is built), and an identifier with the
             same front end reuses it.
``general``  ANY compiled model (creep, temperature, load and other aux channels, rate-dependence,
             saturation, Duhem, Bouc-Wen, ...): a bounded 1-D solve of ``model_step`` on a copy of
             the state per sample (safeguarded secant with bisection on the rising static map),
             then the applied command is committed to the real state. The compensator reads the
             same auxiliary channels the model does.

Dynamics and delay: the compensator inverts the static part (its copy of the model has the
``dynamics`` and ``delay`` effects switched off). The dynamics' inverse ``A(z)/B(z)`` is added as a
feed-forward pre-filter of the reference only when ``B`` is minimum phase (zeros inside the unit
circle with a margin, ``b0 != 0``); otherwise, and for the delay, it is left to feedback.

Feedback (optional): a PID in the output domain (um), added to the reference before the inverse,
so the PID sees the linearised plant (unit gain, the model's dynamics, one sample of measurement
delay). Derivative on the measurement with a first-order filter; anti-windup by conditional
integration (no integration while the command is saturated in the direction the error pushes)
and a clamped integrator. Gains that destabilise the declared dynamics are refused before the loop
starts (closed-loop poles of ``1 + z^-1 G(z) C(z)``).

Online adaptation (optional, paper 000): an :class:`hilbench.online.oiir.OIIR` identifier with the
model's FPMPI front end is updated every sample with (applied command, measured output); its
current weights give a gain ``G = sum p / (1 - sum q)`` and an offset ``b / (1 - sum q)`` between
the front end's output and the measured displacement, and the inverse is asked for
``(y_d - offset) / G`` instead of ``y_d``.

Kernel layout: ``CI`` (int64 structure), ``CP`` (float64 parameters), ``CX`` (float64 state and
scratch) beside the model's ``I, P, X``. :func:`comp_step` computes the command of one sample (no
memory change but the solver's slope estimate and the feedforward filter), :func:`comp_update`
commits the applied command and the measurement. Both are ``_nrt=False`` and allocate nothing, so
they run inside the fused closed loop of :mod:`hilbench.online.tracking`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from hilbench.errors import UserError
from hilbench.models import stepping as ST
from hilbench.models.stepping import model_step
from hilbench.online.oiir import oiir_step_shaped
from hilbench.sim.kernels import sgnpow

__all__ = [
    "Compensator",
    "PID",
    "InstabilityError",
    "inverse_pi_parameters",
    "comp_step",
    "comp_update",
    "comp_block",
    "KINDS",
]


class InstabilityError(UserError):
    """A compensator or feedback configuration that cannot be stable; refused before the loop starts."""


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
N_CI = 29

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
N_CP = 26

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
N_CX = 31


@njit(cache=True, _nrt=False)
def _shaped(I: np.ndarray, P: np.ndarray, v: float) -> float:
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
        xp = _shaped(I, P, X[ST.X_V_PREV]) if X[ST.X_STARTED] != 0.0 else 0.0
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
           aux: np.ndarray, target: float, u: float) -> float:
    """What the solver drives to zero, rising with u."""
    kind = CI[CI_KIND]
    if kind == K_GENERAL:
        o = CI[CI_O_XM]
        nx = CI[CI_NX]
        for i in range(nx):
            CX[o + i] = X[i]
        return model_step(I, P, CX[o : o + nx], u, aux) - target
    us = CP[C_US]
    v = u / us
    if kind == K_FPMPI:
        return (_shaped(I, P, v) - target) * us
    z = target - _poly(CI, CP, v) + CP[C_KE] * v
    return (v - _pi_inverse_checked(CI, CP, CX, I, P, X, z)) * us


@njit(cache=True, _nrt=False)
def _solve(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
           aux: np.ndarray, target: float, x0: float) -> float:
    """Safeguarded secant/bisection for the rising residual on [u_lo, u_hi], started at x0.

    The bracket narrows with every evaluation; a secant step that leaves it, or that did not halve
    the residual, is replaced by bisection; a domain end is probed before bisecting towards it, and
    a target beyond the reachable range gives that end (the command saturates)."""
    a = CP[C_ULO]
    b = CP[C_UHI]
    tol_f = CP[C_TOLF]
    tol_x = CP[C_TOLU]
    lo = a
    hi = b
    lo_known = False
    hi_known = False
    x = min(max(x0, a), b)
    fx = _resid(CI, CP, CX, I, P, X, aux, target, x)
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
        fn = _resid(CI, CP, CX, I, P, X, aux, target, xn)
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
def _fpmpi_commit(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
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
        x = _shaped(I, P, v)
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
def comp_step(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
              y_d: float, aux: np.ndarray) -> float:
    """The command for the desired output y_d (um) of this sample; call :func:`comp_update` with
    what was applied. A non-finite y_d holds the last command."""
    if not math.isfinite(y_d):
        CX[S_HELD] += 1.0
        return CX[S_U]
    target = y_d
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
    # -- feedback and the identified correction -------------------------------------------------------------
    if CI[CI_PID] != 0:
        target += CX[S_PID]
    if CI[CI_ADAPT] != 0:
        target = (target - CX[S_BIAS]) / CX[S_GAIN]
    kind = CI[CI_KIND]
    us = CP[C_US]
    a = CP[C_ULO]
    b = CP[C_UHI]
    if kind == K_GENERAL:
        u = _solve(CI, CP, CX, I, P, X, aux, target, CX[S_UAPP])
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
                u = _solve(CI, CP, CX, I, P, X, aux, xt, CX[S_UAPP])
                CX[S_USOL] = math.nan
        elif kind == K_IM:
            v = CX[S_VPREV]
            ke = CP[C_KE]
            for _ in range(CI[CI_IMIT]):
                v = _pi_inverse_checked(CI, CP, CX, I, P, X, z - _poly(CI, CP, v) + ke * v)
                v = min(max(v, a / us), b / us)
            u = v * us
        else:
            u = _solve(CI, CP, CX, I, P, X, aux, z, CX[S_UAPP])
        if kind != K_FPMPI and kind != K_MPI:
            CX[S_SAT] = 1.0 if u > b else (-1.0 if u < a else 0.0)
    u = min(max(u, a), b)
    CX[S_U] = u
    CX[S_VPREV] = u / us
    return u


@njit(cache=True, _nrt=False)
def comp_update(CI: np.ndarray, CP: np.ndarray, CX: np.ndarray, I: np.ndarray, P: np.ndarray, X: np.ndarray,
                oa: Any, y_d: float, u_applied: float, y_meas: float, aux: np.ndarray) -> None:
    """Commit the applied command to the model's memory; take the measured output (um) into the
    identifier and the feedback for the next sample (NaN: nothing measured)."""
    if not math.isfinite(u_applied):
        u_applied = CX[S_UAPP]
    if CI[CI_FASTCOMMIT] != 0:
        CX[S_YMOD] = _fpmpi_commit(CI, CP, CX, I, P, X, u_applied)
    else:
        CX[S_YMOD] = model_step(I, P, X, u_applied, aux)
    if u_applied != CX[S_U]:
        CX[S_SAT] = 1.0 if CX[S_U] > u_applied else -1.0
    if CX[S_SAT] != 0.0:
        CX[S_SATN] += 1.0
    CX[S_UAPP] = u_applied
    CX[S_VPREV] = u_applied / CP[C_US]
    CX[S_STARTED] = 1.0
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
        # conditional integration: not while the command is limited in the direction e pushes
        if not (CX[S_SAT] * e > 0.0):
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
               oa: Any, y_d: np.ndarray, aux: np.ndarray, out: np.ndarray) -> None:
    """Open loop (feed-forward only): the commands for y_d, each committed as applied, (n,) ->
    out; ``aux`` is (n, channels)."""
    for k in range(y_d.shape[0]):
        u = comp_step(CI, CP, CX, I, P, X, y_d[k], aux[k])
        comp_update(CI, CP, CX, I, P, X, oa, y_d[k], u, math.nan, aux[k])
        out[k] = u


# ==================================================================================================
# building a compensator from a fitted model
# ==================================================================================================


def inverse_pi_parameters(p0: float, s: np.ndarray, p: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """004 eq. 15 for a PI ``p0 v + sum p_i F_{s_i}[v]`` with thresholds ``s`` sorted ascending
    (all > 0): ``(p'_0, r', p')`` of the inverse PI ``p'_0 y + sum p'_i F_{r'_i}[y]``."""
    s = np.asarray(s, float)
    p = np.asarray(p, float)
    cum = p0 + np.concatenate([[0.0], np.cumsum(p)])  # p0 + sum_{j<=i} p_j, i = 0..n
    if np.any(cum <= 0):
        raise ValueError("the PI's cumulative slopes p0 + sum_{j<=i} p_j must be positive")
    r_hat = np.array([p0 * s[i] + np.sum(p[:i] * (s[i] - s[:i])) for i in range(s.size)])
    p_hat = -p / (cum[1:] * cum[:-1])
    return 1.0 / p0, r_hat, p_hat


@dataclass
class PID:
    """Feedback in the output domain (um in, um out): ``kp`` (1), ``ki`` (1/s), ``kd`` (s),
    derivative filter ``tf_s`` (s; default 4 sample periods), integrator clamp ``i_limit`` (um;
    default: the reference's span)."""

    kp: float = 0.2
    ki: float = 300.0
    kd: float = 0.0
    tf_s: float | None = None
    i_limit: float | None = None

    def char_poly(self, fs: float, b: np.ndarray, a: np.ndarray) -> np.ndarray:
        """Coefficients in z^-1 of ``A_G D_C + z^-1 B_G N_C`` (the closed loop's denominator) for the
        loop ``z^-1 G(z) C(z)`` with G = B/A (z^-1 polynomials)."""
        T = 1.0 / fs
        tf = self.tf_s if self.tf_s is not None else 4.0 * T
        d_filt = np.array([tf + T, -tf])
        dc = np.convolve([1.0, -1.0], d_filt)
        nc = (self.kp * dc + self.ki * T * np.pad(d_filt, (0, 1))
              + self.kd * np.convolve([1.0, -1.0], [1.0, -1.0]))
        left = np.convolve(a, dc)
        right = np.concatenate([[0.0], np.convolve(b, nc)])
        n = max(left.size, right.size)
        return np.pad(left, (0, n - left.size)) + np.pad(right, (0, n - right.size))

    def poles(self, fs: float, b: np.ndarray, a: np.ndarray) -> np.ndarray:
        c = np.trim_zeros(self.char_poly(fs, b, a), "b")
        return np.roots(c) if c.size > 1 else np.zeros(0)


def _pi_structure(model: Any) -> dict[str, Any] | None:
    """Equivalent play form of an operator base: sorted positive thresholds, weights, constants."""
    from hilbench.models import bases as C

    base = model.base
    w = np.asarray(model.weights, float)
    if isinstance(base, C.FPMPI):
        n = int(base.constants["n"])
        span = float(base.constants["shaped_max"]) or 1.0
        r = np.arange(n) / n * span
        eta = np.zeros(n)
    elif isinstance(base, C.OperatorBase) and not isinstance(base, C.PD):
        r = np.asarray(base.constants["thresholds"], float)
        eta = base.eta()
    else:
        return None
    p_ops = w[1 : 1 + r.size]
    s = (1.0 + eta) * r / 2.0
    c = (eta - 1.0) * r / 2.0
    zero = s <= 0.0
    p0 = float(np.sum(p_ops[zero]))
    const = float(w[0] + np.sum(p_ops * c))
    idx = np.flatnonzero(~zero)
    order = idx[np.argsort(s[idx], kind="stable")]
    return {"p0": p0, "const": const, "perm": order, "s": s[order], "p": p_ops[order], "c": c[order],
            "n_ops": r.size}


def _polynomial(model: Any, n_ops: int) -> np.ndarray:
    """Coefficients c_0..c_deg of the memoryless polynomial of mpi/pmpi and the asymmetry effect."""
    from hilbench.models import bases as C

    w = np.asarray(model.weights, float)
    coef = np.zeros(9)
    k = 1 + n_ops
    if isinstance(model.base, C.MPI):
        coef[2] += w[k]
        coef[3] += w[k + 1]
        k += 2
    asym = model.effect("asymmetry")
    if asym is not None:
        for power in range(2, asym.order() + 1):
            coef[power] += w[k]
            k += 1
    deg = int(np.max(np.flatnonzero(coef), initial=0))
    return coef[: deg + 1]


#: effects the analytic kinds cover (dynamics and delay are handled outside the static inverse)
_OUTSIDE_STATIC = ("dynamics", "delay")


class Compensator:
    """An inverse-model compensator for a fitted model, with optional PID feedback and online
    adaptation; see the module docstring for the kinds.

    ``limits`` (lo, hi) is the command range (the rig's actuator ``min``/``max``): the inverse never
    asks for more. ``method``: ``auto`` (pi -> ``pi``, pmpi -> ``im``, mpi / pi+asymmetry -> ``mpi``,
    fpmpi -> ``fpmpi``, anything else -> ``general``) or a kind name. ``gain`` is eq. 20's k_e
    (``"auto"``, a number, or None: refuse when eq. 16 fails). ``iterations``: I-M passes per
    sample. ``feedback``: a :class:`PID` (or True for the default gains). ``online``: True or a
    dict of :class:`hilbench.online.oiir.OIIR` options (``M``, ``N``, ``bias``, ``lam``, ...).
    """

    def __init__(
        self,
        model: Any,
        sample_rate_hz: float,
        limits: tuple[float, float],
        *,
        method: str = "auto",
        gain: float | str | None = "auto",
        iterations: int = 1,
        feedback: PID | bool | None = None,
        online: dict[str, Any] | bool | None = None,
        dynamics_feedforward: bool = True,
        reference_span: float | None = None,
        max_iterations: int = 60,
    ):

        if model.weights is None:
            raise UserError("the model has no weights yet: fit it first")
        self.model = model
        self.fs = float(sample_rate_hz)
        lo, hi = float(limits[0]), float(limits[1])
        if not hi > lo:
            raise UserError(f"command limits [{lo:g}, {hi:g}]: expected min < max")
        self.limits = (lo, hi)
        self.notes: list[str] = []
        self.checks: dict[str, Any] = {}
        try:
            compiled = ST.compile_model(model, self.fs)
        except ST.NotCompilable as exc:
            raise UserError(f"model {model.spec!r} cannot be compiled for a compensator: {exc}") from None
        I = compiled.I.copy()
        # the static part: dynamics and delay are inverted (or not) outside the model
        I[ST.I_DYN_ON] = 0
        I[ST.I_DELAY] = 0
        self.I, self.P = I, compiled.P
        self.X = np.zeros(int(I[ST.I_NX]))
        self.channels = list(compiled.channels)
        us = float(model.norm["u_scale"])

        extra = [e.name for e in model.effects if e.name not in _OUTSIDE_STATIC and e.name != "asymmetry"]
        structure = None if extra else _pi_structure(model)
        base = model.base.name
        if method == "auto":
            asym = model.effect("asymmetry") is not None
            if structure is None or (base == "fpmpi" and asym):
                kind = "general"
            elif base == "fpmpi":
                kind = "fpmpi"
            elif base in ("pi", "pi1") and not asym:
                kind = "pi"
            elif base == "pmpi":
                kind = "im"
            else:
                kind = "mpi"
        else:
            kind = method
        if kind not in KINDS:
            raise UserError(f"compensator method {kind!r}: expected auto or one of {', '.join(KINDS)}")
        if kind != "general" and structure is None:
            raise UserError(f"compensator method {kind!r} needs an operator base without effects other than "
                            f"asymmetry, dynamics, delay; model {model.spec!r} has {', '.join(extra) or base}",
                            hint="use method='general' (a per-sample solve of the whole model)")
        if kind == "fpmpi" and base != "fpmpi":
            raise UserError(f"compensator method 'fpmpi' needs an fpmpi model, not {base!r}")
        poly = np.zeros(0)
        if structure is not None and kind in ("mpi", "im"):
            poly = _polynomial(model, structure["n_ops"])
        if kind == "pi" and structure is not None and _polynomial(model, structure["n_ops"]).size > 1:
            raise UserError(f"compensator method 'pi' cannot invert the polynomial of {model.spec!r}",
                            hint="use method='mpi' or 'im'")
        self.kind = kind
        ke = 0.0
        if kind in ("mpi", "im"):
            ke = self._check_eq16(structure["p0"], poly, us, gain, kind)
        n_sorted = 0 if structure is None else int(structure["perm"].size)

        # -- CP ---------------------------------------------------------------------------------------
        cp: list[float] = [0.0] * N_CP
        cp[C_US] = us
        cp[C_ULO], cp[C_UHI] = lo, hi
        ci = np.zeros(N_CI, dtype=np.int64)
        ci[CI_KIND] = KINDS[kind]
        ci[CI_NX] = self.X.size
        ci[CI_MAXIT] = int(max_iterations)
        ci[CI_IMIT] = int(max(1, iterations))

        def put(values: Any) -> int:
            at = len(cp)
            cp.extend(float(x) for x in np.asarray(values, float).ravel())
            return at

        perm = np.zeros(0, dtype=np.int64)
        if structure is not None and kind != "general":
            p0 = structure["p0"] + ke
            if not p0 > 0:
                raise InstabilityError(
                    f"the PI part of {model.spec!r} has p0 = {structure['p0']:.4g} um <= 0 (+ k_e = {ke:.4g}): "
                    "the analytic inverse needs p0 > 0 (004 eq. 15)", hint="use method='general'")
            try:
                ph0, r_hat, p_hat = inverse_pi_parameters(p0, structure["s"], structure["p"])
            except ValueError as exc:
                raise InstabilityError(f"{model.spec!r}: {exc}; the PI part is not invertible",
                                       hint="use method='general'") from None
            cp[C_P0], cp[C_PH0], cp[C_CONST], cp[C_KE] = p0, ph0, structure["const"], ke
            cumulative = p0 + np.concatenate([[0.0], np.cumsum(structure["p"])])
            cp[C_SMIN] = float(np.min(cumulative))
            cp[C_PITOL] = 1e-13 * (abs(p0) + float(np.sum(np.abs(structure["p"]))))
            ci[CI_NOPS] = n_sorted
            perm = structure["perm"].astype(np.int64)
            ci[CI_O_S] = put(structure["s"])
            ci[CI_O_P] = put(structure["p"])
            ci[CI_O_C] = put(structure["c"])
            ci[CI_O_RH] = put(r_hat)
            ci[CI_O_PH] = put(p_hat)
            self.inverse_pi = {"p0_hat": ph0, "thresholds": r_hat.tolist(), "weights": p_hat.tolist()}
        ci[CI_NPOLY] = poly.size
        ci[CI_O_POLY] = put(poly if poly.size else [0.0])
        # -- dynamics feed-forward ------------------------------------------------------------------
        ff_num, ff_den = np.ones(1), np.ones(1)
        dyn = model.effect("dynamics")
        self.dynamics = None
        if dyn is not None:
            b, a = dyn.coefficients(self.fs)
            self.dynamics = (np.asarray(b, float), np.asarray(a, float))
            zeros = np.roots(np.trim_zeros(b, "b")) if np.count_nonzero(b) > 1 else np.zeros(0)
            radius = float(np.max(np.abs(zeros), initial=0.0))
            if not dynamics_feedforward:
                self.notes.append("dynamics feed-forward off: the dynamics are left to feedback")
            elif abs(b[0]) < 1e-9 * np.sum(np.abs(b)) or radius >= 0.98:
                self.notes.append(f"dynamics not inverted in feed-forward: non-minimum-phase (zero at "
                                  f"|z| = {radius:.3g}) or no direct term; left to feedback")
            else:
                ff_num, ff_den = a / b[0], b / b[0]
                self.notes.append(f"dynamics inverse A(z)/B(z) fed forward (zeros at |z| <= {radius:.3g})")
        if model.effect("delay") is not None:
            self.notes.append("delay not compensated in feed-forward (no preview): left to feedback")
        nf = max(ff_num.size, ff_den.size) - 1
        ci[CI_FF] = nf
        if nf > 0:
            from scipy import signal as sps

            n_ = nf + 1
            ff_num = np.pad(ff_num, (0, n_ - ff_num.size))
            ff_den = np.pad(ff_den, (0, n_ - ff_den.size))
            ci[CI_O_FFN] = put(ff_num)
            ci[CI_O_FFD] = put(ff_den)
            ci[CI_O_FFZI] = put(sps.lfilter_zi(ff_num, ff_den))
        # -- solver tolerances and the slope start ----------------------------------------------------
        span_u = hi - lo
        cp[C_TOLU] = 1e-12 * span_u
        # -- PID ------------------------------------------------------------------------------------------
        if feedback is True:
            feedback = PID()
        self.pid: PID | None = feedback or None
        cp[C_T] = 1.0 / self.fs
        if self.pid is not None:
            ci[CI_PID] = 1
            cp[C_KP] = self.pid.kp
            cp[C_KIT] = self.pid.ki / self.fs
            cp[C_KD] = self.pid.kd
            cp[C_TF] = self.pid.tf_s if self.pid.tf_s is not None else 4.0 / self.fs
            cp[C_ILIM] = self.pid.i_limit if self.pid.i_limit is not None else (reference_span or 1e300)
            self._check_pid()
        # -- online adaptation ------------------------------------------------------------------------------
        self.oiir = None
        if online:
            from hilbench.online.oiir import OIIR

            opts = dict(online) if isinstance(online, dict) else {}
            M, N = int(opts.pop("M", 0)), int(opts.pop("N", 0))
            bias = bool(opts.pop("bias", True))
            cp[C_GMIN] = float(opts.pop("gain_min", 0.2))
            cp[C_GMAX] = float(opts.pop("gain_max", 5.0))
            cp[C_WARM] = float(opts.pop("warmup", self.fs))  # 1 s of data before the correction is used
            opts.setdefault("lam", 0.9995)
            opts.setdefault("delta", 1.0)
            theta0 = np.zeros(M + 1 + N + (1 if bias else 0))
            theta0[0] = 1.0  # start from the model being right: y = u_r
            try:
                self.oiir = OIIR.from_model(model, M, N, bias=bias, theta0=theta0, **opts)
            except ValueError as exc:
                raise UserError(f"online adaptation needs the OIIR's FPMPI front end: {exc}",
                                hint="fit an 'fpmpi' model for --online (paper 000)") from None
            ci[CI_ADAPT] = 1
            ci[CI_M], ci[CI_N], ci[CI_BIAS] = M, N, 1 if bias else 0
        self._dummy_oiir = None
        # -- state ----------------------------------------------------------------------------------------
        ci = np.concatenate([ci, perm]) if perm.size else ci
        ci[CI_PERM] = N_CI
        self.CI = ci
        self.CP = np.array(cp, dtype=np.float64)
        nx_total = N_CX
        self.CI[CI_O_XM] = nx_total
        nx_total += self.X.size + 2  # + the (value, slope) buffer of the PI check
        self.CI[CI_O_XFF] = nx_total
        nx_total += max(nf, 1)
        self._nx_total = nx_total
        self.CP[C_SLOPE0] = self._slope0()
        self.CP[C_TOLF] = self._tol_f()
        if kind == "fpmpi":
            self._fast_fpmpi()
        self.reset()

    def _fast_fpmpi(self) -> None:
        """The fpmpi fast path (see :func:`_fpmpi_newton`): the exponents as multiples of 1/q (q <= 24,
        powers <= 96), and the direct commit when the compiled static model is offset + fractional
        polynomial + operators; each checked against the general path on a random walk over the
        command range, and left off when it does not agree."""
        I, P = self.I, self.P
        nin = int(I[ST.I_NIN])
        exps = P[I[ST.I_INEXP] : I[ST.I_INEXP] + nin]
        w = P[I[ST.I_INW] : I[ST.I_INW] + nin]
        q = next((q for q in range(1, 25)
                  if np.all(np.abs(exps * q - np.round(exps * q)) <= 1e-9 * q) and np.all(exps >= 0)
                  and np.max(np.round(exps * q), initial=0) <= 96), 0)
        lo, hi = self.limits
        us = float(self.CP[C_US])
        rng = np.random.default_rng(0)
        walk = np.clip(np.cumsum(rng.normal(0.0, 0.02 * (hi - lo), 400)) + 0.5 * (lo + hi), lo, hi)
        if nin > 0 and q > 0:
            k = np.round(exps * q).astype(np.int64)
            powers = np.unique(k[k > 0])
            weights = np.array([np.sum(w[k == p]) for p in powers])
            self.CI[CI_NT] = powers.size
            self.CI[CI_O_TK] = self.CI.size
            self.CI[CI_O_TW] = self.CP.size
            self.CI = np.concatenate([self.CI, powers])
            self.CP = np.concatenate([self.CP, weights])
            self.CP[C_TQ] = q
            self.CP[C_TC0] = float(np.sum(w[k == 0]))
            self.CP[C_SLO], self.CP[C_SHI] = (float(np.sign(b) * abs(b / us) ** (1.0 / q)) for b in (lo, hi))
            s = np.sign(walk) * np.abs(walk / us) ** (1.0 / q)
            fast = np.array([_tpoly_py(self.CI, self.CP, abs(x))[0] for x in s])
            fast = self.CP[C_TC0] + np.sign(s) * fast
            slow = np.array([_shaped(I, P, float(x / us)) for x in walk])
            if not np.allclose(fast, slow, rtol=1e-12, atol=1e-12 * max(1.0, float(np.max(np.abs(slow))))):
                self.CI[CI_NT] = 0
        # the direct commit: the compiled static model must be offset + operators on the shaped input
        structure_ok = (int(I[ST.I_BASE]) == 1 and int(I[ST.I_EXTRA]) == 0 and int(I[ST.I_ASYM]) == 0
                        and int(I[ST.I_SAT]) == 0 and int(I[ST.I_NCREEP]) == 0 and int(I[ST.I_RATE]) == 0
                        and int(I[ST.I_NAUX]) == 0 and int(I[ST.I_OFF]) == 0 and int(I[ST.I_DYN_ON]) == 0
                        and int(I[ST.I_DELAY]) == 0 and int(I[ST.I_H]) == 1 + int(I[ST.I_NOPS]))
        if structure_ok and not self.channels:
            self.CI[CI_FASTCOMMIT] = 1
            X_fast, X_slow = np.zeros_like(self.X), np.zeros_like(self.X)
            CX = np.zeros(self._nx_total)
            aux = np.zeros(1)
            for u in walk:
                CX[S_USOL] = math.nan
                y_fast = _fpmpi_commit(self.CI, self.CP, CX, I, P, X_fast, float(u))
                y_slow = _model_step_py(I, P, X_slow, float(u), aux)
                if not abs(y_fast - y_slow) <= 1e-10 * (1.0 + abs(y_slow)):
                    self.CI[CI_FASTCOMMIT] = 0
                    break
        fe = self.oiir.front_end if self.oiir is not None else None
        if (fe is not None and self.CI[CI_FASTCOMMIT] != 0 and fe.exps.shape == exps.shape
                and np.array_equal(fe.exps, exps) and np.array_equal(fe.w_p, w)
                and fe.fe[0] == P[ST.P_USCALE]):
            self.CI[CI_FESHARED] = 1

    # -- checks -------------------------------------------------------------------------------------
    def _check_eq16(self, p0: float, poly: np.ndarray, us: float, gain: float | str | None, kind: str) -> float:
        """004 eq. 16 over the command range; eq. 20's k_e when it fails. Returns k_e."""
        lo, hi = self.limits
        v = np.linspace(lo / us, hi / us, 2001)
        dp = np.polyval(np.polyder(poly[::-1]), v) if poly.size > 1 else np.zeros_like(v)
        worst = float(np.max(np.abs(dp)))
        self.checks["eq16"] = {"p0": p0, "max_abs_dP": worst, "holds": bool(p0 > worst),
                               "unit": "um per normalised input", "range": [lo, hi]}
        if isinstance(gain, (int, float)) and not isinstance(gain, bool):
            ke = float(gain)
        elif p0 > worst:
            ke = 0.0
        elif gain == "auto":
            ke = max(0.0, float(np.max(dp))) + 0.05 * max(worst, 1e-12)
        else:
            raise InstabilityError(
                f"004 eq. 16 fails for {self.model.spec!r}: p0 = {p0:.4g} <= max|dP/dv| = {worst:.4g} "
                f"(um per normalised input) over the command range [{lo:g}, {hi:g}], and no proportional "
                "gain k_e was given (eq. 20)", hint="pass gain='auto' or a k_e with p0 + k_e > max|dP/dv - k_e|")
        margin = float(np.max(np.abs(dp - ke)))
        holds = p0 + ke > margin
        self.checks["eq20"] = {"k_e": ke, "p0_plus_ke": p0 + ke, "max_abs_dP_minus_ke": margin, "holds": bool(holds)}
        if not holds and kind == "im":
            raise InstabilityError(
                f"004 eq. 20 fails for {self.model.spec!r} with k_e = {ke:.4g}: p0 + k_e = {p0 + ke:.4g} <= "
                f"max|dP/dv - k_e| = {margin:.4g}: the I-M iteration would not contract (the model's "
                "initial loading curve is not rising over the command range)",
                hint="use method='general', or fit the model as pmpi(invertible=yes), which keeps eq. 16")
        if ke:
            self.notes.append(f"eq. 16 fails (p0 = {p0:.4g} <= {worst:.4g}); eq. 20 gain k_e = {ke:.4g} applied"
                              if p0 <= worst else f"eq. 20 gain k_e = {ke:.4g} applied")
        return ke

    def _check_pid(self) -> None:
        b, a = self.dynamics if self.dynamics is not None else (np.ones(1), np.ones(1))
        delay = self.model.effect("delay")
        if delay is not None:
            d = int(round(delay.param("seconds") * self.fs))
            b = np.concatenate([np.zeros(d), b])
        poles = self.pid.poles(self.fs, b, a)
        radius = float(np.max(np.abs(poles), initial=0.0))
        self.checks["closed_loop"] = {"max_pole_radius": radius, "stable": bool(radius < 1.0 - 1e-9),
                                      "dynamics": "model" if self.dynamics is not None else "none (unit gain)"}
        if not radius < 1.0 - 1e-9:
            what = "the model's dynamics" if self.dynamics is not None else "the compensated (unit-gain) plant"
            raise InstabilityError(
                f"PID kp={self.pid.kp:g}, ki={self.pid.ki:g} 1/s, kd={self.pid.kd:g} s destabilise the loop with "
                f"{what} and one sample of measurement delay: closed-loop pole at |z| = {radius:.4g} >= 1",
                hint="lower the gains (ki/fs < 1 and kp < 1 keep a unit-gain plant stable)")

    def _slope0(self) -> float:
        lo, hi = self.limits
        us = self.CP[C_US]
        if self.kind == "general":
            X0 = np.zeros_like(self.X)
            X1 = np.zeros_like(self.X)
            aux = np.zeros(max(len(self.channels), 1))
            aux[:] = [float(self.model.effect(c).constants["reference"]) for c in self.channels] or [0.0]
            y0 = _model_step_py(self.I, self.P, X0, lo, aux)
            y1 = _model_step_py(self.I, self.P, X1, hi, aux)
            s = (y1 - y0) / (hi - lo)
            if not s > 0:
                raise InstabilityError(
                    f"the static map of {self.model.spec!r} does not rise over the command range [{lo:g}, {hi:g}] "
                    f"({y0:.4g} -> {y1:.4g} um): the compensator assumes a rising actuator")
            self._y_span = abs(y1 - y0)
            return s
        if self.kind == "fpmpi":
            v = np.linspace(lo / us, hi / us, 4001)
            x = np.array([_shaped(self.I, self.P, float(t)) for t in v])
            if np.any(np.diff(x) < -1e-12 * np.ptp(x)):
                self.notes.append("the fractional polynomial is not monotone over the command range: the solve "
                                  "returns a bracketed root")
            return max(float((x[-1] - x[0]) / (v[-1] - v[0])), 1e-9)
        return 1.0

    def _tol_f(self) -> float:
        lo, hi = self.limits
        if self.kind == "general":
            return 1e-9 * max(getattr(self, "_y_span", 1.0), 1e-12)
        return 1e-11 * (hi - lo)

    # -- state ----------------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Fresh model memory, feedback and identifier; the command at the range's low end."""
        self.X[:] = 0.0
        self.CX = np.zeros(self._nx_total)
        self.CX[S_U] = self.CX[S_UAPP] = min(max(0.0, self.limits[0]), self.limits[1])
        self.CX[S_VPREV] = self.CX[S_U] / self.CP[C_US]
        self.CX[S_SLOPE] = self.CP[C_SLOPE0]
        self.CX[S_GAIN] = 1.0
        self.CX[S_YPREV] = math.nan
        if self.oiir is not None:
            self.oiir.reset()
        self._aux = np.zeros(max(len(self.channels), 1))

    def oiir_arrays(self) -> tuple:
        """The identifier's kernel arguments (a small unused one when not adaptive, so the compiled
        loop has one signature)."""
        if self.oiir is not None:
            return self.oiir.kernel_args()
        if self._dummy_oiir is None:
            from hilbench.online.oiir import OIIR, FPMPIFrontEnd

            fe = FPMPIFrontEnd(1.0, np.ones(1), np.ones(1), np.zeros(1), np.ones(1))
            self._dummy_oiir = OIIR(fe, 0, 0)
        return self._dummy_oiir.kernel_args()

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(CI, CP, CX, I, P, X)`` for compiled callers."""
        return self.CI, self.CP, self.CX, self.I, self.P, self.X

    def _aux_row(self, aux: dict[str, float] | None) -> np.ndarray:
        if self.channels:
            for i, c in enumerate(self.channels):
                self._aux[i] = aux[c]  # type: ignore[index]
        return self._aux

    def step(self, y_d: float, aux: dict[str, float] | None = None) -> float:
        """Step mode: the command for y_d (um); then call :meth:`update` with what was applied."""
        return comp_step(self.CI, self.CP, self.CX, self.I, self.P, self.X, float(y_d), self._aux_row(aux))

    def update(self, y_d: float, u_applied: float, y_meas: float = math.nan,
               aux: dict[str, float] | None = None) -> None:
        """Commit the applied command; feed the measured output to feedback and identifier."""
        comp_update(self.CI, self.CP, self.CX, self.I, self.P, self.X, self.oiir_arrays(), float(y_d),
                    float(u_applied), float(y_meas), self._aux_row(aux))

    def feedforward(self, y_d: np.ndarray, aux: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """Block mode, open loop: the commands for a reference, each committed as applied."""
        y = np.ascontiguousarray(y_d, dtype=np.float64)
        out = np.empty_like(y)
        comp_block(self.CI, self.CP, self.CX, self.I, self.P, self.X, self.oiir_arrays(), y,
                   self.aux_matrix(aux, y.shape[0]), out)
        return out

    def aux_matrix(self, aux: dict[str, np.ndarray] | None, n: int) -> np.ndarray:
        if not self.channels:
            return np.zeros((n, 1))
        missing = [c for c in self.channels if aux is None or c not in aux]
        if missing:
            raise UserError(f"the model reads channel(s) {', '.join(missing)}, which were not given")
        return np.ascontiguousarray(np.column_stack([np.asarray(aux[c], float)[:n] for c in self.channels]))  # type: ignore[index]

    def precondition(self, applied: np.ndarray, aux: dict[str, np.ndarray] | None = None) -> None:
        """Feed commands the actuator went through (a ramp before the run) into the model's memory."""
        u = np.ascontiguousarray(applied, dtype=np.float64)
        if u.size == 0:
            return
        out = np.empty_like(u)
        ST.model_block(self.I, self.P, self.X, u, self.aux_matrix(aux, u.shape[0]), out)
        self.CX[S_XP_OK] = 0.0  # the model's memory moved without the fast commit
        self.CX[S_U] = self.CX[S_UAPP] = float(u[-1])
        self.CX[S_VPREV] = float(u[-1]) / self.CP[C_US]

    def peek(self, y_d: float, aux: dict[str, float] | None = None) -> float:
        """The command for y_d without changing any state."""
        saved = (self.CX.copy(), self.X.copy())
        try:
            u = self.step(y_d, aux)
            # the I-M iteration starts from the last command: converge it where the output jumps
            for _ in range(60 if self.kind == "im" else 0):
                self.CX[:], self.X[:] = saved
                self.CX[S_VPREV] = u / self.CP[C_US]
                u_next = self.step(y_d, aux)
                if abs(u_next - u) <= 1e-12 * (self.limits[1] - self.limits[0]):
                    break
                u = u_next
            return u
        finally:
            self.CX[:], self.X[:] = saved

    def counters(self) -> dict[str, Any]:
        return {"samples": int(self.CX[S_NOBS]), "solver_evaluations": int(self.CX[S_EVALS]),
                "limited_samples": int(self.CX[S_SATN]), "references_held": int(self.CX[S_HELD]),
                "analytic_inverse_corrected": int(self.CX[S_FIXED]), "newton_samples": int(self.CX[S_NEWTON]),
                "gain": float(self.CX[S_GAIN]), "offset_um": float(self.CX[S_BIAS])}

    def describe(self) -> dict[str, Any]:
        """What the recording keeps: kind, checks, notes, feedback, identifier."""
        doc: dict[str, Any] = {"model": self.model.spec, "method": self.kind, "limits": list(self.limits),
                               "checks": self.checks, "notes": self.notes}
        if self.kind == "im":
            doc["iterations_per_sample"] = int(self.CI[CI_IMIT])
        if self.pid is not None:
            doc["feedback"] = {"kp": self.pid.kp, "ki_per_s": self.pid.ki, "kd_s": self.pid.kd}
        if self.oiir is not None:
            doc["online"] = {"M": self.oiir.M, "N": self.oiir.N, "bias": self.oiir.bias}
        return doc


@njit(cache=True, _nrt=False)
def _tpoly_py(CI: np.ndarray, CP: np.ndarray, t: float) -> tuple[float, float, float]:
    return _tpoly(CI, CP, t)


@njit(cache=True, _nrt=False)
def _model_step_py(I: np.ndarray, P: np.ndarray, X: np.ndarray, u: float, aux: np.ndarray) -> float:
    return model_step(I, P, X, u, aux)
