"""numba kernels of the models: operators and state equations with explicit state.

Each kernel processes a block of samples and updates the caller's state in place, so block mode
(whole runs) and step mode (blocks of one sample) share the code. The play / one-sided play / M-play
operators come from the simulated plant (:func:`hilbench.sim.kernels.mplay_block`): model and plant
speak the same operator.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from hilbench.sim.kernels import N_TP, TP_A, TP_F, duhem_w_block, mplay_block, turning_point_update

__all__ = [
    "mplay_block",
    "duhem_w_block",
    "bouc_wen_block",
    "bouc_wen_update",
    "lowpass_block",
    "turning_point_frequency",
    "N_TP",
    "fractional_delay",
    "scale_columns",
    "gather_rows_into",
    "lowpass_drift_into",
    "lowpass_drift_sum",
]


@njit(cache=True, inline="always")
def bouc_wen_update(z: float, du: float, beta: float, gamma: float, n: float) -> float:
    """One sample of :func:`bouc_wen_block`: z after an input change du (the step function)."""
    if du != 0.0:
        if n == 1.0:
            s = 1.0 if du > 0.0 else -1.0
            sig = 1.0 if z > 0.0 else (-1.0 if z < 0.0 else s)
            kk = beta * s + gamma * sig
            if abs(kk * du) < 1e-9:
                z_new = z + du * (1.0 - kk * z)
            else:
                z_eq = 1.0 / kk
                z_new = z_eq + (z - z_eq) * math.exp(-kk * du)
            if z_new * sig >= 0.0:
                return z_new
        h = du / 8.0
        ah = abs(h)
        for _ in range(8):
            az = abs(z)
            f1 = h - beta * ah * (az ** (n - 1.0)) * z - gamma * h * az**n
            zm = z + 0.5 * f1
            azm = abs(zm)
            f2 = h - beta * ah * (azm ** (n - 1.0)) * zm - gamma * h * azm**n
            z = z + f2
    return z


@njit(cache=True)
def bouc_wen_block(u: np.ndarray, beta: float, gamma: float, n: float, state: np.ndarray, out: np.ndarray) -> None:
    """Bouc-Wen state z with unit A: dz = du - beta |du| |z|^(n-1) z - gamma du |z|^n.

    Integrated over the input (rate independent); ``state = [z, u_prev]``. For n = 1 the equation
    is linear in z while the signs of du and z hold, dz/du = 1 - (beta sgn(du) + gamma sgn(z)) z,
    and is solved exactly per sample; a step in which z changes sign, and n != 1, use the
    midpoint rule in 8 sub-steps. The model output scales z by A, a linear weight.
    """
    z = state[0]
    u_prev = state[1]
    for k in range(u.shape[0]):
        z = bouc_wen_update(z, u[k] - u_prev, beta, gamma, n)
        u_prev = u[k]
        out[k] = z
    state[0] = z
    state[1] = u_prev


@njit(cache=True)
def lowpass_block(u: np.ndarray, alpha: float, state: np.ndarray, out: np.ndarray) -> None:
    """First-order low-pass x += alpha (u - x): one Kelvin-Voigt creep element; state = [x]."""
    x = state[0]
    for k in range(u.shape[0]):
        x += alpha * (u[k] - x)
        out[k] = x
    state[0] = x


@njit(cache=True)
def lowpass_drift_into(x: np.ndarray, alpha: float, state: np.ndarray, out: np.ndarray, first: int) -> None:
    """:func:`lowpass_block` on every column of x (n, p) in one pass over the rows (state (p,)),
    its drift (low-pass minus input) written straight into the columns ``first .. first + p`` of
    ``out`` (n, >= first + p): no intermediate array per time constant (creep after the hysteresis)."""
    n, p = x.shape
    for k in range(n):
        for j in range(p):
            state[j] += alpha * (x[k, j] - state[j])
            out[k, first + j] = state[j] - x[k, j]


@njit(cache=True)
def lowpass_drift_sum(x: np.ndarray, alphas: np.ndarray, weights: np.ndarray, state: np.ndarray,
                      out: np.ndarray, first: int) -> None:
    """``out[:, first + j] += sum_t weights[t] * (lowpass_t(x[:, j]) - x[:, j])`` over a bank of
    low-passes (alphas (T,), state (T, p)), added in the order of the bank, in one pass over the
    rows: a logarithmic creep law on every hysteresis column."""
    n, p = x.shape
    for k in range(n):
        for t in range(alphas.shape[0]):
            a = alphas[t]
            w = weights[t]
            for j in range(p):
                state[t, j] += a * (x[k, j] - state[t, j])
                out[k, first + j] += w * (state[t, j] - x[k, j])


@njit(cache=True)
def gather_rows_into(x: np.ndarray, rows: np.ndarray, out: np.ndarray, first: int) -> None:
    """``out[:, first .. first + p] = x[rows]`` for x (n, p), without the intermediate copy."""
    p = x.shape[1]
    for r in range(rows.shape[0]):
        k = rows[r]
        for j in range(p):
            out[r, first + j] = x[k, j]


@njit(cache=True)
def scale_columns(matrix: np.ndarray, gain: np.ndarray, scaled: np.ndarray) -> None:
    """``matrix[:, j] *= gain`` for every column j with ``scaled[j]``, in place, in one pass over
    the rows (numpy's masked form gathers, multiplies and scatters a copy)."""
    n, p = matrix.shape
    for k in range(n):
        g = gain[k]
        for j in range(p):
            if scaled[j]:
                matrix[k, j] *= g


@njit(cache=True)
def turning_point_frequency(u: np.ndarray, fs: float, state: np.ndarray, f_out: np.ndarray, a_out: np.ndarray) -> None:
    """Drive frequency (Hz) and amplitude from the last cycle between turning points.

    The same estimator as the simulated plant's 003 rate-dependence
    (:func:`hilbench.sim.kernels.turning_point_update`); ``state`` has ``N_TP`` entries.
    """
    for k in range(u.shape[0]):
        turning_point_update(state, u[k], fs)
        f_out[k] = state[TP_F]
        a_out[k] = state[TP_A]


@njit(cache=True)
def fractional_delay(u: np.ndarray, delay_samples: float, first: float, out: np.ndarray) -> None:
    """u delayed by a (fractional) number of samples, linear interpolation; before the start: first."""
    d_int = int(math.floor(delay_samples))
    frac = delay_samples - d_int
    for k in range(u.shape[0]):
        i0 = k - d_int
        a = u[i0] if i0 >= 0 else first
        b = u[i0 - 1] if i0 - 1 >= 0 else first
        out[k] = (1.0 - frac) * a + frac * b


@njit(cache=True)
def filter_columns(b: np.ndarray, a: np.ndarray, x: np.ndarray, zi: np.ndarray) -> np.ndarray:
    """Filter every column of x (n, p) with the IIR (b, a), a[0] = 1, direct form II transposed.

    ``zi`` (order, p) is the initial filter state of each column (scipy.signal.lfilter convention);
    one pass over the rows keeps the memory access sequential (scipy filters column by column).
    """
    n, p = x.shape
    order = zi.shape[0]
    y = np.empty_like(x)
    z = zi.copy()
    for k in range(n):
        for j in range(p):
            xk = x[k, j]
            yk = b[0] * xk + z[0, j]
            for i in range(order - 1):
                z[i, j] = b[i + 1] * xk + z[i + 1, j] - a[i + 1] * yk
            z[order - 1, j] = b[order] * xk - a[order] * yk
            y[k, j] = yk
    return y


@njit(cache=True)
def delay_rows(x: np.ndarray, delay_samples: float) -> np.ndarray:
    """Rows of x (n, p) delayed by a fractional number of samples (linear interpolation);
    before the start the first row is held."""
    n, p = x.shape
    d_int = int(math.floor(delay_samples))
    frac = delay_samples - d_int
    out = np.empty_like(x)
    for k in range(n):
        i0 = max(k - d_int, 0)
        i1 = max(k - d_int - 1, 0)
        for j in range(p):
            out[k, j] = (1.0 - frac) * x[i0, j] + frac * x[i1, j]
    return out



@njit(cache=True)
def delay_gather(x: np.ndarray, rows: np.ndarray, delay_samples: float) -> np.ndarray:
    """``delay_rows(x, d)[rows]`` without delaying the rows that are not wanted."""
    p = x.shape[1]
    d_int = int(math.floor(delay_samples))
    frac = delay_samples - d_int
    out = np.empty((rows.shape[0], p))
    for r in range(rows.shape[0]):
        k = rows[r]
        i0 = max(k - d_int, 0)
        i1 = max(k - d_int - 1, 0)
        for j in range(p):
            out[r, j] = (1.0 - frac) * x[i0, j] + frac * x[i1, j]
    return out
