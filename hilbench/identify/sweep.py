"""A run that sweeps its drive frequency, and a split of it that trains on rates across the span.

The default split trains on the first part of every run and validates on the rest. On a run whose
drive frequency sweeps (a chirp, or a staircase of rates recorded as one run) that leaves the
highest (or lowest) rates to validation alone: every rate effect is then judged on extrapolation
only, and a model that is right about rates looks wrong (issue 11, item 3c). Such a run is split
into interleaved blocks instead, so training and validation both see rates across the span.

Drive frequency: reversals of the input found with a dead band of REVERSAL_BAND of its span (a
measured input's noise does not make reversals), one frequency per half cycle.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: the input must move back this fraction of its span from its last extreme to count as a reversal
REVERSAL_BAND = 0.05
#: validation rates beyond the training's by this ratio make the run a sweep (as the diagnosis
#: groups rates: closer than 1.5x count as one rate)
SWEEP_RATIO = 1.5
#: interleaved blocks of a swept run
BLOCKS = 10


@njit(cache=True)
def _reversals(u: np.ndarray, band: float, out: np.ndarray) -> int:
    """Indices of the input's extremes (Schmitt trigger with ``band``) into ``out``; their count."""
    count = 0
    direction = 0
    ext = u[0]
    ext_i = 0
    for k in range(1, u.shape[0]):
        x = u[k]
        if direction == 0:  # until the input has left its start by the band
            if abs(x - u[0]) > band:
                direction = 1 if x > u[0] else -1
                ext, ext_i = x, k
        elif direction > 0:
            if x > ext:
                ext, ext_i = x, k
            elif x < ext - band:
                out[count] = ext_i
                count += 1
                direction, ext, ext_i = -1, x, k
        else:
            if x < ext:
                ext, ext_i = x, k
            elif x > ext + band:
                out[count] = ext_i
                count += 1
                direction, ext, ext_i = 1, x, k
    return count


def half_cycles(u: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """(index of the middle of every half cycle, its drive frequency in Hz)."""
    u = np.ascontiguousarray(u, dtype=np.float64)
    finite = np.isfinite(u)
    if u.size < 4 or not finite.all():
        u = np.where(finite, u, np.nanmedian(u) if finite.any() else 0.0)
    span = float(np.ptp(u)) if u.size else 0.0
    if span <= 0.0:
        return np.zeros(0, int), np.zeros(0)
    out = np.empty(u.size, np.int64)
    n = _reversals(u, REVERSAL_BAND * span, out)
    ext = out[:n]
    if ext.size < 2:
        return np.zeros(0, int), np.zeros(0)
    return (ext[1:] + ext[:-1]) // 2, fs / (2.0 * np.diff(ext))


def reversals(u: np.ndarray, span: float) -> int:
    """How many times the input ``u`` turns (Schmitt trigger with a band of REVERSAL_BAND of ``span``,
    the input unit): two turns close a loop. Non-finite samples are left out."""
    u = np.ascontiguousarray(u[np.isfinite(u)], dtype=np.float64)
    if u.size < 3 or not span > 0.0:
        return 0
    out = np.empty(u.size, np.int64)
    return int(_reversals(u, REVERSAL_BAND * span, out))


def sweeps_past_split(u: np.ndarray, fs: float, train: np.ndarray, validation: np.ndarray) -> tuple[float, float] | None:
    """(lowest, highest) drive frequency of the run when its validation rows reach rates SWEEP_RATIO
    beyond those of its training rows, else None."""
    mid, f = half_cycles(u, fs)
    if f.size < 4:
        return None
    f_train, f_val = f[train[mid]], f[validation[mid]]
    if f_train.size < 2 or f_val.size < 1:
        return None
    beyond = f_val.max() >= SWEEP_RATIO * f_train.max() or f_val.min() * SWEEP_RATIO <= f_train.min()
    return (float(f.min()), float(f.max())) if beyond else None


def validation_blocks(train_fraction: float, blocks: int = BLOCKS) -> int:
    """How many of the interleaved blocks validate: the nearest count to the validation fraction."""
    return int(round((1.0 - train_fraction) * blocks))


def interleaved(kept: np.ndarray, train_fraction: float, blocks: int = BLOCKS) -> tuple[np.ndarray, np.ndarray]:
    """Train and validation masks: the kept rows in ``blocks`` equal blocks, of which
    :func:`validation_blocks` validate, spread evenly (never the first: the model's memory starts there)."""
    rows = np.flatnonzero(kept)
    n_val = validation_blocks(train_fraction, blocks)
    train = kept.copy()
    validation = np.zeros_like(kept)
    if rows.size < blocks or n_val <= 0:
        return train, validation
    edges = np.linspace(0, rows.size, blocks + 1).astype(int)
    picks = {min(blocks - 1, int((j + 1) * blocks / (n_val + 1) + 0.5)) for j in range(n_val)}
    for b in sorted(picks):
        sel = rows[edges[b]:edges[b + 1]]
        validation[sel] = True
        train[sel] = False
    return train, validation


__all__ = ["half_cycles", "interleaved", "reversals", "sweeps_past_split", "validation_blocks"]
