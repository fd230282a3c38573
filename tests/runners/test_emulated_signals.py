"""Signals on `hilbench sweep`, `track` and `online` running on real drivers (issue 59): the Modbus AIO +
Keyence template pointed at its emulators (in this process) the way a user would, the command in
another process, paced at the template's rate with --allow-late. The test watches the emulated
amplifier's writes and signals the command once the run is well under way.

SIGTERM (and SIGINT, the same handler): held off to the end of the chunk, the actuator ramped to rest
(the emulator's last command is 0 A), the run recorded ``aborted`` with every sample, one line on
stderr, exit 130 for track and online (a stopped run) and 1 for sweep (its runs did not all complete).
SIGKILL: no chance to do anything; the recording opens as it is, ``running``, with what was flushed.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hilbench.excitation.plan import plan_from_compact
from hilbench.identify.fitting import fit
from hilbench.recording.hdf5 import Recording
from hilbench.recording.recover import write_flags
from hilbench.rig.config import load_rig
from hilbench.rig.emulation import start_emulators
from tests.runners.emulated import RIGS, config_file, record_sim

TEMPLATE = RIGS["modbus-keyence"]
LSB = 20.0 / 65535  # one AO count, A
LONG = "sine:amplitude=1,frequency_hz=0.5,cycles=15"  # 30 s: the signal always comes mid-run


@pytest.fixture(scope="module")
def model_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A PMPI fit over +-1 A (where the simulated plant rises) and a 30 s reference inside its reach."""
    folder = tmp_path_factory.mktemp("signals")
    recording = record_sim(load_rig(TEMPLATE), plan_from_compact(["sine:amplitude=1,frequency_hz=1,phase_deg=-90,"
                                                                   "cycles=2"]), folder / "sweep.h5")
    path = folder / "fit.json"
    fit(recording, "pmpi").model.save(path)
    y = Recording(recording).runs[0].channel("output")
    mid, half = 0.5 * (y.max() + y.min()), 0.3 * (y.max() - y.min())
    return path, f"sine:amplitude={half:.6g},offset={mid:.6g},frequency_hz=0.5,phase_deg=-90,cycles=15"


def _run_and_signal(emu, argv: list[str], sig: int, after_writes: int = 1500,
                    group: bool = False) -> subprocess.CompletedProcess:
    """``group``: signal the command's whole process group, as Ctrl-C in a terminal does."""
    aio = emu.emulators["aio"]
    proc = subprocess.Popen([sys.executable, "-m", "hilbench.cli", *argv], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=group)
    deadline = time.monotonic() + 120
    while len(aio.ao_writes) < after_writes:
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            out, err = proc.communicate()
            pytest.fail(f"the run did not get under way: {err.strip()[-2000:]}")
        time.sleep(0.02)
    if group:
        os.killpg(proc.pid, sig)
    else:
        os.kill(proc.pid, sig)
    out, err = proc.communicate(timeout=60)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def _command(kind: str, config: Path, out: Path, model: tuple[Path, str]) -> list[str]:
    if kind == "sweep":
        return ["sweep", str(config), "-e", LONG, "-o", str(out), "-q", "--allow-late"]
    if kind == "online":  # the training run is under way when the signal comes
        return ["online", str(config), "-e", LONG, "-e", LONG, "--record", str(out), "-q", "--allow-late"]
    return ["track", str(config), "--model", str(model[0]), "-r", model[1], "-o", str(out), "--allow-late"]


@pytest.mark.parametrize("kind", ["sweep", "track", "online"])
def test_sigterm_stops_at_a_safe_point_and_the_run_is_kept_aborted_at_rest(kind, model_file, tmp_path):
    out = tmp_path / f"{kind}.h5"
    with start_emulators(load_rig(TEMPLATE)) as emu:
        done = _run_and_signal(emu, _command(kind, config_file(emu, TEMPLATE, tmp_path), out, model_file),
                               signal.SIGTERM)
        aio = emu.emulators["aio"]
        assert abs(aio.last_ao) <= LSB and abs(emu.world.last_command) <= LSB  # ramped to rest
        steps = np.abs(np.diff(aio.ao_writes))
        assert steps.max() <= 200.0 / 1000.0 + LSB  # never faster than the slew limit
    assert "Traceback" not in done.stderr
    assert done.returncode == (1 if kind == "sweep" else 130), done.stderr
    if kind != "sweep":
        (line,) = done.stderr.strip().splitlines()
        assert "interrupted by SIGTERM" in line and str(out) in line
    (run,) = Recording(out).runs
    assert run.status == "aborted" and "SIGTERM" in run.attrs["reason"] and "ramped to rest" in run.attrs["reason"]
    data = run.data()
    assert run.n_samples > 0 and all(v.size == run.n_samples for v in data.values())
    assert np.all(np.isfinite(data["output"]))


def test_ctrl_c_reaches_the_writer_process_too_and_every_sample_is_kept(tmp_path):
    """Ctrl-C signals the terminal's whole process group: the recording's writer process ignores it and
    writes every sample the loop handed over before the run is closed ``aborted``."""
    out = tmp_path / "sweep.h5"
    with start_emulators(load_rig(TEMPLATE)) as emu:
        done = _run_and_signal(emu, _command("sweep", config_file(emu, TEMPLATE, tmp_path), out, None),
                               signal.SIGINT, group=True)
        aio = emu.emulators["aio"]
        assert abs(aio.last_ao) <= LSB  # ramped to rest
        n_writes = len(aio.ao_writes)
    assert "Traceback" not in done.stderr and done.returncode == 1, done.stderr
    (run,) = Recording(out).runs
    assert run.status == "aborted" and "SIGINT" in run.attrs["reason"]
    data = run.data()
    # every sample the loop took is on disk: the amplifier saw the run's writes plus the ramp to rest
    assert 1500 <= run.n_samples <= n_writes and run.attrs["n_samples"] == run.n_samples
    assert all(v.size == run.n_samples for v in data.values()) and np.all(np.isfinite(data["output"]))


# SIGKILL of a lock-step sweep: tests/recording/test_recording.py
@pytest.mark.parametrize("kind", ["sweep", "track"])
def test_sigkill_leaves_a_recording_that_opens_running_with_what_was_flushed(kind, model_file, tmp_path):
    out = tmp_path / f"{kind}.h5"
    with start_emulators(load_rig(TEMPLATE)) as emu:
        done = _run_and_signal(emu, _command(kind, config_file(emu, TEMPLATE, tmp_path), out, model_file),
                               signal.SIGKILL, after_writes=3000)
    assert done.returncode == -signal.SIGKILL
    # the recording's writer process outlives the loop's by the time it takes to write what it was
    # handed and close the file: then plain h5py opens it (no stale SWMR flags)
    deadline = time.monotonic() + 30
    while write_flags(out) != 0 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert write_flags(out) == 0
    (run,) = Recording(out).runs
    assert run.status == "running"
    data = run.data()
    # flushed at least once a second, and more than a second ran: samples there, every channel alike
    assert run.n_samples > 0 and all(v.size == run.n_samples for v in data.values())
    if kind == "track":
        assert {"reference", "command", "error", "lateness"} <= set(data)
        assert json.loads(run.attrs["compensator"])["method"]
