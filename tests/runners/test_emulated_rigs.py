"""Acceptance: the 001 characterisation sweep through each real-protocol path, against the emulators.

(i) a PI GCS controller on a pty, its wave generator and data recorder playing each run (block
mode); (ii) a Modbus TCP analog I/O module driving the emulated current amplifier with a CANopen
displacement sensor on a python-can virtual bus (fixed-rate loop); (iii) a Keyence LK-G laser on a
serial pty with the actuator on the Modbus path (fixed-rate loop). The fixed-rate loop runs with
``pace=False`` here (as fast as the emulated devices answer, ~1 ms a sample): the emulated plant
advances one sample per command whatever the time, so the recording is the same as paced.

Each recording is compared with the pure simulated backend's recording of the same plan (same
plant, sensors and seed): output channels within sensor noise, and the same diagnosis verdict.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import numpy as np
import pytest

from hilbench.diagnosis.diagnose import diagnose
from hilbench.recording.hdf5 import Recording
from hilbench.rig.config import load_rig
from hilbench.runners.sweep import run_plan
from tests.runners.emulated import (
    NOISE_STD_UM,
    RIGS,
    emulated,
    record_sim,
    reduced_001_plan,
    rms,
)

MODES = {"pi-gcs": "block", "modbus-canopen": "fixed-rate", "modbus-keyence": "fixed-rate"}
AO_LSB_A = 20.0 / 65535  # 16-bit AO over +-10 V at 1 A/V
# two shared, busy cores: the heartbeat consumer of these tests is generous (the heartbeat test
# itself stops the heartbeat for good, so it does not depend on this)
SLOW_HEARTBEAT = {"modbus-canopen": {"lvdt": {"heartbeat_consumer_ms": 2000}}}


# The Modbus paths' simulated references are the same recording (the same plant, sensors and seed;
# only the devices differ): its verdict is computed once per process, keyed by the recorded data, and
# the module runs on one test worker (tests/conftest.py, SHARED_WORKER_MODULES).
_VERDICTS: dict[str, list[tuple[str, bool]]] = {}


def verdict(path) -> list[tuple[str, bool]]:
    digest = hashlib.sha256()
    for run in Recording(path):
        for name, values in sorted(run.data().items()):
            if name != "lateness":  # when each sample was taken, not what was measured
                digest.update(name.encode())
                digest.update(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    key = digest.hexdigest()
    if key not in _VERDICTS:
        d = diagnose(path, "pmpi")
        _VERDICTS[key] = [(c.effect, bool(c.significant)) for c in d.effects]
    return _VERDICTS[key]


@pytest.mark.parametrize("kind", sorted(RIGS))
def test_the_001_sweep_through_each_protocol_path_matches_the_simulated_backend(kind, tmp_path):
    # the pure simulated backend's recording of the same plan on the same rig (plant, sensors, seed)
    sim_path = record_sim(load_rig(RIGS[kind]), reduced_001_plan(), tmp_path / "sim.h5")
    out = tmp_path / f"{kind}.h5"
    runs = reduced_001_plan()
    with emulated(kind, **SLOW_HEARTBEAT.get(kind, {})) as (emu, rig):
        result = run_plan(rig, runs, out, pace=False, chunk_samples=500)
        assert result.status == "complete"
        assert rig.last_applied == 0.0
        # the actuator is back at rest on the device, not just in the rig's books (one AO count)
        assert abs(emu.world.last_command) <= AO_LSB_A
    emulated_runs, sim_runs = list(Recording(out)), list(Recording(sim_path))
    assert [r.n_samples for r in emulated_runs] == [r.n_samples for r in sim_runs] == [1001, 1001, 1001, 2001]
    report = []
    for run, ref in zip(emulated_runs, sim_runs):
        assert run.status == "complete" and run.attrs["mode"] == MODES[kind]
        data, expected = run.data(), ref.data()
        # the input is the applied command (block mode: what the controller's data recorder says it applied)
        assert rms(data["input"] - expected["input"]) < 1e-4
        difference = rms(data["output"] - expected["output"])
        report.append(difference)
        assert difference < 3 * NOISE_STD_UM, (run.name, difference)
        # not a copy: the two recordings are independent noise draws of the same plant
        assert difference > 0.2 * NOISE_STD_UM
        if "current" in data:
            assert rms(data["current"] - expected["current"]) < 1e-3  # A: 16-bit AI at 1 V/A
        if MODES[kind] == "fixed-rate":
            assert np.all(np.isnan(data["lateness"])) and run.attrs["paced"] == 0  # pace=False: no schedule
        devices = json.loads(run.attrs["devices"])
        assert {d["driver"] for d in devices} == {t["driver"] for t in rig.config.devices.values()}
    print(kind, "rms output difference per run (um):", [round(x, 4) for x in report])
    emulated_verdict, sim_verdict = verdict(out), verdict(sim_path)
    print(kind, "diagnosis (effect, significant), emulated:", emulated_verdict, "simulated:", sim_verdict)
    # The two recordings are independent noise draws: the findings (the significant candidates, in
    # rank order) and the candidates tried must agree; the order among the refused ones follows gains
    # of a fraction of a percent, which the noise draw decides.
    assert [v for v in emulated_verdict if v[1]] == [v for v in sim_verdict if v[1]]
    assert sorted(emulated_verdict) == sorted(sim_verdict)


def test_a_paced_fixed_rate_run_records_lateness_and_counts_overruns(tmp_path):
    """Paced at 1 kHz; the emulated Modbus + CANopen chain may or may not keep up: either way the
    lateness of every sample is recorded and the overruns are the samples later than one period."""
    out = tmp_path / "paced.h5"
    runs = reduced_001_plan()[:1]
    with emulated("modbus-canopen", **SLOW_HEARTBEAT["modbus-canopen"]) as (_emu, rig):
        result = run_plan(rig, runs, out)
    assert result.status == "complete"
    run = Recording(out).runs[0]
    lateness = run.data()["lateness"]
    assert lateness.shape == (1001,) and np.all(np.isfinite(lateness)) and np.all(lateness >= 0)
    assert run.attrs["paced"] == 1
    assert run.attrs["overruns"] == int(np.count_nonzero(lateness > 1e-3))
    assert run.attrs["lateness_max_s"] == pytest.approx(lateness.max())
    assert run.attrs["lateness_p50_s"] <= run.attrs["lateness_p99_s"] <= run.attrs["lateness_max_s"]
    # time told honestly: each sample's time is when it was taken (its deadline plus its lateness),
    # the schedule is in the attributes; more than 1 % overruns marks the run late, and show says so
    t = run.data()["time"]
    np.testing.assert_allclose(t, np.arange(1001) / 1000.0 + lateness, rtol=0, atol=1e-9)
    assert run.attrs["time"] == "measured" and "k / 1000 Hz" in run.attrs["schedule"]
    share = 100.0 * run.attrs["overruns"] / 1001
    assert run.attrs["overrun_pct"] == pytest.approx(share) and bool(run.attrs["late"]) == (share > 1.0)
    shown = subprocess.run([sys.executable, "-m", "hilbench.cli", "show", str(out)], capture_output=True, text=True,
                           timeout=60)
    assert shown.returncode == 0
    (line,) = [x.strip() for x in shown.stdout.splitlines() if x.strip().startswith("loop: lateness p50")]
    assert f"{run.attrs['overruns']} overruns" in line and (("LATE" in line) == bool(run.attrs["late"]))
