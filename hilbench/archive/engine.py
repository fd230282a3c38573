"""Tasks spread over Dask: a local cluster sized to the machine, or a cluster the user already runs.

Without a scheduler address (``--scheduler``, else ``$DASK_SCHEDULER_ADDRESS``) the engine starts a
``distributed.LocalCluster`` on 127.0.0.1: one worker process per core (``--workers``), one thread
each, because a task is CPU-bound Python around numpy and numba and a worker per core is what runs
them side by side. With an address it connects to that scheduler and uses its workers as they are.
Either way a task goes to a worker as a few hundred bytes (the command, its options, a path and a
hash), the worker reads the recording itself, and only the task's row comes back: nothing large
travels through the scheduler. The workers therefore need the same recordings at the same paths
(a shared filesystem) and the same hilbench version, which is checked before anything is submitted.

A task that raises comes back as its reason; a worker that dies while running a task is restarted
by its nanny, and the task, retried by Dask up to ``allowed_failures`` more times on other workers,
then comes back as "the worker running it died". Docs: docs/decisions/0091.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from hilbench import __version__
from hilbench.errors import UserError

SCHEDULER_ENV = "DASK_SCHEDULER_ADDRESS"
#: seconds to wait for a scheduler to answer and for its first worker to join
CONNECT_TIMEOUT_S = 20.0


def _worker_facts() -> dict[str, Any]:
    """What the client checks of every worker before it submits anything (runs on the worker)."""
    import platform

    import hilbench

    return {"hilbench": hilbench.__version__, "python": platform.python_version(), "pid": os.getpid()}


def _warm() -> int:
    """Import what every task uses, once per worker, before the first task's clock starts."""
    import hilbench.archive.tasks  # noqa: F401
    import hilbench.diagnosis.diagnose  # noqa: F401
    import hilbench.identify.fitting  # noqa: F401

    return os.getpid()


def _ignore_interrupts() -> None:
    """A local worker leaves Ctrl-C to the client: the terminal sends SIGINT to the whole process
    group, and a worker that raised KeyboardInterrupt would die with a traceback mid-task instead
    of being closed by the client, which keeps the finished rows first."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _plugin(sys_path: Sequence[str], local: bool) -> Any:
    from distributed.diagnostics.plugin import WorkerPlugin

    class WorkerSetup(WorkerPlugin):
        name = "hilbench-worker-setup"

        def setup(self, worker: Any) -> None:  # every worker, those the nanny restarts included
            import sys

            for folder in reversed(sys_path):
                if folder not in sys.path:
                    sys.path.insert(0, folder)
            if local:
                _ignore_interrupts()

    return WorkerSetup()


@dataclass
class Outcome:
    """What came back for one item: its result, or why there is none."""

    index: int
    result: Any = None
    error: str = ""

    @property
    def ok(self) -> bool:
        return not self.error


class DaskEngine:
    """A Dask client for one batch; a context manager that closes what it started."""

    def __init__(self, scheduler: str | None = None, workers: int | None = None, *, allowed_failures: int = 1,
                 local_directory: str | None = None, sys_path: Sequence[str] = ()):
        self.address = scheduler or os.environ.get(SCHEDULER_ENV) or None
        if workers is not None and workers < 1:
            raise UserError(f"{workers}: expected at least 1 worker", where="--workers")
        if workers is not None and self.address:
            raise UserError("--workers sizes the local cluster; an existing cluster keeps its own workers",
                            where="--workers", hint=f"leave out --workers with --scheduler (or ${SCHEDULER_ENV})")
        self.workers = workers
        self.allowed_failures = allowed_failures
        self.local_directory = local_directory
        self.sys_path = list(sys_path)  # folders a task's own modules are imported from (the benchmarks')
        self.client: Any = None
        self.cluster: Any = None

    # -- connection -----------------------------------------------------------------------------

    def __enter__(self) -> DaskEngine:
        try:
            import dask
            from distributed import Client, LocalCluster
        except ImportError as exc:  # pragma: no cover - dask is a dependency; a broken install says so
            raise UserError(f"Dask is not importable ({exc})", hint="pip install 'dask[distributed]'") from None
        for name in ("distributed", "distributed.nanny", "distributed.scheduler", "distributed.worker",
                     "distributed.core", "distributed.comm"):
            logging.getLogger(name).setLevel(logging.ERROR)  # its INFO lines would bury the progress bar
        if self.address:
            self.probe()
            try:
                self.client = Client(self.address, timeout=f"{CONNECT_TIMEOUT_S}s")
            except (OSError, TimeoutError, ValueError) as exc:
                raise UserError(f"no Dask scheduler answers at {self.address} ({' '.join(str(exc).split())[:200]})",
                                where="--scheduler", hint="start one with `dask scheduler`, or leave out --scheduler "
                                f"(and ${SCHEDULER_ENV}) for a local cluster") from None
            try:
                self.client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
            except (TimeoutError, OSError):
                self.close()
                raise UserError(f"the scheduler at {self.address} has no workers (none joined in "
                                f"{CONNECT_TIMEOUT_S:g} s)", where="--scheduler",
                                hint=f"start workers with `dask worker {self.address}`") from None
            self._check_workers()
        else:
            from hilbench.diagnosis.workers import available_cores

            n = self.workers or available_cores()
            # a dead worker's task is retried this many times before it is reported
            environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ"))
            # Dask sets MALLOC_TRIM_THRESHOLD_ in its workers to return memory sooner; setting it at all
            # turns off glibc's adaptive mmap threshold, so every large numpy temporary is mmapped and
            # faulted in afresh: a diagnosis of 1e5 samples took 14.2 s on a worker against 5.0 s in
            # this process. Its statistical profiler, sampling the task's stack every 10 ms, cost most
            # of the rest (6.0 -> 5.2 s). docs/decisions/0091.
            environ["MALLOC_TRIM_THRESHOLD_"] = None
            # worker-saturation 1.0: a worker holds only the task it runs, the rest wait at the scheduler,
            # so a worker killed by one recording takes no other task down with it (Dask counts a death
            # against every task the worker held)
            with dask.config.set({"distributed.scheduler.allowed-failures": self.allowed_failures,
                                  "distributed.scheduler.worker-saturation": 1.0,
                                  "distributed.worker.daemon": True,
                                  "distributed.nanny.pre-spawn-environ": environ,
                                  "distributed.worker.profile.enabled": False}):
                self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                            dashboard_address=None, silence_logs=logging.ERROR,
                                            local_directory=self.local_directory)
                self.client = Client(self.cluster)
        if self.sys_path or self.cluster is not None:
            self.client.register_plugin(_plugin(self.sys_path, local=self.cluster is not None))
        self.client.run(_warm)
        return self

    def probe(self) -> None:
        """Refuse at once an address nothing listens on (the client would retry until its timeout)."""
        import socket
        from urllib.parse import urlsplit

        parts = urlsplit(self.address if "://" in self.address else f"tcp://{self.address}")
        if parts.scheme not in ("tcp", "tls"):
            return  # inproc, ucx, ws: the client says what is wrong
        try:
            port = parts.port
        except ValueError:
            port = None
        if not parts.hostname or port is None:
            raise UserError(f"{self.address!r}: expected tcp://HOST:PORT", where="--scheduler")
        try:
            socket.create_connection((parts.hostname, port), timeout=5.0).close()
        except OSError as exc:
            raise UserError(f"no Dask scheduler answers at {self.address} ({exc.strerror or exc})", where="--scheduler",
                            hint="start one with `dask scheduler`, or leave out --scheduler "
                            f"(and ${SCHEDULER_ENV}) for a local cluster") from None

    def _check_workers(self) -> None:
        facts = self.client.run(_worker_facts)
        wrong = {address: f["hilbench"] for address, f in facts.items() if f["hilbench"] != __version__}
        if wrong:
            address, version = next(iter(wrong.items()))
            self.close()
            raise UserError(f"worker {address} runs hilbench {version}, this client {__version__} "
                            f"({len(wrong)} of {len(facts)} workers differ)", where="--scheduler",
                            hint="install the same hilbench on every worker: results must not depend on where they ran")

    def describe(self) -> dict[str, Any]:
        """Where the tasks run: local or the scheduler's address, and the workers."""
        info = self.client.scheduler_info() if self.client is not None else {"workers": {}}
        workers = info.get("workers", {})
        return {"cluster": "local" if self.cluster is not None else "existing",
                "scheduler": self.client.scheduler.address if self.client is not None else self.address,
                "workers": len(workers), "threads": sum(int(w.get("nthreads", 1)) for w in workers.values())}

    def close(self) -> None:
        if self.client is not None:
            try:
                self.client.close(timeout=10)
            except Exception:  # noqa: BLE001 - closing after a lost scheduler must not hide the real error
                pass
            self.client = None
        if self.cluster is not None:
            try:
                self.cluster.close(timeout=10)
            except Exception:  # noqa: BLE001
                pass
            self.cluster = None

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- work -----------------------------------------------------------------------------------

    def map_unordered(self, func: Callable[[Any], Any], items: Sequence[Any],
                      keys: Sequence[str] | None = None) -> Iterator[Outcome]:
        """Run ``func(item)`` for every item on the workers; yield each outcome as it finishes.

        ``keys`` name the tasks on the scheduler (unique; default: random). Stopping the iteration
        (an interrupt) cancels what has not finished.
        """
        from distributed import as_completed
        from distributed.scheduler import KilledWorker

        futures = [self.client.submit(func, item, key=None if keys is None else f"hilbench-{keys[i]}", pure=False)
                   for i, item in enumerate(items)]
        index = {f.key: i for i, f in enumerate(futures)}
        pending = set(index)
        try:
            for future in as_completed(futures):
                i = index[future.key]
                pending.discard(future.key)
                try:
                    result = future.result()
                except KilledWorker:
                    yield Outcome(i, error="the worker running it died (killed or out of memory), "
                                           f"{self.allowed_failures + 1} time(s) on this task")
                except Exception as exc:  # noqa: BLE001 - one task's error is its outcome
                    yield Outcome(i, error=" ".join(f"{type(exc).__name__}: {exc}".split())[:500])
                else:
                    yield Outcome(i, result=result)
                future.release()
        finally:
            if pending and self.client is not None:
                self.client.cancel([f for f in futures if f.key in pending])
