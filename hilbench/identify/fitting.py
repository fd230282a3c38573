"""Fit a model spec to recordings and report training and validation error (``hilbench fit``).

The orchestration between recordings, :class:`hilbench.models.Model`,
:func:`hilbench.identify.fit_model` and :func:`hilbench.identify.metrics.metrics`:

* every run of every recording is read (:func:`load_runs`); consecutive runs of one file were
  recorded one after the other on the same actuator, so each run after a file's first carries the
  model's memory over (``RunData.chain``), and fitting and simulation always see all runs in order;
* rows are given roles by boolean masks: by default the first 70 % of the samples of every run
  train and the last 30 % validate; runs named with ``train`` train entirely, runs named with
  ``test`` validate entirely (runs in neither get all-False masks);
* the model is fitted on the training rows (or, for :func:`evaluate`, a saved model is used as is),
  simulated free-running over all runs, and scored with all metric keys of DESIGN.md on the
  training rows and on the validation rows, overall and per run.

Units: input in the recording's command unit (V or A), output and errors in the output unit
(usually um), ``mse`` in its square, ``*_pct`` in percent, times in s, rates in Hz.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from hilbench.errors import DataError, UserError
from hilbench.identify import FitReport, fit_model, health
from hilbench.identify.dataset import Dataset, FitRun, PathLike, as_dataset, load_runs, match_runs
from hilbench.identify.metrics import METRIC_KEYS, metrics
from hilbench.identify.sweep import BLOCKS as SWEEP_BLOCKS
from hilbench.identify.sweep import interleaved, sweeps_past_split, validation_blocks

#: in a split's description: some runs were split in interleaved blocks (the notes then say so)
SWEPT = "sweep their drive frequency,"
from hilbench.models import Model, SpecError

ROLES = ("train", "validation")


# -- roles --------------------------------------------------------------------------------------


def assign_roles(
    runs: list[FitRun], train: Sequence[str] | None, test: Sequence[str] | None, train_fraction: float,
    keep: Sequence[np.ndarray] | None = None,
) -> str:
    """Set the train/validation masks of ``runs`` in place; returns a one-line description.

    No selectors: the first ``train_fraction`` of every run's kept samples train, the rest validate.
    ``train`` only: the rest validate; ``test`` only: the rest train; both: runs in neither are unused.
    ``keep`` (one mask per run, default all rows) leaves rows out of both roles (:mod:`.trimming`).
    """
    n_runs = len(runs)
    keeps = list(keep) if keep is not None else [np.ones(len(r.data), bool) for r in runs]
    if not train and not test:
        if not 0.0 < train_fraction <= 1.0:
            raise UserError(f"the training fraction must be in (0, 1], got {train_fraction:g}", where="--train-fraction")
        swept = []
        for r, kept in zip(runs, keeps):
            idx = np.arange(len(r.data))
            rows = np.flatnonzero(kept)
            k = int(math.floor(rows.size * train_fraction))
            cut = int(rows[k]) if k < rows.size else len(r.data)
            r.train, r.validation = kept & (idx < cut), kept & (idx >= cut)
            span = sweeps_past_split(r.data.input, r.data.sample_rate_hz, r.train, r.validation) \
                if validation_blocks(train_fraction) >= 1 else None
            if span is not None:  # a sweep: validation would hold rates training never saw
                r.train, r.validation = interleaved(kept, train_fraction)
                swept.append(f"{r.key} ({span[0]:.3g}-{span[1]:.3g} Hz)")
        pct = 100.0 * train_fraction
        text = f"first {pct:g} % of each run trains, last {100.0 - pct:g} % validates"
        if swept:
            text += (f"; except the runs that {SWEPT} {', '.join(swept)}: {validation_blocks(train_fraction)} of "
                     f"{SWEEP_BLOCKS} interleaved blocks validate, so training sees rates across the span")
        return text
    train_set = match_runs(train or [], runs, "--train")
    test_set = match_runs(test or [], runs, "--test")
    both = train_set & test_set
    if both:
        raise UserError(f"run(s) {', '.join(runs[i].key for i in sorted(both))} named both in --train and --test")
    if not train:
        train_set = set(range(n_runs)) - test_set
    if not test:
        test_set = set(range(n_runs)) - train_set
    for i, (r, kept) in enumerate(zip(runs, keeps)):
        r.train = kept & (i in train_set)
        r.validation = kept & (i in test_set)
    return (f"runs {', '.join(runs[i].key for i in sorted(train_set)) or 'none'} train; "
            f"runs {', '.join(runs[i].key for i in sorted(test_set)) or 'none'} validate")


# -- the result ---------------------------------------------------------------------------------


@dataclass
class FitResult:
    """A fitted (or loaded and evaluated) model with its training and validation error."""

    spec: str
    model: Model
    runs: list[FitRun]
    metrics: dict[str, dict[str, float]]  # {"train": {...}, "validation": {...}}, metric keys + "n"
    split: str  # how rows were given roles, one line
    report: FitReport | None = None  # None when the model was loaded, not fitted
    loaded_from: str | None = None  # the model file, when evaluated without refitting
    output_unit: str = "um"
    input_unit: str = ""
    notes: list[str] = field(default_factory=list)
    #: :func:`hilbench.identify.health.check`: ``status`` ok or flagged, ``reasons``, figures
    health: dict[str, Any] = field(default_factory=dict)
    date: str = field(default_factory=lambda: datetime.now(timezone.utc).isoformat(timespec="seconds"))

    @property
    def refitted(self) -> bool:
        return self.report is not None

    @property
    def simulated(self) -> list[np.ndarray | None]:
        """Free-run model output of every run, output unit (um)."""
        return [r.simulated for r in self.runs]

    @property
    def fitted_on(self) -> list[dict[str, Any]]:
        """Source dicts (file, run, sha256, status) of the runs the model was fitted on."""
        if self.report is None:
            return list(self.model.info.get("fitted_on", []))
        return [dict(r.data.source) for r in self.runs if r.train.any()]

    def fit_info(self) -> dict[str, Any]:
        """The ``fit`` section: time (s), evaluations, shape parameters theta, training rmse."""
        if self.report is None:
            saved = dict(self.model.info.get("fit", {}))
            return {**saved, "refitted": False, "loaded_from": self.loaded_from}
        rep = self.report
        return {
            "refitted": True,
            "seconds": rep.seconds,
            "evaluations": rep.evaluations,
            "starts": rep.starts,
            "theta": dict(rep.theta),
            "rmse": rep.rmse,
            "n_train": rep.n_train,
            "split": self.split,
            "date": self.date,
        }

    def __repr__(self) -> str:
        validation = self.metrics.get("validation") or {}
        verb = "fitted" if self.refitted else "scored"
        return (f"FitResult({self.spec!r} {verb} on {len(self.runs)} run(s): validation rmse "
                f"{validation.get('rmse', float('nan')):.4g} {self.output_unit}, erms "
                f"{validation.get('erms_pct', float('nan')):.3g} %)")

    def to_json(self) -> dict[str, Any]:
        """One JSON-ready document (NaN written as null): spec, model, metrics, runs, fit, fitted_on."""
        return finite_json({
            "spec": self.spec,
            "model": self.model.to_dict(),
            "metrics": self.metrics,
            "runs": [
                {"name": r.key, "file": r.data.source.get("file"), "run": r.data.name, "role": r.role,
                 "status": r.data.source.get("status"),
                 "samples": {"train": int(r.train.sum()), "validation": int(r.validation.sum())},
                 "metrics": r.metrics}
                for r in self.runs
            ],
            "fit": self.fit_info(),
            "fitted_on": self.fitted_on,
            "split": self.split,
            **({"scored": self.metrics["validation"]} if not self.refitted else {}),
            "units": {"input": self.input_unit, "output": self.output_unit},
            "health": self.health,
            "notes": self.notes,
        })

    def save(self, path: PathLike) -> Path:
        """Write the fitted model as JSON: the model plus ``fitted_on``, ``metrics`` and ``fit``.

        :meth:`hilbench.models.Model.load` reads it back and simulates the same output.
        """
        if self.report is None:
            raise UserError("nothing was fitted: the model was loaded from a file; use --json to keep the evaluation",
                            where="-o")
        out = Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        return self.model.save(out)


def finite_json(value: Any) -> Any:
    """NaN and infinities become None (strict JSON); containers are copied."""
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


# -- fitting and evaluation ---------------------------------------------------------------------


def _channels(runs: list[FitRun]) -> tuple[list[str], list[str]]:
    """Channels present in any run, and in every run (recorded order)."""
    union: list[str] = []
    for r in runs:
        for c in ["input", "output", *r.data.aux]:
            if c not in union:
                union.append(c)
    common = [c for c in union if all(c in ("input", "output") or c in r.data.aux for r in runs)]
    return union, common


def _check_aux(model: Model, runs: list[FitRun]) -> None:
    union, _ = _channels(runs)
    for channel in model.aux_channels:
        lacking = [r.key for r in runs if channel not in r.data.aux]
        if lacking and channel in union:
            raise DataError(f"the model needs channel {channel!r}, which runs {', '.join(lacking)} lack")
        if lacking:
            aux = [c for c in union if c not in ("input", "output")]
            raise SpecError(f"the model needs channel {channel!r}, and the recording has none; "
                            f"channels here: {', '.join(aux) or 'none'}")


def _training_size(runs: list[FitRun]) -> int:
    return int(sum(np.count_nonzero(r.train & np.isfinite(r.data.output)) for r in runs))


def _active(runs: list[FitRun]) -> list[FitRun]:
    """The runs with samples: the ones fitted and simulated (an empty run has no memory to add)."""
    return [r for r in runs if len(r.data)]


def _score(runs: list[FitRun], model: Model) -> dict[str, dict[str, float]]:
    """Simulate all runs (memory chained) and compute overall and per-run metrics."""
    for r in runs:
        r.simulated = np.zeros(0)
        r.metrics = {role: None for role in ROLES}
    active = _active(runs)
    for r, y in zip(active, model.simulate_runs([r.data for r in active])):
        r.simulated = y
        r.metrics = {role: (metrics(r.data.output[mask], y[mask]) if mask.any() else None)
                     for role, mask in (("train", r.train), ("validation", r.validation))}
    overall = {}
    for role in ROLES:
        masks = [getattr(r, role) for r in runs]
        measured = np.concatenate([r.data.output[m] for r, m in zip(runs, masks)])
        simulated = np.concatenate([r.simulated[m] for r, m in zip(runs, masks)])
        overall[role] = metrics(measured, simulated)
    return overall


def _validation_note(runs: list[FitRun], notes: list[str]) -> None:
    if not any(r.validation.any() for r in runs):
        notes.append("no validation data: every run trains (name runs with --test to validate on them)")


def fit(
    path_or_paths: Dataset | PathLike | Sequence[PathLike],
    spec: str,
    *,
    train: Sequence[str] | None = None,
    test: Sequence[str] | None = None,
    train_fraction: float = 0.7,
    progress: Callable[[str], None] | None = None,
    start_from: Model | None = None,
) -> FitResult:
    """Fit the model ``spec`` (e.g. ``"pi"``, ``"pmpi+dynamics"``) to one or more recordings.

    ``train``/``test`` name runs (group name, label or 1-based number; with several files
    ``stem:run`` names one file's run, an unqualified name matches in every file);
    without them the first ``train_fraction`` of every run trains and the rest validates. Raises
    :class:`SpecError` for a spec that cannot be built (the message lists the bases, effects and
    channels available), :class:`DataError` for an unknown run, :class:`UserError` for an empty
    training set. ``progress`` receives one-line notes of the shape search. ``start_from``, a fitted
    model, starts the search from its shape parameters where ``spec`` has the same ones (a refit
    with one more effect searches globally only over the new effect's parameters).
    """
    dataset = as_dataset(path_or_paths)
    notes = list(dataset.notes)
    runs, u_unit, y_unit = dataset.fit_runs(), dataset.input_unit, dataset.output_unit
    union, _ = _channels(runs)
    model = Model(spec, channels=union)
    _check_aux(model, runs)
    split = assign_roles(runs, train, test, train_fraction, dataset.keep)
    if SWEPT in split:
        notes.append(f"split: {split}")
    if _training_size(runs) == 0:
        available = ", ".join(f"{r.key} ({len(r.data)} samples, {r.role})" for r in runs)
        raise UserError(f"the training set is empty ({split}): no training sample with a finite output; "
                        f"runs: {available}")
    _validation_note(runs, notes)
    if progress is not None:
        progress(f"fitting {model.spec} on {_training_size(runs)} training samples ({split})")
    active = _active(runs)
    report = fit_model(model, [r.data for r in active], [r.train for r in active], progress=progress,
                       start_from=start_from)
    overall = _score(runs, model)
    result = FitResult(model.spec, model, runs, overall, split, report=report, output_unit=y_unit,
                       input_unit=u_unit, notes=notes)
    _flag(result)
    # what the model file keeps besides the model (Model.from_dict reads these keys back)
    model.info = finite_json({"fitted_on": result.fitted_on, "metrics": overall, "fit": result.fit_info(),
                              "health": result.health})
    return result


def _flag(result: FitResult) -> None:
    """No silent blow-ups: the model's health on the runs scored, its reasons added to the notes."""
    result.health = health.check(result.model, result.runs, result.output_unit)
    result.notes.extend(f"model flagged: {reason}" for reason in result.health["reasons"])


def evaluate(
    path_or_paths: Dataset | PathLike | Sequence[PathLike],
    model: Model,
    *,
    train: Sequence[str] | None = None,
    test: Sequence[str] | None = None,
    train_fraction: float | None = None,
    loaded_from: str | None = None,
) -> FitResult:
    """Score an already fitted ``model`` on recordings without refitting.

    Nothing is trained, so by default every kept row of every run is scored, as one figure (the
    ``validation`` role, ``scored`` in the JSON); ``test`` scores the named runs only. Given
    ``train`` or ``train_fraction``, the rows get the roles :func:`fit` would give them (what a
    diagnosis does: its candidates are refitted on that split, and the saved model is compared on it)."""
    dataset = as_dataset(path_or_paths)
    notes = list(dataset.notes)
    runs, u_unit, y_unit = dataset.fit_runs(), dataset.input_unit, dataset.output_unit
    _check_aux(model, runs)
    if train_fraction is None and not train:
        split = assign_roles(runs, None, test, 1.0, dataset.keep)
        for r in runs:
            if test:
                r.train = np.zeros(len(r.data), bool)
            else:  # no selectors: the whole of every run is scored
                r.validation, r.train = r.train, np.zeros(len(r.data), bool)
        scored = [r.key for r in runs if r.validation.any()]
        split = (f"{'runs ' + ', '.join(scored) if test else 'every run, whole,'} scored; nothing refitted")
    else:
        split = assign_roles(runs, train, test, 0.7 if train_fraction is None else train_fraction, dataset.keep)
        if SWEPT in split:
            notes.append(f"split: {split}")
        _validation_note(runs, notes)
    overall = _score(runs, model)
    result = FitResult(model.spec, model, runs, overall, split, loaded_from=loaded_from, output_unit=y_unit,
                       input_unit=u_unit, notes=notes)
    _flag(result)
    return result


def is_model_file(text: str) -> bool:
    """Whether ``--model`` names a saved model, not a spec: a ``.json`` path, or an existing file given
    with a folder (``./fit.model``; a bare name like ``pi`` stays a spec even if such a file exists)."""
    return text.lower().endswith(".json") or (Path(text).is_file() and Path(text).name != text)


def fit_or_evaluate(
    path_or_paths: Dataset | PathLike | Sequence[PathLike],
    spec_or_file: str,
    **kwargs: Any,
) -> FitResult:
    """:func:`evaluate` a saved model when ``spec_or_file`` is a model file, else :func:`fit` the spec."""
    if is_model_file(spec_or_file):
        kwargs.pop("progress", None)  # nothing is searched
        return evaluate(path_or_paths, Model.load(spec_or_file), loaded_from=spec_or_file, **kwargs)
    return fit(path_or_paths, spec_or_file, **kwargs)


__all__ = ["Dataset", "FitResult", "FitRun", "METRIC_KEYS", "assign_roles", "evaluate", "fit", "fit_or_evaluate",
           "is_model_file", "load_runs"]
