"""Saturation at the output in two forms (tanh, and a knee of adjustable sharpness): the data choose."""

from __future__ import annotations

import numpy as np

from hilbench.identify import fit_model
from hilbench.models import Model, RunData

FS = 1000.0


def _pi_output(v: np.ndarray) -> np.ndarray:
    """A play-operator PI on a normalised input (weights >= 0), um."""
    r = np.array([0.0, 0.2, 0.4, 0.6])
    w = np.array([8.0, 3.0, 2.0, 1.0])
    ops = np.zeros(r.size)
    out = np.empty(v.size)
    for k, x in enumerate(v):
        ops = np.maximum(x - r, np.minimum(x + r, ops))
        out[k] = ops @ w
    return out


def _knee_data(p: float, seed: int = 0) -> tuple[RunData, RunData]:
    """A triangle staircase into a PI whose output saturates with a knee of sharpness p."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, 8.0, 1 / FS)
    amp = np.repeat([0.4, 0.7, 1.0, 0.85, 0.55, 1.0, 0.3, 0.9], int(FS))
    v = amp * (2 / np.pi) * np.arcsin(np.sin(2 * np.pi * 1.0 * t))
    h = _pi_output(v)
    level = 9.0
    y = h / (1.0 + np.abs(h / level) ** p) ** (1.0 / p) + rng.normal(0, 0.02, v.size)
    cut = int(0.7 * v.size)
    return (RunData(10 * v[:cut], y[:cut], {}, FS), RunData(10 * v[cut:], y[cut:], {}, FS, chain=True))


def _validation_rmse(spec: str, train: RunData, test: RunData) -> float:
    model = Model(spec)
    fit_model(model, [train], [np.ones(len(train), bool)])
    y = model.simulate_runs([train, test])[1]
    return float(np.sqrt(np.mean((y - test.output) ** 2)))


def test_a_sharp_knee_is_described_better_by_the_knee_form():
    train, test = _knee_data(p=6.0)
    tanh_form = _validation_rmse("pi+saturation", train, test)
    knee_form = _validation_rmse("pi+saturation(form=knee)", train, test)
    plain = _validation_rmse("pi", train, test)
    assert knee_form < tanh_form < plain, (knee_form, tanh_form, plain)
    assert knee_form < 0.6 * tanh_form


def test_the_knee_form_steps_like_it_simulates():
    train, test = _knee_data(p=3.0, seed=1)
    model = Model("pi+saturation(form=knee)")
    fit_model(model, [train], [np.ones(len(train), bool)])
    stepper = model.stepper(FS)
    stepped = np.array([stepper.step(float(u)) for u in train.input])
    assert stepper.compiled is not None, stepper.fallback_reason
    np.testing.assert_allclose(stepped, model.simulate(train), atol=1e-9)
