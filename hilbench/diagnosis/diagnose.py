"""The diagnosis loop: where a fitted model fails and which effect of DESIGN.md is missing (``hilbench diagnose``).

:func:`diagnose` fits a spec (or evaluates a saved model), then

* splits the squared validation error ``e = model - measured`` (output unit, um) into shares by run,
  time window, input range x direction (rising / falling / turning / hold), |input rate| and the
  range of every auxiliary channel (``where``);
* refits the spec with every effect it lacks and the data can test, on the same split, and calls an
  effect significant when (a) validation rmse drops by more than 10 %, (b) training improves too and
  the two relative gains agree (validation at least half of training's, training at least a quarter
  of validation's: neither an artefact of more parameters nor chance extrapolation), (c) block tests
  on the squared-error differences of contiguous validation blocks (signed ranks over ~20 blocks
  for a gain spread over the record, sign flips of the sum for one concentrated in a few
  stretches, :mod:`hilbench.diagnosis.significance`) give p < 0.01 (when the validation rows are too
  short for that and every other check holds, jointly with the same tests on held-back training
  rows, :mod:`hilbench.diagnosis.replication`), and (d) the current validation error is above the noise floor
  (noise estimated from sample-to-sample residual differences);
* tries every effect of the registry (:mod:`hilbench.effects`) that the data can test
  (:mod:`hilbench.diagnosis.testability`) in the forms its entry lists (:mod:`hilbench.diagnosis.refit`);
  with one training drive rate, calibrates delay and dynamics across the validation rates
  (:mod:`hilbench.diagnosis.rate_calibration`);
* when the base refitted from a significant candidate's shape fits training better, judges every
  refit against that base instead: the gain of a base that had stopped at a poor optimum is not an
  effect's (:mod:`hilbench.diagnosis.base_polish`);
* explains each effect in one sentence from its residual signature (:mod:`hilbench.diagnosis.evidence`),
  judges and ranks them by the measured fractional drop of validation rmse (``expected_gain``; a tie
  is decided by the residual's pattern, :mod:`hilbench.diagnosis.verdict`), and lists the effects the
  data cannot test with the reason;
* when the data show mechanics (a resonance the drive excites and the error follows), tries the
  structure with the hysteresis inside them, ``bouc-wen+restoring-force``, judged as another base is
  (:mod:`hilbench.diagnosis.structure_check`, decision 0103);
* when no single effect carries over but some explained training, judges pairs of them together
  (candidate ``a+b``, :mod:`hilbench.diagnosis.pairs`): creep after each load step;
* when nothing is significant on every validation row and some of them drive past training's input
  range (or carry the hysteresis memory of such an excursion), judges the single effects again on
  the rows within training's reach (:mod:`hilbench.diagnosis.reach`, decision 0071);
* with ``add`` refits with that effect, with ``auto`` adds the best significant effect (or pair)
  while one remains (``steps``).

Units: input in the command unit (V or A), errors in the output unit, rates in input units per s,
times in s, gains as fractions.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

from hilbench import progress
from hilbench.diagnosis.base_check import alternatives, finer_base_check, fit_alternative, wrong_base
from hilbench.diagnosis.base_polish import polished_base, shared_base_shape
from hilbench.diagnosis.pairs import pair_candidates
from hilbench.diagnosis.reach import restricted, within_reach
from hilbench.diagnosis.refit import fit_effect
from hilbench.diagnosis.replication import replicate
from hilbench.diagnosis.resolution import check_resolution
from hilbench.diagnosis.rows import noise_floor, residual_rows
from hilbench.diagnosis.structure_check import structure_check
from hilbench.diagnosis.testability import testable
from hilbench.diagnosis.ranking import rank
from hilbench.diagnosis.verdict import Candidate, judge, verdict
from hilbench.diagnosis.where import where
from hilbench.diagnosis.workers import check_jobs, run_tasks
from hilbench.identify.dataset import Dataset, as_dataset
from hilbench.identify.trimming import Trim
from hilbench.identify.fitting import FitResult, PathLike, finite_json, fit, fit_or_evaluate


@dataclass
class Diagnosis:
    spec: str
    result: FitResult
    where: list[dict[str, Any]]
    effects: list[Candidate]
    untestable: list[dict[str, str]]
    steps: list[dict[str, Any]] = field(default_factory=list)
    noise: float = float("nan")
    rounds: list[Diagnosis] = field(default_factory=list)  # with add/auto: the diagnosis of every step

    @property
    def metrics(self) -> dict[str, dict[str, float]]:
        return self.result.metrics

    @property
    def best(self) -> Candidate | None:
        return self.effects[0] if self.effects else None

    def __repr__(self) -> str:
        found = [c.effect for c in self.effects if c.significant]
        added = [s["added"] for s in self.steps if s.get("added")]
        rmse = self.metrics["validation"].get("rmse", float("nan"))
        return (f"Diagnosis({self.spec!r}: validation rmse {rmse:.4g} {self.result.output_unit}"
                + (f", added {' + '.join(added)}" if added else "")
                + (f", still significant: {', '.join(found)}" if found else ", nothing significant left") + ")")

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "spec": self.spec,
            "metrics": {"train": self.metrics["train"], "validation": self.metrics["validation"]},
            "where": self.where,
            "effects": [c.to_json() for c in self.effects],
            "untestable": self.untestable,
            # the final model's parameters with units (the spec's, after any --add/--auto step)
            "model": {"spec": self.result.model.spec, "parameters": self.result.model.to_dict()["parameters"]},
        }
        if self.result.notes:  # what was left out and why, runs that did not complete, ...
            out["notes"] = list(self.result.notes)
        if self.steps:
            out["steps"] = self.steps
        return finite_json(out)


def _diagnose_once(paths: Dataset, base: FitResult, kw: dict[str, Any], jobs: int) -> Diagnosis:
    rows = residual_rows(base)
    noise = noise_floor(rows)  # the sensor's, from the measured output (diagnosis/noise.py)
    plan = testable(base.spec, base)
    every = residual_rows(base, "all")  # evidence from all rows: holds and steps may all lie in training
    plans = {eff: plan.plan if eff in plan.calibrated else None for eff in plan.tries}
    others = alternatives(base, noise)
    # every candidate refit and every alternative base is fitted from the same base: one batch of
    # independent tasks for the worker processes (diagnosis/workers.py)
    tasks: list[Callable[[], Any]] = [partial(judge, paths, base, eff, every, noise, kw, plans[eff])
                                      for eff in plan.tries]
    tasks += [partial(fit_alternative, paths, base, spec, kw) for spec in others]
    names = [f"diagnose {base.spec}: {eff}" for eff in plan.tries] + [f"diagnose {base.spec}: base {s}" for s in others]
    with progress.task(f"diagnose {base.spec}: effects and bases", total=len(tasks)) as advance:
        done = run_tasks(tasks, jobs, advance, names, shared=paths.runs)
    cands: list[Candidate] = done[: len(plan.tries)]
    other_fits: list[FitResult | None] = done[len(plan.tries):]
    polished = polished_base(paths, base, cands, kw, jobs)
    if polished is not None:
        # the base had stopped at a poor optimum that the refits' searches left: judge every
        # refit against the base at its better optimum (diagnosis/base_polish.py)
        polished.notes.append(
            f"the base {base.spec} was refitted from a candidate's shape to a better optimum (training rmse "
            f"{base.metrics['train']['rmse']:.4g} -> {polished.metrics['train']['rmse']:.4g}); effects are "
            f"judged against it")
        base, rows, every = polished, residual_rows(polished), residual_rows(polished, "all")
        cands = [verdict(base, c.effect, c.fitted, every, noise, plans[c.effect]) if c.fitted is not None else c
                 for c in cands]
        others = alternatives(base, noise)  # the alternatives start from the base's shape: refit them
        other_fits = run_tasks([partial(fit_alternative, paths, base, spec, kw) for spec in others], jobs,
                               shared=paths.runs)
    # every significant refit on the best base shape any of them found (diagnosis/base_polish.py)
    cands = shared_base_shape(paths, base, cands, every, noise, kw, plans, jobs)
    cands += pair_candidates(paths, base, cands, every, noise, kw, jobs)  # overlapping effects, judged together
    untestable = list(plan.untestable)
    # the hysteresis inside the mechanics, when the data show a resonance the drive excites (decision 0103)
    structure = structure_check(paths, base, cands, noise, kw, untestable)
    effect_rmse = [c.evidence["validation_rmse"][1] for c in cands]
    if structure is not None:
        cands.append(structure)
        if structure.significant:  # another base must beat the structure too
            effect_rmse.append(structure.evidence["validation_rmse"][1])
    other_base = wrong_base(base, other_fits, noise, effect_rmse)
    if other_base is not None:
        finer_base_check(paths, base, other_base, cands, kw)  # not the current family at too few operators
        cands.append(other_base)
    if not any(c.replaces_model and c.significant for c in cands):
        # gains the validation rows are too short to confirm alone; not on a base (or structure) the
        # data refuse, where the report is the replacement, not small effects on top of it (issue item 5)
        replicate(paths, base, cands, kw, jobs)
    rank(cands)
    check_resolution(paths, base, cands, noise, kw, jobs)  # the two leaders' order on a finer base
    cands = _within_reach_if_nothing(base, cands, noise, plans)
    base.notes.extend(n for n in plan.notes if n not in base.notes)  # what the training rows cannot identify
    return Diagnosis(base.spec, base, where(rows), cands, untestable, noise=noise)


def _within_reach_if_nothing(base: FitResult, cands: list[Candidate], noise: float,
                             plans: dict[str, Any]) -> list[Candidate]:
    """When no candidate is significant on every validation row and some of those rows drive beyond
    training's input reach (or carry the memory of such an excursion), the single effects judged
    again on the rows within reach alone (:mod:`hilbench.diagnosis.reach`, decision 0071). Their
    verdicts replace the first ones only when one of them is significant, and the base's notes say
    which rows were left out; otherwise the candidates stay as they were."""
    if any(c.significant for c in cands):
        return cands
    reach = within_reach(base)
    if reach is None or not reach.applies:
        return cands
    inside = restricted(base, reach)
    every = residual_rows(inside, "all")  # the evidence from the same rows: training's and those within reach
    # judged on the rows within reach, but the refit a candidate carries stays the one scored on every
    # validation row: --auto continues from it, and the next round's comparisons need the same rows
    again = {id(c): replace(verdict(inside, c.effect, restricted(c.fitted, reach), every, noise, plans[c.effect]),
                            fitted=c.fitted)
             for c in cands if c.effect in plans and c.fitted is not None}
    if not any(c.significant for c in again.values()):
        return cands
    record = {"left_out": reach.left_out, "validation_rows": reach.validation,
              "training_input_range": [reach.lo, reach.hi]}
    for c in again.values():
        c.evidence["judged_within_reach"] = record
        c.explanation += (f"; judged on the validation rows within training's input reach ({reach.left_out} of "
                          f"{reach.validation} left out)")
    out = [again.get(id(c), c) for c in cands]
    rank(out)
    note = reach.note(base.input_unit)
    if note not in base.notes:
        base.notes.append(note)
    return out


def _add(paths: Any, base: FitResult, effect: str, kw: dict[str, Any]) -> FitResult:
    """``--add``: refit with ``effect``, calibrated across drive rates where the diagnosis would."""
    plan = testable(base.spec, base)
    # the same form the diagnosis would try (rate calibration, creep's and rate-dependence's forms)
    return fit_effect(paths, base, effect, kw, plan.plan if effect in plan.calibrated else None)


def _step(result: FitResult, added: str | None, judged: Candidate | None = None) -> dict[str, Any]:
    """One row of the steps table. When the added effect was judged on the validation rows within
    training's input reach (decision 0071), the row also says so and gives the rmse there: on every
    validation row the error may barely move, since the rows beyond reach hold the extrapolation."""
    step = {"spec": result.spec, "added": added, "validation": dict(result.metrics["validation"]),
            "train": dict(result.metrics["train"])}
    if judged is not None and "judged_within_reach" in judged.evidence:
        before, after = judged.evidence["validation_rmse"][:2]
        step["within_reach"] = {**judged.evidence["judged_within_reach"], "validation_rmse": [before, after]}
    return step


def _keep_polished(steps: list[dict[str, Any]], base: FitResult, result: Diagnosis) -> None:
    """When the diagnosis judged against the base refitted to a better optimum (base_polish), that
    refit is the step's model: an added effect's step records it (the starting step stays what the
    user brought)."""
    if result.result is not base and len(steps) > 1:
        steps[-1] = {**steps[-1], **_step(result.result, steps[-1]["added"])}  # keeps how it was judged


def diagnose(
    paths: Dataset | PathLike | Sequence[PathLike],
    spec_or_model_file: str,
    *,
    train: Sequence[str] | None = None,
    test: Sequence[str] | None = None,
    add: str | None = None,
    auto: bool = False,
    max_steps: int = 4,
    train_fraction: float = 0.7,
    trim: Trim | None = None,
    jobs: int | None = None,
) -> Diagnosis:
    """Fit (or load) the model, find where it fails and which effect is missing.

    With ``add`` the effect is added and the model refitted; with ``auto`` the best significant
    effect is added while one remains (at most ``max_steps`` additions). The returned diagnosis is
    of the final model; ``steps`` lists every model tried in order (the first is the start).
    A saved model is evaluated as is for ``metrics``; candidate effects are compared against its
    spec refitted on the same split, so both sides of every comparison saw the same training rows.
    ``trim`` leaves rows out of training and scoring; by default (``Trim(auto=True)``) the rest at the
    start of a capture whose history is unknown (an imported file), which the notes say.
    ``jobs``: worker processes for the refits of a round (default one per core, at most 8;
    :mod:`hilbench.diagnosis.workers`); the result does not depend on it.
    """
    jobs = check_jobs(jobs)
    kw = {"train": train, "test": test, "train_fraction": train_fraction}
    # read once: every refit below works on the same samples and the same trimmed rows
    paths = as_dataset(paths).trimmed(trim if trim is not None else Trim(auto=True))
    start = fit_or_evaluate(paths, spec_or_model_file, **kw)
    base = start if start.refitted else fit(paths, start.spec, **kw)
    steps = [_step(start, None)]
    if add is not None:
        base = _add(paths, base, add, kw)
        steps.append(_step(base, add))
    result = _diagnose_once(paths, base, kw, jobs)
    _keep_polished(steps, base, result)
    rounds = [result]
    if auto:
        with progress.task(f"diagnose --auto: up to {max_steps} steps", total=max_steps) as advance:
            while len(steps) - 1 < max_steps and result.best is not None and result.best.significant:
                best = result.best
                advance(1, f"diagnose --auto: step {len(steps)}, added {best.effect}")
                base = best.fitted if best.fitted is not None else fit(paths, best.spec, **kw)
                steps.append(_step(base, best.effect, best))
                result = _diagnose_once(paths, base, kw, jobs)
                _keep_polished(steps, base, result)
                rounds.append(result)
    result.rounds = rounds
    if add is None and not auto and not start.refitted:
        result.result = start  # report the saved model's own metrics
    if add is not None or auto:
        result.steps = steps
    return result
