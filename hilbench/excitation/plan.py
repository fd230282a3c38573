"""Plans: lists of runs, each an excitation with a label, checked against the rig's limits.

Three ways to write a plan:

* in the rig config, ``[[plan.runs]]`` tables (the rig's default characterisation sweep);
* a plan file: TOML with ``[[runs]]`` tables;
* the compact command-line form, one run per ``--excitation``:
  ``"sine:amplitude=3,frequency_hz=1,cycles=5"``. Lists are written with ``/``
  (``amplitudes=1/2/3``); a value with ``|`` sweeps: ``amplitude=1|2|3`` makes three runs.

A run table holds the excitation's keys plus ``label`` and ``sweep`` (a table of key -> list of
values, expanded to one run per combination). Before anything moves, :func:`check_plan` walks every
sample of every run and refuses a plan that leaves the actuator's range or exceeds its slew limit,
naming the run, the sample time and the value.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from hilbench.errors import ConfigError, PlanLimitError
from hilbench.schema import Key, check_table, parse_scalar, read_toml

from hilbench.excitation.signals import Excitation, make_excitation


class ActuatorLimits(Protocol):
    """What a plan is checked against: the actuator's unit, range and slew limit (a rig's [actuator])."""

    unit: str
    min: float
    max: float
    max_rate: float  # unit per s


@dataclass
class PlannedRun:
    label: str
    excitation: Excitation


def _format_value(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def expand_runs(tables: list[Mapping[str, Any]], *, file: str, table: str = "plan.runs") -> list[PlannedRun]:
    """Expand run tables (with optional ``sweep``) into planned runs with validated excitations."""
    runs: list[PlannedRun] = []
    for i, raw in enumerate(tables):
        where = f"{table}[{i}]"
        entry = dict(raw)
        label = entry.pop("label", None)
        if label is not None and not isinstance(label, str):
            raise ConfigError(f"[{where}] label: expected a string, got {label!r}", where=file)
        sweep = entry.pop("sweep", None) or {}
        if not isinstance(sweep, Mapping) or not all(isinstance(v, list) and v for v in sweep.values()):
            raise ConfigError(f"[{where}] sweep: expected a table of key = [values, ...], got {sweep!r}", where=file)
        keys = list(sweep)
        for combo in itertools.product(*(sweep[k] for k in keys)) if keys else [()]:
            params = {**entry, **dict(zip(keys, combo))}
            excitation = make_excitation(params, file=file, where=where)
            base = label or excitation.kind
            suffix = "-".join(f"{k}={_format_value(v)}" for k, v in zip(keys, combo))
            runs.append(PlannedRun(f"{base}-{suffix}" if suffix else base, excitation))
    if not runs:
        raise ConfigError(f"[{table}]: the plan has no runs", where=file)
    return runs


def parse_compact(spec: str) -> dict[str, Any]:
    """``"sine:amplitude=1|2,frequency_hz=1,cycles=5"`` -> a run table (with ``sweep``)."""
    where = f"--excitation {spec!r}"
    kind, _, rest = spec.partition(":")
    if not kind.strip():
        raise ConfigError("expected KIND:key=value,...", where=where)
    table: dict[str, Any] = {"kind": kind.strip()}
    sweep: dict[str, list[Any]] = {}
    for item in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise ConfigError(f"expected key=value, got {item!r}", where=where)
        key = key.strip()
        if "|" in value:
            sweep[key] = [parse_scalar(v) for v in value.split("|")]
        elif "/" in value:
            table[key] = [parse_scalar(v) for v in value.split("/")]
        else:
            table[key] = parse_scalar(value)
    if sweep:
        table["sweep"] = sweep
    return table


def plan_from_compact(specs: list[str]) -> list[PlannedRun]:
    runs: list[PlannedRun] = []
    for spec in specs:
        runs += expand_runs([parse_compact(spec)], file=f"--excitation {spec!r}", table="excitation")
    return runs


def _plans_folder() -> Path:
    """experiments/plans as installed (package data hilbench.plans), else next to the source tree."""
    try:
        return Path(str(resources.files("hilbench.plans")))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / "experiments" / "plans"


def builtin_plans() -> dict[str, Path]:
    """The packaged plans of the papers by name (file stem, e.g. ``paper-004-tracking``)."""
    return {p.stem: p for p in sorted(_plans_folder().glob("*.toml"))}


def resolve_plan_path(name_or_path: str | Path) -> Path:
    """A plan file by path, or a packaged plan by name: ``paper-004-tracking``, ``004-tracking`` or ``004``
    (a unique prefix after ``paper-``), so plans work from any directory after ``pip install``."""
    path = Path(name_or_path)
    if path.exists():
        return path
    text = str(name_or_path)
    plans = builtin_plans()
    stem = Path(text).stem if text.endswith(".toml") else text
    if Path(text).name != text and not path.exists():  # a path with folders: look for its file name too
        stem = Path(text).stem
    for candidate in (stem, f"paper-{stem}"):
        if candidate in plans:
            return plans[candidate]
    matches = [name for name in plans if name.startswith(f"paper-{stem}-") or name.startswith(f"{stem}-")]
    if len(matches) == 1:
        return plans[matches[0]]
    short = ", ".join(name.removeprefix("paper-") for name in plans)
    if len(matches) > 1:
        raise ConfigError(f"the plan name matches several packaged plans: {', '.join(matches)}", where=text,
                          hint="give one of them in full")
    raise ConfigError(f"no such file, and no packaged plan of that name; packaged plans: {short}", where=text,
                      hint="give a TOML path, or a packaged plan's name such as 004-tracking")


def load_plan_file(path: str | Path) -> list[PlannedRun]:
    path = resolve_plan_path(path)
    _, data = read_toml(path)
    top = check_table(data, {"runs": Key("tables", required=True), "description": Key("str", default="")},
                      file=str(path), table="")
    return expand_runs(top["runs"], file=str(path), table="runs")


def check_plan(runs: list[PlannedRun], actuator: ActuatorLimits, sample_rate_hz: float) -> dict[str, Any]:
    """Refuse a plan that would leave the actuator's range or slew limit; return its totals.

    Walks every sample chunk by chunk (memory stays bounded for any length). The slew limit is
    checked within each run; between runs the rig ramps at ``max_rate`` by itself.
    """
    unit = actuator.unit
    max_step = actuator.max_rate / sample_rate_hz * (1 + 1e-9)
    total = 0
    for index, run in enumerate(runs, start=1):
        name = f"plan run {index} {run.label!r}"
        start = 0
        previous: float | None = None
        for chunk in run.excitation.chunks(sample_rate_hz):
            bad = np.flatnonzero(~np.isfinite(chunk) | (chunk < actuator.min) | (chunk > actuator.max))
            if bad.size:
                k = int(bad[0])
                raise PlanLimitError(
                    f"{name} at t={(start + k) / sample_rate_hz:.6g} s: value {chunk[k]:.6g} {unit} is outside "
                    f"the actuator range [{actuator.min:g}, {actuator.max:g}] {unit}",
                    hint="lower the amplitude or offset, or correct [actuator] min/max",
                )
            steps = np.abs(np.diff(chunk if previous is None else np.concatenate([[previous], chunk])))
            fast = np.flatnonzero(steps > max_step)
            if fast.size:
                k = int(fast[0]) + (0 if previous is None else -1) + 1
                rate = steps[fast[0]] * sample_rate_hz
                raise PlanLimitError(
                    f"{name} at t={(start + k) / sample_rate_hz:.6g} s: value {chunk[k]:.6g} {unit} changes at "
                    f"{rate:.6g} {unit}/s, above the slew limit max_rate = {actuator.max_rate:g} {unit}/s",
                    hint="lower the frequency or amplitude, give steps a rise_s, or correct [actuator] max_rate",
                )
            previous = float(chunk[-1])
            start += chunk.shape[0]
        total += start
    return {"runs": len(runs), "samples": total, "duration_s": total / sample_rate_hz}
