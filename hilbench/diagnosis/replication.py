"""A second, independent block test on held-back training rows, for gains the validation rows are
too short to confirm alone (decision 0052).

The block tests (:mod:`hilbench.diagnosis.significance`) refer the validation gain to random sign
flips of contiguous blocks, so their p-value cannot fall below 2**-k when the gain sits in k
independent stretches: a velocity damping at the 5 steps of a test run reaches p = 0.03 at best
(2**-5, however large the gain: validation 51 % lower, training 71 %, in one such case), a creep
or a temperature drift on a record a few correlation lengths long fills 20 blocks that are barely
independent (p 0.07 and 0.03 for two such drifts, validation 14 % and 12 % lower). The validation
rows are then too short to tell, not the effect too weak.

The training rows hold more of the same evidence, but the refit saw them. So a candidate that failed
the block test only, at a validation p below ``sqrt(P_MAX)``, is refitted together with the base on
training without one of REPLICATION_FOLDS folds of it, and the same block tests compare the two inner
fits on the rows each fold held back (cross-validation, decision 0056). The folds are the interleaved
blocks of :func:`hilbench.identify.sweep.interleaved` (BLOCKS of them; never the first, where the
model's memory starts), so every training row but the first block's is held back once: evidence
that sits in a few stretches of training (the steps of a staircase, where a sub-sample sensor delay
shows) is in the test wherever the stretches fall. One fold of two blocks held back missed them
(a 0.8-sample sensor delay: 3 % lower on its held-back rows, 60 % on all folds' together). Neither inner
fit of a fold saw its rows, and they are not validation rows: under no effect
the two p-values are independent and uniform, so the chance that both fall below ``sqrt(P_MAX)`` is
P_MAX. The joint p-value ``max(p_validation, p_held_back)**2`` replaces the block test's p, and the
check ``blocks_p_below_0.01`` keeps its meaning: the gain is not chance at the 1 % level. The
held-back rows must also show a gain over MIN_GAIN (``held_back_gain_over_10pct``), as validation
must: a real but small improvement is a base family slightly off the plant's, bent a little closer. Requiring
both (rather than combining them, e.g. by Fisher's method) keeps the user's validation rows a judge:
a gain on training rows alone, however clear, does not make a candidate significant.

Only candidates that failed the block test alone are refitted, so the cost falls on the few cases it
can change: every other check (the gain, the agreement of training and validation, the error above
the sensor noise, the pair's margin) must already hold.
"""

from __future__ import annotations

import math
from dataclasses import replace
from functools import partial
from typing import Any

import numpy as np

from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.significance import BlockTests, block_tests
from hilbench.diagnosis.verdict import Candidate, relative_gain
from hilbench.diagnosis.workers import run_tasks
from hilbench.identify.dataset import Dataset, as_dataset
from hilbench.identify.fitting import FitResult, assign_roles, fit
from hilbench.identify.sweep import BLOCKS

#: the check the replication may settle (verdict.py names it)
BLOCK_CHECK = "blocks_p_below_0.01"
#: the check the replication adds: the held-back rows' rmse falls by more than MIN_GAIN too
HELD_BACK_CHECK = "held_back_gain_over_10pct"
#: the folds of the cross-validation over the training rows: each holds back about 1 - INNER_SPLIT
#: of them (two of the BLOCKS interleaved blocks), as one held-back fold did before (decision 0056)
REPLICATION_FOLDS = round(1.0 / (1.0 - T.INNER_SPLIT))


def replication_level() -> float:
    """The p each of the two independent block tests must reach: their joint level is P_MAX."""
    return math.sqrt(T.P_MAX)


def needs_replication(c: Candidate) -> bool:
    """Failed the block test and nothing else, at a validation p below :func:`replication_level`;
    judged on the user's split (not a rate calibration, whose rows are other runs, nor the base or structure check)."""
    checks = c.evidence.get("checks") or {}
    failed = [k for k, ok in checks.items() if not ok]
    return (not c.significant and failed == [BLOCK_CHECK] and c.fitted is not None and not c.replaces_model
            and "rate_calibration" not in c.evidence
            and float(c.evidence.get("p_value", 1.0)) < replication_level())


def held_back_folds(train: np.ndarray, folds: int = REPLICATION_FOLDS, blocks: int = BLOCKS) -> list[np.ndarray]:
    """The rows each fold holds back of one run's ``train`` rows: those rows in ``blocks`` equal blocks,
    the first kept in every fold (the model's memory starts there), the others dealt to the folds in
    turn, so neighbouring blocks fall in different folds and every fold spans the record."""
    rows = np.flatnonzero(train)
    out = [np.zeros_like(train) for _ in range(folds)]
    if rows.size < blocks:
        return out
    edges = np.linspace(0, rows.size, blocks + 1).astype(int)
    for b in range(1, blocks):
        out[(b - 1) % folds][rows[edges[b]:edges[b + 1]]] = True
    return out


def _user_runs(dataset: Dataset, kw: dict[str, Any]) -> list[Any]:
    user = dataset.fit_runs()
    assign_roles(user, kw.get("train"), kw.get("test"), float(kw.get("train_fraction", 0.7)), dataset.keep)
    return user


def inner_fit_errors(paths: Any, spec: str, kw: dict[str, Any], start_from: Any, fold: int) -> list[np.ndarray]:
    """``spec`` fitted on the training rows less the rows fold ``fold`` holds back (warm from
    ``start_from``, as every refit is), and its error on those rows, one array per run (NaN elsewhere)."""
    dataset = as_dataset(paths)
    user = _user_runs(dataset, kw)
    held_back = [held_back_folds(u.train)[fold] for u in user]
    out = [np.full(u.data.output.shape[0], np.nan) for u in user]
    if not any(h.any() for h in held_back):
        return out
    result = fit(replace(dataset, keep=[u.train & ~h for u, h in zip(user, held_back)]), spec,
                 train_fraction=1.0, start_from=start_from)
    for o, r, rows in zip(out, result.runs, held_back):
        if r.simulated is not None and r.simulated.size == o.size and rows.any():
            o[rows] = (r.simulated - r.data.output)[rows]
    return out


def _cross_validated(per_fold: list[list[np.ndarray]]) -> np.ndarray:
    """The folds' held-back errors merged (each row is held back by one fold at most), runs in
    order and rows in time order; rows no fold held back are dropped."""
    merged = []
    for k in range(len(per_fold[0])):
        run = np.full(per_fold[0][k].shape, np.nan)
        for fold in per_fold:
            held = np.isfinite(fold[k])
            run[held] = fold[k][held]
        merged.append(run)
    e = np.concatenate(merged) if merged else np.zeros(0)
    return e[np.isfinite(e)]


def replicate(paths: Any, base: FitResult, cands: list[Candidate], kw: dict[str, Any], jobs: int = 1) -> None:
    """Settle the block test of every candidate that :func:`needs_replication` on held-back training
    rows (module docstring), in place: the evidence gains ``replication`` and the joint p-value."""
    todo = [c for c in cands if needs_replication(c)]
    if not todo:
        return
    specs = [base.spec, *(c.spec for c in todo)]
    tasks = [(s, f) for s in specs for f in range(REPLICATION_FOLDS)]
    per_task = run_tasks([partial(inner_fit_errors, paths, s, kw, base.model, f) for s, f in tasks], jobs,
                         names=[f"replicate on held-back training (fold {f + 1} of {REPLICATION_FOLDS}): {s}"
                                for s, f in tasks])
    errors = [_cross_validated(per_task[k * REPLICATION_FOLDS:(k + 1) * REPLICATION_FOLDS]) for k in range(len(specs))]
    e_base = errors[0]
    for c, e_new in zip(todo, errors[1:]):
        if e_base.size == 0 or e_new.size != e_base.size:
            continue
        settle(c, block_tests(e_base, e_new), _rms(e_base), _rms(e_new), int(e_base.size))


def settle(c: Candidate, held: BlockTests, rms_base: float, rms_new: float, rows: int) -> None:
    """The verdict of ``c`` with the block tests ``held`` on the held-back training rows (``rows``
    of them; rmse ``rms_base`` -> ``rms_new``, output unit), in place: the evidence gains
    ``replication``, the joint p-value and the held-back gain's check; a candidate made significant
    says so in its explanation, as the failed checks say why one is not (issue item 8)."""
    p_validation = float(c.evidence["p_value"])
    joint = max(p_validation, held.p) ** 2
    c.evidence["replication"] = {
        "validation_p": p_validation, "held_back_p": held.p, "held_back_blocks_improved": [held.better, held.blocks],
        "held_back_rows": rows, "held_back_rmse": [rms_base, rms_new], "level_each": replication_level(),
    }
    c.evidence["p_value"] = joint
    c.evidence["checks"][BLOCK_CHECK] = joint < T.P_MAX
    # the held-back rows replicate the whole of what validation asks: not chance, and large
    # enough to matter (MIN_GAIN: below it a refit buys as much on unseen rows by chance, or a
    # base family slightly off the plant's is bent a little closer; on a clean rig, a knee on a
    # one-sided PI: validation 17 % lower at p 0.097, held-back rows 8 % lower at p 1e-4)
    c.evidence["checks"][HELD_BACK_CHECK] = relative_gain(rms_base, rms_new) > T.MIN_GAIN
    c.significant = all(c.evidence["checks"].values())
    if c.significant:
        better, blocks = (c.evidence.get("blocks_improved") or [0, 0])[:2]
        c.explanation += (
            f"; significant on two block tests together: p = {p_validation:.2g} on validation ({better} of "
            f"{blocks} blocks improved) and {held.p:.2g} on training rows held back from a refit ({held.better} "
            f"of {held.blocks}, rmse {100 * relative_gain(rms_base, rms_new):.1f} % lower), each below "
            f"{replication_level():.2g}: jointly p = {joint:.2g}")


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2))) if e.size else math.nan
