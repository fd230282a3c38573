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
    "lowpass_block",
    "turning_point_frequency",
    "N_TP",
    "fractional_delay",
]


@njit(cache=True)
def bouc_wen_block(u: np.ndarray, beta: float, gamma: float, n: float, state: np.ndarray, out: np.ndarray) -> None:
    """Bouc-Wen state z with unit A: dz = du - beta |du| |z|^(n-1) z - gamma du |z|^n.

    Integrated over the input (rate independent) with the midpoint rule in 8 sub-steps per sample;
    ``state = [z, u_prev]``. The model output scales z by A, which is therefore a linear weight.
    """
    z = state[0]
    u_prev = state[1]
    for k in range(u.shape[0]):
        du = (u[k] - u_prev) / 8.0
        if du != 0.0:
            adu = abs(du)
            for _ in range(8):
                az = abs(z)
                f1 = du - beta * adu * (az ** (n - 1.0)) * z - gamma * du * az**n
                zm = z + 0.5 * f1
                azm = abs(zm)
                f2 = du - beta * adu * (azm ** (n - 1.0)) * zm - gamma * du * azm**n
                z = z + f2
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
def turning_point_frequency(u: np.ndarray, fs: float, state: np.ndarray, f_out: np.ndarray, a_out: np.ndarray) -> None:
    """Drive frequency (Hz) and amplitude from the last half cycle between turning points.

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
