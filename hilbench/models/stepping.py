"""A fitted model compiled for step mode: flat parameter arrays, explicit state, one numba step.

:func:`compile_model` flattens a fitted :class:`~hilbench.models.model.Model` into three arrays:

- ``I`` (int64): the structure (which base, which effects, sizes) and offsets into ``P`` and ``X``;
- ``P`` (float64): every number the model needs (thresholds, eta, weights, polynomial and
  fractional-polynomial coefficients, creep filters, rate and aux-channel constants, dynamics b/a
  and the unit steady-state filter start, delay);
- ``X`` (float64): the model's memory (operator outputs, Duhem / Bouc-Wen state, creep low-passes,
  turning-point estimator, dynamics filter state, delay ring buffer) and per-sample scratch.

:func:`model_step` ``(I, P, X, u, aux) -> y`` evaluates one sample (um) and is the loop body of
:func:`model_block`, so a block of n samples equals n steps. Both are ``@njit(cache=True)`` and take
only arrays and scalars, so a compiled closed loop (model step + :func:`hilbench.sim.kernels.plant_step`
per sample) calls them directly; from Python one step costs one dispatcher call with five arguments.
``model_step`` is inlined into its numba callers (the compensator's kernels call a non-inlined copy:
typing the whole model again at each of their call sites cost ~40 s of a cold compile, and a call
measured no slower there) and compiled without NRT refcounting (``_nrt=False``,
it allocates nothing): a compiled caller should also be ``_nrt=False``, or each call pays an
atomic incref/decref per array argument (see :func:`hilbench.sim.kernels.plant_step`).

The arithmetic follows the block path of :meth:`Model.simulate` (regressor columns times weights,
then delay, then the dynamics started in steady state as ``lfilter_zi`` does), so the two agree to
rounding. The columns are formed per sample in the same order as the block path's regressor matrix,
and the weights are taken in that order: the hysteresis columns (base, asymmetry, saturation) are
kept in a scratch row because creep (output form), rate-dependence and aux channels modulate them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from hilbench.models.kernels import bouc_wen_update
from hilbench.sim.kernels import N_TP, TP_A, TP_F, turning_point_update

# -- structure: indices into I ---------------------------------------------------------------------
I_BASE = 0  # 0 linear, 1 operators (pi, pi1, mpi, pmpi, pd, fpmpi), 2 ISSF-Duhem, 3 Bouc-Wen
I_NOPS = 1
I_R = 2  # P offset: thresholds
I_ETA = 3  # P offset: eta
I_NIN = 4  # fractional polynomial terms (fpmpi), 0 = none
I_INEXP = 5  # P offset: exponents
I_INW = 6  # P offset: weights
I_EXTRA = 7  # 0 none, 1 v^2 and v^3 (mpi, pmpi), 2 dead zones (pd)
I_NDZ = 8  # dead zones (pd) or Duhem-D thresholds
I_DZ = 9  # P offset of those
I_DSHAPE = 10  # Duhem shape: 1 Gompertz, 2 modified tanh, 3 dead-zone operators
I_OFF = 11  # column index of the base's offset column
I_ASYM = 12  # asymmetry order (0 = none)
I_SAT = 13  # 0 none, 1 input form, 2 output form (tanh), 3 knee, 4 wiener (knee of the reference h)
I_NBA = 14  # hysteresis columns before saturation (base + asymmetry)
I_H = 15  # all hysteresis columns (base + asymmetry + saturation)
I_NKPRE = 16  # of the columns before saturation, those that are not the offset
I_NK = 17  # all hysteresis columns that are not the offset
I_W = 18  # P offset: weights of the hysteresis columns (H of them)
I_NCREEP = 19
I_CREEP_OUT = 20  # 1 = output form (low-passes of the hysteresis columns too)
I_CREEP_A = 21  # P offset: low-pass coefficients
I_W_CREEP = 22  # P offset: creep weights
I_RATE = 23  # 0 none, 1 damping, 2 frequency
I_ORDER = 24  # frequency-form polynomial order
I_MOMENTS = 25  # P offset: harmonic moments (order + 1)
I_W_RATE = 26
I_NAUX = 27
I_AUX = 28  # P offset: (reference, scale) per aux channel
I_W_AUX = 29
I_DYN_N = 30  # dynamics order (0 = none or a pure gain)
I_DYN_ON = 31
I_DYN_B = 32
I_DYN_A = 33
I_DYN_ZI = 34
I_DELAY = 35  # 1 = delay on
I_DELAY_DI = 36  # whole samples of the delay
I_DELAY_L = 37  # ring buffer length (DI + 2)
I_X_OPS = 38  # X offsets
I_X_ROW = 39
I_X_XK = 40
I_X_LP = 41
I_X_LPH = 42
I_X_TP = 43
I_X_DYN = 44
I_X_BUF = 45
I_NB = 46  # base columns
I_NX = 47  # length of X
I_RATE_K = 48  # P offset: rate-dependence gain coefficients (damping: g; frequency: k_1..k_order)
I_AUX_G = 49  # P offset: aux channels' gain coefficients g
I_SHAPE_IN = 50  # 1 = the drive is shaped by a knee before everything (saturation(form=hammerstein))
I_SAT_REF = 51  # P offset: reference weights of the non-offset columns before saturation (form=wiener)
N_I = 52

# -- scalars: indices into P --------------------------------------------------------------------------
P_FS = 0
P_USCALE = 1
P_ALPHA = 2  # Duhem alpha
P_MU_A = 3  # mu1 / mu3
P_MU_B = 4  # mu2 / mu4
P_MU_C = 5  # the shape function's constant term
P_BW_BETA = 6
P_BW_GAMMA = 7
P_BW_N = 8
P_SAT_S = 9
P_RATE_M = 10
P_RATE_Q = 11  # reference rate (damping form)
P_VDOT_MAX = 12
P_F_REF = 13
P_DELAY_FRAC = 14
P_DYN_B0 = 15  # b[0] (the whole filter when it is a pure gain)
P_SAT_P = 16  # sharpness of the saturation knee (form=knee)
P_GAIN_FLOOR = 17  # floor of the loop gains (effect_components.GAIN_FLOOR)
P_SHAPE_S = 18  # the drive's knee (form=hammerstein), normalised input
P_SHAPE_P = 19  # its sharpness
P_SHAPE_NORM = 20  # k(1 / s): the shaped drive is k(v / s) / k(1 / s)
P_SAT_HSCALE = 21  # the reference's largest |h| on training (form=wiener), um
P_RATE_LAG = 22  # 1: the rate terms read the input rate so far (a compensator's copy, see model_step)
N_P = 23

# -- state: scalar part of X ------------------------------------------------------------------------------
X_STARTED = 0
X_V_PREV = 1
X_Z = 2  # Duhem w or Bouc-Wen z
X_U_PREV = 3  # previous raw input (Duhem, Bouc-Wen)
X_BUF_IDX = 4
X_VDOT_PREV = 5  # the input rate so far (1/s, normalised input; P_RATE_LAG)
N_X = 6
#: the rate so far, with P_RATE_LAG: a first-order low-pass of the input rate with this time constant
#: (s; at least one sample), far quicker than any drive whose rate the rate terms describe
RATE_LAG_S = 1e-3


class NotCompilable(Exception):
    """The model has a part the compiled step does not cover; the caller falls back to Python."""


@njit(cache=True, inline="always")
def _sgn(x: float) -> float:
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else 0.0)


@njit(cache=True, inline="always", _nrt=False)
def model_step(I: np.ndarray, P: np.ndarray, X: np.ndarray, u: float, aux: np.ndarray) -> float:
    """One sample of a compiled model (see the module docstring): input u (command unit), aux
    channel values in the model's order; returns the model output, um. Updates X in place."""
    fs = P[P_FS]
    v = u / P[P_USCALE]
    if I[I_SHAPE_IN] == 1:  # the drive saturates before everything (Saturation.shape_input)
        xs = v / P[P_SHAPE_S]
        v = xs * (1.0 + abs(xs) ** P[P_SHAPE_P]) ** (-1.0 / P[P_SHAPE_P]) / P[P_SHAPE_NORM]
        u = v * P[P_USCALE]
    first = X[X_STARTED] == 0.0
    vdot = 0.0 if first else (v - X[X_V_PREV]) * fs
    X[X_V_PREV] = v
    if P[P_RATE_LAG] != 0.0:
        # An inverse solving this sample's input from its output: with this sample's rate, the rate
        # terms (gain k(|v'|) on the loop, damping sgn(v')|v'|^m) weigh the input by the sample rate
        # and the map from input to output falls as well as rises; solved per sample it chatters
        # between the branches. The rate so far (the previous samples', low-passed over RATE_LAG_S
        # so a jump of one sample does not swing the next) leaves only the hysteresis to solve.
        rate_so_far = X[X_VDOT_PREV]
        X[X_VDOT_PREV] += (vdot - rate_so_far) / max(1.0, RATE_LAG_S * fs)
        vdot = rate_so_far
    row = I[I_X_ROW]
    base = I[I_BASE]
    # -- base: hysteresis columns ----------------------------------------------------------------
    if base == 1:
        x = v
        nin = I[I_NIN]
        if nin > 0:  # fractional polynomial of the input (000 eq. 4-5)
            x = 0.0
            av = abs(v)
            sv = _sgn(v)
            for k in range(nin):
                e = P[I[I_INEXP] + k]
                if e == 0.0:
                    term = 1.0
                elif e == 0.5:
                    term = sv * math.sqrt(av)
                else:
                    term = sv * av**e
                x += P[I[I_INW] + k] * term
        X[row] = 1.0
        o_r = I[I_R]
        o_eta = I[I_ETA]
        o_ops = I[I_X_OPS]
        for i in range(I[I_NOPS]):
            r = P[o_r + i]
            w = min(x + P[o_eta + i] * r, X[o_ops + i])
            w = max(x - r, w)
            X[o_ops + i] = w
            X[row + 1 + i] = w
        c = row + 1 + I[I_NOPS]
        extra = I[I_EXTRA]
        if extra == 1:
            X[c] = v * v
            X[c + 1] = v**3.0
        elif extra == 2:
            for k in range(I[I_NDZ]):
                d = P[I[I_DZ] + k]
                X[c + k] = max(v - d, 0.0) if d >= 0.0 else min(v - d, 0.0)
    elif base == 0:
        X[row] = v
        X[row + 1] = 1.0
    else:
        if first:
            X[X_U_PREV] = u
            X[X_Z] = u if base == 2 else 0.0
        du = u - X[X_U_PREV]
        z = X[X_Z]
        if base == 2:  # ISSF-Duhem state with beta = alpha (001 eq. 17), exact for linear input
            alpha = P[P_ALPHA]
            if du != 0.0:
                ba = alpha / alpha
                s = 1.0 if du > 0.0 else -1.0
                w_eq_prev = ba * X[X_U_PREV] - s * ba / alpha
                w_eq = ba * u - s * ba / alpha
                z = w_eq + (z - w_eq_prev) * math.exp(-alpha * abs(du))
        else:
            z = bouc_wen_update(z, du, P[P_BW_BETA], P[P_BW_GAMMA], P[P_BW_N])
        X[X_Z] = z
        X[X_U_PREV] = u
        X[row] = u
        X[row + 1] = 1.0
        if base == 3:
            X[row + 2] = z
        else:
            shape = I[I_DSHAPE]
            if shape == 1:
                X[row + 2] = 2.0 * math.exp(-math.exp(-P[P_MU_A] * z - P[P_MU_B])) - P[P_MU_C]
            elif shape == 2:
                X[row + 2] = 2.0 * math.tanh(-math.exp(-P[P_MU_A] * z - P[P_MU_B])) - P[P_MU_C]
            else:
                X[row + 2] = z
                for k in range(I[I_NDZ]):
                    r = P[I[I_DZ] + k]
                    X[row + 3 + k] = max(z - r, 0.0) if r > 0.0 else min(z - r, 0.0)
    # -- asymmetry: v^2 .. v^order ----------------------------------------------------------------
    c = row + I[I_NB]
    for k in range(2, I[I_ASYM] + 1):
        X[c] = v * v if k == 2 else X[c - 1] * v  # successive products, as the block columns
        c += 1
    # the hysteresis columns that are not the offset, in order (the modulated effects' inputs)
    xk = I[I_X_XK]
    off = I[I_OFF]
    j = 0
    for i in range(I[I_NBA]):
        if i != off:
            X[xk + j] = X[row + i]
            j += 1
    # -- saturation --------------------------------------------------------------------------------
    sat = I[I_SAT]
    if sat != 0:
        if sat != 4:  # the memoryless terms (every form but wiener)
            av = abs(v)
            sv = _sgn(v)
            X[c] = math.tanh(v / P[P_SAT_S])
            X[c + 1] = sv * math.sqrt(av)
            X[c + 2] = sv * av ** (1.0 / 3.0)
            c += 3
        if sat >= 2:  # output forms: copies of the hysteresis columns times phi(v/s) - 1 (wiener: one column)
            xs = v / P[P_SAT_S]
            h_ref = 0.0
            if sat == 4:  # wiener: the knee of the reference hysteresis output h_ref / (s h_scale)
                ref = I[I_SAT_REF]
                for i in range(I[I_NKPRE]):
                    h_ref += P[ref + i] * X[xk + i]
                xs = h_ref / (P[P_SAT_S] * P[P_SAT_HSCALE])
            if sat >= 3:  # knee of sharpness p
                phi = (1.0 + abs(xs) ** P[P_SAT_P]) ** (-1.0 / P[P_SAT_P])
            else:
                phi = math.tanh(xs) / xs if abs(xs) > 1e-8 else 1.0
            if sat == 4:  # one column: h_ref (phi - 1)
                X[c] = h_ref * (phi - 1.0)
                c += 1
            else:
                for i in range(I[I_NKPRE]):
                    X[c] = X[xk + i] * (phi - 1.0)
                    c += 1
        for i in range(I[I_NBA], I[I_H]):
            X[xk + j] = X[row + i]
            j += 1
    # -- the hysteresis part of the output ---------------------------------------------------------
    H = I[I_H]
    ow = I[I_W]
    h = 0.0
    for i in range(H):
        h += X[row + i] * P[ow + i]
    nk = I[I_NK]
    rgain = 1.0  # rate-dependence's gain on the hysteresis columns but the offset (003 eq. 9)
    # -- creep: drift parts lp(x) - x of first-order low-passes (searched elements or the fixed bank) --
    nc = I[I_NCREEP]
    if nc > 0:
        o_a = I[I_CREEP_A]
        o_lp = I[I_X_LP]
        o_wc = I[I_W_CREEP]
        for k in range(nc):
            if first:
                X[o_lp + k] = v
            ak = P[o_a + k]
            X[o_lp + k] += ak * (v - X[o_lp + k])
            h += P[o_wc + k] * (X[o_lp + k] - v)
        if I[I_CREEP_OUT] != 0:
            o_lph = I[I_X_LPH]
            ow2 = o_wc + nc
            for k in range(nc):
                ak = P[o_a + k]
                for i in range(nk):
                    s_i = o_lph + k * nk + i
                    xi = X[xk + i]
                    if first:
                        X[s_i] = xi
                    X[s_i] += ak * (xi - X[s_i])
                    h += P[ow2 + k * nk + i] * (X[s_i] - xi)
    # -- rate-dependence (003) -------------------------------------------------------------------
    rate_form = I[I_RATE]
    if rate_form != 0:
        vmax = P[P_VDOT_MAX]
        vdc = min(max(vdot, -vmax), vmax)
        sg = _sgn(vdot)
        m = P[P_RATE_M]
        o_wr = I[I_W_RATE]
        o_k = I[I_RATE_K]
        if rate_form == 1:
            rate = abs(vdc) / P[P_RATE_Q]
            rgain = 1.0 + P[o_k] * rate
            h += P[o_wr] * sg * rate**m
        else:
            o_tp = I[I_X_TP]
            tp = X[o_tp : o_tp + N_TP]
            turning_point_update(tp, v, fs)
            f = tp[TP_F]
            fn = min(f / P[P_F_REF], 1.0)
            q = 2.0 * math.pi * f * tp[TP_A]
            md = sg * abs(vdc / q) ** m if q > 0.0 else 0.0
            order = I[I_ORDER]
            o_mom = I[I_MOMENTS]
            power = 1.0
            for jj in range(order):
                h += P[o_wr + jj] * md * (power * P[o_mom + jj])
                power *= fn
            power = 1.0
            for jj in range(1, order + 1):
                power *= fn
                rgain += P[o_k + jj - 1] * P[o_mom + jj] * power
        rgain = max(rgain, P[P_GAIN_FLOOR])
    # -- auxiliary channels: offset and gain changes -------------------------------------------------
    naux = I[I_NAUX]
    if naux > 0:
        o_aux = I[I_AUX]
        k = I[I_W_AUX]
        for ch in range(naux):
            da = (aux[ch] - P[o_aux + 2 * ch]) / P[o_aux + 2 * ch + 1]
            h += P[k] * da
            rgain *= max(1.0 + P[I[I_AUX_G] + ch] * da, P[P_GAIN_FLOOR])
            k += 1
    if rgain != 1.0:
        # the hysteresis columns but the offset, scaled by the loop gains: (gain - 1) times their sum
        hk = 0.0
        for i in range(H):
            if i != off:
                hk += X[row + i] * P[ow + i]
        h += (rgain - 1.0) * hk
    # -- delay: the static part's output, fractional samples, first value held before the start --------
    if I[I_DELAY] != 0:
        buf = I[I_X_BUF]
        L = I[I_DELAY_L]
        if first:
            for i in range(L):
                X[buf + i] = h
        idx = (int(X[X_BUF_IDX]) + 1) % L
        X[buf + idx] = h
        X[X_BUF_IDX] = idx
        di = I[I_DELAY_DI]
        frac = P[P_DELAY_FRAC]
        h = (1.0 - frac) * X[buf + (idx - di) % L] + frac * X[buf + (idx - di - 1) % L]
    # -- dynamics: direct form II transposed, started in steady state (lfilter_zi) ----------------------
    y = h
    if I[I_DYN_ON] != 0:
        nd = I[I_DYN_N]
        if nd == 0:
            y = P[P_DYN_B0] * h
        else:
            zs = I[I_X_DYN]
            ob = I[I_DYN_B]
            oa = I[I_DYN_A]
            if first:
                for i in range(nd):
                    X[zs + i] = P[I[I_DYN_ZI] + i] * h
            y = P[ob] * h + X[zs]
            for i in range(nd - 1):
                X[zs + i] = P[ob + i + 1] * h + X[zs + i + 1] - P[oa + i + 1] * y
            X[zs + nd - 1] = P[ob + nd] * h - P[oa + nd] * y
    X[X_STARTED] = 1.0
    return y


@njit(cache=True, _nrt=False)
def model_block(I: np.ndarray, P: np.ndarray, X: np.ndarray, u: np.ndarray, aux: np.ndarray, out: np.ndarray) -> None:
    """n = len(u) samples: :func:`model_step` per sample; ``aux`` is (n, channels), ``out`` (n,)."""
    for n in range(u.shape[0]):
        out[n] = model_step(I, P, X, u[n], aux[n])


# ====================================================================================================
# flattening a fitted model
# ====================================================================================================


class _Flat:
    def __init__(self) -> None:
        self.I = np.zeros(N_I, dtype=np.int64)
        self.P: list[float] = [0.0] * N_P
        self.nx = N_X

    def put(self, values: Any) -> int:
        at = len(self.P)
        self.P.extend(float(x) for x in np.asarray(values, float).ravel())
        return at

    def state(self, n: int) -> int:
        at = self.nx
        self.nx += int(n)
        return at


def compile_model(model: Any, sample_rate_hz: float) -> CompiledModel:
    """Flatten a fitted model for :func:`model_step`; raises :class:`NotCompilable` for what it
    does not cover (the caller keeps the Python path for it)."""
    from hilbench.models import bases as C
    from hilbench.models.effect_components import GAIN_FLOOR

    if model.weights is None:
        raise NotCompilable("the model has no weights")
    fs = float(sample_rate_hz)
    f = _Flat()
    I = f.I
    f.P[P_FS] = fs
    f.P[P_USCALE] = float(model.norm["u_scale"])
    f.P[P_GAIN_FLOOR] = GAIN_FLOOR
    base = model.base
    # -- base ---------------------------------------------------------------------------------------
    if isinstance(base, C.Linear):
        I[I_BASE], nb, off = 0, 2, 1
    elif isinstance(base, (C.OperatorBase, C.FPMPI)):
        I[I_BASE], off = 1, 0
        if isinstance(base, C.FPMPI):
            if "shaped_max" not in base.constants:
                raise NotCompilable("fpmpi without a frozen input range (shaped_max)")
            n_ops = int(base.constants["n"])
            span = float(base.constants["shaped_max"]) or 1.0
            r = np.arange(n_ops) / n_ops * span
            eta = np.zeros(n_ops)
            exps = [float(e) for e in base.constants["exponents"]]
            params = iter(base.params)
            ws = [1.0 if e == 1.0 else next(params).value for e in exps]
            I[I_NIN] = len(exps)
            I[I_INEXP] = f.put(exps)
            I[I_INW] = f.put(ws)
            extra_cols = 0
        else:
            r = np.asarray(base.constants["thresholds"], float)
            eta = base.eta()
            extra_cols = len(base.extra_names())
            if isinstance(base, C.PD):
                I[I_EXTRA] = 2
                dz = np.asarray(base.constants["dead_zones"], float)
                I[I_NDZ], I[I_DZ] = dz.size, f.put(dz)
            elif isinstance(base, C.MPI):
                I[I_EXTRA] = 1
            elif extra_cols:
                raise NotCompilable(f"{base.name}: extra columns {base.extra_names()}")
        I[I_NOPS] = r.size
        I[I_R], I[I_ETA] = f.put(r), f.put(eta)
        I[I_X_OPS] = f.state(r.size)
        nb = 1 + r.size + extra_cols
    elif isinstance(base, C.DuhemBase):
        I[I_BASE], off = 2, 1
        f.P[P_ALPHA] = base.param("alpha")
        if isinstance(base, C.DuhemD):
            I[I_DSHAPE] = 3
            thr = base.thresholds()
            I[I_NDZ], I[I_DZ] = thr.size, f.put(thr)
            nb = 3 + thr.size
        elif isinstance(base, C.DuhemM):
            I[I_DSHAPE] = 2
            f.P[P_MU_A], f.P[P_MU_B] = base.param("mu3"), base.param("mu4")
            f.P[P_MU_C] = 2.0 * math.tanh(-math.exp(-base.param("mu4")))
            nb = 3
        elif isinstance(base, C.DuhemG):
            I[I_DSHAPE] = 1
            f.P[P_MU_A], f.P[P_MU_B] = base.param("mu1"), base.param("mu2")
            f.P[P_MU_C] = 2.0 * math.exp(-math.exp(-base.param("mu2")))
            nb = 3
        else:
            raise NotCompilable(f"Duhem shape of {base.name}")
    elif isinstance(base, C.BoucWen):
        I[I_BASE], off, nb = 3, 1, 3
        beta = base.param("beta")
        f.P[P_BW_BETA], f.P[P_BW_GAMMA] = beta, beta * base.param("gamma_over_beta")
        f.P[P_BW_N] = float(base.constants["n"])
    else:
        raise NotCompilable(f"base {base.name}")
    I[I_NB], I[I_OFF] = nb, off
    # -- hysteresis effects ---------------------------------------------------------------------------
    asym = model.effect("asymmetry")
    n_asym = 0
    if asym is not None:
        I[I_ASYM] = asym.order()
        n_asym = asym.order() - 1
    nba = nb + n_asym
    I[I_NBA] = nba
    I[I_NKPRE] = nba - 1
    sat = model.effect("saturation")
    n_sat = 0
    if sat is not None and sat.shapes_input:
        s_knee, p_knee = sat.param("s"), sat.param("p")
        I[I_SHAPE_IN] = 1
        f.P[P_SHAPE_S], f.P[P_SHAPE_P] = s_knee, p_knee
        f.P[P_SHAPE_NORM] = (1.0 / s_knee) * (1.0 + (1.0 / s_knee) ** p_knee) ** (-1.0 / p_knee)
    elif sat is not None and not (sat.needs_reference and "reference_names" not in sat.constants):
        # (form=wiener before its reference is set adds no columns, in the block path as here)
        form = str(sat.options.get("form", "output"))
        output_form = form in ("output", "knee", "wiener")
        I[I_SAT] = {"output": 2, "knee": 3, "wiener": 4}.get(form, 1)
        f.P[P_SAT_S] = sat.param("s")
        if form in ("knee", "wiener"):
            f.P[P_SAT_P] = sat.param("p")
        if form == "wiener":
            ref = dict(zip(sat.constants["reference_names"], sat.constants["reference_weights"]))
            pre = [name for i, name in enumerate(model.weight_names[:nba]) if i != off]
            I[I_SAT_REF] = f.put(np.array([ref.get(name, 0.0) for name in pre], float))
            f.P[P_SAT_HSCALE] = float(sat.constants["h_scale"])
        n_sat = 1 if form == "wiener" else 3 + (nba - 1 if output_form else 0)
    H = nba + n_sat
    I[I_H] = H
    nk = H - 1
    I[I_NK] = nk
    I[I_X_ROW] = f.state(H)
    I[I_X_XK] = f.state(nk)
    w = np.asarray(model.weights, float)
    I[I_W] = f.put(w)  # the whole weight vector; the segments follow in the model's column order
    k = H
    # -- creep --------------------------------------------------------------------------------------------
    creep = model.effect("creep")
    if creep is not None:
        taus = creep.time_constants()  # searched (form=input, output) or the fixed bank (form=bank)
        nc = taus.size
        I[I_NCREEP] = nc
        I[I_CREEP_A] = f.put([1.0 - math.exp(-1.0 / (fs * t)) for t in taus])
        I[I_X_LP] = f.state(nc)
        form = str(creep.options.get("form", "input"))
        if form in ("log", "log-output"):
            # the logarithmic law: one weight per column over the whole bank, copied per element for
            # the kernel (the input's nc, then the hysteresis columns' nc x nk, element-major)
            spectrum = creep.log_spectrum()
            per_element = [float(w[k]) * spectrum]
            k += 1
            if form == "log-output":
                per_element.append(np.outer(spectrum, w[k : k + nk]).ravel())
                I[I_CREEP_OUT] = 1
                I[I_X_LPH] = f.state(nc * nk)
                k += nk
            I[I_W_CREEP] = f.put(np.concatenate(per_element))
        else:
            I[I_W_CREEP] = I[I_W] + k
            k += nc
        if form == "output":
            I[I_CREEP_OUT] = 1
            I[I_X_LPH] = f.state(nc * nk)
            k += nc * nk
    # -- rate-dependence ---------------------------------------------------------------------------------
    rate = model.effect("rate-dependence")
    if rate is not None:
        f.P[P_RATE_M] = rate.param("m")
        f.P[P_VDOT_MAX] = float(rate.constants.get("vdot_max", np.inf))
        I[I_W_RATE] = I[I_W] + k
        I[I_RATE_K] = f.put(rate.gain_coefficients())
        if rate.constants["form"] == "damping":
            I[I_RATE] = 1
            f.P[P_RATE_Q] = float(rate.constants["rate_ref"])
            k += 1
        elif rate.constants["form"] == "frequency":
            I[I_RATE] = 2
            order = int(rate.constants["order"])
            I[I_ORDER] = order
            I[I_MOMENTS] = f.put(rate.harmonic_moments())
            f.P[P_F_REF] = float(rate.constants["f_ref"])
            I[I_X_TP] = f.state(N_TP)
            k += order
        else:
            raise NotCompilable(f"rate-dependence form {rate.constants['form']!r}")
    # -- auxiliary channels ---------------------------------------------------------------------------------
    channels = model.aux_channels
    if channels:
        I[I_NAUX] = len(channels)
        refs = []
        for c in channels:
            e = model.effect(c)
            refs += [float(e.constants["reference"]), float(e.constants["scale"])]
        I[I_AUX] = f.put(refs)
        I[I_AUX_G] = f.put([model.effect(c).param("g") for c in channels])
        I[I_W_AUX] = I[I_W] + k
        k += len(channels)
    if k != w.size:
        raise NotCompilable(f"weight layout: {k} columns expected, the model has {w.size} weights")
    # -- delay and dynamics ------------------------------------------------------------------------------------
    delay = model.effect("delay")
    if delay is not None:
        d = delay.param("seconds") * fs
        di = int(math.floor(d))
        I[I_DELAY], I[I_DELAY_DI], I[I_DELAY_L] = 1, di, di + 2
        f.P[P_DELAY_FRAC] = d - di
        I[I_X_BUF] = f.state(di + 2)
    dyn = model.effect("dynamics")
    if dyn is not None:
        from scipy import signal as sps

        b, a = dyn.coefficients(fs)
        I[I_DYN_ON] = 1
        f.P[P_DYN_B0] = float(b[0])
        nd = max(len(a), len(b)) - 1
        I[I_DYN_N] = nd
        if nd > 0:
            I[I_DYN_B], I[I_DYN_A] = f.put(b), f.put(a)
            I[I_DYN_ZI] = f.put(sps.lfilter_zi(b, a))
            I[I_X_DYN] = f.state(nd)
    I[I_NX] = f.nx
    return CompiledModel(I, np.array(f.P, dtype=np.float64), channels, model.spec)


def without_rate_terms(I: np.ndarray) -> np.ndarray:
    """A copy of a compiled model's integer layout with its rate terms (rate-dependence) switched off;
    nothing else reads the input rate, so the float layout ``P`` serves it unchanged."""
    I = I.copy()
    I[I_RATE] = 0
    return I


class CompiledModel:
    """A fitted model flattened for :func:`model_step`, with its own state ``X``.

    ``step(u, aux)`` from Python; ``arrays()`` gives ``(I, P, X)`` for compiled callers.
    """

    def __init__(self, I: np.ndarray, P: np.ndarray, channels: list[str], spec: str = ""):
        self.I = I
        self.P = P
        self.channels = list(channels)
        self.spec = spec
        self.X = np.zeros(int(I[I_NX]))
        self._aux = np.zeros(max(len(self.channels), 1))

    def new_state(self) -> np.ndarray:
        return np.zeros(int(self.I[I_NX]))

    def reset(self) -> None:
        self.X[:] = 0.0

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.I, self.P, self.X

    def step(self, u: float, aux: dict[str, float] | None = None) -> float:
        """One sample (um); ``aux`` holds this sample's value of every aux channel of the model."""
        if self.channels:
            a = self._aux
            for i, c in enumerate(self.channels):
                a[i] = aux[c]  # type: ignore[index]
        return _model_step(self.I, self.P, self.X, float(u), self._aux)

    def block(self, u: np.ndarray, aux: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """len(u) samples from the current state (the same as as many steps)."""
        u = np.ascontiguousarray(u, dtype=np.float64)
        if self.channels:
            a = np.ascontiguousarray(np.column_stack([np.asarray(aux[c], float) for c in self.channels]))  # type: ignore[index]
        else:
            a = np.zeros((u.shape[0], 1))
        out = np.empty(u.shape[0])
        model_block(self.I, self.P, self.X, u, a, out)
        return out


_model_step = model_step
