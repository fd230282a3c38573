"""`hilbench online RIG` on a rig of real devices identifies live (issue 59): the Modbus AIO + Keyence
template pointed at its emulators, the command in another process. The training run is swept and the
offline model fitted on it; the other run is swept with the online identifier in the fixed-rate loop,
its prediction and weights recorded as channels while it runs; the replay of the recording (what the
comparison scores) gives the same predictions, so the figures are those of the live loop.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from hilbench.recording.hdf5 import Recording
from hilbench.rig.config import load_rig
from hilbench.rig.emulation import start_emulators
from tests.runners.emulated import RIGS, config_file

TEMPLATE = RIGS["modbus-keyence"]
TRAIN = "sine:amplitude=1,frequency_hz=1,cycles=3"
IDENTIFY = "sine:amplitude=0.8,offset=0.1,frequency_hz=2,cycles=4"


def test_online_on_real_devices_identifies_live_and_matches_the_replay(tmp_path):
    out = tmp_path / "online.h5"
    with start_emulators(load_rig(TEMPLATE)) as emu:
        config = config_file(emu, TEMPLATE, tmp_path)
        done = subprocess.run([sys.executable, "-m", "hilbench.cli", "online", str(config), "-e", TRAIN, "-e", IDENTIFY,
                               "--record", str(out), "--allow-late", "--global-starts", "4", "--json", "-q"],
                              capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    doc = json.loads(done.stdout)
    assert doc["mode"] == "rig-live"
    (entry,) = doc["runs"]
    assert entry["live_vs_replay_max_abs"] <= 1e-9  # the live loop's predictions are the replay's
    assert np.isfinite(entry["online"]["re_n2_pct"]) and np.isfinite(entry["persistence"]["re_n2_pct"])
    train, identified = Recording(out).runs
    assert train.attrs["experiment"] == "online training" and "online" not in train.channels
    assert identified.status == "complete" and identified.attrs["mode"] == "fixed-rate"
    data = identified.data()
    weights = [c for c in data if c.startswith("weight_")]
    assert len(weights) == 3 + 1 + 5  # p0..p3, q1..q5 (000: M = 3, N = 5)
    assert all(data[c].size == identified.n_samples for c in ["online", *weights])
    assert np.all(np.isfinite(data["online"]))
    assert json.loads(identified.attrs["online_identifier"])["M"] == 3
