"""A batch: one command over every recording of some sources, on Dask, resumable, one row per task.

:func:`run_batch` finds the recordings, keys each by its content and the options, skips what the
output folder already holds, runs the rest on the engine and keeps every row the moment it arrives.
Two files with the same bytes are computed once and get a row each. A file that cannot be read on
the client (permissions, a folder named .h5) gets its failed row without reaching a worker; a file
that cannot be parsed fails on its worker like any other task. An interrupt (Ctrl-C) stops the
submissions, keeps every finished row and still writes the table, the summary and the report.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hilbench import progress
from hilbench.archive.engine import DaskEngine
from hilbench.archive.results import HASHES_FILE, ResultStore
from hilbench.archive.sources import HashCache, find_recordings
from hilbench.archive.tasks import (
    COMMANDS,
    EACH,
    ArchiveTask,
    base_row,
    run_task,
)
from hilbench.errors import UserError


@dataclass
class BatchSummary:
    """What a batch did; ``to_json`` is summary.json."""

    command: str
    options: dict[str, Any]
    output: Path
    tasks: int = 0
    skipped: int = 0  # rows the folder already held
    computed: int = 0  # rows computed by this batch
    failed: int = 0  # rows with status failed, among this batch's tasks
    interrupted: bool = False
    cluster: dict[str, Any] = field(default_factory=dict)
    wall_s: float = 0.0
    files: dict[str, str] = field(default_factory=dict)
    rows: list[dict[str, Any]] = field(default_factory=list)

    def __repr__(self) -> str:
        return (f"BatchSummary({self.command}: {len(self.rows)} rows of {self.tasks}, {self.failed} failed, "
                f"{self.computed} computed, {self.skipped} already there{', interrupted' if self.interrupted else ''};"
                f" {self.output / 'results.parquet'})")

    def to_json(self) -> dict[str, Any]:
        done = [r for r in self.rows if r["status"] == "done"]
        task_s = sorted(float(r["task_s"]) for r in done if r.get("task_s") == r.get("task_s"))
        return {
            "command": self.command, "options": self.options, "output": str(self.output),
            "tasks": self.tasks, "rows": len(self.rows), "done": len(done), "failed": self.failed,
            "skipped_already_done": self.skipped, "computed": self.computed, "interrupted": self.interrupted,
            "missing": self.tasks - len(self.rows), "cluster": self.cluster, "wall_s": round(self.wall_s, 3),
            "task_s": {"median": task_s[len(task_s) // 2], "max": task_s[-1], "sum": sum(task_s)} if task_s else None,
            "failures": [{"file": r["file"], "run": r["run"], "error": r["error"]}
                         for r in self.rows if r["status"] != "done"],
            "files": self.files,
        }


def _run_names(path: Path) -> list[str]:
    from hilbench.recording.hdf5 import Recording

    return [run.name for run in Recording(path).runs]


def plan_tasks(command: str, paths: Sequence[Path], options: dict[str, Any], each: str, hashes: HashCache,
               ) -> tuple[list[ArchiveTask], list[dict[str, Any]]]:
    """The tasks of a batch, and the failed rows of files the client could not read or list."""
    tasks: list[ArchiveTask] = []
    failed: list[dict[str, Any]] = []
    for path in paths:
        try:
            digest = hashes.digest(path)
        except OSError as exc:
            # keyed by the path: there is no content to key it by, and the next batch tries again
            row = base_row(ArchiveTask(command, str(path), f"unreadable:{path}", options))
            row["error"] = f"cannot read the file: {exc.strerror or exc}"
            failed.append(row)
            continue
        if each == "file":
            tasks.append(ArchiveTask(command, str(path), digest, options))
            continue
        try:
            names = _run_names(path)
        except UserError:  # not a recording: one task for the file, which fails on its worker with the reason
            tasks.append(ArchiveTask(command, str(path), digest, options))
            continue
        tasks.extend(ArchiveTask(command, str(path), digest, options, run=name) for name in names)
    return tasks, failed


def run_batch(command: str, sources: Sequence[str], options: dict[str, Any], output: Path, *,
              scheduler: str | None = None, workers: int | None = None, each: str = "file",
              retry_failed: bool = False, report: bool = True,
              note: Callable[[str], None] = lambda _: None) -> BatchSummary:
    """Run ``command`` (fit, diagnose, online) with ``options`` over the recordings of ``sources``.

    Rows go to ``output`` (a folder: rows.jsonl as they arrive; results.parquet, results.csv,
    summary.json and report.html at the end). Raises KeyboardInterrupt after writing them when
    interrupted.
    """
    if command not in COMMANDS:
        raise UserError(f"{command!r}: expected one of {', '.join(COMMANDS)}", where="COMMAND")
    if each not in EACH:
        raise UserError(f"{each!r}: expected one of {', '.join(EACH)}", where="--each")
    if output.exists() and not output.is_dir():
        raise UserError("expected a folder for the results, found a file", where=str(output))
    started = time.monotonic()
    engine = DaskEngine(scheduler, workers)  # its settings are checked before anything is written
    if engine.address:
        engine.probe()
    paths = find_recordings(sources)
    store = ResultStore(output)
    summary = BatchSummary(command, options, output)
    hashes = HashCache(output / HASHES_FILE)
    tasks: list[ArchiveTask] = []
    unreadable: list[dict[str, Any]] = []
    try:
        tasks, unreadable = plan_tasks(command, paths, options, each, hashes)
        hashes.save()
        for row in unreadable:
            store.add(row)
        order = [t.key for t in tasks] + [r["key"] for r in unreadable]
        summary.tasks = len(order)
        todo: dict[str, ArchiveTask] = {}
        for task in tasks:
            if store.done(task.key, retry_failed):
                summary.skipped += 1
            elif task.key not in todo:  # identical content and options: computed once
                todo[task.key] = task
        note(f"{len(paths)} recordings, {summary.tasks} tasks: {summary.skipped} already in {output}, "
             f"{len(todo)} to run")
        if todo:
            pending = list(todo.values())
            with engine:
                summary.cluster = engine.describe()
                note(f"running on {summary.cluster['cluster']} Dask cluster {summary.cluster['scheduler']}: "
                     f"{summary.cluster['workers']} workers, {summary.cluster['threads']} threads")
                with progress.task(f"batch {command}", total=len(pending)) as advance:
                    for outcome in engine.map_unordered(run_task, pending, [t.key for t in pending]):
                        task = pending[outcome.index]
                        if outcome.ok:
                            row = outcome.result
                        else:  # the worker died, or the task could not even start
                            row = base_row(task)
                            row["error"] = outcome.error
                        store.add(row)
                        summary.computed += 1
                        advance(1, f"batch {command}: {Path(task.file).name}")
    except KeyboardInterrupt:
        summary.interrupted = True
        raise
    finally:
        store.close()
        summary.rows = _rows_for(store, tasks, unreadable)
        summary.failed = sum(r["status"] != "done" for r in summary.rows)
        summary.wall_s = time.monotonic() - started
        if summary.rows or summary.tasks:
            summary.files = {k: str(v) for k, v in store.write_tables(summary.rows).items()}
            if report:
                from hilbench.report.archive_report import write_archive_report

                summary.files["report"] = str(write_archive_report(summary.rows, output / "report.html", command))
            summary.files["summary"] = str(output / "summary.json")
            store.write_summary(summary.to_json())
    return summary


def _rows_for(store: ResultStore, tasks: Sequence[ArchiveTask], unreadable: list[dict[str, Any]],
              ) -> list[dict[str, Any]]:
    """The table of this batch: a row per task that has one, named after the task's own file."""
    rows = []
    for task in tasks:
        found = store.table([task.key])
        if found:
            row = dict(found[0])
            row.update(file=task.file, name=Path(task.file).name, run=task.run)
            rows.append(row)
    rows.extend(store.table([r["key"] for r in unreadable]))
    return rows


__all__ = ["BatchSummary", "plan_tasks", "run_batch"]
