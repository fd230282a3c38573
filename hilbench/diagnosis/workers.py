"""Independent refits of a diagnosis round, run side by side in worker processes.

A diagnosis round refits the model once per candidate effect and once per alternative base; the
refits share nothing but their inputs (the dataset, the fitted base, the split), so they can run at
the same time. They are CPU-bound Python around numpy and numba, which holds the GIL for much of a
fit, so the workers are processes. They are forked: a child starts with the parent's memory (the
dataset, the base, the compiled kernels) and only the results travel back, pickled. Results come
back in the order of the tasks, so the verdicts do not depend on ``jobs``; a task's exception is
raised in the caller as if the task had run there.

Where fork is not the platform's safe default (Windows, macOS) or the caller is itself a daemonic
worker (a multiprocessing pool's), the tasks run one after the other in the caller. Docs:
docs/decisions/0028.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Any, TypeVar

from hilbench import progress
from hilbench.errors import UserError

T = TypeVar("T")

#: more processes than this gain little: a round has about a dozen refits, the slowest about a
#: third of the round's work
MAX_JOBS = 8

# The tasks of the pool being run. Set before the pool forks its workers, which inherit them; a
# worker receives only the index of the task to run (closures need not be picklable).
_tasks: Sequence[Callable[[], Any]] = ()
_in_worker = False  # a worker's own tasks run in it: no pools of pools


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform tells)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def default_jobs() -> int:
    """Worker processes of a diagnosis when the caller does not say: one per core, at most MAX_JOBS."""
    return max(1, min(available_cores(), MAX_JOBS))


def check_jobs(jobs: int | None) -> int:
    """``jobs`` validated (None: :func:`default_jobs`); a UserError names the value otherwise."""
    if jobs is None:
        return default_jobs()
    if isinstance(jobs, bool) or not isinstance(jobs, int) or not 1 <= jobs <= 256:
        raise UserError(f"jobs {jobs!r}: expected a whole number of worker processes from 1 to 256",
                        where="--jobs")
    return jobs


def _can_fork() -> bool:
    return (sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()
            and not multiprocessing.current_process().daemon and not _in_worker)


def _worker_start() -> None:
    global _in_worker
    _in_worker = True
    # the parent shows the progress of the round; a child's nested fits would draw over it
    progress._display = None


def _run(index: int) -> Any:
    return _tasks[index]()


def run_tasks(tasks: Sequence[Callable[[], T]], jobs: int, advance: Callable[..., None] = progress._noop,
              names: Sequence[str] | None = None) -> list[T]:
    """Every task's result, in the order of ``tasks``; up to ``jobs`` run at once (module docstring).

    ``advance(1, text)`` is called as each task finishes (``names`` label them). Long tasks should
    come first: the pool hands them out in order."""
    labels = list(names) if names is not None else [str(k) for k in range(len(tasks))]
    if jobs <= 1 or len(tasks) <= 1 or not _can_fork():
        out = []
        for task, label in zip(tasks, labels):
            out.append(task())
            advance(1, f"{label} done")
        return out
    global _tasks
    previous, _tasks = _tasks, tasks
    try:
        context = multiprocessing.get_context("fork")
        with ProcessPoolExecutor(max_workers=min(jobs, len(tasks)), mp_context=context,
                                 initializer=_worker_start) as pool:
            futures = {pool.submit(_run, k): k for k in range(len(tasks))}
            results: dict[int, Any] = {}
            pending = set(futures)
            try:
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for f in done:
                        results[futures[f]] = f.result()  # a task's exception is raised here
                        advance(1, f"{labels[futures[f]]} done")
            except BaseException:
                for f in pending:
                    f.cancel()
                raise
        return [results[k] for k in range(len(tasks))]
    finally:
        _tasks = previous
