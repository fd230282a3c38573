"""Checks of the arrays handed to the identification methods: one-line errors naming the argument."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hilbench.errors import UserError


# ------------------------------------------------------------------------------------------------
# input checks
# ------------------------------------------------------------------------------------------------
def as_1d(x: Any, name: str) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        raise UserError(f"{name}: expected an array of numbers") from None
    if a.ndim != 1:
        raise UserError(f"{name}: expected a 1-D array, got shape {a.shape}")
    return a


def same_length(**arrays: np.ndarray) -> int:
    lengths = {k: v.shape[0] for k, v in arrays.items()}
    if len(set(lengths.values())) > 1:
        text = ", ".join(f"{k} has {n}" for k, n in lengths.items())
        raise UserError(f"the arrays must have the same length: {text} samples")
    return next(iter(lengths.values()))


def require_finite(x: np.ndarray, name: str) -> None:
    if not np.all(np.isfinite(x)):
        bad = int(np.sum(~np.isfinite(x)))
        raise UserError(f"{name}: {bad} samples are NaN or infinite (sensor out of range?); cut them out first")


def require_positive(value: float, name: str) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise UserError(f"{name}: expected a positive number, got {value!r}")
    return value
