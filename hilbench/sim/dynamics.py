"""Discretisation of the linear dynamics of a rig's [plant.dynamics] table."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from hilbench.errors import ConfigError


def discretize_dynamics(d: dict[str, Any], sample_rate_hz: float, method: str = "zoh") -> tuple[np.ndarray, np.ndarray]:
    """Discrete (b, a) of the dynamics table, a[0] = 1; continuous forms by ``method``.

    Zero-order hold (the plant: a DAC holds each command) or first-order hold (the models: same
    poles, but a static gain maps to itself, so very fast dynamics reduce to none).
    """
    if d["kind"] == "discrete":
        b = np.asarray(d["b"], float)
        a = np.asarray(d["a"], float)
        if a.size == 0 or a[0] == 0:
            raise ConfigError("[plant.dynamics] a: expected a[0] != 0")
    else:
        if d["kind"] == "second-order":
            wn = 2 * math.pi * d["natural_frequency_hz"]
            num = [d["gain"] * wn**2]
            den = [1.0, 2 * d["zeta"] * wn, wn**2]
        else:
            num, den = list(d["num"]), list(d["den"])
            if len(num) > len(den):
                raise ConfigError("[plant.dynamics] transfer-function must be proper (len(num) <= len(den))")
        from scipy import signal as sps  # imported here: scipy.signal costs ~1.5 s and ~60 MB

        bd, ad, _ = sps.cont2discrete((num, den), 1.0 / sample_rate_hz, method=method)
        b = np.asarray(bd, float).ravel()
        a = np.asarray(ad, float).ravel()
    b, a = b / a[0], a / a[0]
    n = max(len(a), len(b))
    b = np.pad(b, (0, n - len(b)))
    a = np.pad(a, (0, n - len(a)))
    if n > 1 and np.any(np.abs(np.roots(a)) >= 1.0):
        raise ConfigError(
            f"[plant.dynamics] the discrete dynamics are unstable at {sample_rate_hz:g} Hz "
            f"(pole magnitudes {np.round(np.abs(np.roots(a)), 4).tolist()}); expected all poles inside the unit circle"
        )
    return b, a
