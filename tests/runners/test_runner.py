"""The runner: plan checked first, failures and interrupts make safe and close with a status."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from hilbench.rig.config import load_rig
from hilbench.errors import PlanLimitError
from hilbench.recording.recover import write_flags
from hilbench.excitation.plan import plan_from_compact
from hilbench.recording.hdf5 import Recording
from hilbench.rig.rig import Rig
from hilbench.runners.sweep import run_plan


def test_complete_sweep_records_what_was_applied(write_rig, tmp_path):
    rig = Rig(load_rig(write_rig()))
    runs = plan_from_compact(["sine:amplitude=2|4,frequency_hz=2,cycles=2,offset=1"])
    result = run_plan(rig, runs, tmp_path / "r.h5", chunk_samples=300)
    assert result.status == "complete" and [r.samples for r in result.runs] == [1001, 1001]
    run = Recording(tmp_path / "r.h5").run("2")
    data = run.data()
    np.testing.assert_allclose(data["input"], runs[1].excitation.generate(1000.0))
    assert json.loads(run.attrs["excitation"])["amplitude"] == 4.0
    assert "[rig]" in run.attrs["rig"] and json.loads(run.attrs["devices"])[0]["driver"] == "sim"
    assert rig.last_applied == 0.0  # back at rest after the sweep


def test_plan_outside_limits_writes_nothing(write_rig, tmp_path):
    rig = Rig(load_rig(write_rig()))
    with pytest.raises(PlanLimitError):
        run_plan(rig, plan_from_compact(["sine:amplitude=11,frequency_hz=0.1,cycles=1"]), tmp_path / "r.h5")
    assert not (tmp_path / "r.h5").exists()


def test_exception_mid_run_fails_safely(write_rig, tmp_path, monkeypatch):
    rig = Rig(load_rig(write_rig()))
    calls = {"n": 0}
    original = rig.measure

    def flaky(applied):
        calls["n"] += 1
        if calls["n"] == 4:
            raise RuntimeError("sensor lost")
        return original(applied)

    monkeypatch.setattr(rig, "measure", flaky)
    with pytest.raises(RuntimeError, match="sensor lost"):
        run_plan(rig, plan_from_compact(["sine:amplitude=3,frequency_hz=1,cycles=3,offset=3"]), tmp_path / "r.h5",
                 chunk_samples=250)
    monkeypatch.setattr(rig, "measure", original)
    run = Recording(tmp_path / "r.h5").run("1")
    assert run.status == "failed" and "RuntimeError: sensor lost" in run.attrs["reason"]
    assert run.n_samples == 500  # the chunks before the failure are kept
    assert rig.last_applied == rig.actuator.rest  # made safe
    assert write_flags(tmp_path / "r.h5") == 0


def test_sigint_aborts_makes_safe_and_closes(tmp_path):
    out = tmp_path / "r.h5"
    log = tmp_path / "log.jsonl"
    proc = subprocess.Popen(
        [sys.executable, "-m", "hilbench.cli", "sweep", "gmm-issf-duhem", "-o", str(out), "--realtime", "-q",
         "--log", str(log)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )
    deadline = time.monotonic() + 60
    while not (log.exists() and log.read_text().count("\n") >= 2) and time.monotonic() < deadline:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGINT)
    assert proc.wait(timeout=30) == 1
    rec = Recording(out)
    assert len(rec) == 1  # no further runs started
    run = rec.runs[0]
    assert run.status == "aborted" and "interrupted by SIGINT" in run.attrs["reason"]
    assert "ramped to rest" in run.attrs["reason"]
    assert 0 < run.n_samples < 3001
    with h5py.File(out, "r") as f:  # closed cleanly: plain h5py opens it
        assert f[f"runs/{run.name}"].attrs["status"] == "aborted"


def test_the_fixed_rate_loops_process_writes_no_hdf5_while_it_runs(write_rig, tmp_path, monkeypatch):
    """The samples go to the writer process through shared slots; this process only writes attributes."""
    import hilbench.recording.hdf5 as hdf5

    rig = Rig(load_rig(write_rig()), lockstep=False)
    runs = plan_from_compact(["sine:amplitude=2,frequency_hz=2,cycles=2,offset=1"])
    writes = []
    monkeypatch.setattr(h5py.Dataset, "__setitem__", lambda self, key, value: writes.append(self.name))
    monkeypatch.setattr(hdf5.RunWriter, "append", lambda self, data: writes.append("append"))
    result = run_plan(rig, runs, tmp_path / "r.h5", mode="fixed-rate", pace=False, chunk_samples=64)
    assert writes == [] and result.status == "complete"
    monkeypatch.undo()
    run = Recording(tmp_path / "r.h5").runs[0]
    assert run.status == "complete" and run.n_samples == 1001 and run.attrs["n_samples"] == 1001
    np.testing.assert_allclose(run.channel("input"), runs[0].excitation.generate(1000.0))
    np.testing.assert_array_equal(run.channel("time"), np.arange(1001) / 1000.0)


def test_the_loop_asks_the_os_for_what_the_rig_config_says_and_undoes_it(write_rig, tmp_path):
    """lock_memory / loop_priority / loop_cpu: each done or refused with its reason in the run's
    attributes (permission depends on the machine), and the loop's thread is as before afterwards."""
    import dataclasses

    config = dataclasses.replace(load_rig(write_rig()), lock_memory=True, loop_priority=10, loop_cpu=0)
    rig = Rig(config, lockstep=False)
    affinity, policy = os.sched_getaffinity(0), os.sched_getscheduler(0)
    run_plan(rig, plan_from_compact(["sine:amplitude=1,frequency_hz=5,cycles=1"]), tmp_path / "r.h5",
             mode="fixed-rate", pace=True)
    assert os.sched_getaffinity(0) == affinity and os.sched_getscheduler(0) == policy
    run = Recording(tmp_path / "r.h5").runs[0]
    notes = run.attrs["loop_tuning"]
    assert ("memory locked" in notes) != ("memory not locked" in notes)
    assert ("pinned to CPU 0" in notes) and ("SCHED_FIFO priority 10" in notes or "priority 10 refused" in notes)
    from hilbench.recording.lateness import loop_figures, loop_line

    assert notes in loop_line(loop_figures(run.attrs))
    # the first deadline is set once the first chunk is ready: the first sample is less than a period late
    assert 0.0 <= run.channel("lateness")[0] < 1.0 / config.sample_rate_hz
