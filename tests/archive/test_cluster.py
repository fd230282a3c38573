"""The batch against a Dask cluster it did not start: a real scheduler and two workers, each its own
process on 127.0.0.1, as `dask scheduler` and `dask worker` start them on a lab's machines. And a
worker that dies under a task: the task becomes a failed row, the others finish."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from hilbench.archive.engine import DaskEngine
from hilbench.archive.example import write_example_archive
from hilbench.archive.results import read_table


def _start(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    with open(log, "wb") as out:
        return subprocess.Popen([sys.executable, "-m", *args], stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[str]:
    """A scheduler and two single-thread workers, separate processes; yields the scheduler's address."""
    info = tmp_path / "scheduler.json"
    processes = [_start(["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                         "--scheduler-file", str(info)], tmp_path / "scheduler.log")]
    try:
        deadline = time.monotonic() + 60
        while not info.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert info.exists(), (tmp_path / "scheduler.log").read_text()
        address = json.loads(info.read_text())["address"]
        for name in ("w1", "w2"):
            processes.append(_start(["distributed.cli.dask_worker", address, "--name", name, "--nthreads", "1",
                                     "--nworkers", "1", "--no-dashboard", "--no-nanny"], tmp_path / f"{name}.log"))
        yield address
    finally:  # workers first, then the scheduler they would otherwise wait for
        for p in reversed(processes):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def test_batch_runs_on_an_existing_scheduler_and_its_workers(cluster: str, tmp_path: Path) -> None:
    archive = tmp_path / "archive"
    write_example_archive(archive, 12, seconds=2.0, seed=5)
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, "-m", "hilbench.cli", "batch", "fit", str(archive), "-m", "pi",
                           "--scheduler", cluster, "-o", str(out), "--json"], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["cluster"]["cluster"] == "existing" and summary["cluster"]["scheduler"] == cluster
    assert summary["cluster"]["workers"] == 2
    rows = read_table(out / "results.parquet")
    assert len(rows) == 12 and all(r["status"] == "done" for r in rows)
    assert len({r["worker"] for r in rows}) == 2  # both worker processes ran tasks
    # the same through the environment variable a Dask deployment sets
    env = {**os.environ, "DASK_SCHEDULER_ADDRESS": cluster}
    again = subprocess.run([sys.executable, "-m", "hilbench.cli", "batch", "fit", str(archive), "-m", "pi",
                            "--train-fraction", "0.6", "-o", str(out), "--json"], capture_output=True, text=True,
                           timeout=300, env=env)
    assert again.returncode == 0, again.stderr
    assert json.loads(again.stdout)["cluster"]["scheduler"] == cluster


def _dies_on_two(item: int) -> int:
    if item == 2:
        os._exit(3)  # what an out-of-memory kill looks like to the scheduler: the process is gone
    return item * 10


def test_a_worker_that_dies_fails_its_task_and_the_rest_finish() -> None:
    with DaskEngine(workers=2) as engine:
        outcomes = {o.index: o for o in engine.map_unordered(_dies_on_two, list(range(6)))}
    assert sorted(outcomes) == list(range(6))
    assert not outcomes[2].ok and "died" in outcomes[2].error
    assert [outcomes[i].result for i in (0, 1, 3, 4, 5)] == [0, 10, 30, 40, 50]
