"""Issue 11, items 3 and 4: a capture trained at one drive rate and validated at one other still shows
its dead time, in the power-on step at its start (the command at its level from the first sample,
the output moving to it with the actuator's own transient). The diagnosis reads the delay off that
step and confirms it on the validation run; before, the delay was "untestable" and nothing was found.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hilbench.diagnosis.diagnose import diagnose
from hilbench.recording.hdf5 import RecordingWriter
from hilbench.sim.plant import Plant
from hilbench.sim.schema import SensorModel, check_plant

FS = 10_000.0
DELAY_S = 0.0004  # 4 samples: at 60 Hz a 9 degree lag, at 10 Hz 1.4 degrees
UNITS = {"time": "s", "input": "V", "output": "um"}


def _plant() -> Plant:
    tables = {
        "hysteresis": {"model": "play", "input_scale": 90.0, "output_scale": 6.0, "linear_gain": 0.4,
                       "thresholds": [0.1, 0.3, 0.5, 0.7], "weights": [0.3, 0.2, 0.15, 0.1]},
        "delay": {"seconds": DELAY_S},
        "dynamics": {"kind": "second-order", "zeta": 0.04, "natural_frequency_hz": 700.0},
    }
    return Plant(check_plant(tables, "test", FS), FS, [SensorModel("output")], seed=0)


def _capture(path: Path) -> Path:
    """Two imported-style runs: a rest at -60 V from the first sample after a power-on step the input
    does not show (the plant starts at 0 V), then a staircase of triangles at 10 Hz (training) or 60 Hz."""
    rng = np.random.default_rng(5)
    writer = RecordingWriter(path)
    for name, f in (("10_hz", 10.0), ("60_hz", 60.0)):
        rest = int(0.6 * FS)
        n_cycles = int(3 * f)
        t_act = np.arange(int(n_cycles / f * FS)) / FS
        phase = (f * t_act) % 1.0
        tri = 1.0 - 4.0 * np.abs(phase - 0.5)  # -1 .. 1, starting at -1
        amp = 60.0 * (0.4 + 0.6 * np.minimum(1.0, t_act * f / (0.7 * n_cycles)))  # growing maxima
        u_act = np.clip(-60.0 + (amp * (tri + 1.0)), -60.0, 60.0)
        u = np.concatenate([np.full(rest, -60.0), u_act])
        plant = _plant()
        # the rig was at 0 V until it was switched on, with the first recorded sample
        applied = np.concatenate([[0.0] * 3, u])
        y = plant.simulate(applied).true_output[3:]
        y = y + rng.normal(0, 0.002, y.size)
        time = np.arange(u.size) / FS
        writer.write_run(name, {"time": time, "input": u, "output": y}, UNITS, experiment="import", excitation="",
                         sample_rate_hz=FS)
    return path


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _capture(tmp_path_factory.mktemp("power-on") / "whole.h5")


def test_the_delay_is_calibrated_on_the_power_on_step_and_confirmed(capture: Path) -> None:
    d = diagnose(capture, "pi", train=["10hz"], test=["60hz"])
    delay = next(c for c in d.effects if c.effect == "delay")
    step = delay.evidence["rate_calibration"]["power_on_step"]
    # the step comes with the first recorded sample: the dead time is the plant's, within a sample
    assert step["dead_time_s"] == pytest.approx(DELAY_S, abs=1.0 / FS)
    assert "power-on step" in delay.explanation
    table = [(c.effect, round(c.expected_gain, 3), c.significant) for c in d.effects]
    assert delay.significant and d.effects[0] is delay, table


def test_auto_adds_the_calibrated_delay_and_the_error_falls(capture: Path) -> None:
    d = diagnose(capture, "pi", train=["10hz"], test=["60hz"], auto=True)
    added = [s["added"] for s in d.steps]
    assert added[:2] == [None, "delay"], d.steps
    first, last = d.steps[0]["validation"]["rmse"], d.steps[-1]["validation"]["rmse"]
    assert last < 0.5 * first, (first, last)
