"""Two slow effects at once (issue 62, issue 60's known miss): creep with a housing that warms, creep
with a load staircase, drawn per seed by ``benchmarks/diagnosis_cases.py`` (``draw_slow_pair``), and
the warming alone. ``--auto`` must add both effects where both are hidden and no creep where none
is, and the verdicts report the numbers that tell the two apart: the drift along holds a channel
term leaves (creep's signature) and the channel's trace a creep term leaves."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import diagnosis_cases as DC

from hilbench import effects as E
from hilbench.diagnosis.diagnose import diagnose
from hilbench.diagnosis.evidence import HOLD_END_ROWS, slow_signatures
from hilbench.diagnosis.thresholds import CREEP_MIN_DRIFT_OVER_NOISE, MIN_GAIN
from tests.diagnosis.test_creep_signature import FS, NOISE, _creep, _rows


def _added(d) -> set[str]:
    return {part for s in d.steps[1:] for part in s["added"].split("+")}


def test_slow_signatures_tell_a_drift_along_holds_from_a_channels_trace():
    rng = np.random.default_rng(3)
    creep = _creep()
    n = creep.size
    rows = _rows(creep + rng.normal(0.0, NOISE, n))
    rows.aux["temperature"] = 25.0 + np.linspace(0.0, 3.0, n)  # a warming housing
    trace = 0.05 * (rows.aux["temperature"] - 25.0)
    # a channel term that left creep: the drift stands far beyond the noise, no channel trace
    left_creep = slow_signatures(rows, creep + rng.normal(0.0, NOISE, n), NOISE)
    assert left_creep["holds"] == 4
    assert left_creep["drift_left_over_noise"] > 10 * CREEP_MIN_DRIFT_OVER_NOISE
    assert left_creep["drift_left_um"] * np.sqrt(HOLD_END_ROWS / 2.0) / NOISE == \
        pytest.approx(left_creep["drift_left_over_noise"])
    # a decay alternating in sign from hold to hold: a ramp takes a tenth of it at most
    assert left_creep["channel_trace"]["temperature"]["explained"] < 0.2
    # a creep term that left the channel: its trace is most of the residual, many noise floors, and
    # along a 1 s hold the warming moves 0.05 * 3 / 4.8 um, a few standard errors, not tens
    left_channel = slow_signatures(rows, trace + rng.normal(0.0, NOISE, n), NOISE)
    assert left_channel["channel_trace"]["temperature"]["explained"] > 0.9
    # the ramp's 0.15 um, as an rms 0.15 / sqrt(12) about its mean, over the noise
    assert left_channel["channel_trace"]["temperature"]["rms_over_noise"] == pytest.approx(0.15 / 12**0.5 / NOISE,
                                                                                          rel=0.05)
    assert left_channel["drift_left_over_noise"] < left_creep["drift_left_over_noise"] / 5
    # both gone: noise only
    clean = slow_signatures(rows, rng.normal(0.0, NOISE, n), NOISE)
    assert clean["drift_left_over_noise"] < CREEP_MIN_DRIFT_OVER_NOISE
    assert clean["channel_trace"]["temperature"]["rms_over_noise"] < 0.2
    assert FS == 1000.0  # the rows' rate the drift's ends are counted at


def _first_round(d, effect: str):
    return next(c for c in d.rounds[0].effects if c.effect == effect)


def test_creep_with_a_warming_housing_gets_both_effects(tmp_path):
    """Issue 60's known miss: creep with a temperature drift found as temperature alone."""
    case = DC.draw_slow_pair(10, "creep+warming")  # pi1, a log creep, 15120 samples at 2 kHz, one run
    paths, kw = DC.write_case(case, tmp_path)
    d = diagnose(paths, case.spec, auto=True, jobs=1, **kw)
    assert {"creep", "temperature"} <= _added(d), d.steps
    # the temperature term alone leaves creep's drift along the holds, far beyond the noise
    temp = _first_round(d, "temperature")
    left = temp.evidence["slow_signatures"]
    assert left["drift_left_over_noise"] >= CREEP_MIN_DRIFT_OVER_NOISE, left
    assert "still drifts along holds" in temp.explanation
    # and creep, added after it, lowers the validation rmse by more than the effect bar
    assert d.steps[-1]["validation"]["rmse"] < (1.0 - MIN_GAIN) * d.steps[1]["validation"]["rmse"], d.steps


def test_creep_with_a_load_staircase_gets_both_effects(tmp_path):
    case = DC.draw_slow_pair(10, "creep+load-staircase")  # pi1, a log creep, 14462 samples at 500 Hz
    paths, kw = DC.write_case(case, tmp_path)
    d = diagnose(paths, case.spec, auto=True, jobs=1, **kw)
    assert {"creep", "load"} <= _added(d), d.steps
    left = _first_round(d, "load").evidence["slow_signatures"]
    assert left["drift_left_over_noise"] >= CREEP_MIN_DRIFT_OVER_NOISE, left


def test_a_warming_housing_alone_gets_no_creep(tmp_path):
    case = DC.draw_slow_pair(19, "warming")  # pi1, a ramp, 13041 samples at 1 kHz, two runs
    assert case.hidden == ["temperature"] and "creep" not in case.tables
    paths, kw = DC.write_case(case, tmp_path)
    d = diagnose(paths, case.spec, auto=True, jobs=1, **kw)
    assert "temperature" in _added(d) and "creep" not in _added(d), d.steps
    temp = _first_round(d, "temperature")
    assert E.effect("temperature").signature == "channel"
    assert temp.evidence["slow_signatures"]["drift_left_over_noise"] < CREEP_MIN_DRIFT_OVER_NOISE, \
        temp.evidence["slow_signatures"]
