"""The NI-DAQmx path end to end (issue 61): paper 000's rig on an NI 9263 + NI 9215 cDAQ
(``configs/templates/gmm-ni-9263-9215.toml``) dry-run as a user would: ``hilbench emulate T
--write-config OUT`` in one process (NI's gRPC device server emulated), then, from this one through
NI's own ``nidaqmx`` client, a sweep (one buffered generation on the DAQ's clock), a fit, and a
feedforward + feedback ``track``, whose per-sample loop is paced by the emulated NI 9215's sample
clock (decision 0101). The tracking error is compared with the same track on the simulated rig; the
emulated plant advances one sample per AO write, so a late sample changes when, not what, it
measures. And the rate check still refuses, before anything moves, a rate the devices cannot hold
when the DAQ's clock paces the loop.
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.drivers.test_ni_daqmx import needs_nidaqmx

REPO = Path(__file__).resolve().parents[2]
TEMPLATE = REPO / "configs" / "templates" / "gmm-ni-9263-9215.toml"
WIPE = "sine:amplitude=0.95,offset=1.05,frequency_hz=1,phase_deg=-90,cycles=2"  # 0.1..2 A: the actuator's memory set
SWEEP = "sine:amplitude=0.7,offset=1.2,frequency_hz=1,phase_deg=-90,cycles=3"  # 0.5..1.9 A: where the plant rises
KP, KI = 0.3, 30.0  # um/um, 1/s
REFERENCE = "sine:amplitude=8,offset=30,frequency_hz=1,phase_deg=-90,cycles=1"  # um, inside the reachable range


@needs_nidaqmx
def test_sweep_and_feedback_track_of_the_000_rig_through_nidaqmx_paced_by_the_emulated_sample_clock(tmp_path):
    import h5py
    from typer.testing import CliRunner

    from hilbench.cli import app
    from hilbench.online.pid import PID
    from hilbench.online.tracking import track
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig
    from tests.runners.emulated import sim_reference

    runner = CliRunner()
    written = tmp_path / "rig-emulated.toml"
    emulate = subprocess.Popen([sys.executable, "-m", "hilbench.cli", "emulate", str(TEMPLATE), "--json",
                                "--write-config", str(written), "--seconds", "300"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 90
        while not written.exists() and emulate.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert written.exists(), emulate.stderr.read() if emulate.poll() is not None else "no config written"
        assert load_rig(written).devices["daq"]["url"].startswith("grpc://127.0.0.1:")

        check = runner.invoke(app, ["sweep", str(written), "--check", "--json", "-e", SWEEP])
        assert check.exit_code == 0, check.output
        trips = json.loads(check.stdout)["round_trips"]
        assert trips["mode"] == "block"  # a sweep is one buffered generation on the DAQ's clock
        assert trips["paced_by"].startswith("device daq")  # and a loop on it would be paced by the DAQ
        for plan, swept in ((WIPE, tmp_path / "wipe.h5"), (SWEEP, tmp_path / "sweep.h5")):
            result = runner.invoke(app, ["sweep", str(written), "-e", plan, "-o", str(swept), "-q", "--json"])
            assert result.exit_code == 0, result.output
        model_file = tmp_path / "fit.json"  # paper 000's model, fitted on the emulated sweep
        result = runner.invoke(app, ["fit", str(swept), "-m", "fpmpi+dynamics", "-o", str(model_file), "--json"])
        assert result.exit_code == 0, result.output

        # the machine is shared and loaded: the emulated devices may not hold 1 kHz, which the run
        # records (--allow-late) rather than refuses; the refusal itself is the test below
        tracked = tmp_path / "track.h5"
        # gains given (checked on the identified loop): the designed ones depend on the fit's flattest
        # local gain, which this short sweep leaves to chance
        result = runner.invoke(app, ["track", str(written), "-m", str(model_file), "-r", REFERENCE, "--feedback",
                                     "--kp", str(KP), "--ki", str(KI), "--allow-late", "-o", str(tracked), "--json"])
        assert result.exit_code == 0, result.output
        document = json.loads(result.stdout)
    finally:
        emulate.send_signal(signal.SIGINT)
        _, stderr = emulate.communicate(timeout=30)
    assert emulate.returncode == 0, stderr

    with h5py.File(tracked, "r") as f:
        (run,) = [f["runs"][name] for name in f["runs"]]
        attrs = dict(run.attrs)
        lateness, taken = run["lateness"][:], run["time"][:]
    # the per-sample loop ran (feedback needs it), paced by the emulated NI 9215's clock
    assert attrs["mode"] == "fixed-rate" and attrs["status"] == "complete"
    assert str(attrs["clock"]).startswith("device daq: DAQmx continuous AI at 1000 Hz")
    n = lateness.size
    # the reference's 1001 samples after the dynamics' pre-actuation (the run's first samples)
    assert n == 1001 + int(attrs["preactuation_samples"]) and document["preactuation_samples"] == n - 1001
    assert np.all(np.isfinite(lateness)) and np.all(lateness >= 0.0)
    assert np.all(np.diff(taken) > 0)
    # no sample before its tick: the k-th sample at least k - 1 periods after the first (ticks missed
    # while the loop was late are skipped, never run ahead of)
    assert np.all(taken >= (np.arange(n) - 1) * 1e-3 - 1e-4)
    # lateness recorded as the other figures are: per sample, in the run's attributes, in the output
    loop = document["loop"]
    assert loop["paced"] is True and 0 <= int(attrs["clock_late_samples"]) < n
    assert loop["clock_late_samples"] == int(attrs["clock_late_samples"])
    assert loop["lateness_max_s"] == pytest.approx(float(lateness.max()))
    assert loop["late"] == bool(attrs["late"])
    emulated_rmse = document["metrics"]["rmse"]

    # the same compensator on the simulated rig: same plant, sensors, seed, limits
    simulated = track(Rig(sim_reference(load_rig(TEMPLATE))), model_file, REFERENCE, feedback=PID(KP, KI, 0.0))
    assert math.isfinite(emulated_rmse) and math.isfinite(simulated.metrics["rmse"])
    print(f"rmse emulated {emulated_rmse:.4f} um, simulated {simulated.metrics['rmse']:.4f} um; lateness p50 "
          f"{loop['lateness_p50_s']:.3g} s, p99 {loop['lateness_p99_s']:.3g} s, max {loop['lateness_max_s']:.3g} s; "
          f"{loop['overruns']} overruns, the DAQ reported {loop['clock_late_samples']} of {n} late")
    assert emulated_rmse == pytest.approx(simulated.metrics["rmse"], rel=0.25)


@needs_nidaqmx
def test_a_rate_the_devices_cannot_hold_is_refused_when_the_daqs_clock_paces_the_loop(tmp_path):
    """The check times the write and the reads after each tick of the DAQ's clock (the wait for the
    tick is the period, not the devices' work): 50 kHz is far above any gRPC round trip; refused in
    one line before anything moves. A DAQ clock at another rate than the rig's is refused too."""
    import dataclasses

    from hilbench.errors import UserError
    from hilbench.rig.config import load_rig
    from hilbench.rig.emulation import start_emulators
    from hilbench.rig.rig import Rig
    from hilbench.runners.rate_check import require_rate
    from tests.runners.emulated import with_device_settings

    config = load_rig(TEMPLATE)
    with start_emulators(config) as emu:
        fast = with_device_settings(emu.config_for_emulators(), "daq", sample_rate_hz=50000.0)
        with Rig(dataclasses.replace(fast, sample_rate_hz=50000.0)) as rig:
            writes = len(emu.emulators["daq"].ao_writes)
            with pytest.raises(UserError) as caught:
                require_rate(rig)
            line = str(caught.value)
            assert "\n" not in line and "sample_rate_hz = 50000 cannot be held" in line and "daq" in line
            written = emu.emulators["daq"].ao_writes[writes:]
            assert written and set(written) == {written[0]}  # the actuator held still
            assert rig.devices_by_name["daq"].clock_stats()["samples"] >= 300  # each round trip from a tick
        with Rig(with_device_settings(emu.config_for_emulators(), "daq", sample_rate_hz=500.0)) as rig, \
                pytest.raises(UserError, match=r"device 'daq' runs its sample clock at 500 Hz and the rig's "
                                               r"sample_rate_hz is 1000"):
            require_rate(rig)
