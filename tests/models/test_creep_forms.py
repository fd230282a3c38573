"""Creep that spans decades (issue: "Creep spans decades"): a fixed log-spaced Kelvin-Voigt bank
(``creep(form=bank)``) against two fitted elements (``creep``), on a play-operator PI plus creep of
two laws, after a staircase of steps held 2-7 s:

* ``kv``: three Kelvin-Voigt elements spread over decades, 0.01 s, 0.3 s and 10 s, equal gains;
* ``log``: a logarithmic law gamma log10(1 + t / t0) after each step (t0 = 10 ms), which keeps
  moving over the whole record.

The creep follows either the input's steps or the hysteresis output's (``drive``), added by
post-processing; 80 s at 1 kHz, the last 30 % for validation (memory chained from training).
Validation rmse (um) measured when written, seed 0, noise 0.01 um:

=====  ======  =========  ===========  ==========
law    drive   no creep   creep (2 KV)  bank
=====  ======  =========  ===========  ==========
kv     input   0.632      0.043        0.048
kv     output  0.616      0.051        0.032
log    input   1.028      0.303        0.034
log    output  0.936      0.347        0.112
=====  ======  =========  ===========  ==========

The bank lowers the error without creep 13-30x here (seeds 1-3: 3.7-63x); on the logarithmic law
it is 3-9x below the two-element chain (seeds 1-3: 1.3-16x), which finds the creep but cannot
follow it over the decades. On three discrete elements the fixed grid is about as good as the
chain, which can place two of its elements exactly on the slow ones (bank / chain 0.44-1.18 over
seeds 0-3); the diagnosis lets the data choose between the forms. Creep that follows the hysteresis
output is followed less well by the bank of the input (log: 0.11 vs 0.034 um).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilbench.identify import fit_model
from hilbench.models import Model, RunData

FS = 1000.0
DURATION_S = 80.0
KV = ((1.0, 0.01), (1.0, 0.3), (1.0, 10.0))  # (gain um per unit step, time constant s)
LOG_GAMMA, LOG_T0 = 1.0, 0.01  # um per unit step per decade, s


def pi_output(v: np.ndarray) -> np.ndarray:
    """A play-operator PI on the normalised input (weights >= 0), um; its thresholds lie on the
    model's grid (half the input range, 10 operators) so the hysteresis itself is no error source."""
    r = np.array([0.0, 0.2, 0.4, 0.6])
    w = np.array([8.0, 3.0, 2.0, 1.0])
    ops = np.zeros(r.size)
    out = np.empty(v.size)
    for k, x in enumerate(v):
        ops = np.maximum(x - r, np.minimum(x + r, ops))
        out[k] = ops @ w
    return out


def staircase(seed: int) -> np.ndarray:
    """Steps to random levels in [-1, 1] held 2-7 s, after holds at +1 and -1 (the full range)."""
    rng = np.random.default_rng(seed)
    parts = [np.full(int(3 * FS), 1.0), np.full(int(3 * FS), -1.0)]
    n = sum(p.size for p in parts)
    while n < DURATION_S * FS:
        m = int(rng.uniform(2.0, 7.0) * FS)
        parts.append(np.full(m, rng.uniform(-1.0, 1.0)))
        n += m
    return np.concatenate(parts)[: int(DURATION_S * FS)]


def creep_after_steps(x: np.ndarray, law: str) -> np.ndarray:
    """Creep after each step dx of x, superposed: dx * sum g (1 - exp(-t / tau)) (kv) or
    dx * gamma log10(1 + t / t0) (log), t from the step."""
    t = np.arange(x.size) / FS
    dx = np.diff(x, prepend=x[0])
    out = np.zeros(x.size)
    for k in np.flatnonzero(dx):
        tt = t[k:] - t[k]
        if law == "kv":
            out[k:] += dx[k] * sum(g * (1.0 - np.exp(-tt / tau)) for g, tau in KV)
        else:
            out[k:] += dx[k] * LOG_GAMMA * np.log10(1.0 + tt / LOG_T0)
    return out


def creep_data(law: str, drive: str = "input", seed: int = 0) -> tuple[RunData, RunData]:
    """(training, validation) runs: 10 V full scale, output um; validation chained to training."""
    v = staircase(seed)
    h = pi_output(v)
    x = v if drive == "input" else h / 14.0  # 14 um: the PI's output at full drive
    y = h + creep_after_steps(x, law) + np.random.default_rng(seed + 1).normal(0.0, 0.01, v.size)
    cut = int(0.7 * v.size)
    return (RunData(10.0 * v[:cut], y[:cut], {}, FS), RunData(10.0 * v[cut:], y[cut:], {}, FS, chain=True))


def _fit(spec: str, train: RunData, test: RunData) -> tuple[float, Model]:
    model = Model(spec)
    fit_model(model, [train], [np.ones(len(train), bool)])
    y = model.simulate_runs([train, test])[1]
    return float(np.sqrt(np.mean((y - test.output) ** 2))), model


@pytest.mark.parametrize("law,drive", [("kv", "input"), ("kv", "output"), ("log", "input"), ("log", "output")])
def test_a_bank_removes_creep_over_decades(law, drive):
    train, test = creep_data(law, drive)
    none, _ = _fit("pi", train, test)
    chain, _ = _fit("pi+creep", train, test)
    bank, model = _fit("pi+creep(form=bank)", train, test)
    print(f"{law}/{drive}: validation rmse no creep {none:.4f}, creep (2 KV) {chain:.4f}, bank {bank:.4f} um")
    assert bank < none / 3.0, (none, chain, bank)
    if law == "log":
        # creep over decades: the chain finds it but cannot follow it (seeds 0-3: bank / chain
        # 0.06-0.20 with the input's steps, 0.32-0.78 with the hysteresis output's)
        assert bank < (0.3 if drive == "input" else 0.6) * chain, (none, chain, bank)
    else:
        # three discrete elements, two of which the chain places exactly: the fixed grid keeps up
        # (seeds 0-3: bank / chain 0.44-1.18)
        assert bank < 1.5 * chain, (none, chain, bank)
    # the bank is fixed by the record, nothing searched, and creeps along the input's change
    creep = model.effect("creep")
    assert creep.params == [] and model.shape_params() == []
    taus = creep.time_constants()
    assert taus.size <= 16 and math.isclose(taus[0], 3.0 / FS) and math.isclose(taus[-1], len(train) / FS)
    w = model.weights[[i for i, name in enumerate(model.weight_names) if name.startswith("creep[")]]
    assert w.size == taus.size and np.all(w >= -1e-12 * np.abs(w).max()) and np.any(w > 0.0)  # rounding


def test_the_fitted_log_creep_is_a_flat_spectrum_and_steps_like_it_simulates():
    """A logarithmic law is a flat retardation spectrum per decade: the bank's weights between a
    few t0 and the record's length are alike; the compiled step mode equals the block simulation."""
    train, test = creep_data("log", "input", seed=2)
    model = Model("pi+creep(form=bank)")
    fit_model(model, [train], [np.ones(len(train), bool)])
    taus = model.effect("creep").time_constants()
    w = model.weights[[i for i, name in enumerate(model.weight_names) if name.startswith("creep[")]]
    inner = (taus > 10 * LOG_T0) & (taus < 0.3 * taus[-1])
    per_decade = w[inner] * (taus.size - 1) / math.log10(taus[-1] / taus[0])  # um per unit step per decade
    print("weights per decade", np.round(per_decade, 3))
    assert inner.sum() >= 4
    assert np.all(np.abs(per_decade - LOG_GAMMA) < 0.3 * LOG_GAMMA), per_decade
    stepper = model.stepper(FS)
    stepped = np.array([stepper.step(float(u)) for u in train.input[:20000]])
    assert stepper.compiled is not None, stepper.fallback_reason
    np.testing.assert_allclose(stepped, model.simulate(train)[:20000], atol=1e-9)


def test_bank_time_constants():
    from hilbench.models.effect_components import creep_bank_time_constants

    taus = creep_bank_time_constants(60.0, 1000.0)
    assert math.isclose(taus[0], 0.003) and math.isclose(taus[-1], 60.0)
    ratios = taus[1:] / taus[:-1]
    assert np.allclose(ratios, ratios[0]) and 10 ** (1 / 3.0) >= ratios[0] > 10 ** (1 / 4.0)  # ~3 per decade
    assert creep_bank_time_constants(4 * 3600.0, 10_000.0).size == 16  # hours at 10 kHz: bounded
    short = creep_bank_time_constants(0.001, 1000.0)  # a record shorter than the bank's start: one decade
    assert 2 <= short.size <= 4 and math.isclose(short[-1], 0.03)


@pytest.mark.parametrize("law", ["log", "kv"])
def test_the_log_form_is_the_banks_flat_spectrum_with_one_weight(law):
    """creep(form=log) weights the bank by the law's spectrum: on a logarithmic law it validates as
    well as the free bank, finds the law's t0 and its weight is the law's gamma per decade; on
    discrete Kelvin-Voigt elements it still removes most of the creep. The compiled step mode equals
    the block simulation."""
    train, test = creep_data(law, "input")
    none, _ = _fit("pi", train, test)
    bank, _ = _fit("pi+creep(form=bank)", train, test)
    log, model = _fit("pi+creep(form=log)", train, test)
    print(f"{law}: validation rmse no creep {none:.4f}, bank {bank:.4f}, log {log:.4f} um")
    names = [n for n in model.weight_names if n.startswith("creep")]
    assert names == ["creep[log]"] and [p.name for p in model.shape_params()] == ["t0"]
    if law == "log":
        t0 = model.effect("creep").param("t0")
        assert 0.5 * LOG_T0 < t0 < 2.0 * LOG_T0, t0
        assert log < 1.5 * bank and log < none / 3.0, (none, bank, log)
        taus = model.effect("creep").time_constants()
        w = float(model.weights[model.weight_names.index("creep[log]")])
        per_decade = w * (taus.size - 1) / math.log10(taus[-1] / taus[0])
        assert abs(per_decade - LOG_GAMMA) < 0.3 * LOG_GAMMA, per_decade
    else:
        assert log < none / 2.0, (none, bank, log)
    stepper = model.stepper(FS)
    stepped = np.array([stepper.step(float(u)) for u in train.input[:20000]])
    assert stepper.compiled is not None, stepper.fallback_reason
    np.testing.assert_allclose(stepped, model.simulate(train)[:20000], atol=1e-9)


def test_output_form_copies_creep_along_the_operators_and_carry_to_another_run():
    """creep(form=output): a copy's weight is a creep gain (>= 0, a passive retardation spectrum)
    times its operator's weight (>= 0), so it is bounded at 0 like the operator's. Free copies traded
    against each other in training and blew up on a test run with another excitation (decision
    0036; randomized seed 251: 0.116 -> 0.412 um free, 0.116 -> 0.058 um bounded)."""
    train, _ = creep_data("log", "output", seed=0)
    other_train, _ = creep_data("log", "output", seed=5)  # another staircase, a run of its own
    test = RunData(other_train.input, other_train.output, {}, FS)
    model = Model("pi+creep(form=output)")
    fit_model(model, [train], [np.ones(len(train), bool)])
    copies = [i for i, name in enumerate(model.weight_names) if name.startswith("w[") and "*creep[" in name]
    w = model.weights[copies]
    assert copies and np.all(w >= -1e-12 * np.abs(w).max()), w
    none = Model("pi")
    fit_model(none, [train], [np.ones(len(train), bool)])
    rmse = {m.spec: float(np.sqrt(np.mean((m.simulate(test) - test.output) ** 2))) for m in (none, model)}
    print("validation rmse on another run", rmse)
    assert rmse[model.spec] < 0.5 * rmse[none.spec], rmse


def test_a_logarithmic_law_after_the_hysteresis_is_followed_by_the_law_on_every_column():
    """creep(form=log-output): the logarithmic law on the input and on every hysteresis column, one
    weight each. Piezo creep is logarithmic in time and follows the strain the hysteresis made; the
    bank of the input misses the creep of the loop's own steps, and two searched elements per
    column cannot follow the decades (seed 2, measured when written: log-output 0.0102 um, at the
    0.01 um noise; bank 0.055, output 0.132). The compiled step mode equals the block simulation."""
    train, test = creep_data("log", "output", seed=2)
    rmse = {f: _fit(f"pi+creep(form={f})", train, test)[0] for f in ("bank", "output", "log-output")}
    print("validation rmse", rmse)
    assert rmse["log-output"] < 0.5 * min(rmse["bank"], rmse["output"]), rmse
    assert rmse["log-output"] < 0.02, rmse  # twice the sensor noise
    _, model = _fit("pi+creep(form=log-output)", train, test)
    copies = [i for i, name in enumerate(model.weight_names) if name.startswith("w[") and name.endswith("*creep[log]")]
    assert copies and np.all(model.weights[copies] >= 0.0), model.weight_names
    stepper = model.stepper(FS)
    stepped = np.array([stepper.step(u) for u in train.input[:20000]])
    np.testing.assert_allclose(stepped, model.simulate(train)[:20000], atol=1e-9)
