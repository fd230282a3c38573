"""Tracking on a rig of real drivers (the Modbus AIO + Keyence template against its emulators) runs
the runner's fixed-rate loop with the compensator as its law (issue 59): the recording is streamed
and closed with its status, Ctrl-C is held off to the end of a chunk and leaves an ``aborted`` run at
rest, a transport closed mid-run leaves a ``failed`` run naming the device, at rest, with every
sample before it; paced, the first sample is on time (the kernels compiled before the first deadline).
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from drivers.base import DeviceLost
from hilbench.errors import RunStopped
from hilbench.excitation.plan import plan_from_compact
from hilbench.identify.fitting import fit
from hilbench.online import tracking_devices
from hilbench.online.tracking import track
from hilbench.recording.hdf5 import Recording
from hilbench.rig.config import load_rig
from hilbench.rig.rig import Rig
from tests.runners.emulated import RIGS, emulated, first_line, ramp_ok, record_sim, sim_reference

LSB = 20.0 / 65535  # one AO count, A
MAX_STEP = 200.0 / 1000.0  # max_rate / fs, A per sample
SWEEP = "sine:amplitude=1,frequency_hz=1,phase_deg=-90,cycles=2"  # where the simulated plant rises
REFERENCE_SHARE = 0.8  # of the recorded output range, centred


def _fit_pmpi(kind: str, folder: Path) -> dict:
    """A PMPI fit of the rig's simulated reference over +-1 (A or V: where the simulated plant rises), and
    a 1 Hz reference over 80 % of what it reached."""
    config = load_rig(RIGS[kind])
    recording = record_sim(config, plan_from_compact([SWEEP]), folder / "sweep.h5")
    model = fit(recording, "pmpi").model
    y = Recording(recording).runs[0].channel("output")
    mid, half = 0.5 * (y.max() + y.min()), 0.5 * REFERENCE_SHARE * (y.max() - y.min())
    reference = f"sine:amplitude={half:.6g},offset={mid:.6g},frequency_hz=1,phase_deg=-90,cycles=1"
    return {"model": model, "reference": reference, "config": config, "folder": folder}


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return _fit_pmpi("modbus-keyence", tmp_path_factory.mktemp("emulated-track"))


def _at_rest(emu, rig) -> None:
    aio = emu.emulators["aio"]
    assert abs(aio.last_ao) <= LSB and abs(emu.world.last_command) <= LSB
    assert ramp_ok(aio.ao_writes, MAX_STEP, -6.5, 6.5, LSB)  # never beyond the limits or the slew rate
    assert rig.last_applied == 0.0


def test_track_on_devices_records_the_fixed_rate_loop_and_matches_the_simulated_rig(fitted, tmp_path: Path):
    sim = track(Rig(sim_reference(fitted["config"])), fitted["model"], fitted["reference"])
    out = tmp_path / "track.h5"
    with emulated("modbus-keyence") as (emu, rig):
        rig.pace = False  # the emulated plant advances one sample per write whatever the time
        result = track(rig, fitted["model"], fitted["reference"], output=out)
        rig.stop(True)
        _at_rest(emu, rig)
    (run,) = Recording(out).runs
    assert run.status == "complete" and run.attrs["mode"] == "fixed-rate" and run.attrs["experiment"] == "track"
    data = run.data()
    for channel in ("reference", "command", "error", "lateness", "input", "output", "current"):
        assert channel in data and data[channel].size == result.reference.size
    np.testing.assert_allclose(data["error"], data["reference"] - data["output"])
    np.testing.assert_array_equal(data["output"], result.output)
    assert result.file == str(out) and result.group == run.name
    # the run's figures are in the recording, as a lock-step run's are
    import json

    assert json.loads(run.attrs["metrics"]) == pytest.approx(result.metrics)
    assert json.loads(run.attrs["compensator"])["counters"]["samples"] == result.reference.size
    # the same compensator through the real protocols: the laser's quantisation and the AO's counts
    # on top of the same plant; within the simulated run's error plus a few of the sensor's noise
    print("rmse um: devices", result.metrics["rmse"], "simulated", sim.metrics["rmse"])
    assert result.metrics["rmse"] <= sim.metrics["rmse"] + 3 * 0.05 + 0.01


def _inject_at(monkeypatch, sample: int, action) -> list[int]:
    """Run ``action()`` once, right after the law committed ``sample`` samples (inside the loop)."""
    fired: list[int] = []
    commit = tracking_devices.CompensatorLaw.commit

    def wrapped(self, reference, applied, row):
        commit(self, reference, applied, row)
        if self.k == sample and not fired:
            fired.append(self.k)
            action()

    monkeypatch.setattr(tracking_devices.CompensatorLaw, "commit", wrapped)
    return fired


def test_ctrl_c_mid_track_is_held_to_the_chunk_end_and_the_run_is_aborted_at_rest(fitted, tmp_path, monkeypatch):
    out = tmp_path / "track.h5"
    fired = _inject_at(monkeypatch, 300, lambda: os.kill(os.getpid(), signal.SIGINT))
    with emulated("modbus-keyence") as (emu, rig):
        rig.pace = False
        with pytest.raises(RunStopped, match="interrupted by SIGINT") as info:
            track(rig, fitted["model"], fitted["reference"], output=out)
        assert info.value.exit_code == 130 and "\n" not in info.value.line()
        _at_rest(emu, rig)
    assert fired == [300]
    (run,) = Recording(out).runs
    chunk = int(0.2 * 1000)  # the runner's chunk: 0.2 s
    assert run.status == "aborted" and run.n_samples == 2 * chunk  # the chunk in progress finished
    assert "ramped to rest" in run.attrs["reason"]
    assert "metrics" in run.attrs  # the figures of what ran


def test_a_transport_closed_mid_track_fails_naming_the_device_and_keeps_the_samples(fitted, tmp_path, monkeypatch):
    out = tmp_path / "track.h5"
    holder: dict = {}
    _inject_at(monkeypatch, 300, lambda: holder["emu"].emulators["laser"].disconnect())
    with emulated("modbus-keyence") as (emu, rig):
        holder["emu"] = emu
        rig.pace = False
        with pytest.raises(DeviceLost) as info:
            track(rig, fitted["model"], fitted["reference"], output=out)
        assert str(out) in info.value.hilbench_recorded
        _at_rest(emu, rig)
    (run,) = Recording(out).runs
    assert run.status == "failed" and run.attrs["made_safe"] == 1
    line = first_line(run.attrs["reason"])
    assert "device 'laser'" in line and "actuator ramped to rest" in line
    assert 300 <= run.n_samples < 400  # every sample before the fault
    assert np.all(np.isfinite(run.channel("output")))


def test_paced_the_first_sample_is_on_time(fitted, tmp_path):
    """The compensator's kernels are compiled (or loaded) before the first deadline: the first sample
    is taken less than one period late."""
    with emulated("modbus-keyence") as (emu, rig):
        rig.pace = True
        short = fitted["reference"].replace("cycles=1", "duration_s=0.1")
        track(rig, fitted["model"], short, output=tmp_path / "t.h5")
        rig.stop(True)
    (run,) = Recording(tmp_path / "t.h5").runs
    lateness = run.channel("lateness")
    assert np.isfinite(lateness[0]) and lateness[0] < 1.0 / 1000.0


def test_a_device_fault_reaches_the_user_as_one_line_naming_the_device_and_the_recording(capsys):
    import typer

    from hilbench.cli.app import user_errors

    @user_errors
    def command() -> None:
        error = DeviceLost("laser", "the serial link closed")
        error.hilbench_recorded = "t.h5 run r0001-track (failed; actuator ramped to rest)"
        raise error

    with pytest.raises(typer.Exit) as info:
        command()
    assert info.value.exit_code == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "laser" in err and "serial link closed" in err and "t.h5 run r0001-track" in err


@pytest.fixture(scope="module")
def fitted_pi(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return _fit_pmpi("pi-gcs", tmp_path_factory.mktemp("emulated-track-pi"))


def test_on_a_controller_that_plays_waveforms_the_feedforward_is_played_and_read_back(fitted_pi, tmp_path):
    """PI's wave generator plays the compensator's commands (computed before the run) and its data
    recorder reads the output back: the run is recorded with the reference, command and error, and
    tracks as the same compensator does on the simulated rig."""
    sim = track(Rig(sim_reference(fitted_pi["config"])), fitted_pi["model"], fitted_pi["reference"])
    out = tmp_path / "track.h5"
    with emulated("pi-gcs") as (emu, rig):
        result = track(rig, fitted_pi["model"], fitted_pi["reference"], output=out)
        rig.stop(True)
    (run,) = Recording(out).runs
    assert run.status == "complete" and run.attrs["mode"] == "block" and "wave generator" in run.attrs["played"]
    data = run.data()
    for channel in ("reference", "command", "error", "input", "output"):
        assert data[channel].size == result.reference.size
    np.testing.assert_allclose(data["error"], data["reference"] - data["output"])
    assert "wave generator" in result.compensator["played"] and not result.loop
    assert json.loads(run.attrs["metrics"]) == pytest.approx(result.metrics)
    assert not result.health["degraded"], result.health
    print("rmse um: played", result.metrics["rmse"], "simulated", sim.metrics["rmse"])
    assert result.metrics["rmse"] <= sim.metrics["rmse"] + 3 * 0.05 + 0.05


def test_feedback_on_a_controller_that_plays_waveforms_is_refused_before_anything_moves(fitted_pi, tmp_path):
    from hilbench.errors import UserError

    with emulated("pi-gcs") as (emu, rig):
        before = rig.last_applied
        with pytest.raises(UserError, match="feedback needs the measured output inside the loop") as info:
            track(rig, fitted_pi["model"], fitted_pi["reference"], feedback=True, output=tmp_path / "t.h5")
        assert "--feedback" in info.value.hint and rig.last_applied == before
    assert not (tmp_path / "t.h5").exists()
