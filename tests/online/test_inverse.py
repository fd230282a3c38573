"""Inverse models: inverse o forward = identity (hypothesis over random monotone models and inputs),
004's I-M compensator and its stability conditions, refusal of configurations that cannot be stable."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hilbench.models import Model
from hilbench.models.components import ShapeParam
from hilbench.models.stepping import compile_model
from hilbench.online.inverse import PID, Compensator, InstabilityError, inverse_pi_parameters

FS = 1000.0
SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _operator_model(spec: str, thresholds: np.ndarray, weights: list[float], eta: np.ndarray | None = None) -> Model:
    """A fitted-looking operator model without fitting: thresholds and weights set directly."""
    model = Model(spec)
    model.norm = {"u_scale": 1.0}
    model.sample_rate_hz = FS
    model.base.constants["thresholds"] = [float(r) for r in thresholds]
    if eta is not None:
        model.base.params = [ShapeParam(f"eta_{i}", float(e), -0.99, 1.5)
                             for i, (r, e) in enumerate(zip(thresholds, eta)) if r > 0]
    model.weights = np.asarray(weights, float)
    return model


def _fpmpi_model(w_p: list[float], w_h: list[float], span: float) -> Model:
    model = Model(f"fpmpi(n={len(w_h)})")
    model.norm = {"u_scale": 1.0}
    model.base.constants.update({"exponents": [0.0, 1.0, 2.0, 0.5, 3.0, 1.0 / 3.0], "n": len(w_h), "shaped_max": span})
    model.base.params = [ShapeParam(f"wP_{i}", w, -3.0, 3.0) for i, w in enumerate(w_p)]
    model.weights = np.array([0.3, *w_h])
    return model


def _input(seed: int, n: int = 1500, lo: float = -1.0, hi: float = 1.0) -> np.ndarray:
    """A random piecewise-monotone input with turning points at random levels (minor loops)."""
    rng = np.random.default_rng(seed)
    levels = rng.uniform(lo, hi, 12)
    knots = np.sort(rng.choice(np.arange(1, n - 1), size=11, replace=False))
    return np.interp(np.arange(n), np.concatenate([[0], knots]), levels)


def _roundtrip(model: Model, u: np.ndarray, method: str, limits=(-1.5, 1.5), **options) -> tuple[np.ndarray, Compensator]:
    y = compile_model(model, FS).block(u)
    comp = Compensator(model, FS, limits, method=method, **options)
    return comp.feedforward(y), comp


weights = st.lists(st.floats(0.0, 2.0), min_size=3, max_size=8)


@SETTINGS
@given(p=weights, p0=st.floats(0.2, 3.0), seed=st.integers(0, 10_000), data=st.data())
def test_pi_inverse_is_exact(p: list[float], p0: float, seed: int, data: st.DataObject) -> None:
    gaps = data.draw(st.lists(st.floats(0.02, 0.3), min_size=len(p), max_size=len(p)))
    r = np.concatenate([[0.0], np.cumsum(gaps)])
    model = _operator_model(f"pi(n={r.size})", r, [0.1, p0, *p])
    u = _input(seed)
    u_back, comp = _roundtrip(model, u, "auto")
    assert comp.kind == "pi"
    np.testing.assert_allclose(u_back, u, atol=1e-9)


@SETTINGS
@given(p=weights, seed=st.integers(0, 10_000), a2=st.floats(-0.4, 0.4), a3=st.floats(-0.2, 0.2), data=st.data())
def test_mpi_inverse_is_exact(p: list[float], seed: int, a2: float, a3: float, data: st.DataObject) -> None:
    r = np.linspace(0.0, 0.8, len(p) + 1)
    model = _operator_model(f"mpi(n={r.size})", r, [0.0, 1.5, *p, a2, a3])
    u = _input(seed)
    u_back, comp = _roundtrip(model, u, "mpi")
    assert comp.kind == "mpi"  # (eq. 20 gain picked where eq. 16 fails on the range)
    np.testing.assert_allclose(u_back, u, atol=1e-8)


@SETTINGS
@given(p=weights, seed=st.integers(0, 10_000), data=st.data())
def test_pmpi_inverse_is_exact_for_any_eta(p: list[float], seed: int, data: st.DataObject) -> None:
    """M-play operators (eta != 1) written as play operators: the analytic inverse stays exact."""
    r = np.linspace(0.0, 1.2, len(p) + 1)
    eta = np.array(data.draw(st.lists(st.floats(-0.9, 1.4), min_size=r.size, max_size=r.size)))
    model = _operator_model(f"pmpi(n={r.size})", r, [0.2, 2.0, *p, -0.5, 0.3], eta)
    u = _input(seed, lo=0.0, hi=1.0)
    u_back, comp = _roundtrip(model, u, "mpi", limits=(-0.5, 1.5))
    np.testing.assert_allclose(u_back, u, atol=1e-8)
    # 004's I-M compensator (eq. 13): u_d(k-1) in the polynomial, one pass per sample; it converges
    # to the same inverse with more passes, and its error with one pass is small on a slow input
    u_im, im = _roundtrip(model, u, "im", limits=(-0.5, 1.5), iterations=40)
    assert im.kind == "im"
    np.testing.assert_allclose(u_im, u, atol=1e-7)
    slow = 0.5 - 0.45 * np.cos(2 * np.pi * 0.5 * np.arange(2000) / FS)  # at most 1.4e-3 per sample
    u_im1, _ = _roundtrip(model, slow, "im", limits=(-0.5, 1.5))
    assert np.max(np.abs(u_im1 - slow)) < 2e-3


@SETTINGS
@given(w_h=st.lists(st.floats(0.0, 2.0), min_size=3, max_size=8), w_p=st.lists(st.floats(0.0, 1.0), min_size=5,
       max_size=5), seed=st.integers(0, 10_000))
def test_fpmpi_inverse_is_exact(w_h: list[float], w_p: list[float], seed: int) -> None:
    """Operators inverted analytically, then the fractional polynomial (monotone: weights >= 0)."""
    model = _fpmpi_model(w_p, [1.0 + w_h[0], *w_h[1:]], span=2.0)
    u = _input(seed)
    u_back, comp = _roundtrip(model, u, "auto")
    assert comp.kind == "fpmpi"
    np.testing.assert_allclose(u_back, u, atol=1e-8)


@SETTINGS
@given(w_h=st.lists(st.floats(0.0, 2.0), min_size=3, max_size=8), w_p=st.lists(st.floats(0.0, 0.2), min_size=5,
       max_size=5), fall=st.floats(0.7, 1.0), seed=st.integers(0, 10_000))
def test_fpmpi_inverse_is_exact_on_the_monotone_part_of_its_range(w_h: list[float], w_p: list[float], fall: float,
                                                                  seed: int) -> None:
    """A cubic term that turns the polynomial over inside the fitted +-1 (its slope at 1 is below
    1.6 - 3 x 0.7 < 0), with the rising part the widest: the analytic inverse still runs (main
    solved every sample with the general path, ~2.5x slower in the fused loop) on the monotone part,
    narrowed to where the polynomial rises, with the part's reach; its commands stay inside and drive
    the model to the outputs asked for, as the general path's do."""
    model = _fpmpi_model([*w_p[:3], -fall, w_p[4]], [1.0 + w_h[0], *w_h[1:]], span=2.0)
    comp = Compensator(model, FS, (-1.5, 1.5))
    assert comp.kind == "fpmpi" and comp.range.sub_range
    lo, hi = comp.bracket
    assert -1.0 <= lo < hi <= 1.0 and hi - lo < 2.0
    part = Compensator(model, FS, (-1.5, 1.5), method="general").range  # the part, before narrowing
    assert comp.range.output[1] - comp.range.output[0] >= 0.99 * (part.output[1] - part.output[0])
    u = _input(seed, lo=lo, hi=hi)
    y = compile_model(model, FS).block(u)
    u_back = comp.feedforward(y)
    assert np.all((u_back >= lo) & (u_back <= hi))
    span = float(np.ptp(y))
    np.testing.assert_allclose(compile_model(model, FS).block(u_back), y, atol=1e-8 * span)
    assert comp.counters()["newton_samples"] > 0.9 * u.size
    general = Compensator(model, FS, (-1.5, 1.5), method="general")
    np.testing.assert_allclose(compile_model(model, FS).block(general.feedforward(y)), y, atol=1e-7 * span)


def test_general_inverse_covers_effects_creep_and_aux() -> None:
    """ANY compiled model: a per-sample solve of model_step, here with creep and a temperature channel."""
    model = Model("pi(n=4)+creep(n=2)+temperature")
    model.norm = {"u_scale": 1.0}
    model.base.constants["thresholds"] = [0.0, 0.1, 0.3, 0.5]
    creep, temp = model.effects
    creep.params = [ShapeParam("tau_0", 0.05, 0.01, 10.0, "s"), ShapeParam("tau_1", 0.5, 0.01, 10.0, "s")]
    temp.constants.update({"reference": 25.0, "scale": 5.0})
    # the loop's gain changes by 10 % per 5 degC (decision 0019)
    temp.params = [ShapeParam("g", 0.1, -0.5, 0.5, "per channel std")]
    # weights: offset, 4 operators, 2 creep, temperature offset
    model.weights = np.array([0.0, 1.0, 0.5, 0.3, 0.2, 0.15, 0.1, 0.05])
    u = _input(3, n=3000)
    temperature = np.linspace(20.0, 35.0, u.size)
    y = compile_model(model, FS).block(u, {"temperature": temperature})
    comp = Compensator(model, FS, (-1.5, 1.5))
    assert comp.kind == "general"
    u_back = comp.feedforward(y, {"temperature": temperature})
    np.testing.assert_allclose(u_back, u, atol=1e-7)
    # beyond the reachable range the command saturates at the limit, never beyond
    out = Compensator(model, FS, (-0.5, 0.5)).feedforward(np.full(50, 1e3), {"temperature": np.full(50, 25.0)})
    assert np.all(out == 0.5)


def test_inverse_pi_parameters_follow_eq_15() -> None:
    p0, s, p = 2.0, np.array([0.5, 1.0, 2.0]), np.array([1.0, 0.5, 0.25])
    ph0, rh, ph = inverse_pi_parameters(p0, s, p)
    assert ph0 == pytest.approx(0.5)
    assert rh == pytest.approx([1.0, 2.0 + 0.5, 4.0 + 1.0 * 1.5 + 0.5 * 1.0])
    assert ph == pytest.approx([-1.0 / (3.0 * 2.0), -0.5 / (3.5 * 3.0), -0.25 / (3.75 * 3.5)])
    # eq. 18: sum p'_i = 1 / (p0 + sum p) - 1 / p0
    assert np.sum(ph) == pytest.approx(1.0 / (p0 + p.sum()) - 1.0 / p0)


def _strong_polynomial() -> Model:
    r = np.linspace(0.0, 0.8, 5)
    return _operator_model("pmpi(n=5)", r, [0.0, 1.0, 0.5, 0.3, 0.2, 0.1, 2.0, -0.3], np.full(5, 0.5))


def test_eq16_violated_without_gain_is_refused() -> None:
    model = _strong_polynomial()  # P'(v) = 4 v - 0.9 v^2 reaches 3.1 > p0 = 1 on [0, 1]
    with pytest.raises(InstabilityError, match="eq. 16"):
        Compensator(model, FS, (0.0, 1.0), method="im", gain=None)


def test_eq20_gain_restores_the_im_compensator() -> None:
    model = _strong_polynomial()
    comp = Compensator(model, FS, (0.0, 1.0), method="im", gain="auto", iterations=60)
    assert not comp.checks["eq16"]["holds"] and comp.checks["eq20"]["holds"]
    assert comp.checks["eq20"]["k_e"] > 0
    u = _input(5, lo=0.0, hi=1.0)
    y = compile_model(model, FS).block(u)
    np.testing.assert_allclose(comp.feedforward(y), u, atol=1e-7)
    # an explicit k_e that does not satisfy eq. 20 is refused, naming the condition
    with pytest.raises(InstabilityError, match="eq. 20"):
        Compensator(model, FS, (0.0, 1.0), method="im", gain=0.0)


def test_destabilising_pid_is_refused_naming_the_pole() -> None:
    model = _operator_model("pi(n=3)", np.array([0.0, 0.2, 0.4]), [0.0, 1.0, 0.5, 0.2])
    Compensator(model, FS, (-1.0, 1.0), feedback=PID(kp=0.2, ki=0.3 * FS))  # stable: accepted
    with pytest.raises(InstabilityError, match=r"pole at \|z\|"):
        Compensator(model, FS, (-1.0, 1.0), feedback=PID(kp=0.5, ki=2.0 * FS))
    # with lightly damped dynamics declared, gains stable for a unit plant are refused
    dyn = Model("pi(n=3)+dynamics(natural_frequency_hz=50,zeta=0.05)")
    dyn.norm = {"u_scale": 1.0}
    dyn.base.constants["thresholds"] = [0.0, 0.2, 0.4]
    dyn.effects[0].constants["kind"] = "second-order"
    dyn.effects[0].params = [ShapeParam("natural_frequency_hz", 50.0, 1, 1e4), ShapeParam("zeta", 0.05, 0.01, 3)]
    dyn.weights = np.array([0.0, 1.0, 0.5, 0.2])
    with pytest.raises(InstabilityError, match="dynamics"):
        Compensator(dyn, FS, (-1.0, 1.0), feedback=PID(kp=0.9, ki=0.3 * FS))


def test_online_needs_the_fpmpi_front_end() -> None:
    model = _operator_model("pi(n=3)", np.array([0.0, 0.2, 0.4]), [0.0, 1.0, 0.5, 0.2])
    with pytest.raises(Exception, match="fpmpi"):
        Compensator(model, FS, (-1.0, 1.0), online=True)


def test_step_mode_equals_block_mode() -> None:
    model = _operator_model("pmpi(n=4)", np.linspace(0, 0.6, 4), [0.0, 1.0, 0.4, 0.2, 0.1, -0.2, 0.1], np.full(4, 0.3))
    y = compile_model(model, FS).block(_input(9, lo=0.0, hi=1.0))
    block = Compensator(model, FS, (0.0, 1.2)).feedforward(y)
    comp = Compensator(model, FS, (0.0, 1.2))
    steps = []
    for value in y:
        u = comp.step(value)
        comp.update(value, u)
        steps.append(u)
    np.testing.assert_array_equal(np.array(steps), block)
