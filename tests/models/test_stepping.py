"""The compiled step mode (hilbench.models.stepping): every base and effect steps like the block
simulation, the compiled block kernel equals its steps, and ModelStepper uses the compiled path."""

from __future__ import annotations

import numpy as np
import pytest

from hilbench.identify import fit_model
from hilbench.models import Model, RunData
from hilbench.models.stepping import compile_model, model_step

FS = 1000.0


def data(n: int = 2500, seed: int = 0) -> RunData:
    """Unipolar chirp-like input with a random walk (turning points at changing frequencies, so the
    frequency form of rate-dependence sees several drive frequencies) and a temperature channel."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FS
    u = 2.0 + 1.8 * np.exp(-t / 4) * np.sin(2 * np.pi * (1.3 + 2 * t) * t) + 0.05 * rng.standard_normal(n).cumsum() / 30
    y = np.empty(n)
    w = 0.0
    for k, x in enumerate(u):
        w = max(x - 0.3, min(x + 0.3, w))
        y[k] = 2.0 * x + 1.5 * w + 0.1 * x**2
    temperature = 25 + 3 * np.sin(2 * np.pi * t / 5)
    return RunData(u, y + 0.01 * rng.standard_normal(n), {"temperature": temperature}, FS, "r")


def with_random_weights(spec: str, run: RunData, seed: int = 1) -> Model:
    """Shape parameters inside their bounds and random weights of both signs: every column counts,
    so a column out of place in the compiled layout shows."""
    model = Model(spec, channels=["input", "output", "temperature"])
    model.prepare([run])
    rng = np.random.default_rng(seed)
    for p in model.shape_params():
        if p.lower < p.upper:
            lo, hi = (np.log(p.lower), np.log(p.upper)) if p.log else (p.lower, p.upper)
            x = lo + (hi - lo) * rng.uniform(0.3, 0.7)
            p.value = float(np.exp(x) if p.log else x)
    model.finalize([run])
    for effect in model.effects:
        if getattr(effect, "needs_reference", False):  # saturation(form=wiener): a random reference
            _, names, _, _ = model.design(run)
            effect.set_reference({n: float(rng.uniform(0.5, 2.0)) for n in names}, 3.0)
    _, names, _, _ = model.design(run)
    model.weight_names = names
    model.weights = rng.normal(size=len(names))
    return model


def stepped(model: Model, run: RunData) -> tuple[np.ndarray, object]:
    stepper = model.stepper(FS)
    out = np.array([stepper.step(u, {"temperature": T}) for u, T in zip(run.input, run.aux["temperature"])])
    return out, stepper


ALL_BASES = ["linear", "pi", "pi1", "mpi", "pmpi", "pd", "fpmpi", "duhem-g", "duhem-m", "duhem-d", "bouc-wen",
             "bouc-wen(n=2)"]
EFFECT_SPECS = [
    "pi+asymmetry", "pi+asymmetry(order=3)", "pi+saturation", "pi+saturation(form=input)", "pi+saturation(form=knee)",
    "pi+creep", "pi+creep(form=bank)", "pi+creep(form=log)", "pi+asymmetry+creep(form=bank,per_decade=3)+dynamics",
    "pi+creep(n=3,form=output)", "pmpi+creep(form=log-output)", "pi+rate-dependence(form=damping)", "pi1+asymmetry+rate-dependence(form=frequency)",
    "pi+rate-dependence(form=frequency,waveform=triangle)", "pmpi+dynamics", "fpmpi+dynamics+delay", "pi+temperature",
    "pi(n=16)+delay+dynamics(kind=first-order)", "pi+dynamics(kind=discrete,pairs=1,zeros=1)",
    "pmpi+asymmetry+saturation+creep(form=output)+rate-dependence(form=damping)+temperature+delay+dynamics",
    "duhem-d+asymmetry+saturation+creep+rate-dependence(form=frequency)+temperature+delay+dynamics",
    "bouc-wen+saturation+creep(form=output)+temperature+dynamics(kind=first-order)",
    "duhem-d+asymmetry+creep(form=log-output)+delay",
    "linear+asymmetry+saturation(form=input)+rate-dependence(form=damping)+delay",
    "pmpi+saturation(form=hammerstein)+creep(form=log-output)+rate-dependence(form=damping)+dynamics",
    "duhem-d+saturation(form=hammerstein)+asymmetry+delay", "bouc-wen+saturation(form=hammerstein)+temperature",
    "pi1+saturation(form=wiener)", "pmpi+asymmetry+saturation(form=wiener)+creep(form=output)+rate-dependence(form=damping)+temperature+delay+dynamics",
    "duhem-d+saturation(form=wiener)+creep(form=log-output)",
]


@pytest.mark.parametrize("spec", ALL_BASES + EFFECT_SPECS)
def test_compiled_step_equals_block_simulation(spec):
    run = data()
    model = with_random_weights(spec, run)
    y = model.simulate(run)
    out, stepper = stepped(model, run)
    assert stepper.compiled is not None, stepper.fallback_reason  # no fallback to Python for any spec
    np.testing.assert_allclose(out, y, rtol=0, atol=1e-11 * max(1.0, np.abs(y).max()))
    # the compiled block kernel is the same loop body: a block equals its steps exactly
    compiled = compile_model(model, FS)
    half = len(run) // 2
    first = compiled.block(run.input[:half], {"temperature": run.aux["temperature"][:half]})
    rest = [compiled.step(u, {"temperature": T}) for u, T in zip(run.input[half:], run.aux["temperature"][half:])]
    np.testing.assert_array_equal(np.concatenate([first, rest]), out)


@pytest.mark.parametrize("spec", ["pi", "pmpi+dynamics", "pi+creep+temperature+delay"])
def test_fitted_model_steps_like_its_simulation_and_the_python_stepper(spec):
    run = data(seed=3)
    model = Model(spec, channels=["input", "output", "temperature"])
    fit_model(model, [run], [np.arange(len(run)) < 1800], max_evaluations=30, global_starts=2, local_starts=1)
    y = model.simulate(run)
    out, stepper = stepped(model, run)
    np.testing.assert_allclose(out, y, rtol=0, atol=1e-11 * max(1.0, np.abs(y).max()))
    python = [stepper.step_python(u, {"temperature": T}) for u, T in zip(run.input[:300], run.aux["temperature"][:300])]
    np.testing.assert_allclose(python, y[:300], rtol=0, atol=1e-9 * max(1.0, np.abs(y).max()))
    # reset: fresh memory, the same output again
    stepper.reset()
    again = [stepper.step(u, {"temperature": T}) for u, T in zip(run.input[:50], run.aux["temperature"][:50])]
    np.testing.assert_array_equal(again, out[:50])


def test_state_is_explicit_and_callable_from_numba():
    from numba import njit

    run = data()
    model = with_random_weights("pmpi+creep+dynamics", run)
    I, P, X = compile_model(model, FS).arrays()

    @njit(_nrt=False)
    def loop(I, P, X, u, aux, out):
        for n in range(u.shape[0]):
            out[n] = model_step(I, P, X, u[n], aux)

    out = np.empty(len(run))
    loop(I, P, X, run.input, np.zeros(1), out)
    np.testing.assert_allclose(out, model.simulate(run), rtol=0, atol=1e-11 * max(1.0, np.abs(out).max()))
    # two models stepped side by side keep their own memory
    other = compile_model(model, FS)
    assert not np.array_equal(X, other.X)
    other.step(float(run.input[0]))
    assert other.X[0] == 1.0  # started


def test_unfitted_model_is_refused():
    from hilbench.models.stepping import NotCompilable

    with pytest.raises(NotCompilable):
        compile_model(Model("pi"), FS)
