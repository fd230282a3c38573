"""``diagnose`` on third-party measured data (``../shared/data/real``); skipped when it is absent.

Issue acceptance: "piezo-dspace-preisach 20/40/100 Hz with ``pi`` trained at 20 Hz points at a rate
effect and adding it lowers the 100 Hz error; the creep records of pnzt-piezoceramic-aixacct point
at creep". What the data show (figures measured when written; thresholds leave a margin):

* piezo-dspace-preisach. The three captures are imported with :func:`import_files` (runs do not
  chain); the 1.5 s rest at -90 V (and the power-on step) is cut off and only the active parts are
  written to a second recording with :meth:`RecordingWriter.write_run`, because ``diagnose`` trains
  and scores whole runs. With the whole captures the rest rows dominate and no effect is
  significant.

  - train 20 Hz, test 40 + 100 Hz (the issue's protocol). A lag fitted from 20 Hz loops alone is
    wrong (pi+delay: 0.24 ms, and the 100 Hz error rises 0.1216 -> 0.1274 um) because at one rate
    phase lag looks like loop width. So delay and dynamics are calibrated across rates
    (:mod:`hilbench.diagnosis.rate_calibration`): shape fitted on 20 + 40 Hz and fixed, the model refitted
    on 20 Hz, confirmed on 100 Hz, which no fit saw. ``delay`` ranks first and is significant:
    100 Hz rmse 0.1216 -> 0.0939 um (gain 23 %, p 2e-6, 40 Hz 0.0907 -> 0.0822), delay 0.176 ms;
    ``asymmetry`` follows (22 % on 40 + 100 Hz). ``rate-dependence`` is untestable: its
    rate-weighted operator weights cannot be learned from one training rate.
  - train 20 + 40 Hz, test 100 Hz: two drive frequencies in training make the lag identifiable
    directly; ``delay`` ranks first and is significant, 100 Hz rmse 0.1188 -> 0.0924 um.

* pnzt-piezoceramic-aixacct ``RMN_TRAP_1400V_1000V_CREEP.dat``: 4 blocks (68, 68, 105, 1400 s)
  read with :func:`load_aixacct_dat`, one run each (input V+ in V, output D1 in um). V+ carries
  ~1 V of noise on the holds; the diagnosis recognises holds inside a dead band of 5 input-noise
  stds (:mod:`hilbench.diagnosis.input_motion`), so creep is testable as read. The ceramic is driven bipolar
  beyond its coercive field and its strain is a butterfly (SOURCE.md): even in the input, which
  ``pi`` cannot follow. Started from ``pi+asymmetry`` (the butterfly's even part), creep ranks
  first and is significant: default 70/30 split, validation rmse 0.1773 -> 0.0978 um (gain 45 %,
  p 2e-4), the residual drifting along the holds by 1.45x its rms. Started from ``pi`` nothing is
  significant: creep alone lowers training 0.385 -> 0.269 um but validation only 0.9 %, asymmetry
  alone worsens validation (the two only pay together); tables 1-3 train, table 4 (1400 s hold)
  test: the creep fitted on <= 105 s holds does not extrapolate to 1400 s (logarithmic creep).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hilbench.diagnosis.diagnose import Diagnosis, diagnose
from hilbench.identify.fitting import load_runs
from hilbench.recording.importers import import_files
from hilbench.recording.aixacct import load_aixacct_dat
from hilbench.recording.hdf5 import RecordingWriter
from tests.conftest import require_real_data

DSPACE_DIR = "piezo-dspace-preisach"
DSPACE_FILES = ("20_hz_no_lp.mat", "40_hz_no_lp.mat", "100_hz_no_lp.mat")
DSPACE_MAP = {"Y(3)": "input[V]", "Y(1)": "output[um]"}
DSPACE_LABELS = ["20hz", "40hz", "100hz"]
DSPACE_ACTIVE_S = 1.5
CREEP_FILE = ("pnzt-piezoceramic-aixacct", "RMN_TRAP_1400V_1000V_CREEP.dat")
RATE_EFFECTS = ("rate-dependence", "delay", "dynamics")
DEAD_BAND_V = 5.0
UNITS = {"time": "s", "input": "V", "output": "um"}


def _source(*parts: str) -> Path:
    path = require_real_data().joinpath(*parts)
    if not path.exists():
        pytest.skip(f"{path} not found")
    return path


def _effect(d: Diagnosis, name: str):
    return next(c for c in d.effects if c.effect == name)


@pytest.fixture(scope="module")
def dspace_active(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The 20/40/100 Hz captures, active parts only (t >= 1.5 s), one run each, not chained."""
    files = [_source(DSPACE_DIR, name) for name in DSPACE_FILES]
    folder = tmp_path_factory.mktemp("real-diag")
    full = folder / "dspace-full.h5"
    import_files(files, full, mapping=DSPACE_MAP, run_names=DSPACE_LABELS)
    out = folder / "dspace-active.h5"
    writer = RecordingWriter(out)
    for run, label in zip(load_runs(full), DSPACE_LABELS):
        k = int(round(DSPACE_ACTIVE_S * run.sample_rate_hz))
        assert np.all(run.input[:k] == -90.0)  # the rest that is cut off
        n = len(run) - k
        writer.write_run(label, {"time": np.arange(n) / run.sample_rate_hz, "input": run.input[k:],
                                 "output": run.output[k:]}, UNITS,
                         experiment="import", excitation="", sample_rate_hz=run.sample_rate_hz)
    return out


def _dead_band(v: np.ndarray, band: float) -> np.ndarray:
    out = np.empty_like(v)
    held = v[0]
    for i, x in enumerate(v):
        if abs(x - held) > band:
            held = x
        out[i] = held
    return out


def _creep_recording(path: Path, band: float | None) -> Path:
    writer = RecordingWriter(path)
    for b in load_aixacct_dat(_source(*CREEP_FILE)):
        t = b["time"]
        u = b["voltage"] if band is None else _dead_band(b["voltage"], band)
        writer.write_run(f"table{b['table']}", {"time": t - t[0], "input": u, "output": b["displacement"]}, UNITS,
                         experiment="import", excitation="", sample_rate_hz=(len(t) - 1) / (t[-1] - t[0]))
    return path


# -- piezo-dspace-preisach --------------------------------------------------------------------------


def _validation_rmse(d: Diagnosis, key: str) -> float:
    run = next(r for r in d.result.runs if r.key == key)
    e = (run.simulated - run.data.output)[run.validation]
    return float(np.sqrt(np.mean(e**2)))


def test_dspace_pi_trained_at_20hz(dspace_active: Path) -> None:
    """The issue's protocol: a rate effect (delay, calibrated on 40 Hz) ranks first and lowers the
    100 Hz error. The 20 Hz run comes at several amplitudes (rates spread 6.9x), so rate-dependence's
    damping is tested there (decision 0064) and refused: learned at 20 Hz, it doubles the 40/100 Hz error."""
    d = diagnose(dspace_active, "pi", train=["20hz"], test=["40hz", "100hz"])
    assert [r.data.name for r in d.result.runs if r.validation.any()] == ["0002-40hz", "0003-100hz"]
    assert d.best is not None and d.best.effect in RATE_EFFECTS and d.best.significant
    assert d.best.effect == "delay"  # measured 23 %, asymmetry next with 22 %
    ev = d.best.evidence
    assert ev["rate_calibration"]["calibrated_on"] == ["0002-40hz"]
    assert ev["rate_calibration"]["confirmed_on"] == ["0003-100hz"]
    before, after = ev["confirmation_rmse"]  # measured 0.1216 -> 0.0939 um at 100 Hz
    assert after < 0.85 * before and ev["p_value"] < 1e-3
    assert 5e-5 < d.best.fitted.model.effect("delay").param("seconds") < 4e-4  # measured 0.176 ms
    assert "delay(seconds=" in d.best.spec  # the calibrated shape is written into the spec
    rate = _effect(d, "rate-dependence")  # measured: training -33 %, validation +100 %
    assert not rate.significant and rate.expected_gain < 0
    assert _effect(d, "asymmetry").significant  # measured 22 %, a static effect found as well


def test_dspace_add_delay_lowers_the_100hz_error(dspace_active: Path) -> None:
    d = diagnose(dspace_active, "pi", train=["20hz"], test=["40hz", "100hz"], add="delay")
    assert [s["added"] for s in d.steps] == [None, "delay"]
    assert d.spec.startswith("pi+delay(seconds=")
    start = diagnose(dspace_active, "pi", train=["20hz"], test=["40hz", "100hz"])
    before, after = _validation_rmse(start, "0003-100hz"), _validation_rmse(d, "0003-100hz")
    assert after < 0.85 * before, (before, after)  # measured 0.1216 -> 0.0939 um
    assert d.steps[1]["validation"]["rmse"] < d.steps[0]["validation"]["rmse"]  # 0.1005 -> 0.0857 um


def test_dspace_pi_trained_at_20_and_40hz(dspace_active: Path) -> None:
    """Two drive frequencies in training: delay is pointed at and lowers the 100 Hz error."""
    d = diagnose(dspace_active, "pi", train=["20hz", "40hz"], test=["100hz"])
    assert d.best is not None and d.best.effect in RATE_EFFECTS and d.best.significant
    assert d.best.effect == "delay"
    before, after = d.best.evidence["validation_rmse"]  # measured 0.1188 -> 0.0924 um
    assert after < 0.85 * before
    assert d.best.evidence["p_value"] < 1e-3  # measured 1e-6
    assert _effect(d, "dynamics").significant  # measured 21 %


def test_dspace_whole_captures_auto_reaches_1pct_at_100hz(tmp_path: Path) -> None:
    """Issue 11 acceptance: the captures imported whole (rests and power-on step included, import's
    own run names), ``--model pi --train 20hz --test 100hz --auto``: validation erms <= 1.0 % of range
    at 100 Hz, and the notes say what was left out. The delay comes from the power-on step at the
    start of the 20 Hz capture (measured: 0.102 ms; 1.68 % -> 0.91 %)."""
    whole = tmp_path / "whole.h5"
    import_files([_source(DSPACE_DIR, name) for name in DSPACE_FILES], whole, mapping=DSPACE_MAP)
    d = diagnose(whole, "pi", train=["20hz"], test=["100hz"], auto=True)
    assert d.metrics["validation"]["erms_pct"] <= 1.0, d.steps
    assert sum("left out 0-1.5" in n and "rests at -90" in n for n in d.result.notes) == 3
    added = [s["added"] for s in d.steps]
    assert "delay" in added, d.steps
    first = d.rounds[0]
    delay = _effect(first, "delay")
    assert 0.00005 <= delay.evidence["rate_calibration"]["power_on_step"]["dead_time_s"] <= 0.0002
    assert "power-on step" in delay.explanation


# -- pnzt-piezoceramic-aixacct --------------------------------------------------------------------------


def test_aixacct_creep_file_parses() -> None:
    blocks = load_aixacct_dat(_source(*CREEP_FILE))
    assert [b["table"] for b in blocks] == [1, 2, 3, 4]
    assert all(b["time"].size == 5000 for b in blocks)
    assert [round(float(b["time"][-1])) for b in blocks] == [68, 68, 105, 1400]
    for b in blocks:
        assert b["header"]["SampleName"].startswith("CREEP_1400V_1000V")
        assert 1470 < b["voltage"].max() < 1480 and -1335 < b["voltage"].min() < -1325
        assert np.all(np.isfinite(b["displacement"])) and np.ptp(b["displacement"]) < 3.0  # um, not nm
        assert np.all(np.diff(b["time"]) > 0)
        assert b["displacement"][0] == 0.0


def test_aixacct_creep_holds_found_in_the_noise(tmp_path: Path) -> None:
    """V+ as measured never holds bit-for-bit still (noise ~1 V), yet the holds are recognised."""
    d = diagnose(_creep_recording(tmp_path / "creep.h5", None), "pi")
    assert "creep" not in {u["effect"] for u in d.untestable}
    creep = _effect(d, "creep")
    assert creep.evidence["checks"]["drift_on_holds"]  # measured drift/rms 0.91
    assert creep.evidence["hold_rows"] > 0.8  # measured 0.996
    assert "the drift is there" in creep.explanation
    # from pi, creep alone does not pay on validation (the butterfly error swamps it)
    assert not creep.significant  # measured 0.9 %, p 0.30


def test_aixacct_creep_records_point_at_creep(tmp_path: Path) -> None:
    """With the butterfly's even part modelled, creep ranks first and is significant."""
    d = diagnose(_creep_recording(tmp_path / "creep.h5", None), "pi+asymmetry")
    assert d.best is not None and d.best.effect == "creep" and d.best.significant
    before, after = d.best.evidence["validation_rmse"]  # measured 0.1773 -> 0.0978 um
    assert after < 0.7 * before
    assert d.best.evidence["p_value"] < 1e-3  # measured 2.4e-4
    assert d.best.evidence["drift_over_rms"] > 0.5  # measured 1.45
    assert d.best.explanation.endswith("creep")
    # same answer with a hand-made dead band on the input
    d5 = diagnose(_creep_recording(tmp_path / "creep5.h5", DEAD_BAND_V), "pi+asymmetry")
    assert d5.best is not None and d5.best.effect == "creep" and d5.best.significant
