"""Cases of the randomized diagnosis benchmark (benchmarks/diagnosis_cases.py), drawn with fixed seeds.

Each case is a simulated actuator with one hidden effect of a form drawn at random (or none),
recorded as a bench records it (rest, power-on step, a program of triangles, sines, noise, ...,
sensor noise and quantisation), diagnosed from the start spec without the effect. What is asserted
is what the diagnosis SHOULD find. The seeded regressions, each with what once went wrong and the
decision that fixed it, are listed in benchmarks/diagnosis_regressions.py; this suite runs one case
per mechanism (``SUITE``: every effect and form, a pair, reach, the wrong base, the tie rules) and
``python benchmarks/bench_diagnosis_random.py --regressions`` runs them all. The floating-point
kernels the verdicts rest on are pinned for the whole suite (tests/conftest.py), so no outcome here
depends on the CPU. The generator is not tuned to the diagnosis, and nothing here is tuned per case.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import diagnosis_cases as DC
import diagnosis_regressions as DR

from hilbench.diagnosis.diagnose import diagnose

#: the regressions this suite runs (seed -> the mechanism it stands for); the others run in the benchmark.
#: An even v^6 and the base's resolution (4223, decision 0060) are diagnosed in test_resolution.py.
SUITE = {
    7538: "asymmetry even-2; the wrong base: another base must beat a finer current one (0077)",
    16: "saturation on the output (knee); the sum test over blocks (0022)",
    805: "saturation on the drive (Hammerstein knee, 0039)",
    122: "creep over decades (Kelvin-Voigt bank)",
    4586: "creep, logarithmic; a drift measured against the noise (0059)",
    175: "delay of the sensor; runs that sweep their rate split in interleaved blocks",
    2033: "delay of the amplifier; nothing left to explain only within the noise floor's own uncertainty (0045)",
    68: "the tie rules: on a one-sided drive even and odd patterns look alike, and parsimony decides",
    165: "rate-dependence, a gain with the drive frequency",
    7708: "rate-dependence, velocity damping; steps as a second rate (0074)",
    107: "hysteresis from a linear start: one-sided play",
    266: "hysteresis from a linear start: Duhem butterflies, each loop family tried",
    4042: "hysteresis from a linear start: play; no loop shape from an inner fit that never turns (0057)",
    110: "temperature, a warm-up ramp; reach: the channel's reach beyond training's (0042)",
    7736: "temperature, cycling; a rest that a recorded channel moves is data (0073)",
    1518: "load, a placed weight; the channel's reach against the error above the noise (0044)",
    181: "two effects: a resonance near the drive and a temperature ramp (0030)",
    17: "clean: an irrelevant drifting temperature flags nothing",
}


def _in_suite(cases: list[DR.Regression]) -> list:
    return [pytest.param(r, id=r.id) for r in cases if r.seed in SUITE]


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    return tmp_path


def test_the_suite_runs_regressions_each_listed_once():
    assert len(DR.seeds()) == len(DR.ALL)  # a seed is one case
    assert set(SUITE) <= set(DR.seeds())
    for r in DR.ALL:  # the draw each id names
        case = DC.draw_case(r.seed)
        assert case.hidden == (list(r.hidden) or ["none"]), r.id
        if r.form is not None:
            assert case.forms[r.hidden[0]] == r.form, r.id


def test_generator_is_deterministic_and_realistic():
    a, b = DC.draw_case(22), DC.draw_case(22)
    assert a.to_json() == b.to_json()
    for seed in (16, 60, 110, 122, 175):
        c = DC.draw_case(seed)
        assert 10_000 <= c.samples() <= 60_000
        assert 0.001 - 1e-12 <= c.noise_std_um / c.output_span_um <= 0.02 + 1e-12
        assert all(v >= DC.MIN_SNR * 0.999 for v in c.snr.values()), c.snr
        assert c.runs[0]["pieces"][0]["kind"] == "hold" and c.runs[0]["pieces"][0]["level"] == 0.0  # from rest


@pytest.mark.parametrize("regression", _in_suite(DR.SINGLE))
def test_hidden_effect_ranked_first_and_significant(regression, folder):
    seed, (hidden,), form, _ = regression
    case = DC.draw_case(seed)
    assert case.hidden == [hidden] and case.forms[hidden] == form  # the draw the id names
    paths, kw = DC.write_case(case, folder)
    d = diagnose(paths, case.spec, **kw)
    table = [(c.effect, round(c.expected_gain, 3), c.significant) for c in d.effects]
    assert d.effects and d.effects[0].effect == hidden and d.effects[0].significant, table


# 2051 (an even v^4 that keeps its quartic where validation extrapolates) runs in the benchmark
@pytest.mark.parametrize(("seed", "form", "order"), [pytest.param(2129, "even-2", "asymmetry(order=2)", id="2129-even-2"),
                                                     pytest.param(6743, "even-4", "asymmetry", id="6743-even-4-within-reach")])
def test_the_polynomial_order_is_chosen_where_it_must_extrapolate(seed, form, order, folder):
    """Decision 0046: where validation drives beyond training (2129, 1.23x), v^2 alone unless
    v^2..v^4 predicts the training rows at the largest inputs better from the rows below them; an
    even v^4 keeps its quartic. Decision 0069: where validation stays within training's reach
    (6743, a one-sided drive), nothing extrapolates, and the order is chosen on the training fit
    as any effect's form: the quartic, where the largest inputs' rows, fitted by none of the base's
    top operators, kept v^2 and a saturation ranked first."""
    case = DC.draw_case(seed)
    assert case.hidden == ["asymmetry"] and case.forms["asymmetry"] == form
    paths, kw = DC.write_case(case, folder)
    d = diagnose(paths, case.spec, **kw)
    (asym,) = [c for c in d.effects if c.effect == "asymmetry"]
    assert asym.spec == f"{case.spec}+{order}", asym.spec
    assert d.effects[0] is asym and asym.significant


def test_a_resonance_rung_by_few_steps_is_found_and_only_the_block_test_may_doubt_it(folder):
    """Seed 43: a 250 Hz resonance at zeta 0.04 on an m-play rig under a PMPI base. The scan of the
    natural frequency missed its narrow basin (7 % lower validation rmse); started at the residual
    spectrum's peaks it finds it (59 %, decision 0023). The test run rings it only at its two
    steps and where its sine starts (the sines stay far below 250 Hz): 96 % of the validation gain
    sits in 3 of the 200 blocks, the other blocks change by small amounts either way. A sign-flip test over three events
    cannot reach p < 0.01 on them alone, so whether the joint block test passes rests on those tiny
    differences, which move with the CPU's floating-point kernels (below 0.01 on the machines of
    earlier sessions, 0.082 on the AMD EPYC of 2026-11-26 with the same numpy, scipy and numba: 37
    of 200 blocks improved, the signed ranks' p 1.0, the sum's 0.044). What must hold on every machine: the
    resonance ranked first with its frequency and damping found, and no check but the block test in
    doubt."""
    case = DC.draw_case(43)
    assert case.hidden == ["dynamics"] and case.forms["dynamics"] == "resonance-above-drive"
    paths, kw = DC.write_case(case, folder)
    d = diagnose(paths, case.spec, **kw)
    first = d.effects[0]
    assert first.effect == "dynamics" and first.expected_gain > 0.5, [(c.effect, c.expected_gain) for c in d.effects]
    (dynamics,) = first.fitted.model.effects
    found = {p.name: p.value for p in dynamics.params}
    assert found["natural_frequency_hz"] == pytest.approx(250.0, rel=0.05)
    assert found["zeta"] == pytest.approx(case.tables["dynamics"]["zeta"], rel=0.3)
    failed = {k for k, ok in first.evidence["checks"].items() if not ok}
    assert failed <= {"blocks_p_below_0.01"}, failed
    assert first.significant == (not failed)


@pytest.mark.parametrize("regression", _in_suite(DR.CLEAN))
def test_clean_case_flags_nothing(regression, folder):
    seed = regression.seed
    case = DC.draw_case(seed)
    assert case.hidden == ["none"]
    paths, kw = DC.write_case(case, folder)
    d = diagnose(paths, case.spec, **kw)
    assert not any(c.significant for c in d.effects), [(c.effect, c.expected_gain) for c in d.effects if c.significant]


@pytest.mark.parametrize("regression", _in_suite(DR.TWO_EFFECT))
def test_two_hidden_effects_one_ranked_first_and_significant(regression, folder):
    seed, hidden = regression.seed, regression.hidden
    case = DC.draw_case(seed)
    assert tuple(case.hidden) == hidden
    paths, kw = DC.write_case(case, folder)
    d = diagnose(paths, case.spec, **kw)
    table = [(c.effect, round(c.expected_gain, 3), c.significant) for c in d.effects]
    assert d.effects and d.effects[0].significant, table
    assert all(part in hidden for part in d.effects[0].effect.split("+")), table
