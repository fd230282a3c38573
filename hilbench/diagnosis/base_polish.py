"""The base's own optimum first: an effect is credited only with what the base cannot do alone.

A refit with one more effect runs a local search over every shape parameter, the base's included,
from the fitted base. When the base's fit had stopped at a poor local optimum, that search can
move the base's shape to a better one, and the effect gets the credit for it: on a clean case
with a PMPI base, for example, saturation and dynamics each lowered the validation
rmse 51 %, and the PMPI base alone, started from either refit's shape, lowered it exactly as much
(training 0.995 -> 0.860, validation 1.78 -> 0.866), with the dynamics parked above Nyquist.

So after the single effects are fitted, the base is refitted from the shape of each significant
candidate (and of each that a second block test may still make significant, decision 0052); if one of these fits the training rows better than the base by more than
POLISH_MIN_TRAIN_GAIN, it becomes the base the candidates are judged against (chosen on training
rows only, so the validation comparison stays fair). Docs: docs/decisions/0024.

The same holds between the candidates: a base with a free loop shape (PMPI's etas) has near-equal
optima, and each refit settles in one. After the polish every significant candidate is refitted
from the base shape of the one that fits the training rows best, and kept when that fits its own
training rows better (:func:`shared_base_shape`, decision 0075).
"""

from __future__ import annotations

from functools import partial
from typing import Any

from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.replication import needs_replication
from hilbench.diagnosis.verdict import Candidate, relative_gain, verdict
from hilbench.diagnosis.workers import run_tasks
from hilbench.identify.dataset import Dataset
from hilbench.identify.fitting import FitResult, fit


def polished_base(paths: Dataset, base: FitResult, cands: list[Candidate], kw: dict[str, Any],
                  jobs: int = 1) -> FitResult | None:
    """The base spec refitted from the best significant candidate's shape, when that fits the
    training rows better than ``base`` by more than POLISH_MIN_TRAIN_GAIN; else None. The refits
    run in up to ``jobs`` processes (:mod:`hilbench.diagnosis.workers`)."""
    # a candidate the held-back training rows may still make significant (decision 0052) could
    # owe its gain to the base's poor optimum just as well (on a clean PMPI case a saturation
    # validated 50 % lower at block p 0.014, and its held-back rows confirmed the base's better optimum)
    starts = [c.fitted.model for c in cands if (c.significant or needs_replication(c)) and c.fitted is not None]
    refits = run_tasks([partial(fit, paths, base.spec, start_from=m, **kw) for m in starts], jobs, shared=paths.runs)
    best: FitResult | None = None
    for refit in refits:
        if best is None or refit.metrics["train"]["rmse"] < best.metrics["train"]["rmse"]:
            best = refit
    old_t = base.metrics["train"]["rmse"]
    if best is None or relative_gain(old_t, best.metrics["train"]["rmse"]) <= T.POLISH_MIN_TRAIN_GAIN:
        return None
    return best


def _base_shape(model: Any) -> dict[str, float]:
    """The searched shape parameters of a model's hysteresis base (PMPI's etas, Duhem's, Bouc-Wen's)."""
    return {p.name: float(p.value) for p in model.base.shape() if p.upper > p.lower}


def shared_base_shape(paths: Dataset, base: FitResult, cands: list[Candidate], rows: Any, noise: float,
                      kw: dict[str, Any], plans: dict[str, Any], jobs: int = 1) -> list[Candidate]:
    """The significant candidates, each refitted from the base shape of the one that fits the
    training rows best, and judged again when that start fits its own training rows better by more
    than POLISH_MIN_TRAIN_GAIN (decision 0075).

    A base with a free loop shape has near-equal optima, and each refit's search settles in one of
    them: the shape belongs to the base, not to the effect, so an optimum one refit found is open to
    every other. Without it the leaders are compared on different bases as much as on their
    effects (for example a sensor delay of 1.45 samples under ``pmpi``: the delay's refit
    stopped at training 0.0119 um and validated 0.0120, the lag's at 0.0058 and 0.0065; the delay
    started from the lag's etas trains at 0.0058 and validates at 0.0065 too). Chosen on training
    rows only, so the validation comparison stays fair."""
    if not _base_shape(base.model):
        return cands
    judged = [c for c in cands if c.significant and c.fitted is not None]
    if len(judged) < 2:
        return cands
    donor = min(judged, key=lambda c: c.fitted.metrics["train"]["rmse"])
    shape = _base_shape(donor.fitted.model)
    best_t = donor.fitted.metrics["train"]["rmse"]
    takers = [c for c in judged if c is not donor and _base_shape(c.fitted.model) != shape
              and relative_gain(c.fitted.metrics["train"]["rmse"], best_t) > T.POLISH_MIN_TRAIN_GAIN]
    refits = run_tasks([partial(fit, paths, c.fitted.spec, start_from=donor.fitted.model, **kw) for c in takers],
                       jobs, shared=paths.runs)
    again: dict[int, Candidate] = {}
    for c, refit in zip(takers, refits):
        old_t, new_t = c.fitted.metrics["train"]["rmse"], refit.metrics["train"]["rmse"]
        if relative_gain(old_t, new_t) <= T.POLISH_MIN_TRAIN_GAIN:
            continue
        new = verdict(base, c.effect, refit, rows, noise, plans.get(c.effect))
        new.evidence["shared_base_shape"] = {"from": donor.effect, "train_rmse": [old_t, new_t]}
        new.explanation += (f"; refitted from {donor.effect}'s base shape, which fits its training rows better "
                            f"({old_t:.4g} -> {new_t:.4g})")
        again[id(c)] = new
    return [again.get(id(c), c) for c in cands]
