"""Rate-dependence and auxiliary channels scale the whole hysteresis loop by one gain (decisions
0018 and 0019): one shape parameter and a few weights, not a weighted copy of every column."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hilbench.errors import UserError
from hilbench.identify import fit_model
from hilbench.models import Model, RunData

FS = 1000.0


def _run(temperature_from: float, temperature_to: float, seed: int, label: str) -> RunData:
    """A play hysteresis whose gain rises 1 %/K (the piezoelectric coefficient) with a thermal strain
    of 0.2 um/K, driven by a 2 Hz sine while the temperature ramps."""
    rng = np.random.default_rng(seed)
    n = 6000
    t = np.arange(n) / FS
    u = 5.0 + 4.5 * np.sin(2 * np.pi * 2.0 * t)
    temperature = np.linspace(temperature_from, temperature_to, n)
    w, h = 0.0, np.empty(n)
    for k, x in enumerate(u):
        w = max(x - 0.8, min(x + 0.8, w))
        h[k] = 1.5 * x + 2.0 * w
    y = (1.0 + 0.01 * (temperature - 25.0)) * h + 0.2 * (temperature - 25.0)
    return RunData(u, y + 0.005 * rng.standard_normal(n), {"temperature": temperature}, FS, label)


def _weights(spec: str, run: RunData) -> list[str]:
    model = Model(spec, channels=["input", "output", "temperature"])
    model.prepare([run])
    _, names, _, _ = model.design(run)
    return names


@pytest.mark.parametrize(("spec", "extra_weights", "gain_params"), [
    ("pi(n=6)+rate-dependence(form=damping)", 1, {"g"}),
    ("pi(n=6)+rate-dependence(form=frequency,order=2)", 2, {"k_1", "k_2"}),
    ("pi(n=6)+temperature", 1, {"g"}),
])
def test_one_gain_adds_a_shape_parameter_and_few_weights(spec, extra_weights, gain_params):
    run = _run(24.0, 30.0, 0, "a")
    base = _weights("pi(n=6)", run)
    assert len(_weights(spec, run)) == len(base) + extra_weights
    model = Model(spec, channels=["input", "output", "temperature"])
    model.prepare([run])
    effect = model.components[-1]
    assert gain_params <= {p.name for p in effect.shape()}


def test_a_temperature_gain_is_found_and_extrapolates_beyond_the_training_temperatures():
    train = _run(22.0, 27.0, 1, "train")
    test = _run(27.0, 35.0, 2, "test")  # hotter than any training row
    model = Model("pi(n=8)+temperature", channels=["input", "output", "temperature"])
    fit_model(model, [train], [np.ones(len(train), bool)])
    effect = model.effect("temperature")
    # 1 %/K times the training's standard deviation of the temperature, per standard deviation
    expected = 0.01 * float(np.std(train.aux["temperature"]))
    assert effect.param("g") == pytest.approx(expected, rel=0.15)
    e = model.simulate(test) - test.output
    span = float(np.ptp(test.output))
    assert np.sqrt(np.mean(e**2)) < 0.005 * span  # the base alone is off by several % at 35 degC
    base = Model("pi(n=8)", channels=["input", "output", "temperature"])
    fit_model(base, [train], [np.ones(len(train), bool)])
    e_base = base.simulate(test) - test.output
    assert np.sqrt(np.mean(e_base**2)) > 10 * np.sqrt(np.mean(e**2))


def test_a_model_file_with_the_old_copies_is_refused_with_one_line(tmp_path):
    run = _run(24.0, 30.0, 3, "a")
    model = Model("pi(n=6)+rate-dependence(form=damping)+temperature", channels=["input", "output", "temperature"])
    fit_model(model, [run], [np.ones(len(run), bool)])
    path = model.save(tmp_path / "fit.json")
    assert Model.load(path).effect("temperature").param("g") == pytest.approx(model.effect("temperature").param("g"))
    doc = json.loads(path.read_text())
    for comp in doc["components"]:
        if comp["name"] == "rate-dependence":
            comp["shape"] = [p for p in comp["shape"] if p["name"] == "m"]  # as written before the gain
    path.write_text(json.dumps(doc))
    with pytest.raises(UserError, match="older layout.*fit the model again") as info:
        Model.load(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)  # one line naming the file


def test_joined_training_runs_are_measured_each_on_its_own():
    """Training runs are joined for prepare; the jump from one run's end to the next's start is no
    rate and no turning point: the frequency reference is the fastest run's drive frequency, and the
    rate guard the fastest run's rate (a junction gave 12.5 kHz from 10-1500 Hz runs and left the
    gain polynomial no reach)."""
    runs = []
    for f_hz in (10.0, 200.0, 1500.0):
        t = np.arange(int(4 * 50_000 / f_hz)) / 50_000
        u = 70.0 - 50.0 * np.cos(2 * np.pi * f_hz * t)
        u = u[: int(0.7 * u.size)]  # the training part: the first 70 % of each run ends mid-cycle
        runs.append(RunData(u, u.copy(), {}, 50_000.0, f"{f_hz:g} Hz"))
    model = Model("pi1+rate-dependence(form=frequency)")
    model.prepare(runs)
    rate = model.effect("rate-dependence").constants
    assert rate["f_ref"] == pytest.approx(1500.0, rel=0.02)
    fastest = 2 * np.pi * 1500.0 * 50.0 / 120.0  # the 1500 Hz sine's peak rate, normalised (1/s)
    assert rate["vdot_max"] == pytest.approx(fastest, rel=0.05)
