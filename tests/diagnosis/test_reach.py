"""Validation rows within training's input reach (hilbench/diagnosis/reach.py, decision 0071)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import diagnosis_cases as DC

from hilbench.cli.summaries import diagnosis_lines
from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.diagnose import diagnose
from hilbench.diagnosis.reach import outside_envelope
from hilbench.report.diagnosis_report import _steps_section


def test_an_excursion_and_its_memory_are_outside_until_the_opposite_end_wipes_it():
    # training's range -1..1 V; the envelope widens it by REACH_ENVELOPE of the 2 V span
    m = T.REACH_ENVELOPE * 2.0
    u = np.array([0.0, 1.0 + 0.5 * m,  # inside the widened range: judged
                  1.5, 0.5, 0.0, -0.9 + 0.5 * m,  # beyond it, then the memory of the turning point at 1.5
                  -1.0, 0.0, 0.5,  # back at the opposite end: the excursion is wiped out
                  -1.6, 0.9, 1.0])  # below the range, until back at the top end
    out = outside_envelope(u, -1.0, 1.0)
    assert out.tolist() == [False, False, True, True, True, True, False, False, False, True, True, False]


def test_no_excursion_leaves_every_row_in():
    u = np.sin(np.linspace(0.0, 20.0, 500))
    assert not outside_envelope(u, -1.0, 1.0).any()


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    # each test writes its own files: a module-wide folder would tie them to one test worker
    return tmp_path


def test_a_creep_masked_by_the_memory_of_an_excursion_is_found_within_reach(folder):
    # randomized seed 7141: a logarithmic creep under a play base, one run split at 68 %. The
    # staircase of the validation rows steps to 1.37 V, past training's 1.07 V, and down to 0.25 V:
    # every model carries the excursion's memory there. On every row the creep refit lowers the
    # validation rmse 6 % (0.074 -> 0.069 um, p 0.39) and nothing is significant; within reach it
    # lowers it 75 %, to about the sensor noise (0.011 um)
    case = DC.draw_case(7141)
    paths, kw = DC.write_case(case, folder / "c7141")
    d = diagnose(paths, case.spec, jobs=1, **kw)
    first = d.effects[0]
    assert first.significant and first.effect == "creep"
    reach = first.evidence["judged_within_reach"]
    assert 0 < reach["left_out"] < reach["validation_rows"]
    old, new = first.evidence["validation_rmse"]
    assert old < d.metrics["validation"]["rmse"]  # judged on fewer rows than every validation row
    assert new < 0.5 * old
    assert any("beyond training's input range" in n for n in d.result.notes)


def test_auto_continues_from_a_refit_scored_on_every_validation_row(folder):
    # the same case with --auto: the candidate judged within reach carries the refit scored on every
    # validation row, so the next round compares models on the same rows (it raised a shape error
    # when the carried refit had only the rows within reach)
    case = DC.draw_case(7141)
    paths, kw = DC.write_case(case, folder / "c7141-auto")
    d = diagnose(paths, case.spec, jobs=1, auto=True, max_steps=2, **kw)
    first = d.rounds[0].effects[0]
    assert first.effect == "creep" and "judged_within_reach" in first.evidence
    rows = sum(int(r.validation.sum()) for r in d.rounds[0].result.runs)
    assert sum(int(r.validation.sum()) for r in first.fitted.runs) == rows
    assert [s["added"] for s in d.steps][:2] == [None, "creep"]
    assert d.steps[1]["validation"]["rmse"] == pytest.approx(first.fitted.metrics["validation"]["rmse"])
    # the step says on which rows the effect was judged, and the rmse there
    reach = d.steps[1]["within_reach"]
    assert reach["validation_rmse"] == first.evidence["validation_rmse"]
    assert 0 < reach["left_out"] < reach["validation_rows"] == rows
    lines = diagnosis_lines(d.to_json())
    step = next(line for line in lines if line.strip().startswith("1  ") and "creep" in line)
    assert f"{reach['left_out']} of {rows} rows left out" in step
    assert "rows left out: " in _steps_section(d)  # the HTML report's steps table too
