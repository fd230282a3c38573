"""Tracking a reference fast enough for the actuator's dynamics to matter (issue 58): a play actuator
behind a 182 Hz resonance (zeta 0.46) sampled at 25 kHz, fitted as ``pi+dynamics`` from a sweep, tracks
a 29.3 Hz sine over 80 % of its recorded output. The compensator inverts the model's dynamics with a
preview of the whole reference and the run starts once the approach has settled; without the preview
the output lags the reference by ~9 deg (the error that was left to feedback before)."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest

from hilbench.excitation.plan import expand_runs
from hilbench.identify.fitting import fit
from hilbench.online.tracking import track
from hilbench.recording.hdf5 import Recording
from hilbench.rig.config import load_rig
from hilbench.rig.rig import Rig
from hilbench.runners.sweep import run_plan

RIG = """
[rig]
name = "play-behind-a-resonance"
sample_rate_hz = 25000.0
seed = 8

[actuator]
driver = "sim"
unit = "V"
min = -56.2
max = 56.2
max_rate = 56750.0
rest = 0.0

[[sensors]]
channel = "output"
unit = "um"
driver = "sim"
noise_std = 0.036

[plant.hysteresis]
model = "play"
input_scale = 56.2
linear_gain = 0.502107
thresholds = [0.064159, 0.123488, 0.32795]
weights = [0.467358, 0.851944, 0.634324]
output_scale = 15.5126

[plant.dynamics]
kind = "second-order"
natural_frequency_hz = 182.1
zeta = 0.46

[[plan.runs]]
label = "sine"
kind = "sine"
phase_deg = -90.0
frequency_hz = 10.7
cycles = 2
sweep = { amplitude = [19.28, 38.55, 55.08] }

[[plan.runs]]
label = "triangle"
kind = "triangle"
amplitude = 55.08
phase_deg = -90.0
duration_s = 0.187
sweep = { frequency_hz = [10.7, 22.07, 45.52] }

[[plan.runs]]
label = "chirp"
kind = "chirp"
amplitude = 27.54
f_start_hz = 22.07
f_end_hz = 109.3
method = "logarithmic"
duration_s = 0.187
"""


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> dict:
    folder = tmp_path_factory.mktemp("preview-tracking")
    rig = folder / "rig.toml"
    rig.write_text(textwrap.dedent(RIG), encoding="utf-8")
    config = load_rig(rig)
    recording = folder / "sweep.h5"
    with Rig(config) as opened:
        run_plan(opened, expand_runs(config.plan, file=config.path), recording)
    result = fit(recording, "pi+dynamics")
    y = np.concatenate([run.channel("output") for run in Recording(recording)])
    lo, hi = float(y.min()), float(y.max())
    reference = (f"sine:amplitude={0.4 * (hi - lo):.6g},offset={0.5 * (hi + lo):.6g},frequency_hz=29.3,cycles=3,"
                 "phase_deg=-90")
    return {"rig": rig, "model": result.model, "validation": result.metrics["validation"]["erms_pct"],
            "reference": reference}


def test_the_dynamics_inverted_with_a_preview_track_within_the_models_own_error(fitted: dict) -> None:
    val = fitted["validation"]
    ff = track(fitted["rig"], fitted["model"], fitted["reference"])
    lagging = track(fitted["rig"], fitted["model"], fitted["reference"], preview=False)
    e, e_lag = ff.metrics["erms_pct"], lagging.metrics["erms_pct"]
    print(f"\nerms_pct: previewed {e:.3f}, without preview {e_lag:.3f}, the model's validation {val:.3f}")
    assert e <= max(2 * val, val + 0.3)
    assert e <= 0.2 * e_lag
    assert ff.compensator["preview"]["dynamics"] and ff.compensator["held_before_run_samples"] > 0
    assert any("preview of the whole reference" in note for note in ff.compensator["notes"])
    fb = track(fitted["rig"], fitted["model"], fitted["reference"], feedback=True).metrics["erms_pct"]
    print(f"with designed feedback {fb:.3f}")
    assert fb <= e


def test_a_triangle_starting_at_its_corner_is_tracked_from_its_first_sample(fitted: dict, tmp_path: Path) -> None:
    """A triangle that starts moving at once: the inverse's part before the first sample (the hold's
    sample and the regularised inverse's ringing, decision 0121) runs as the run's first samples, so
    the first half period is tracked as well as the later ones. Without it the plant left a sample
    late and its resonance rang through the first period (0.78 um rms, 5.3x the later error on this
    rig; with it 0.12 um). The pre-actuation is recorded at the run's start and left out of the
    figures."""
    reference = fitted["reference"].replace("sine:", "triangle:").replace("frequency_hz=29.3", "frequency_hz=20")
    out = tmp_path / "track.h5"
    result = track(fitted["rig"], fitted["model"], reference, output=out)
    lead = result.preactuation["input"].size
    assert lead > 0 and result.compensator["preview"]["preactuation_samples"] == lead
    fs = 25000.0
    half = int(fs / 20 / 2)
    e = np.abs(result.error)
    first, later = float(np.sqrt(np.mean(e[:half] ** 2))), float(np.sqrt(np.mean(e[half:] ** 2)))
    print(f"\nrms error: first half period {first:.4g} um, later {later:.4g} um, {lead} samples of pre-actuation")
    assert first <= 1.5 * later
    assert result.metrics["erms_pct"] <= max(2 * fitted["validation"], fitted["validation"] + 0.3)
    run = Recording(out).run(result.group)
    assert int(run.attrs["preactuation_samples"]) == lead
    assert run.channel("output").size == lead + result.output.size
    np.testing.assert_array_equal(run.channel("reference")[:lead], np.full(lead, result.reference[0]))
