"""Independent refits of a diagnosis round, run side by side in worker processes.

A diagnosis round refits the model once per candidate effect and once per alternative base; the
refits share nothing but their inputs (the dataset, the fitted base, the split), so they can run at
the same time. They are CPU-bound Python around numpy and numba, which holds the GIL for much of a
fit, so the workers are processes. They are forked: a child starts with the parent's memory (the
dataset, the base, the compiled kernels) and only the results travel back, pickled. A result
refers to the caller's recorded runs (a fit's runs hold their data): the objects named ``shared``
are pickled as references and resolved to the caller's own on return, so each result carries its
fit's arrays only, not another copy of the recording. Results come back in the order of the tasks,
so the verdicts do not depend on ``jobs``; a task's exception is raised in the caller as if the task
had run there.

Where fork is not the platform's safe default (Windows, macOS) or the caller is itself a daemonic
worker (a multiprocessing pool's), the tasks run one after the other in the caller. Docs:
docs/decisions/0028.
"""

from __future__ import annotations

import ctypes
import io
import multiprocessing
import os
import pickle
import signal
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
_shared: dict[int, int] = {}  # id() of an object the caller shares (the same in a forked child) -> index
_in_worker = False  # a worker's own tasks run in it: no pools of pools
_PR_SET_PDEATHSIG = 1  # linux/prctl.h


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
        raise UserError(f"expected a whole number of worker processes from 1 to 256, got {jobs!r}", where="--jobs")
    return jobs


def _can_fork() -> bool:
    return (sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()
            and not multiprocessing.current_process().daemon and not _in_worker)


def _worker_start(parent: int) -> None:
    global _in_worker
    _in_worker = True
    # the parent shows the progress of the round; a child's nested fits would draw over it
    progress._display = None
    _end_with_parent(parent)


def _end_with_parent(parent: int) -> None:
    """A worker of a caller that was killed (SIGTERM, SIGKILL) would wait for tasks forever, holding
    a copy of its memory: Linux sends it SIGTERM when the caller ends (prctl PR_SET_PDEATHSIG)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the caller ended before the request took effect
        os._exit(1)


class _SharedPickler(pickle.Pickler):
    def persistent_id(self, obj: Any) -> int | None:
        return _shared.get(id(obj))


class _SharedUnpickler(pickle.Unpickler):
    def __init__(self, data: bytes, shared: Sequence[Any]):
        super().__init__(io.BytesIO(data))
        self.shared = shared

    def persistent_load(self, pid: Any) -> Any:
        return self.shared[pid]


def _run(index: int) -> bytes:
    out = io.BytesIO()
    _SharedPickler(out, protocol=pickle.HIGHEST_PROTOCOL).dump(_tasks[index]())
    return out.getvalue()


def _stop(pool: ProcessPoolExecutor) -> None:
    """Cancel the tasks not started and end the workers now, mid-fit."""
    # the processes first: shutdown forgets them (Python 3.14 has terminate_workers() for this)
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.terminate()


def run_tasks(tasks: Sequence[Callable[[], T]], jobs: int, advance: Callable[..., None] = progress._noop,
              names: Sequence[str] | None = None, shared: Sequence[Any] = ()) -> list[T]:
    """Every task's result, in the order of ``tasks``; up to ``jobs`` run at once (module docstring).

    ``advance(1, text)`` is called as each task finishes (``names`` label them). Long tasks should
    come first: the pool hands them out in order. ``shared``: objects the results may refer to
    that stay the caller's (the recorded runs), not copied back."""
    labels = list(names) if names is not None else [str(k) for k in range(len(tasks))]
    if jobs <= 1 or len(tasks) <= 1 or not _can_fork():
        out = []
        for task, label in zip(tasks, labels):
            out.append(task())
            advance(1, f"{label} done")
        return out
    global _tasks, _shared
    previous, _tasks = _tasks, tasks
    previous_shared, _shared = _shared, {id(obj): k for k, obj in enumerate(shared)}
    try:
        context = multiprocessing.get_context("fork")
        with ProcessPoolExecutor(max_workers=min(jobs, len(tasks)), mp_context=context,
                                 initializer=_worker_start, initargs=(os.getpid(),)) as pool:
            futures = {pool.submit(_run, k): k for k in range(len(tasks))}
            results: dict[int, Any] = {}
            pending = set(futures)
            try:
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for f in done:
                        # a task's exception is raised here
                        results[futures[f]] = _SharedUnpickler(f.result(), shared).load()
                        advance(1, f"{labels[futures[f]]} done")
            except BaseException:
                _stop(pool)  # an error or Ctrl-C: the other refits are not waited for
                raise
        return [results[k] for k in range(len(tasks))]
    finally:
        _tasks, _shared = previous, previous_shared
