"""The refits of a diagnosis round run in worker processes; the result does not depend on how many."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from hilbench.diagnosis.diagnose import diagnose
from hilbench.diagnosis.workers import check_jobs, default_jobs, run_tasks
from hilbench.errors import DataError, UserError
from hilbench.excitation.plan import plan_from_compact
from hilbench.rig.config import load_rig
from hilbench.rig.rig import Rig
from hilbench.runners.sweep import run_plan

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="worker processes are forked on Linux only")


def _slow_pid(seconds: float, tag: int) -> tuple[int, int]:
    time.sleep(seconds)
    return tag, os.getpid()


@linux_only
def test_tasks_run_in_other_processes_and_come_back_in_order():
    advanced: list[str] = []
    # the first task finishes last: the results must still come back in the order of the tasks
    tasks = [lambda k=k: _slow_pid(0.3 if k == 0 else 0.01, k) for k in range(5)]
    out = run_tasks(tasks, 2, lambda amount=1, text=None: advanced.append(text), [f"t{k}" for k in range(5)])
    assert [tag for tag, _ in out] == [0, 1, 2, 3, 4]
    pids = {pid for _, pid in out}
    assert os.getpid() not in pids and len(pids) == 2
    assert sorted(advanced) == [f"t{k} done" for k in range(5)]
    assert advanced[-1] == "t0 done"  # progress follows completion, not submission


@linux_only
def test_shared_objects_come_back_as_the_callers_own():
    big = [np.arange(10.0), np.ones(3)]
    out = run_tasks([lambda: {"data": big[0], "pid": os.getpid()}, lambda: (big[1], big[0] * 2)], 2, shared=big)
    assert out[0]["data"] is big[0] and out[1][0] is big[1]  # references, not copies
    assert out[0]["pid"] != os.getpid()
    np.testing.assert_array_equal(out[1][1], big[0] * 2)  # what a task made is copied back


def test_one_job_runs_in_the_caller():
    out = run_tasks([lambda: os.getpid(), lambda: os.getpid()], 1)
    assert out == [os.getpid(), os.getpid()]


def _bad() -> None:
    raise DataError("no column 'output'", where="run.h5: run2", hint="import with --output")


@linux_only
def test_a_task_error_is_raised_in_the_caller_whole():
    with pytest.raises(DataError) as info:
        run_tasks([lambda: 1, _bad], 2)
    assert info.value.where == "run.h5: run2" and info.value.hint == "import with --output"
    assert str(info.value) == "run.h5: run2: no column 'output'"


@linux_only
def test_an_error_ends_the_other_workers_without_waiting_for_them():
    t0 = time.monotonic()
    with pytest.raises(DataError):
        run_tasks([lambda: time.sleep(120), lambda: (time.sleep(0.5), _bad())], 2)
    # the sleeping worker was terminated, not waited for (it would take 120 s)
    assert time.monotonic() - t0 < 60


_KILLED_CALLER = """
import os, sys, time
from hilbench.diagnosis.workers import run_tasks
def task():
    with open(sys.argv[1], "a") as f:
        f.write(f"{os.getpid()}\\n")
    time.sleep(300)
run_tasks([task, task], 2)
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:  # a zombie is dead, only not yet reaped
        return f.read().rsplit(")", 1)[1].split()[0] != "Z"


@linux_only
def test_workers_end_when_their_caller_is_killed(tmp_path):
    pids_file = tmp_path / "pids"
    caller = subprocess.Popen([sys.executable, "-c", _KILLED_CALLER, str(pids_file)])
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(pids_file.read_text().split() if pids_file.exists() else []) < 2:
            time.sleep(0.1)
        workers = [int(p) for p in pids_file.read_text().split()]
        assert len(workers) == 2
    finally:
        caller.kill()  # SIGKILL: no chance to shut its pool down
        caller.wait()
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and any(_alive(p) for p in workers):
        time.sleep(0.1)
    assert not any(_alive(p) for p in workers)  # they would sleep 300 s, then wait for tasks forever


def test_jobs_are_checked():
    assert check_jobs(None) == default_jobs() >= 1
    assert check_jobs(3) == 3
    for bad in (0, -1, 1000, 2.5, True):
        with pytest.raises(UserError, match="--jobs"):
            check_jobs(bad)


@linux_only
def test_the_diagnosis_does_not_depend_on_jobs(tmp_path):
    # a PMPI model on a Duhem-like rig: candidate refits and alternative bases (the wrong-base check)
    out = tmp_path / "duhem.h5"
    run_plan(Rig(load_rig("gmm-issf-duhem")), plan_from_compact(["sine:amplitude=3|6,frequency_hz=1,cycles=2"]), out)
    one = diagnose(out, "pmpi", jobs=1)
    two = diagnose(out, "pmpi", jobs=2)
    assert any(c.effect == "base" for c in one.effects)  # the alternative bases were fitted
    assert json.dumps(one.to_json(), sort_keys=True) == json.dumps(two.to_json(), sort_keys=True)
    # the refits came back from the workers referring to the caller's recorded runs, not copies
    recorded = [r.data for r in two.result.runs]
    fitted = [c.fitted for c in two.effects if c.fitted is not None]
    assert fitted and all(r.data is d for f in fitted for r, d in zip(f.runs, recorded))


def test_cli_rejects_a_bad_jobs_value(tmp_path):
    out = tmp_path / "r.h5"
    out.write_bytes(b"")
    r = subprocess.run([sys.executable, "-m", "hilbench.cli", "diagnose", str(out), "--model", "pi", "--jobs", "0"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "--jobs" in lines[0] and "1 to 256" in lines[0], r.stderr
