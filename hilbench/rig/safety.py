"""The rig's one actuator path: clamp to the limits, slew-limit, and say what was really applied.

Every command of every backend passes through :func:`command_path` (DESIGN.md, "Safety"); the rig
records its output as the ``input`` channel. NaN commands hold the last applied value rather than
pass garbage to an amplifier.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
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
    """Commands from ``start`` (excluded) to ``target`` (included) at most ``max_step`` apart."""
    distance = abs(target - start)
    n = int(math.ceil(distance / max_step)) if distance > 0 else 0
    return np.linspace(start, target, n + 1)[1:]
