"""Feedback in the output domain for the compensators: a PID on the displacement error (um), with
the closed loop's characteristic polynomial so that gains that destabilise the declared dynamics
are refused before the loop starts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PID:
    """Feedback in the output domain (um in, um out): ``kp`` (1), ``ki`` (1/s), ``kd`` (s),
    derivative filter ``tf_s`` (s; default 4 sample periods), integrator clamp ``i_limit`` (um;
    default: the reference's span). ``reversal_guard`` (on by default): the command never moves
    against the reference's direction, so feedback adds no reversals (see
    :func:`hilbench.online.inverse_kernels.comp_step`, decision 0080).

    The defaults (kp 0.2, ki 300 1/s) suit the piezo-pmpi stage only; ``Compensator(feedback=True)``
    designs gains from the identified loop (:mod:`hilbench.online.feedback_design`)."""

    kp: float = 0.2
    ki: float = 300.0
    kd: float = 0.0
    tf_s: float | None = None
    i_limit: float | None = None
    reversal_guard: bool = True

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
