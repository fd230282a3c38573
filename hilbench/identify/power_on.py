"""The power-on step at the start of a capture, read as a step response: dead time and ringing.

Measured captures often start the moment the rig is switched on: the command is already at its first
level in the first sample (the controller starts output and recording together), while the output
still sits where the sensor was zeroed and then moves to the new level with the actuator's own
transient (piezo-dspace-preisach: -90 V from the first sample, the output at 0 um, moving from the
third sample, ringing at ~710 Hz and settling at -3.4 um within 50 ms). The input does not show the
step, so the model cannot use these rows (:mod:`hilbench.identify.trimming` leaves them out), but they
are a clean step response: the only place in a capture driven at one rate where the *dead time*
shows apart from the loop width (at one drive frequency a delay and a wider loop look alike).

:func:`power_on_step` fits a second-order-plus-dead-time response to the first rise of the transient,
from the record start (taken as the step time) to a little past the first extremum: the dead time
is the time from the record start to the response's onset. The step may have come before the first
sample, never after (the output would not have moved yet at the onset), so the value is a lower
bound of the true dead time; the fit's R^2 and residual say how well the shape holds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import optimize

from hilbench.identify.statistics import difference_noise_std
from hilbench.identify.step_response import second_order_step

#: the response must move by this many sensor-noise sigmas to count as a step
MIN_STEP_SIGMAS = 20.0
#: samples fitted past the first extremum, as a multiple of the samples up to it (the shape of the
#: rise and the first peak fix dead time and ringing; later ringing adds amplitude-dependent effects)
PAST_PEAK = 1.0
#: a fit explaining less of the rise than this is no step response
MIN_R2 = 0.95


@dataclass
class PowerOnStep:
    """A second-order-plus-dead-time fit to a capture's power-on transient (times in s from the
    record start; the output's unit)."""

    dead_time_s: float
    natural_frequency_hz: float
    zeta: float
    y0: float  # output before the response
    y_settled: float  # where the rest settles
    r2: float  # of the normalised rise
    samples: int  # fitted

    def to_json(self) -> dict[str, Any]:
        return {k: float(v) if isinstance(v, float) else v for k, v in self.__dict__.items()}


def power_on_step(y: np.ndarray, sample_rate_hz: float, rest: int, max_dead_time_s: float = 0.005) -> PowerOnStep | None:
    """The power-on step response in the first ``rest`` samples of ``y`` (the input holding its
    first value there), or None when the rest holds no clean step: the output barely moves, starts
    moving from the first sample (no baseline), or the fit explains less than MIN_R2 of the rise."""
    if rest < 32:
        return None
    y = np.asarray(y[:rest], dtype=np.float64)
    if not np.isfinite(y).all():
        return None
    settled_part = y[rest // 2:]
    y_ss = float(np.median(settled_part))
    noise = difference_noise_std(np.diff(settled_part, 4), order=4)
    y0 = float(y[0])
    step = y_ss - y0
    if not abs(step) > MIN_STEP_SIGMAS * max(noise, 1e-12 * abs(step)):
        return None
    r = (y - y0) / step
    # the first extremum after the rise passes half the step (the peak of the ringing, or the end of
    # an overdamped rise: where it stops growing)
    above = np.flatnonzero(r > 0.5)
    if above.size == 0 or above[0] < 1:
        return None
    k = int(above[0])
    while k + 1 < rest and r[k + 1] >= r[k]:
        k += 1
    n = min(rest, k + 1 + max(4, int(PAST_PEAK * (k + 1))))
    t = np.arange(n) / sample_rate_hz
    rr = r[:n]
    t_half = above[0] / sample_rate_hz  # the rise's half-way time bounds the dead time and sets wn's scale

    def resid(p: np.ndarray) -> np.ndarray:
        return p[3] * second_order_step(t - p[0], p[1], p[2]) - rr

    best = None
    hi_td = min(max_dead_time_s, t_half)
    for frac in (0.2, 0.5, 0.8):  # starts spread over the admissible dead times: the fit is local
        wn0 = 2.0 / max(t_half * (1.0 - frac), 1.0 / sample_rate_hz)
        x0 = [frac * hi_td, 0.3, min(wn0, 0.9 * math.pi * sample_rate_hz), 1.0]
        try:
            res = optimize.least_squares(resid, x0, bounds=([0.0, 0.005, 1e-3, 0.2],
                                                            [hi_td, 5.0, math.pi * sample_rate_hz, 5.0]))
        except ValueError:
            continue
        if res.success and (best is None or res.cost < best.cost):
            best = res
    if best is None:
        return None
    ss_tot = float(np.sum((rr - rr.mean()) ** 2))
    r2 = 1.0 - 2.0 * best.cost / ss_tot if ss_tot > 0 else 0.0
    if r2 < MIN_R2:
        return None
    td, zeta, wn, _ = (float(v) for v in best.x)
    return PowerOnStep(td, wn / (2 * math.pi), zeta, y0, y_ss, r2, n)


__all__ = ["PowerOnStep", "power_on_step"]
