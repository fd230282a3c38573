"""Creep over decades, diagnosed: a PI with logarithmic creep after each input step (ms to the
record's length) is diagnosed from ``pi``; creep ranks first and significant, the data choose a
form over the fixed log-spaced bank (``creep(form=bank)``, or the logarithmic law on it), and --auto
lowers the validation error many times.

Measured when written (80 s at 1 kHz, the last 30 % validation): creep first, p ~1e-6, validation
rmse 1.028 -> 0.034 um with ``pi+creep(form=bank)``; before the bank, the diagnosis added ``creep``
(two fitted elements) and left 0.32 um.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hilbench.diagnosis.diagnose import diagnose
from hilbench.recording.hdf5 import RecordingWriter
from tests.models.test_creep_forms import FS, creep_after_steps, pi_output, staircase


def _recording(path: Path, law: str, seed: int = 0) -> Path:
    v = staircase(seed)
    y = pi_output(v) + creep_after_steps(v, law) + np.random.default_rng(seed + 1).normal(0.0, 0.01, v.size)
    RecordingWriter(path).write_run("steps", {"time": np.arange(v.size) / FS, "input": 10.0 * v, "output": y},
                                    {"time": "s", "input": "V", "output": "um"}, experiment="t", excitation="{}",
                                    sample_rate_hz=FS)
    return path


def test_logarithmic_creep_is_found_and_the_bank_removes_it(tmp_path):
    d = diagnose(_recording(tmp_path / "log_creep.h5", "log"), "pi", auto=True)
    first = d.rounds[0].effects
    summary = [(c.effect, round(c.expected_gain, 3), c.significant) for c in first]
    print(summary)
    assert first[0].effect == "creep", summary
    assert first[0].significant and first[0].evidence["p_value"] < 0.01, summary
    added = [s["added"] for s in d.steps[1:]]
    assert added and added[0] == "creep", added
    # the data chose a form over the log-spaced bank (the bank, the law on the input or the law on
    # the input and the hysteresis columns: alike on this law), not two searched elements
    spec = d.steps[1]["spec"]
    assert any(f"creep(form={f})" in spec for f in ("bank", "log", "log-output")), spec
    before, after = d.steps[0]["validation"]["rmse"], d.steps[-1]["validation"]["rmse"]
    print("validation rmse", before, "->", after, [s["spec"] for s in d.steps])
    # the issue asks for 3x; the bank gives 30x (two fitted elements: about 3x, 1.03 -> 0.32 um)
    assert before >= 10.0 * after, (before, after)
    assert not any(c.significant for c in d.effects)  # nothing significant left
