"""The residual rows the diagnosis reasons on: model minus measured with what statistics need.

Rows are the samples of every run (validation rows, or all rows for evidence), concatenated, with
the input's motion (rate, direction, time since it last changed), the measured output's smoothed
derivatives and the auxiliary channels. Units: the input's unit, the output's unit, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilbench.diagnosis.input_motion import motion
from hilbench.diagnosis.noise import residual_noise_floor, sensor_noise
from hilbench.errors import UserError
from hilbench.identify.dataset import FitRun
from hilbench.identify.fitting import FitResult


@dataclass
class ResidualRows:
    """Validation rows of every run, concatenated, with what the statistics need."""

    e: np.ndarray  # model - measured
    u: np.ndarray
    du: np.ndarray  # input rate, input unit / s
    y: np.ndarray  # measured
    dy: np.ndarray
    d2y: np.ndarray
    since: np.ndarray  # time since the input last changed (s), inf-free
    direction: np.ndarray  # "rising", "falling", "turning", "hold"
    run: np.ndarray  # run index
    t: np.ndarray  # time in the run (s)
    aux: dict[str, np.ndarray]
    keys: list[str]


def smooth(x: np.ndarray, k: int) -> np.ndarray:
    if k <= 1 or x.size < k:
        return x
    return np.convolve(x, np.ones(k) / k, mode="same")


def _rows_of(run: FitRun, rows: str) -> np.ndarray | None:
    """The mask of a run's rows that :func:`residual_rows` takes (``rows``: "validation" or "all"),
    or None for a run that gives none."""
    m = (run.validation if rows == "validation" else run.validation | run.train) & np.isfinite(run.data.output)
    if not m.any() or run.simulated is None or run.simulated.size == 0:
        return None
    return m


def residual_errors(result: FitResult, rows: str = "validation") -> np.ndarray:
    """The ``e`` of :func:`residual_rows` alone (the same rows in the same order, model - measured),
    without the input's motion and the output's derivatives: a refit's residual on a base's rows."""
    masks = [(r, _rows_of(r, rows)) for r in result.runs]
    return np.concatenate([(r.simulated - r.data.output)[m] for r, m in masks if m is not None] or [np.zeros(0)])


def residual_rows(result: FitResult, rows: str = "validation") -> ResidualRows:
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("e", "u", "du", "y", "dy", "d2y", "since", "direction",
                                                             "run", "t")}
    aux: dict[str, list[np.ndarray]] = {}
    span = max(float(np.ptp(np.concatenate([r.data.input for r in result.runs if len(r.data)]))), 1e-12)
    common = None
    for r in result.runs:
        if len(r.data):
            common = set(r.data.aux) if common is None else common & set(r.data.aux)
    keys = []
    for k, r in enumerate(result.runs):
        m = _rows_of(r, rows)
        if m is None:
            continue
        fs = r.data.sample_rate_hz
        sig = motion(r.data.input, fs, span)
        y = r.data.output
        ys = smooth(np.nan_to_num(y), max(int(fs / 200), 1))
        dy = np.gradient(ys) * fs
        d2y = np.gradient(smooth(dy, max(int(fs / 200), 1))) * fs
        parts["e"].append((r.simulated - y)[m])
        parts["u"].append(r.data.input[m])
        parts["du"].append(sig["du"][m])
        parts["y"].append(y[m])
        parts["dy"].append(dy[m])
        parts["d2y"].append(d2y[m])
        parts["since"].append(sig["since"][m])
        parts["direction"].append(sig["direction"][m])
        parts["run"].append(np.full(int(m.sum()), len(keys)))
        parts["t"].append(np.arange(len(r.data))[m] / fs)
        for c in common or ():
            aux.setdefault(c, []).append(r.data.aux[c][m])
        keys.append(r.key)
    if not keys:
        raise UserError("no validation rows: name runs with --test, or use a training fraction below 1")
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    return ResidualRows(**cat, aux={c: np.concatenate(v) for c, v in aux.items()}, keys=keys)


def noise_floor(rows: ResidualRows | np.ndarray, run: np.ndarray | None = None) -> float:
    """The sensor's noise floor, output unit: on residual ``rows``, estimated from the measured output
    itself (:func:`hilbench.diagnosis.noise.sensor_noise`, a :class:`~hilbench.diagnosis.noise.NoiseFloor`
    whose ``estimates`` also hold the old residual-based one under ``"residual"``).

    ``noise_floor(e, run)`` on bare arrays is that old estimate: the robust std of the residual's
    sample-to-sample differences, which fast model error inflates (kept for comparison)."""
    if not isinstance(rows, ResidualRows):
        return residual_noise_floor(np.asarray(rows), np.asarray(run))
    floor = sensor_noise(rows.y, rows.run, rows.t, rows.direction == "hold", rows.since)
    floor.estimates["residual"] = residual_noise_floor(rows.e, rows.run)
    return floor
