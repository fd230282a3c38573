"""A dataset: the runs of one or more recordings, read once and shared by every fit.

Fitting a spec, refitting it with each candidate effect, calibrating across rates: all of it works
on the same :class:`Dataset`, so a diagnosis reads its HDF5 files once. A dataset hands each fit
fresh :class:`FitRun` objects (their roles and outputs are the fit's own) over the same read-only
sample arrays.

Units: input in the recording's command unit (V or A), output in its unit (usually um), auxiliary
channels in theirs, sample rates in Hz.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Union

import numpy as np

from hilbench.errors import DataError, UserError
from hilbench.identify.trimming import Trim
from hilbench.models import RunData
from hilbench.recording.hdf5 import Recording, Run

PathLike = Union[str, "os.PathLike[str]"]
#: channels that are not auxiliary inputs of a model
NON_AUX = ("time", "input", "output", "lateness", "reference")


@dataclass
class FitRun:
    """One run in a fit: its data, which rows train and which validate, the model's output."""

    key: str  # the name shown and matched: the group name, ``stem:group`` with several files
    data: RunData
    train: np.ndarray  # bool mask of training rows
    validation: np.ndarray  # bool mask of validation rows
    simulated: np.ndarray | None = None  # free-run model output, output unit (um)
    metrics: dict[str, dict[str, float] | None] = field(default_factory=dict)

    @property
    def role(self) -> str:
        """``train``, ``validation``, ``train+validation`` (split run) or ``unused``."""
        roles = [r for r, m in (("train", self.train), ("validation", self.validation)) if m.any()]
        return "+".join(roles) or "unused"


def _sha256(*arrays: np.ndarray) -> str:
    digest = hashlib.sha256()
    for a in arrays:
        digest.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    return digest.hexdigest()


def load_runs(path: PathLike, run_names: Sequence[str] | None = None) -> list[RunData]:
    """The runs of the recording ``path`` as :class:`RunData`, in recorded order.

    ``input`` is the applied command (V or A), ``output`` the displacement (um), ``aux`` every other
    channel except time, lateness and reference (e.g. temperature in degC, load in N),
    ``sample_rate_hz`` in Hz. ``source`` names the file, the run, a SHA-256 of the input and output
    samples (little-endian float64, input then output) and the run's status: a run that did not
    complete (killed, aborted) is still usable, every recorded sample is valid.

    A run recorded right after the previous one of the same sweep (attribute ``previous_run``) has
    ``chain=True``: the model's memory carries over, as the actuator's did; the first run of a
    sweep starts from the rig's rest value (``approach_from``). Imported runs start afresh.
    ``run_names`` (group name, label or 1-based number) returns only those runs; give none when
    fitting, so the memory is right.
    """
    recording = Recording(path)
    selected = recording.runs if run_names is None else [recording.run(name) for name in run_names]
    return _run_data(recording, selected)


def _follows(run: Run, earlier: list[RunData]) -> bool:
    """The run was recorded right after the previous one on the same actuator (same sweep)."""
    previous = str(run.attrs.get("previous_run", ""))
    return bool(previous) and bool(earlier) and earlier[-1].name == previous


def _run_data(recording: Recording, selected: list[Run]) -> list[RunData]:
    out: list[RunData] = []
    for run in selected:
        missing = [c for c in ("input", "output") if c not in run.channels]
        if missing:
            raise DataError(
                f"run {run.name} has no {' or '.join(repr(m) for m in missing)} channel to fit "
                f"(channels: {', '.join(run.channels) or 'none'})",
                where=str(recording.path),
            )
        data = run.data()
        source = {"file": str(recording.path), "run": run.name, "sha256": _sha256(data["input"], data["output"]),
                  "status": run.status or "unknown"}
        approach = run.attrs.get("approach_from")
        out.append(RunData(
            input=data["input"], output=data["output"],
            aux={c: v for c, v in data.items() if c not in NON_AUX},
            sample_rate_hz=run.sample_rate_hz, name=run.name, source=source,
            chain=_follows(run, out),
            approach_from=float(approach) if approach is not None and not _follows(run, out) else None,
        ))
    return out



def _aliases(run: RunData, stem: str, file: str, several: bool) -> set[str]:
    name = run.name
    names = {name, name.split("-", 1)[1] if "-" in name else name}
    if name[:4].isdigit():
        names.add(str(int(name[:4])))
    if several:
        names |= {f"{prefix}:{n}" for n in list(names) for prefix in (stem, file)}
    return names


def _folded(name: str) -> str:
    """A run name as typed loosely: lower case, letters and digits only (``20_hz_no_lp`` -> ``20hznolp``)."""
    return "".join(ch for ch in name.lower() if ch.isalnum())


def match_runs(selectors: Sequence[str], runs: list[FitRun], option: str) -> set[int]:
    """Runs named by ``selectors``: exactly (group name, label, number, ``stem:run``), else by a
    unique short form (``20hz`` for ``0001-20_hz_no_lp``: the folded label starts with it)."""
    files = sorted({r.data.source.get("file", "") for r in runs})
    several = len(files) > 1
    chosen: set[int] = set()
    for selector in selectors:
        hits = {i for i, r in enumerate(runs)
                if selector in _aliases(r.data, Path(r.data.source.get("file", "")).stem,
                                        r.data.source.get("file", ""), several)}
        if not hits and _folded(selector):
            short = _folded(selector)
            hits = {i for i, r in enumerate(runs)
                    if any(_folded(a).startswith(short) for a in _aliases(r.data, "", "", False) if not a.isdigit())}
            if len(hits) > 1:
                names = ", ".join(runs[i].key for i in sorted(hits))
                raise DataError(f"{selector!r} is short for several runs ({names}); name one of them in full",
                                where=option)
        if not hits:
            available = ", ".join(r.key for r in runs) or "none"
            raise DataError(f"no run {selector!r} in {', '.join(files)}; available runs: {available}", where=option)
        chosen |= hits
    return chosen


@dataclass
class Dataset:
    """Every run of every file, read once (empty or incomplete runs noted), with the units."""

    paths: list[Path]
    runs: list[RunData]
    keys: list[str]  # the name shown and matched: the group name, ``stem:group`` with several files
    input_unit: str
    output_unit: str
    notes: list[str] = field(default_factory=list)
    #: rows each run keeps for training and scoring (None: all), see :meth:`trimmed`
    keep: list[np.ndarray] | None = None

    @classmethod
    def load(cls, path_or_paths: PathLike | Sequence[PathLike]) -> Dataset:
        paths = _paths(path_or_paths)
        notes: list[str] = []
        several = len(paths) > 1
        runs: list[RunData] = []
        keys: list[str] = []
        units: dict[str, set[str]] = {"input": set(), "output": set()}
        for path in paths:
            recording = Recording(path)
            for run in recording.runs:
                for c in units:
                    if c in run.units:
                        units[c].add(run.units[c])
            for data in _run_data(recording, recording.runs):
                status = data.source["status"]
                if len(data) == 0:
                    notes.append(f"run {data.name} of {path} has no samples")
                elif status != "complete":
                    notes.append(f"run {data.name} of {path} is {status!r}; its {len(data)} recorded samples are used")
                for array in (data.input, data.output, *data.aux.values()):
                    array.flags.writeable = False  # shared by every fit: nobody may change it
                keys.append(f"{path.stem}:{data.name}" if several else data.name)
                runs.append(data)
        if not runs:
            raise DataError(f"no runs in {', '.join(map(str, paths))}")
        if len(units["output"]) > 1:
            notes.append(f"runs differ in output unit: {', '.join(sorted(units['output']))}")
        return cls(paths, runs, keys, "/".join(sorted(units["input"])), "/".join(sorted(units["output"])) or "um",
                   notes)

    def only(self, selector: str) -> Dataset:
        """The dataset of one run (group name, label or 1-based number), read as if its file held it alone."""
        index = match_runs([selector], self.fit_runs(), "RUN")
        if len(index) != 1:
            raise DataError(f"{selector!r} names {len(index)} runs; expected one", where=str(self.paths[0]))
        i = index.pop()
        return Dataset(self.paths, [self.runs[i]], [self.runs[i].name], self.input_unit, self.output_unit,
                       list(self.notes))

    def fit_runs(self) -> list[FitRun]:
        """Fresh runs for one fit: no roles yet, no model output."""
        return [FitRun(key, data, np.zeros(len(data), bool), np.zeros(len(data), bool))
                for key, data in zip(self.keys, self.runs)]


    def trimmed(self, trim: Trim | None) -> Dataset:
        """The same runs with the rows ``trim`` leaves out marked (they are still simulated), and a
        note per reason. The leading rest is left out only where the run's history is unknown (an
        imported capture: it neither follows a recorded run nor starts from the rig's rest)."""
        if trim is None or not trim.active:
            return self
        runs = self.fit_runs()
        keeps, notes = [], list(self.notes)
        for i, r in enumerate(runs):
            history_known = r.data.chain or r.data.approach_from is not None
            kept, why = trim.keep(r.data.input, r.data.output, r.data.sample_rate_hz,
                                  lambda selector, i=i: i in match_runs([selector], runs, "--exclude"), r.key,
                                  history_known=history_known, channels=list(r.data.aux.values()))
            keeps.append(kept)
            notes.extend(why)
        return Dataset(self.paths, self.runs, self.keys, self.input_unit, self.output_unit, notes, keeps)


def as_dataset(data: Dataset | PathLike | Sequence[PathLike]) -> Dataset:
    """A dataset as given, or read from a path or paths."""
    return data if isinstance(data, Dataset) else Dataset.load(data)


def _paths(path_or_paths: PathLike | Sequence[PathLike]) -> list[Path]:
    if isinstance(path_or_paths, (str, os.PathLike)):
        return [Path(path_or_paths)]
    paths = [Path(p) for p in path_or_paths]
    if not paths:
        raise UserError("no recording given")
    return paths
