"""Recordings: format_version 1 readable with plain h5py, streaming, status last, crash safety."""

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

from hilbench.errors import DataError
from hilbench.recording.recover import clear_stale_write_flags, lookup3, write_flags
from hilbench.recording.hdf5 import ChannelSpec, Recording, RecordingWriter

CHANNELS = [ChannelSpec("time", "s"), ChannelSpec("input", "V"), ChannelSpec("output", "um")]


def begin(writer: RecordingWriter, label: str = "sine"):
    return writer.begin_run(label, CHANNELS, experiment="test", excitation={"kind": "sine"},
                            sample_rate_hz=100.0, rig_toml="[rig]\nname = 'x'\n", devices=[{"driver": "sim"}])


def test_format_with_plain_h5py(tmp_path):
    path = tmp_path / "r.h5"
    writer = RecordingWriter(path)
    run = begin(writer)
    for k in range(3):
        t = np.arange(k * 100, (k + 1) * 100) / 100.0
        run.append({"time": t, "input": np.sin(t), "output": 2 * np.sin(t)})
    run.finish("complete")
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "hilbench-recording" and f.attrs["format_version"] == 1
        assert f.attrs["created"].endswith("+00:00") and f.attrs["hilbench_version"]
        g = f["runs/0001-sine"]
        for key in ("experiment", "excitation", "sample_rate_hz", "started", "ended", "status", "reason", "rig", "devices"):
            assert key in g.attrs, key
        assert g.attrs["status"] == "complete" and json.loads(g.attrs["excitation"]) == {"kind": "sine"}
        assert json.loads(g.attrs["devices"]) == [{"driver": "sim"}]
        for name, unit in (("time", "s"), ("input", "V"), ("output", "um")):
            ds = g[name]
            assert ds.dtype == np.float64 and ds.shape == (300,) and ds.maxshape == (None,) and ds.chunks
            assert ds.attrs["units"] == unit
        np.testing.assert_allclose(g["output"][:], 2 * np.sin(np.arange(300) / 100.0))


def test_runs_append_and_reader(tmp_path):
    path = tmp_path / "r.h5"
    for label in ("a", "b"):
        writer = RecordingWriter(path)
        run = begin(writer, label)
        run.append({"time": np.arange(5.0), "input": np.ones(5), "output": np.zeros(5)})
        run.finish("complete")
    rec = Recording(path)
    assert [r.name for r in rec] == ["0001-a", "0002-b"]
    assert rec.run("b").channels == ["time", "input", "output"]
    assert rec.run("2").units["input"] == "V"
    with pytest.raises(DataError, match="no run 'c'; available: 0001-a, 0002-b"):
        rec.run("c")
    with pytest.raises(DataError, match="run has no channel 'load'"):
        rec.run("a").channel("load")


def test_status_written_last_and_failed_reason(tmp_path):
    path = tmp_path / "r.h5"
    run = begin(RecordingWriter(path))
    with h5py.File(path, "r", swmr=True) as f:
        assert f["runs/0001-sine"].attrs["status"] == "running"
    run.append({"time": np.arange(3.0), "input": np.ones(3), "output": np.ones(3)})
    run.finish("failed", "Traceback: boom")
    summary = Recording(path).summary()["runs"][0]
    assert summary["status"] == "failed" and "boom" in summary["reason"] and summary["n_samples"] == 3


def test_mismatched_block_refused(tmp_path):
    run = begin(RecordingWriter(tmp_path / "r.h5"))
    with pytest.raises(ValueError, match="differ in length"):
        run.append({"time": np.arange(3.0), "input": np.ones(2), "output": np.ones(3)})


def test_not_a_recording(tmp_path):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.attrs["format"] = "something"
    with pytest.raises(DataError, match="not a hilbench recording"):
        Recording(other)
    text = tmp_path / "t.h5"
    text.write_text("hello")
    with pytest.raises(DataError, match="not a readable HDF5 file"):
        Recording(text)
    with pytest.raises(DataError, match="file not found"):
        Recording(tmp_path / "none.h5")


def test_lookup3_reference_values():
    # Bob Jenkins' published driver values for hashlittle
    assert lookup3(b"", 0) == 0xDEADBEEF
    assert lookup3(b"Four score and seven years ago", 0) == 0x17770551
    assert lookup3(b"Four score and seven years ago", 1) == 0xCD628161


def test_sigkill_mid_sweep_leaves_flushed_samples(tmp_path):
    """A realtime sweep killed with SIGKILL: the file opens, status running, every flushed sample there."""
    out = tmp_path / "killed.h5"
    log = tmp_path / "flush.log"
    cmd = [sys.executable, "-m", "hilbench.cli", "sweep", "gmm-issf-duhem", "-o", str(out), "--realtime", "-q",
           "--log", str(log)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if log.exists() and log.read_text().count('"flushed"') >= 4:
            break
        time.sleep(0.05)
    else:
        proc.kill()
        pytest.fail(f"no flushes logged: {proc.stderr.read().decode()}")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    events = [json.loads(line) for line in log.read_text().splitlines()]
    assert events[0]["event"] == "run-started"
    last = [e for e in events if e["event"] == "flushed"][-1]
    assert last["event"] == "flushed" and last["samples"] > 0

    # hilbench and h5py (SWMR read) open it as it is
    rec = Recording(out)
    run = rec.run(last["run"])
    assert run.status == "running"
    assert run.n_samples >= last["samples"]
    data = run.data()
    # every flushed sample is there and is what the deterministic simulation produces
    from hilbench.rig.config import load_rig
    from hilbench.excitation.plan import expand_runs
    from hilbench.rig.rig import Rig

    cfg = load_rig("gmm-issf-duhem")
    planned = expand_runs(cfg.plan, file=cfg.path)[0]
    rig = Rig(cfg)
    u = planned.excitation.generate(cfg.sample_rate_hz)[: run.n_samples]
    rig.start_run(float(u[0]))
    expected = rig.measure(rig.apply(u))["output"]
    np.testing.assert_array_equal(data["output"], expected)
    np.testing.assert_array_equal(data["time"], np.arange(run.n_samples) / cfg.sample_rate_hz)

    # plain h5py refuses the killed writer's flags until they are cleared (h5clear -s in Python)
    assert write_flags(out) != 0
    assert clear_stale_write_flags(out)
    with h5py.File(out, "r") as f:
        assert f[f"runs/{run.name}"].attrs["status"] == "running"
        assert f[f"runs/{run.name}/output"].shape[0] == run.n_samples


def test_writer_appends_after_a_killed_writer(tmp_path):
    path = tmp_path / "r.h5"
    code = (
        "import numpy as np, os, sys\n"
        "from hilbench.recording.hdf5 import RecordingWriter, ChannelSpec\n"
        f"w = RecordingWriter({str(path)!r})\n"
        "r = w.begin_run('a', [ChannelSpec('time','s'), ChannelSpec('input','V'), ChannelSpec('output','um')],"
        " experiment='t', excitation={}, sample_rate_hz=1.0)\n"
        "r.append({'time': np.arange(10.0), 'input': np.ones(10), 'output': np.ones(10)}); r.flush()\n"
        "os.kill(os.getpid(), 9)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=False)
    assert write_flags(path) != 0
    run = begin(RecordingWriter(path), "b")  # clears the stale flags, appends
    run.append({"time": np.arange(2.0), "input": np.ones(2), "output": np.ones(2)})
    run.finish("complete")
    rec = Recording(path)
    assert [(r.name, r.status, r.n_samples) for r in rec] == [("0001-a", "running", 10), ("0002-b", "complete", 2)]


def test_live_writer_flags_are_not_cleared(tmp_path):
    path = tmp_path / "r.h5"
    run = begin(RecordingWriter(path))
    run.append({"time": np.arange(3.0), "input": np.ones(3), "output": np.ones(3)})  # now open in SWMR mode
    assert write_flags(path) != 0
    with pytest.raises(DataError, match=f"being written by process {os.getpid()}"):
        RecordingWriter(path)  # the live writer's flags are not touched
    assert write_flags(path) != 0
    run.finish("complete")
    assert write_flags(path) == 0
