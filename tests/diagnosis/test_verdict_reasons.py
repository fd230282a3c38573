"""Every verdict gives its reason: a candidate that is not significant names each failed check with what
was measured and what was required, in ``to_json()`` (``evidence["failed_checks"]``), at the end of its
explanation, in the text output (``diagnosis_lines``) and in the HTML report's evidence."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest

from hilbench.cli.summaries import diagnosis_lines, diagnosis_summary_lines
from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.diagnose import diagnose
from hilbench.diagnosis.verdict import Candidate, check_reason, failed_checks, relative_gain
from hilbench.recording.hdf5 import RecordingWriter
from hilbench.report.diagnosis_report import evidence_cell
from hilbench.rig.config import load_rig
from hilbench.sim.plant import Plant
from tests.conftest import MINIMAL_RIG

FS = 1000.0


@pytest.fixture(scope="module")
def asymmetric_sine(tmp_path_factory) -> Path:
    """One 2 Hz sine run on a plant with a hidden asymmetry: with 'pi+saturation' the only effect the
    data can test is asymmetry (one drive frequency, no holds, no channels)."""
    folder = tmp_path_factory.mktemp("reasons")
    rig = folder / "rig.toml"
    rig.write_text(textwrap.dedent(MINIMAL_RIG) + "\n[plant.asymmetry]\ncoefficients = [0.0, 0.0, 0.05, 0.01]\n",
                   encoding="utf-8")
    plant = Plant.from_rig(load_rig(rig))
    u = 5.0 * np.sin(2 * np.pi * 2.0 * np.arange(4000) / FS)
    out = folder / "sine.h5"
    RecordingWriter(out).write_run("sine", {"time": np.arange(u.size) / FS, "input": u,
                                            "output": plant.simulate(u).output},
                                   {"time": "s", "input": "V", "output": "um"}, experiment="t", excitation="{}",
                                   sample_rate_hz=FS)
    return out


def test_only_candidate_fails_one_check_and_says_by_how_much(asymmetric_sine, monkeypatch):
    # asymmetry removes ~98 % of the error and passes every check at the shipped thresholds; asking
    # for a 99 % drop makes the gain the one check it fails (the wrong-base search is switched off so
    # that asymmetry stays the only candidate)
    monkeypatch.setattr(T, "MIN_GAIN", 0.99)
    monkeypatch.setattr(T, "WRONG_BASE_NOISE_FACTOR", float("inf"))
    d = diagnose(asymmetric_sine, "pi+saturation")
    assert [c.effect for c in d.effects] == ["asymmetry"]
    doc = json.loads(json.dumps(d.to_json(), allow_nan=False))
    cand = doc["effects"][0]
    ev = cand["evidence"]
    assert not cand["significant"]
    assert [k for k, ok in ev["checks"].items() if not ok] == ["gain_over_10pct"]
    (failed,) = ev["failed_checks"]
    gain = relative_gain(*ev["validation_rmse"])
    assert 0.9 < gain < 0.99
    assert failed["check"] == "gain_over_10pct"
    assert failed["measured"] == pytest.approx(gain) == pytest.approx(cand["expected_gain"])
    assert failed["required"] == "> 0.99"
    assert failed["text"] == f"validation rmse fell {100 * gain:.2g} %, less than the 99 % required"
    assert cand["explanation"].endswith("; not significant: " + failed["text"])
    # the text output shows it on the candidate's line
    (line,) = [ln for ln in diagnosis_lines(doc) if ln.lstrip().startswith("asymmetry")]
    assert "not significant" in line and line.endswith(failed["text"])
    # and the compact view (one screen) names the failed check, measured against required
    (line,) = [ln for ln in diagnosis_summary_lines(doc) if ln.lstrip().startswith("asymmetry")]
    assert line.split()[1] == "refused" and line.endswith(failed["text"])
    # untestable verdicts keep their reasons
    reasons = {u["effect"]: u["reason"] for u in doc["untestable"]}
    assert "never holds still" in reasons["creep"]
    # the noise floor says how it was estimated, the old residual-based estimate among them
    est = ev["noise_floor_estimates"]
    assert est["chosen"] in est and est[est["chosen"]] == pytest.approx(ev["noise_floor"])
    assert est["residual"] > 0
    # the HTML report's evidence cell says it too
    assert f"✗ gain_over_10pct: {failed['text']}" in evidence_cell(d.effects[0].to_json()["evidence"])


def test_significant_candidate_has_no_failed_checks(asymmetric_sine):
    d = diagnose(asymmetric_sine, "pi+saturation")
    best = d.effects[0]
    assert best.effect == "asymmetry" and best.significant
    doc = best.to_json()
    assert doc["evidence"]["failed_checks"] == [] and "not significant" not in doc["explanation"]


def _evidence_with(**over):
    ev = {"validation_rmse": [1.0, 0.938], "train_rmse": [1.0, 0.9], "p_value": 0.034, "blocks_improved": [12, 20],
          "noise_floor": 0.5, "checks": {}}
    ev.update(over)
    return ev


def test_each_check_reads_measured_against_required():
    ev = _evidence_with()
    r = check_reason("gain_over_10pct", ev)
    assert r["measured"] == pytest.approx(0.062) and r["required"] == "> 0.1"
    assert r["text"] == "validation rmse fell 6.2 %, less than the 10 % required"
    r = check_reason("blocks_p_below_0.01", ev)
    assert r["measured"] == 0.034 and "p = 0.034 (12 of 20" in r["text"] and r["required"] == "< 0.01"
    r = check_reason("error_above_noise", ev, "um")
    assert r["measured"] == pytest.approx(2.0) and "(1 um rms) is 2x the sensor noise floor (0.5 um)" in r["text"]
    # training and validation disagree: each way says which
    r = check_reason("train_and_validation_agree", _evidence_with(train_rmse=[1.0, 1.02]))
    assert r["measured"]["training_gain"] == pytest.approx(-0.02) and "training rmse rose 2 %" in r["text"]
    r = check_reason("train_and_validation_agree", _evidence_with(train_rmse=[1.0, 0.5]))
    assert "more parameters, not physics" in r["text"]
    r = check_reason("train_and_validation_agree", _evidence_with(validation_rmse=[1.0, 0.5], train_rmse=[1.0, 0.99]))
    assert "chance extrapolation" in r["text"]
    r = check_reason("calibration_and_confirmation_agree",
                     _evidence_with(confirmation_rmse=[2.0, 1.0], calibration_rmse=[1.0, 1.1]))
    assert "calibration rmse rose 10 %" in r["text"] and r["measured"]["confirmation_gain"] == pytest.approx(0.5)
    # creep's drift: small against the rms, and either small against the noise or not what creep's
    # refit removes
    r = check_reason("drift_on_holds", _evidence_with(drift_over_rms=0.05, drift_over_noise=1.2, drift_removed=0.9))
    assert r["measured"]["drift_over_rms"] == 0.05 and f"less than the {T.CREEP_MIN_DRIFT:g}x" in r["text"]
    assert f"1.2x the noise's standard error on a drift, less than the {T.CREEP_MIN_DRIFT_OVER_NOISE:g}x" in r["text"]
    r = check_reason("drift_on_holds", _evidence_with(drift_over_rms=0.15, drift_over_noise=12.0, drift_removed=-0.21))
    assert r["measured"]["drift_removed"] == -0.21 and "creep's refit removes -21 % of that drift" in r["text"]
    r = check_reason("drift_on_holds", _evidence_with(drift_over_rms=0.25, drift_over_noise=1.0, drift_removed=0.05))
    assert r["measured"]["drift_over_noise"] == 1.0
    assert f"0.25x its rms but only 1x the noise's standard error on a drift, less than the {T.CREEP_MIN_DRIFT_OVER_NOISE:g}x" in r["text"]
    r = check_reason("training_not_worse", _evidence_with(train_rmse=[1.0, 1.05]))
    assert r["measured"] == pytest.approx(0.05) and "rose 5 %" in r["text"]
    assert check_reason("some_new_check", ev)["text"] == "the check some_new_check does not hold"
    ev["checks"] = {"gain_over_10pct": False, "blocks_p_below_0.01": True, "error_above_noise": False}
    assert [f["check"] for f in failed_checks(ev)] == ["gain_over_10pct", "error_above_noise"]


def test_candidate_built_elsewhere_gets_its_reasons():
    # e.g. the wrong-base check builds its Candidate with checks but no reasons
    ev = _evidence_with(checks={"validation_2x_lower": False, "training_lower_too": True})
    c = Candidate("base", "pmpi", False, 0.2, "the loop itself has another shape", ev)
    doc = c.to_json()
    assert doc["evidence"]["failed_checks"][0]["check"] == "validation_2x_lower"
    assert doc["evidence"]["failed_checks"][0]["measured"] == pytest.approx(1 / 0.938)
    assert doc["explanation"].endswith("less than the 2x required")
    # checks added after judging (a pair's) are reasoned as they stand when the candidate is written
    c.evidence["checks"]["pair_over_each_single"] = False
    c.evidence["gain_over_best_single"] = 0.04
    assert c.to_json()["evidence"]["failed_checks"][1]["text"] == (
        "the pair's validation rmse is 4 % below the best single effect's, less than the 10 % required")


def test_a_rise_is_not_called_less_than_the_fall_required():
    """The measured dSPACE capture's dynamics (2026-12-04): 'validation at the confirming rates rmse rose
    43 %, less than the 10 % required' read as if a rise fell short of a fall; a rise says what is
    required instead, for the held-back rows too."""
    r = check_reason("gain_over_10pct", _evidence_with(validation_rmse=[1.0, 1.43]))
    assert r["text"] == "validation rmse rose 43 %, where a fall of 10 % is required"
    ev = _evidence_with(replication={"held_back_rmse": [0.06, 0.066]})
    r = check_reason("held_back_gain_over_10pct", ev)
    assert r["text"] == "on the held-back training rows the rmse rose 10 %, where a fall of 10 % is required"
