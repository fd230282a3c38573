"""``diagnose`` on third-party measured data (``../shared/data/real``); skipped when it is absent.

Issue acceptance: "piezo-dspace-preisach 20/40/100 Hz with ``pi`` trained at 20 Hz points at a rate
effect and adding it lowers the 100 Hz error; the creep records of pnzt-piezoceramic-aixacct point
at creep". What the data show (figures measured when written; thresholds leave a margin):

* piezo-dspace-preisach. The three captures are imported with :func:`import_files` (runs do not
  chain); the 1.5 s rest at -90 V (and the power-on step) is cut off and only the active parts are
  written to a second recording with :meth:`RecordingWriter.write_run`, because ``diagnose`` trains
  and scores whole runs. With the whole captures the rest rows dominate and no effect is
  significant (creep/delay/dynamics/rate-dependence all lower validation rmse by < 0 %).

  - train 20 Hz, test 40 + 100 Hz (the issue's protocol): ``asymmetry`` ranks first and is
    significant (validation rmse 0.1005 -> 0.0783 um, gain 22 %, p 1e-5), then ``saturation``
    (12 %). The rate-type effects are NOT significant: ``delay`` 1.4 % (p 0.27), ``dynamics``
    -0.4 %, ``rate-dependence`` -120 % (it overfits the 20 Hz loop). This is the known limit of
    tests/test_real_data.py: the lag that matters at 100 Hz (~0.12 ms) is not identifiable from
    20 Hz loops alone. Part of the acceptance therefore does not hold under this protocol.
  - train 20 + 40 Hz, test 100 Hz: two drive frequencies in training make the lag identifiable;
    ``delay`` ranks first and is significant, 100 Hz rmse 0.1188 -> 0.0924 um (gain 22 %,
    p 1e-6), ``dynamics`` is significant too (21 %). Here the rate effect is pointed at and lowers
    the 100 Hz error.

* pnzt-piezoceramic-aixacct ``RMN_TRAP_1400V_1000V_CREEP.dat``: 4 blocks (68, 68, 105, 1400 s)
  read with :func:`load_aixacct_dat`, one run each (input V+ in V, output D1 in um). The measured
  V+ carries ~1 V of noise on the holds, so as read the input "never holds still" and creep is
  untestable. With a 5 V dead band on the input (the held value changes only when V+ moves by
  more than 5 V; ramps of ~1e5 V/s are unaffected) creep becomes testable and its physical
  signature is there (residual drift along holds / rms 1.19 >= 0.2), but the refit does not pay:
  default 70/30 split, validation rmse 0.1221 -> 0.1209 um (gain 0.9 %, p 0.30, train
  0.385 -> 0.269 um); tables 1-3 train, table 4 (1400 s hold) test: creep gain 6.3 % (p 0.29)
  while ``asymmetry`` (40 %) and ``saturation`` (40 %) rank first. ``pi`` cannot follow the
  butterfly loop of a bipolar-driven ceramic (SOURCE.md), and that error swamps the creep. Creep is
  therefore detected as a drift on holds but not ranked first/significant.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hilbench.diagnosis import Diagnosis, diagnose
from hilbench.fitting import load_runs
from hilbench.importers import import_files
from hilbench.importers_aixacct import load_aixacct_dat
from hilbench.recording import RecordingWriter
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


def test_dspace_pi_trained_at_20hz(dspace_active: Path) -> None:
    """The issue's protocol: asymmetry comes out on top; rate effects are not identifiable from 20 Hz."""
    d = diagnose(dspace_active, "pi", train=["20hz"], test=["40hz", "100hz"])
    assert [r.data.name for r in d.result.runs if r.validation.any()] == ["0002-40hz", "0003-100hz"]
    assert d.best is not None and d.best.effect == "asymmetry" and d.best.significant  # measured 22 %
    assert d.best.expected_gain > 0.15
    assert d.best.evidence["p_value"] < 1e-3  # measured 1e-5
    for name in RATE_EFFECTS:  # measured delay 1.4 %, dynamics -0.4 %, rate-dependence -120 %
        c = _effect(d, name)
        assert not c.significant and c.expected_gain < 0.05
    assert not any(u["effect"] in RATE_EFFECTS for u in d.untestable)  # tested, not merely skipped


def test_dspace_pi_trained_at_20_and_40hz(dspace_active: Path) -> None:
    """Two drive frequencies in training: delay is pointed at and lowers the 100 Hz error."""
    d = diagnose(dspace_active, "pi", train=["20hz", "40hz"], test=["100hz"])
    assert d.best is not None and d.best.effect in RATE_EFFECTS and d.best.significant
    assert d.best.effect == "delay"
    before, after = d.best.evidence["validation_rmse"]  # measured 0.1188 -> 0.0924 um
    assert after < 0.85 * before
    assert d.best.evidence["p_value"] < 1e-3  # measured 1e-6
    assert _effect(d, "dynamics").significant  # measured 21 %


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


def test_aixacct_creep_untestable_as_read(tmp_path: Path) -> None:
    """V+ as measured never holds still (noise ~1 V), so creep cannot be tried."""
    d = diagnose(_creep_recording(tmp_path / "creep.h5", None), "pi")
    assert "creep" in {u["effect"] for u in d.untestable}


def test_aixacct_creep_with_dead_band(tmp_path: Path) -> None:
    """Holds recognised: creep's drift signature is there, but the refit gain is not significant."""
    path = _creep_recording(tmp_path / "creep.h5", DEAD_BAND_V)
    d = diagnose(path, "pi")
    creep = _effect(d, "creep")
    assert creep.evidence["checks"]["drift_on_holds"]  # measured drift/rms 1.19
    assert creep.evidence["drift_over_rms"] > 0.5
    assert not creep.significant and creep.expected_gain < 0.10  # measured 0.9 %, p 0.30
    assert creep.evidence["train_rmse"][1] < 0.8 * creep.evidence["train_rmse"][0]  # 0.385 -> 0.269 um
    # the 1400 s hold as the test run: asymmetry/saturation (the butterfly) outrank creep
    d4 = diagnose(path, "pi", train=["table1", "table2", "table3"], test=["table4"])
    assert d4.best is not None and d4.best.effect in ("asymmetry", "saturation") and d4.best.significant
    c4 = _effect(d4, "creep")
    assert not c4.significant and 0.0 < c4.expected_gain < 0.15  # measured 6.3 %, p 0.29
