"""Validation rows within training's input reach: the second look when every row says nothing.

A test run that drives past training's input range leaves the model extrapolating: past the range
the play operators have no identified thresholds and no memoryless term was fitted. After the
excursion the hysteresis memory holds a turning point training never produced, and it stays until
the input comes back to the range's opposite end, which wipes it out of every operator (the
wiping-out property of Preisach and play hysteresis). Every model carries that bias over those rows,
the truth's form included (decision 0055: on a logarithmic creep under a play base, 0.36-0.48 um
over the last half of the test run, where the creep had lowered the error 7x before the excursion).

:func:`within_reach` marks the rows outside that envelope: from the first sample beyond training's
range widened by REACH_ENVELOPE of its span, until the input comes back within REACH_ENVELOPE of
the range's opposite end. :func:`restricted` gives a fit result whose validation rows are only
those, with its validation metrics recomputed, for :func:`hilbench.diagnosis.verdict.verdict` to
judge a refit on.

Decision 0055 measured leaving those rows out of every verdict: it gained as many cases as it
lost, since the rows past the range also carry the strongest evidence of effects that act at large
drives. Decision 0071 keeps every row's verdict first and takes this one only when every row's
verdict found nothing: it cannot then take a finding away, only let the bias stop hiding one.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from hilbench.diagnosis import thresholds as T
from hilbench.identify.dataset import FitRun
from hilbench.identify.fitting import FitResult
from hilbench.identify.metrics import metrics


def training_range(result: FitResult) -> tuple[float, float] | None:
    """The smallest and largest input of the training rows (input unit), None without any."""
    parts = [r.data.input[r.train] for r in result.runs if r.train.any()]
    if not parts:
        return None
    u = np.concatenate(parts)
    return float(np.min(u)), float(np.max(u))


def _latched(set_rows: np.ndarray, reset_rows: np.ndarray) -> np.ndarray:
    """Per row, whether the latest of the set and reset events up to it is a set (a set and a
    reset on the same row count as set): a latch, vectorized."""
    n = set_rows.size
    idx = np.arange(n)
    last_set = np.maximum.accumulate(np.where(set_rows, idx, -1))
    last_reset = np.maximum.accumulate(np.where(reset_rows & ~set_rows, idx, -1))
    return (last_set >= 0) & (last_set > last_reset)


def outside_envelope(u: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Rows of a run's input ``u`` (in time order) beyond [lo, hi] widened by REACH_ENVELOPE of its
    span, and the rows after such an excursion until the input comes back within REACH_ENVELOPE of
    the range's opposite end (module docstring)."""
    u = np.asarray(u, float)
    margin = T.REACH_ENVELOPE * max(hi - lo, 0.0)
    above = _latched(u > hi + margin, u < lo + margin)
    below = _latched(u < lo - margin, u > hi - margin)
    return above | below


@dataclasses.dataclass(frozen=True)
class Reach:
    """Which validation rows lie within training's reach, per run (masks over each run's rows)."""

    keep: list[np.ndarray]  # per run: validation rows within the envelope
    left_out: int  # validation rows left out
    validation: int  # validation rows in all
    lo: float
    hi: float

    @property
    def applies(self) -> bool:
        """Rows are left out and enough remain to judge on (REACH_MIN_KEPT of validation's)."""
        kept = self.validation - self.left_out
        return self.left_out > 0 and kept >= T.REACH_MIN_KEPT * self.validation

    def note(self, unit: str = "") -> str:
        u = f" {unit}" if unit else ""
        return (f"{self.left_out} of {self.validation} validation rows drive beyond training's input range "
                f"({self.lo:.4g} to {self.hi:.4g}{u}, widened by {100 * T.REACH_ENVELOPE:g} %) or carry the "
                "hysteresis memory of such an excursion; effects judged again without them, since none was "
                "significant on every validation row")


def within_reach(result: FitResult) -> Reach | None:
    """The validation rows of ``result`` within training's input reach (module docstring); None
    when there is no training or no validation row."""
    span = training_range(result)
    if span is None:
        return None
    lo, hi = span
    keep, left, total = [], 0, 0
    for r in result.runs:
        valid = r.validation & np.isfinite(r.data.output)
        inside = valid & ~outside_envelope(r.data.input, lo, hi) if valid.any() else valid
        keep.append(inside)
        left += int(valid.sum() - inside.sum())
        total += int(valid.sum())
    if total == 0:
        return None
    return Reach(keep, left, total, lo, hi)


def restricted(result: FitResult, reach: Reach) -> FitResult:
    """``result`` with only the validation rows within reach, its validation metrics recomputed
    (the runs' simulations and training rows unchanged; a shallow copy, the original untouched)."""
    runs: list[FitRun] = []
    for r, keep in zip(result.runs, reach.keep):
        run = dataclasses.replace(r, validation=r.validation & keep)
        if run.simulated is not None and run.simulated.size and run.validation.any():
            run.metrics = {**r.metrics, "validation": metrics(r.data.output[run.validation],
                                                              run.simulated[run.validation])}
        runs.append(run)
    parts = [(r.data.output[r.validation], r.simulated[r.validation]) for r in runs
             if r.validation.any() and r.simulated is not None and r.simulated.size]
    measured = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0)
    simulated = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0)
    return dataclasses.replace(result, runs=runs, metrics={**result.metrics,
                                                             "validation": metrics(measured, simulated)})
