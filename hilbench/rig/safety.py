"""The rig's one actuator path: clamp to the limits, slew-limit, and say what was really applied.

Every command of every backend passes through :func:`command_path` (DESIGN.md, "Safety"); the rig
records its output as the ``input`` channel. NaN commands hold the last applied value rather than
pass garbage to an amplifier.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


# Compiled eagerly, at import, for the one signature every caller uses (C-contiguous float64 arrays,
# float limits): the fixed-rate loop's first sample calls it, and a lazy compile (or even a load from
# numba's cache) there took 0.26 s on an idle machine and over 2 s on a loaded one, which tripped the
# watchdog before sample 1.
@njit("int64(float64[::1], float64, float64, float64, float64[::1], float64[::1])", cache=True)
def command_path(
    command: np.ndarray, lo: float, hi: float, max_step: float, state: np.ndarray, out: np.ndarray
) -> int:
    """The rig's single actuator path: clamp to [lo, hi], then slew-limit to max_step per sample.

    ``state[0]`` is the last applied value. Returns how many samples had to be changed, so the
    caller can say so; ``out`` receives what was really applied.
    """
    last = state[0]
    changed = 0
    for n in range(command.shape[0]):
        x = command[n]
        if x != x:  # NaN: hold the last value rather than pass garbage to the amplifier
            x = last
        c = min(max(x, lo), hi)
        c = min(max(c, last - max_step), last + max_step)
        if c != command[n]:
            changed += 1
        out[n] = c
        last = c
    state[0] = last
    return changed


def ramp(start: float, target: float, max_step: float) -> np.ndarray:
    """Commands from ``start`` (excluded) to ``target`` (included) at most ``max_step`` apart.

    "At most" is checked as :func:`command_path` checks it, in floating point: linspace's rounding
    can put a step one ulp past ``max_step``, the slew limiter would then clip it and the ramp would
    end an ulp beside ``target`` (a ramp to rest ending at -2.8e-16 instead of 0). One more sample
    makes every step pass.
    """
    distance = abs(target - start)
    if not distance > 0:
        return np.empty(0)
    n = int(math.ceil(distance / max_step))
    for _ in range(8):
        points = np.linspace(start, target, n + 1)
        before, after = points[:-1], points[1:]
        if np.all((after >= before - max_step) & (after <= before + max_step)):
            break
        n += 1
    return points[1:]
