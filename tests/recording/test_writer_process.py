"""The writer process of the fixed-rate loop: slots handed over are written, whatever the loop's process does."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from hilbench.recording.hdf5 import ChannelSpec, Recording, RecordingWriter, RunWriter
from hilbench.recording.recover import write_flags
from hilbench.recording.writer_process import RecordingWriterError, WriterProcess

CHANNELS = [ChannelSpec("time", "s"), ChannelSpec("input", "V"), ChannelSpec("output", "um")]


def begin(writer: RecordingWriter, label: str = "run") -> RunWriter:
    return writer.begin_run(label, CHANNELS, experiment="test", excitation={}, sample_rate_hz=1000.0)


@pytest.mark.parametrize("ordered", [True, False], ids=["shared-counters", "socket"])
def test_more_chunks_than_slots_are_all_written_in_order_and_the_status_comes_last(tmp_path, ordered):
    path = tmp_path / "r.h5"
    writer = RecordingWriter(path)
    rng = np.random.default_rng(0)
    with WriterProcess(len(CHANNELS), chunk=37, slots=3, ordered=ordered) as stream:
        writer.helper_pids = [stream.pid]
        expected = []
        for label in ("a", "b"):  # two runs through one process
            run = stream.open_run(begin(writer, label))
            pieces = []
            for _ in range(20):  # 20 chunks through 3 slots: the loop waits for slots to come back
                n = int(rng.integers(0, 38))
                block = run.slot()
                values = rng.standard_normal((3, n))
                block[:, :n] = values
                run.commit(n)
                pieces.append(values)
            tail = np.vstack([np.arange(100.0), np.ones(100), -np.ones(100)])
            for start in range(0, 100, 37):  # a block longer than a slot, handed over slot by slot
                block = run.slot()
                n = min(37, 100 - start)
                block[:, :n] = tail[:, start:start + n]
                run.commit(n)
            pieces.append(tail)
            run.finish("complete", extra_attrs={"note": label})
            expected.append(np.hstack(pieces))
    rec = Recording(path)
    assert [r.status for r in rec] == ["complete", "complete"]
    for run, values in zip(rec, expected):
        data = run.data()
        assert run.n_samples == values.shape[1] and run.attrs["n_samples"] == values.shape[1]
        np.testing.assert_array_equal(np.vstack([data[c.name] for c in CHANNELS]), values)
    assert write_flags(path) == 0  # closed cleanly: plain h5py opens it
    with h5py.File(path, "r") as f:
        assert f["runs/0002-b"].attrs["note"] == "b"


def test_the_writer_keeps_what_it_was_given_when_the_loops_process_is_killed(tmp_path):
    path = tmp_path / "r.h5"
    code = f"""
import os, numpy as np
from hilbench.recording.hdf5 import RecordingWriter, ChannelSpec
from hilbench.recording.writer_process import WriterProcess
w = RecordingWriter({str(path)!r})
stream = WriterProcess(2, chunk=100, slots=4)
w.helper_pids = [stream.pid]
run = stream.open_run(w.begin_run('a', [ChannelSpec('time', 's'), ChannelSpec('input', 'V')], experiment='t',
                                  excitation={{}}, sample_rate_hz=1.0))
for k in range(30):
    block = run.slot()
    block[0, :100] = np.arange(100 * k, 100 * (k + 1))
    block[1, :100] = -block[0, :100]
    run.commit(100)
print(stream.pid, flush=True)
os.kill(os.getpid(), 9)
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == -9, done.stderr
    writer_pid = int(done.stdout.split()[0])
    # the writer process writes the 30 chunks it was handed, closes the file and exits
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            os.kill(writer_pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    else:
        pytest.fail("the writer process outlived its loop by 30 s")
    (run,) = Recording(path).runs
    assert run.status == "running" and run.n_samples == 3000
    np.testing.assert_array_equal(run.channel("time"), np.arange(3000.0))
    np.testing.assert_array_equal(run.channel("input"), -np.arange(3000.0))
    assert write_flags(path) == 0  # the writer closed the file: no stale SWMR flags


@pytest.mark.parametrize("ordered", [True, False], ids=["shared-counters", "socket"])
def test_a_writer_process_that_dies_fails_the_run_with_its_reason_and_keeps_what_it_wrote(tmp_path, ordered):
    path = tmp_path / "r.h5"
    writer = RecordingWriter(path)
    with WriterProcess(len(CHANNELS), chunk=10, slots=2, ordered=ordered) as stream:
        run = stream.open_run(begin(writer))
        block = run.slot()
        block[:, :10] = 1.0
        run.commit(10)
        time.sleep(3 * run.run.flush_interval_s)  # no more appends: the writer flushes by itself
        stream._process.kill()  # what the OOM killer or a crash of the writer does
        stream._process.wait(10)
        with pytest.raises(RecordingWriterError, match="writer process ended"):
            for _ in range(3):  # the pipe is closed: handing over or waiting for a slot says so
                run.slot()
                run.commit(10)
        with pytest.raises(RecordingWriterError):
            run.finish("complete")
    (kept,) = Recording(path).runs
    assert kept.status == "failed" and "writer process" in kept.attrs["reason"]
    assert kept.n_samples >= 10  # what was written before it died


@pytest.mark.parametrize("ordered", [True, False], ids=["shared-counters", "socket"])
def test_a_writer_that_frees_no_slot_fails_the_run_saying_what_it_was_doing(tmp_path, ordered, monkeypatch):
    """A stalled writer is told apart: stuck in a call on the file, or (here) not given the processor."""
    import hilbench.recording.writer_process as wp

    monkeypatch.setattr(wp, "WRITER_TIMEOUT_S", 1.0)
    path = tmp_path / "r.h5"
    writer = RecordingWriter(path)
    with WriterProcess(len(CHANNELS), chunk=10, slots=2, ordered=ordered) as stream:
        run = stream.open_run(begin(writer))
        time.sleep(0.2)
        os.kill(stream.pid, signal.SIGSTOP)  # what a starved or frozen writer looks like to the loop
        try:
            with pytest.raises(RecordingWriterError) as info:
                for _ in range(3):
                    block = run.slot()
                    block[:, :10] = 1.0
                    run.commit(10)
            said = str(info.value)
            assert "freed no slot in 1 s: it is waiting for chunks and last looked" in said, said
            assert float(said.split("last looked ")[1].split(" s")[0]) >= 1.0, said
            if sys.platform.startswith("linux"):
                assert "(process state T (stopped)" in said, said
        finally:
            os.kill(stream.pid, signal.SIGCONT)
        run.finish("failed", str(info.value))
    (kept,) = Recording(path).runs
    assert kept.status == "failed" and "last looked" in kept.attrs["reason"]


def test_a_writer_that_stops_answering_reaches_the_user_as_one_line(capsys):
    """CI saw `sweep` end in a traceback when the writer process freed no slot in 30 s: the error
    is the recording's, not a bug, and is told in one line with exit status 1."""
    import typer

    from hilbench.cli.app import user_errors

    @user_errors
    def command() -> None:
        raise RecordingWriterError("the recording's writer process freed no slot in 30 s (the disk is that far behind)")

    with pytest.raises(typer.Exit) as info:
        command()
    assert info.value.exit_code == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "freed no slot" in err and "Traceback" not in err
