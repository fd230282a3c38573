"""One command on one recording: the task a batch runs on a worker, and the row it returns.

A task calls the library function its single command calls (`fit` -> :func:`fit_or_evaluate`,
`diagnose` -> :func:`hilbench.diagnosis.diagnose.diagnose`, `online` -> :func:`online_on_recordings`)
with the same options, builds the document that command prints with ``--json``, and turns it into
one row (:func:`row_fields`). So a recording gives the same row from `hilbench batch` as from the
single command's JSON. Whatever goes wrong inside becomes a row with status ``failed`` and its
reason on one line; only the worker's death escapes, and the engine makes that a row too.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hilbench import __version__
from hilbench.errors import UserError

COMMANDS = ("fit", "diagnose", "online")
#: every run of the file in one task (as the single command reads a file), or each run alone
EACH = ("file", "run")
ALL_RUNS = "*"


#: every option of each command, with the single command's default (the keys the CLI's batch writes)
DEFAULTS: dict[str, dict[str, Any]] = {
    "fit": {"model": None, "train": [], "test": [], "train_fraction": None},
    "diagnose": {"model": None, "add": None, "auto": False, "train": [], "test": [], "train_fraction": 0.7,
                 "from_s": None, "to_s": None, "exclude": []},
    "online": {"train": [], "train_fraction": 0.3, "orders": "3,5", "forgetting": 1.0,
               "forgetting_kind": "directional", "delta": 1.0e5, "online_model": None, "settle": 0.5,
               "global_starts": 16},
}


def default_options(command: str, given: dict[str, Any]) -> dict[str, Any]:
    """The options of ``command`` with the single command's defaults where ``given`` is silent (for
    `online`, ``model`` names the saved front end, as `hilbench online --model`)."""
    if command not in DEFAULTS:
        raise UserError(f"{command!r}: expected one of {', '.join(COMMANDS)}", where="command")
    given = dict(given)
    if command == "online" and "model" in given:
        given["online_model"] = given.pop("model")
    unknown = sorted(set(given) - set(DEFAULTS[command]))
    if unknown:
        raise UserError(f"{', '.join(unknown)}: not an option of {command}; expected "
                        f"{', '.join(k for k in DEFAULTS[command])}", where="options")
    options = {**DEFAULTS[command], **given}
    if command in ("fit", "diagnose") and not options["model"]:
        raise UserError(f"{command} needs model= (a spec such as 'pi', or a FIT.json)", where="model")
    for key in ("train", "test", "exclude"):
        if key in options:
            options[key] = list(options[key])
    return options


@dataclass(frozen=True)
class ArchiveTask:
    """What a worker needs: the command, its options (JSON-ready), the recording and which runs."""

    command: str
    file: str  # absolute path, the same on every worker (a shared filesystem)
    content_hash: str
    options: dict[str, Any] = field(hash=False)
    run: str = ALL_RUNS  # a run's group name, or ALL_RUNS

    @property
    def key(self) -> str:
        """The result's identity: content, run, command, options and the hilbench version that computed it."""
        return task_key(self.content_hash, self.run, self.command, self.options)


def task_key(content_hash: str, run: str, command: str, options: dict[str, Any]) -> str:
    text = json.dumps({"sha256": content_hash, "run": run, "command": command, "options": options,
                       "hilbench": __version__}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _one_line(exc: BaseException) -> str:
    text = exc.line() if isinstance(exc, UserError) else f"{type(exc).__name__}: {exc}"
    return " ".join(text.split())[:500]


def _dataset(task: ArchiveTask) -> Any:
    from hilbench.identify.dataset import Dataset

    dataset = Dataset.load(task.file)
    return dataset if task.run == ALL_RUNS else dataset.only(task.run)


def _runs_document(task: ArchiveTask, dataset: Any) -> dict[str, Any]:
    """What the row says of the recording itself: when, how long, units, the auxiliary channels' means."""
    from hilbench.recording.hdf5 import Recording

    created = Recording(task.file).attrs.get("created", "")
    aux: dict[str, list[np.ndarray]] = {}
    for run in dataset.runs:
        for name, values in run.aux.items():
            aux.setdefault(name, []).append(values)
    means = {name: float(np.nanmean(np.concatenate(parts))) for name, parts in aux.items()
             if sum(p.size for p in parts)}
    return {
        "recorded": str(created or ""),
        "runs": len(dataset.runs),
        "samples": int(sum(len(r) for r in dataset.runs)),
        "sample_rate_hz": float(dataset.runs[0].sample_rate_hz) if dataset.runs else math.nan,
        "input_unit": dataset.input_unit,
        "output_unit": dataset.output_unit,
        "aux_means": means,
    }


def command_document(command: str, data: Any, options: dict[str, Any]) -> dict[str, Any]:
    """The document `hilbench COMMAND DATA --json` prints for these options (less the output paths)."""
    if command == "fit":
        from hilbench.identify.fitting import fit_or_evaluate, is_model_file

        fraction = options.get("train_fraction")
        if fraction is None and not is_model_file(options["model"]):
            fraction = 0.7
        result = fit_or_evaluate(data, options["model"], train=options.get("train") or None,
                                 test=options.get("test") or None, train_fraction=fraction)
        return result.to_json()
    if command == "diagnose":
        from hilbench.diagnosis.diagnose import diagnose
        from hilbench.identify.trimming import Trim, parse_window

        trim = Trim(auto=True, from_s=options.get("from_s"), to_s=options.get("to_s"),
                    windows=[parse_window(w) for w in options.get("exclude", [])])
        # one process per task: the batch's parallelism is across recordings (the result does not depend on jobs)
        return diagnose(data, options["model"], train=options.get("train") or None, test=options.get("test") or None,
                        add=options.get("add"), auto=bool(options.get("auto")),
                        train_fraction=options.get("train_fraction", 0.7), trim=trim, jobs=1).to_json()
    if command == "online":
        from hilbench.cli.online_commands import online_on_recordings, parse_orders

        M, N = parse_orders(options.get("orders", "3,5"))
        model = options.get("online_model")
        doc, _, _ = online_on_recordings(
            data, train=list(options.get("train", [])), train_fraction=options.get("train_fraction", 0.3), M=M, N=N,
            forgetting=options.get("forgetting", 1.0), forgetting_kind=options.get("forgetting_kind", "directional"),
            delta=options.get("delta", 1.0e5), model=Path(model) if model else None, settle=options.get("settle", 0.5),
            global_starts=options.get("global_starts", 16), note=lambda _: None)
        return doc
    raise UserError(f"{command!r}: expected one of {', '.join(COMMANDS)}", where="COMMAND")


def _finite(value: Any) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return math.nan
    return number if math.isfinite(number) else math.nan


def _parameters(model_dict: dict[str, Any] | None) -> list[dict[str, Any]]:
    if not model_dict:
        return []
    parameters = model_dict.get("parameters", {})
    shape = [{"name": f"{p['component']}.{p['name']}", "value": p["value"], "unit": p["unit"]}
             for p in parameters.get("shape", [])]
    return shape + [{"name": w["name"], "value": w["value"], "unit": w["unit"]} for w in parameters.get("weights", [])]


def row_fields(command: str, doc: dict[str, Any]) -> dict[str, Any]:
    """The result columns of a row, from the document the single command prints with ``--json``."""
    fields: dict[str, Any] = {"final_spec": "", "effects_found": "", "effects_added": "", "parameters": "[]",
                              "train_rmse": math.nan, "validation_rmse": math.nan, "validation_erms_pct": math.nan,
                              "validation_re_n2_pct": math.nan, "online_re_n2_pct": math.nan,
                              "offline_re_n2_pct": math.nan, "persistence_re_n2_pct": math.nan}
    if command in ("fit", "diagnose"):
        metrics = doc.get("metrics", {})
        train, validation = metrics.get("train") or {}, metrics.get("validation") or {}
        fields.update(train_rmse=_finite(train.get("rmse")), validation_rmse=_finite(validation.get("rmse")),
                      validation_erms_pct=_finite(validation.get("erms_pct")),
                      validation_re_n2_pct=_finite(validation.get("re_n2_pct")), final_spec=doc.get("spec", ""),
                      metrics=json.dumps(metrics, sort_keys=True))
        fields["parameters"] = json.dumps(_parameters(doc.get("model")))
    if command == "diagnose":
        fields["effects_found"] = ";".join(e["effect"] for e in doc.get("effects", []) if e.get("significant"))
        fields["effects_added"] = ";".join(s["added"] for s in doc.get("steps", []) if s.get("added"))
    if command == "online":
        runs = doc.get("runs", [])

        def mean_of(kind: str) -> float:
            values = [_finite((r.get(kind) or {}).get("re_n2_pct")) for r in runs]
            values = [v for v in values if math.isfinite(v)]
            return float(np.mean(values)) if values else math.nan

        fields.update(online_re_n2_pct=mean_of("online"), offline_re_n2_pct=mean_of("offline"),
                      persistence_re_n2_pct=mean_of("persistence"), final_spec=doc.get("offline", {}).get("spec", ""),
                      train_rmse=_finite(doc.get("offline", {}).get("train", {}).get("rmse")),
                      metrics=json.dumps({r["run"]: {k: r.get(k) for k in ("online", "offline", "persistence")}
                                          for r in runs}, sort_keys=True))
        fields["parameters"] = json.dumps([{"name": name, "value": value, "unit": ""} for r in runs[-1:]
                                           for name, value in r.get("weights_final", {}).items()])
    return fields


def base_row(task: ArchiveTask) -> dict[str, Any]:
    """The columns every row has, filled from the task alone (what a failed row keeps)."""
    return {
        "file": task.file, "name": Path(task.file).name, "run": task.run, "content_hash": task.content_hash,
        "command": task.command, "spec": str(task.options.get("model", "")),
        "options": json.dumps(task.options, sort_keys=True), "key": task.key, "status": "failed", "error": "",
        "hilbench_version": __version__,
    }


def run_task(task: ArchiveTask) -> dict[str, Any]:
    """Run the task here (a worker) and return its row; never raises for the task's own failures."""
    from threadpoolctl import threadpool_limits

    started = time.perf_counter()
    row = base_row(task)
    row["worker"] = f"{socket.gethostname()}:{os.getpid()}"
    try:
        # one core per task: the engine runs one task per worker thread, one thread per worker
        with threadpool_limits(1):
            dataset = _dataset(task)
            read_s = time.perf_counter() - started
            row.update(_runs_document(task, dataset))
            doc = command_document(task.command, dataset, task.options)
        row.update(row_fields(task.command, doc))
        row.update(status="done", read_s=read_s, compute_s=time.perf_counter() - started - read_s,
                   notes=json.dumps(doc.get("notes", [])))
    except Exception as exc:  # noqa: BLE001 - a task's failure is its row's status, the batch goes on
        row["error"] = _one_line(exc)
    row["task_s"] = time.perf_counter() - started
    row["finished"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    if isinstance(row.get("aux_means"), dict):
        row["aux_means"] = json.dumps(row["aux_means"], sort_keys=True)
    return row
