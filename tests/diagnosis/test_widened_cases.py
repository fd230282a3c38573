"""The widened suite of the randomized diagnosis benchmark (issue 62, item 4) and its report.

No diagnosis runs here: the generator (classic draws unchanged, widened draws deterministic, the new
bases and knees physical) and the benchmark's seed classes and confusion matrices on made-up rows.
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import bench_diagnosis_random as B
import diagnosis_cases as DC
import diagnosis_regressions as DR

from hilbench.sim.plant import Plant
from hilbench.sim.schema import SensorModel, check_plant


@pytest.mark.parametrize("reg", DR.ALL[::12], ids=lambda r: r.id)
def test_classic_draws_are_what_the_regressions_recorded(reg):
    case = DC.draw_case(reg.seed)
    assert case.suite == "classic"
    assert tuple(h for h in case.hidden if h != "none") == reg.hidden
    if reg.form is not None:
        assert case.forms[reg.hidden[0]] == reg.form


def test_widened_hidden_draws_pair_creep_with_a_slow_channel():
    draws = [DC.draw_hidden(DC.case_rng(s, "widened"), "widened") for s in range(3000)]
    kinds = Counter("clean" if h == ["none"] else ("two" if len(h) == 2 else "single") for h in draws)
    assert kinds["clean"] / 3000 == pytest.approx(DC.P_CLEAN, abs=0.03)
    pairs = [tuple(h) for h in draws if len(h) == 2]
    slow = Counter(p for p in pairs if p[0] == "creep" and p[1] in ("temperature", "load"))
    # 40 % drawn as a slow pair, plus the random pairs that happen to be one
    assert 0.35 < sum(slow.values()) / len(pairs) < 0.6
    assert set(slow) == {("creep", "temperature"), ("creep", "load")}
    # the classic stream draws differently (its own root), so widened seed n is not classic seed n
    assert [DC.draw_hidden(DC.case_rng(s)) for s in range(50)] != draws[:50]


def test_widened_case_is_deterministic_and_its_base_is_drawn_with_its_spec():
    a, b = DC.draw_case(21, "widened"), DC.draw_case(21, "widened")
    assert a.to_json() == b.to_json() and a.suite == "widened"
    assert a.spec == ("linear" if "hysteresis" in a.hidden else DC.BASE_SPEC.get(a.family, a.spec))
    with pytest.raises(ValueError, match="suite: 'wide'"):
        DC.draw_case(1, "wide")


@pytest.mark.parametrize("family", ["preisach", "bouc-wen"])
def test_widened_bases_are_valid_lagging_loops(family):
    rng = np.random.default_rng(4)
    for _ in range(3):
        table, spec, _ = DC._widened_base_table(rng, family, u_max=10.0)
        assert spec == {"preisach": "pi", "bouc-wen": "bouc-wen"}[family]
        fs = 1000.0
        plant = Plant(check_plant({"hysteresis": table}, "<case>", fs), fs, [SensorModel("output")])
        u = 10.0 * np.sin(2 * np.pi * np.arange(3001) / 1000.0)
        y = plant.simulate(u).output[2000:]
        assert np.all(np.isfinite(y))
        assert y[500] > y[0]  # u = 0 falling above u = 0 rising: the output lags as an actuator's does
        assert np.argmax(y) in range(200, 300)  # and it rises with the drive up to the drive's maximum


@pytest.mark.parametrize("shape", ["arctan", "exp"])
def test_soft_knees_are_odd_unit_slope_and_saturate_at_the_level(shape):
    x = np.linspace(-50.0, 50.0, 20001)
    y = DC.soft_knee(x, 2.0, shape)
    np.testing.assert_allclose(y, -y[::-1], atol=1e-12)
    assert np.gradient(y, x)[10000] == pytest.approx(1.0, rel=5e-3)
    assert np.all(np.diff(y) > 0) and np.all(np.abs(y) < 2.0) and abs(y[-1]) > 1.9


def row(seed, kind, hidden, first=None, added=None, error=False):
    r = {"seed": seed, "seed_class": B.seed_class(seed), "kind": kind, "hidden": hidden,
         "significant": [first] if first else [], "ranked_first": first, "forms": {}}
    if added is not None:
        r["auto_added"] = added
    if error:
        r = {"seed": seed, "seed_class": B.seed_class(seed), "kind": kind, "hidden": hidden, "error": "diagnose: x"}
    return r


def test_seed_classes_matrices_and_fresh_acceptance():
    rows = [
        row(9700, "single", ["creep"], "creep", ["creep"]),
        row(9701, "single", ["saturation"], "asymmetry", ["asymmetry"]),
        row(9702, "two", ["creep", "load"], "load", ["load"]),
        row(9703, "two", ["creep", "temperature"], "creep", ["temperature", "creep"]),
        row(9704, "clean", ["none"], None, []),
        row(9705, "single", ["delay"], error=True),
        row(12, "single", ["saturation"], "saturation", ["saturation"]),
        row(13, "clean", ["none"], "asymmetry", ["asymmetry"]),
    ]
    rep = B.seed_class_report(rows, auto=True)
    m = rep["confusion_per_effect"]
    assert m["saturation"] == {"asymmetry": 1, "saturation": 1}
    assert m["creep (pair)"] == {"load": 1, "creep": 1}
    assert m["load (pair)"] == {"load": 1} and m["none"] == {"nothing": 1, "asymmetry": 1}
    assert "delay" not in m  # a case that raised has no verdict to count
    assert rep["confusion_auto_added"]["creep (pair)"] == {"load": 1, "creep": 1, "temperature": 1}
    assert rep["confusion_auto_added"]["none"] == {"nothing": 1, "asymmetry": 1}
    assert rep["seed_classes"]["fresh"]["n"] == 6 and rep["seed_classes"]["development"]["n"] == 2
    assert rep["seed_classes"]["development"]["rates"]["clean_nothing_flagged"] == 0.0
    acc = rep["acceptance_fresh"]  # fresh only: the development rows do not count
    assert acc["single_ranked_first"]["rate"] == pytest.approx(1 / 3)  # 9705 raised: a miss
    assert acc["two_effect_both_added_by_auto"]["rate"] == 0.5
    assert acc["clean_nothing_flagged"] == {"rate": 1.0, "n": 1, "target": 0.95, "met": True}
    assert not acc["single_ranked_first"]["met"]
    table = B.confusion_table(m)
    lines = table.splitlines()
    assert len(lines) == 1 + len(m) and lines[0].split()[-1] == "nothing"
    header = lines[0].split()[3:]  # after the corner "hidden / first"
    cells = next(line for line in lines if line.startswith("creep (pair)")).split()[2:]
    assert dict(zip(header, cells)) == {"asymmetry": ".", "creep": "1", "load": "1", "saturation": ".",
                                        "nothing": "."}
    assert B.seed_class_report([r for r in rows if r["seed"] < 9700], auto=True)["acceptance_fresh"] is None
