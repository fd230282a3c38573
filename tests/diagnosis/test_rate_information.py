"""Issue 11, item 3a: rate effects are judged on the information in the data, not on labels.

A triangle's corners ring the actuator's resonance at any drive frequency: trained on a 10 Hz
triangle alone, the diagnosis identifies a 350 Hz resonance and predicts a 60 Hz run with it. A
10 Hz sine holds no content above 10 Hz: there the dynamics stay untestable, and the reason says how
far the training input's content reaches.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hilbench.diagnosis.diagnose import diagnose
from hilbench.diagnosis.input_motion import excited_bandwidth_hz
from hilbench.recording.hdf5 import RecordingWriter
from hilbench.sim.plant import Plant
from hilbench.sim.schema import SensorModel, check_plant

FS = 10_000.0
RESONANCE_HZ = 350.0
UNITS = {"time": "s", "input": "V", "output": "um"}


def _drive(kind: str, f: float) -> np.ndarray:
    t = np.arange(int(3.0 * FS)) / FS
    if kind == "triangle":
        return 60.0 * (1.0 - 4.0 * np.abs((f * t) % 1.0 - 0.5))
    return -60.0 * np.cos(2 * np.pi * f * t)


def _recording(path: Path, kind: str) -> Path:
    rng = np.random.default_rng(3)
    writer = RecordingWriter(path)
    for name, f in (("10_hz", 10.0), ("60_hz", 60.0)):
        tables = {"hysteresis": {"model": "play", "input_scale": 90.0, "output_scale": 6.0, "linear_gain": 0.4,
                                 "thresholds": [0.1, 0.3, 0.5, 0.7], "weights": [0.3, 0.2, 0.15, 0.1]},
                  "dynamics": {"kind": "second-order", "zeta": 0.05, "natural_frequency_hz": RESONANCE_HZ}}
        plant = Plant(check_plant(tables, "test", FS), FS, [SensorModel("output")], seed=0)
        u = _drive(kind, f)
        pre = int(0.2 * FS)  # settled at the first command before the recording starts
        y = plant.simulate(np.concatenate([np.full(pre, u[0]), u])).true_output[pre:]
        writer.write_run(name, {"time": np.arange(u.size) / FS, "input": u, "output": y + rng.normal(0, 0.002, u.size)},
                         UNITS, experiment="import", excitation="", sample_rate_hz=FS)
    return path


def test_excited_bandwidth_tells_a_triangle_from_a_sine() -> None:
    assert excited_bandwidth_hz(_drive("triangle", 10.0), FS) > 200.0  # harmonics to ~30x
    assert excited_bandwidth_hz(_drive("sine", 10.0), FS) < 30.0


def test_triangle_corners_at_10hz_identify_the_resonance(tmp_path: Path) -> None:
    d = diagnose(_recording(tmp_path / "tri.h5", "triangle"), "pi", train=["10hz"], test=["60hz"])
    table = [(c.effect, round(c.expected_gain, 3), c.significant) for c in d.effects]
    top = d.effects[0]
    assert top.effect == "dynamics" and top.significant, table
    assert top.evidence["validation_rmse"][1] < 0.3 * top.evidence["validation_rmse"][0]
    dyn = top.fitted.model.effect("dynamics")
    fn = next(p.value for p in dyn.params if p.name == "natural_frequency_hz")
    assert fn == pytest.approx(RESONANCE_HZ, rel=0.05)


def test_a_sine_at_10hz_leaves_the_dynamics_untestable_and_says_why(tmp_path: Path) -> None:
    d = diagnose(_recording(tmp_path / "sine.h5", "sine"), "pi", train=["10hz"], test=["60hz"])
    reason = next(u["reason"] for u in d.untestable if u["effect"] == "dynamics")
    assert "its content reaches" in reason and "Hz" in reason
