"""The simulated plant: block mode equals step mode, reproducible, and each effect does its physics."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbench.rig.config import load_rig
from hilbench.rig.rig import Rig
from hilbench.sim import kernels as K
from hilbench.sim.plant import Plant

FS = 1000.0


def make_plant(write_rig, extra: str = "") -> Plant:
    return Plant.from_rig(load_rig(write_rig(extra)))


def sine(n: int = 3000, amp: float = 5.0, f: float = 1.0) -> np.ndarray:
    return amp * np.sin(2 * np.pi * f * np.arange(n) / FS)


ALL_EFFECTS = """
[plant.amplifier]
gain = 1.0
bandwidth_hz = 200.0
slew_rate = 5000.0
[plant.delay]
seconds = 0.003
[plant.asymmetry]
coefficients = [0.0, 0.0, 0.05, -0.01]
[plant.saturation]
level = 8.0
[plant.rate_dependence]
coefficient = 0.2
exponent = 0.9
reference_rate = 30.0
[plant.creep]
gains = [0.05, 0.03]
time_constants_s = [0.5, 5.0]
[plant.dynamics]
kind = "second-order"
zeta = 0.3
natural_frequency_hz = 60.0
[plant.temperature]
gain_per_degC = 0.01
strain_um_per_degC = 0.2
trajectory = { kind = "ramp", start = 20.0, end = 30.0, duration_s = 3.0 }
[plant.load]
gain_per_N = 0.001
compliance_um_per_N = 0.02
trajectory = { kind = "placed-weight", mass_kg = 2.0, at_s = 1.0 }
[[sensors]]
channel = "temperature"
unit = "degC"
driver = "sim"
noise_std = 0.05
[[sensors]]
channel = "load"
unit = "N"
driver = "sim"
noise_std = 0.1
"""


def test_block_equals_step_mode_with_every_effect(write_rig):
    block = make_plant(write_rig, ALL_EFFECTS)
    step = make_plant(write_rig, ALL_EFFECTS)
    assert set(block.effects) >= {"hysteresis", "asymmetry", "saturation", "rate-dependence", "dynamics",
                                  "creep", "delay", "temperature", "load", "amplifier"}
    u = sine()
    a = block.simulate(u)
    outs = [step.step(x) for x in u]
    np.testing.assert_array_equal(a.output, np.concatenate([o.output for o in outs]))
    np.testing.assert_array_equal(a.aux["temperature"], np.concatenate([o.aux["temperature"] for o in outs]))
    np.testing.assert_array_equal(a.aux["load"], np.concatenate([o.aux["load"] for o in outs]))


def test_seeded_runs_are_reproducible_and_seeds_differ(write_rig, tmp_path):
    u = sine()
    one = make_plant(write_rig).simulate(u).output
    two = make_plant(write_rig).simulate(u).output
    np.testing.assert_array_equal(one, two)
    other = Plant.from_rig(load_rig(write_rig().parent / "rig.toml"))
    other.seed = 8
    other.reset()
    assert not np.array_equal(other.simulate(u).output, one)


def test_noise_level_matches_sensor(write_rig):
    p = make_plant(write_rig)
    r = p.simulate(sine())
    assert np.std(r.output - r.true_output) == pytest.approx(0.01, rel=0.1)


def test_pi_plant_matches_play_operator_sum(write_rig):
    p = make_plant(write_rig)
    u = sine()
    y = p.simulate(u).true_output
    r = np.array([0.5, 1.0, 2.0])
    w = np.array([0.5, 0.3, 0.2])
    state = np.zeros(3)
    expected = np.empty_like(u)
    for n, x in enumerate(u):
        state = np.maximum(x - r, np.minimum(x + r, state))
        expected[n] = 1.0 * x + w @ state
    np.testing.assert_allclose(y, expected, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(
    v=st.lists(st.floats(-10, 10), min_size=2, max_size=60),
    r=st.floats(0, 3),
    eta=st.floats(-1, 1.5),
)
def test_mplay_bounds_and_special_cases(v, r, eta):
    v = np.asarray(v)
    out = np.empty((v.size, 1))
    K.mplay_block(v, np.array([r]), np.array([eta]), np.zeros(1), out)
    # M-play output lies between v - r and max(v + eta r, v - r) (004 eq. 6)
    assert np.all(out[:, 0] >= v - r - 1e-12)
    assert np.all(out[:, 0] <= np.maximum(v + eta * r, v - r) + 1e-12)
    # eta = 1 is the play operator: |v - w| <= r once the input has moved
    play = np.empty((v.size, 1))
    K.mplay_block(v, np.array([r]), np.ones(1), np.zeros(1), play)
    assert np.all(np.abs(v - play[:, 0]) <= r + 1e-12)


def test_one_sided_play_is_mplay_with_eta_zero():
    v = np.array([0.0, 1.0, 2.0, 1.5, 0.2, 1.7])
    out = np.empty((v.size, 1))
    K.mplay_block(v, np.array([0.5]), np.zeros(1), np.zeros(1), out)
    # 003 eq. 2: F = max(v - r, min(v, F_prev))
    prev, expected = 0.0, []
    for x in v:
        prev = max(x - 0.5, min(x, prev))
        expected.append(prev)
    np.testing.assert_allclose(out[:, 0], expected)


def test_duhem_state_is_exact_for_linear_input():
    alpha, beta = 0.5, 2.0
    u = np.linspace(0.0, 4.0, 9)  # coarse steps: an Euler scheme would be far off
    out = np.empty_like(u)
    K.duhem_w_block(u, alpha, beta, np.zeros(2), out)
    # dw/du = beta u - alpha w, w(0) = 0  ->  w = beta/alpha (u - 1/alpha + e^{-alpha u}/alpha)
    exact = beta / alpha * (u - 1 / alpha + np.exp(-alpha * u) / alpha)
    np.testing.assert_allclose(out, exact, atol=1e-12)


def test_dynamics_static_gain_and_resonance(write_rig):
    p = make_plant(write_rig, '[plant.dynamics]\nkind = "second-order"\ngain = 2.0\nzeta = 0.1\nnatural_frequency_hz = 50.0\n')
    y = p.simulate(np.full(3000, 1.0)).true_output
    # step 1 V: PI gives 1 + 0.5*0.5 + 0.3*0 ... settle at 2 x static hysteresis output
    static = 1.0 + 0.5 * 0.5
    assert y[-1] == pytest.approx(2.0 * static, rel=1e-3)
    overshoot = (y.max() - y[-1]) / y[-1]
    assert overshoot == pytest.approx(np.exp(-np.pi * 0.1 / np.sqrt(1 - 0.01)), rel=0.05)


def test_creep_drifts_after_step_and_settles(write_rig):
    p = make_plant(write_rig, "[plant.creep]\ngains = [0.1]\ntime_constants_s = [1.0]\n")
    y = p.simulate(np.concatenate([np.zeros(10), np.full(8000, 2.0)])).true_output
    h = 2.0 + 0.5 * 1.5 + 0.3 * 1.0  # hysteresis output at 2 V from virgin state
    assert y[11] == pytest.approx(h, rel=0.01)
    assert y[10 + 1000] == pytest.approx(h * (1 + 0.1 * (1 - np.exp(-1))), rel=1e-3)
    assert y[-1] == pytest.approx(h * 1.1, rel=1e-3)


def test_delay_shifts_output(write_rig):
    base = make_plant(write_rig).simulate(sine()).true_output
    delayed = make_plant(write_rig, "[plant.delay]\nseconds = 0.025\n").simulate(sine()).true_output
    np.testing.assert_allclose(delayed[25:], base[:-25], atol=1e-12)


def test_amplifier_slew_and_limit(write_rig):
    p = make_plant(write_rig, "[plant.amplifier]\nslew_rate = 100.0\noutput_limit = [-3.0, 3.0]\n")
    r = p.simulate(np.concatenate([np.zeros(5), np.full(100, 5.0)]))
    assert np.max(np.diff(r.drive)) == pytest.approx(0.1)
    assert r.drive.max() == pytest.approx(3.0)


def test_sensor_quantization_and_out_of_range(write_rig):
    from tests.conftest import MINIMAL_RIG

    rig = MINIMAL_RIG.replace("noise_std = 0.01", 'quantization = 0.25\nrange = [-2.0, 2.0]\nout_of_range = "nan"')
    p = Plant.from_rig(load_rig(write_rig(base=rig)))
    y = p.simulate(sine(amp=3.0)).output
    finite = y[np.isfinite(y)]
    np.testing.assert_allclose(finite / 0.25, np.round(finite / 0.25), atol=1e-9)
    assert np.isnan(y).any() and finite.max() <= 2.0 and finite.min() >= -2.0


def test_temperature_and_load_change_the_output(write_rig):
    temp = make_plant(write_rig, """
[plant.temperature]
gain_per_degC = 0.02
strain_um_per_degC = 0.5
trajectory = { kind = "cooling", initial = 42.5, ambient = 20.0, time_constant_s = 1.0 }
[[sensors]]
channel = "temperature"
unit = "degC"
driver = "sim"
""")
    r = temp.simulate(np.zeros(3000))
    assert r.aux["temperature"][0] == pytest.approx(42.5) and r.aux["temperature"][-1] < 22.0
    # at zero input the output is the thermal strain alone
    np.testing.assert_allclose(r.true_output, 0.5 * (r.aux["temperature"] - 20.0), atol=1e-9)

    load = make_plant(write_rig, """
[plant.load]
compliance_um_per_N = 0.1
trajectory = { kind = "placed-weight", mass_kg = 1.0, at_s = 1.0, contacts = 1, settle_hz = 5.0, damping = 0.1 }
[[sensors]]
channel = "load"
unit = "N"
driver = "sim"
""")
    r = load.simulate(np.zeros(4000))
    force = r.aux["load"]
    assert force[:1000].max() == 0.0 and force[-1] == pytest.approx(9.80665, rel=0.01)
    assert force.max() > 1.5 * 9.80665  # the weight overshoots as it lands
    np.testing.assert_allclose(r.true_output, -0.1 * force, atol=1e-9)


def test_rig_command_path_clamps_and_slew_limits(write_rig):
    rig = Rig(load_rig(write_rig()))
    applied = rig.apply(np.array([0.0, 50.0, 50.0, -50.0, np.nan]))
    np.testing.assert_allclose(applied, [0.0, 1.0, 2.0, 1.0, 1.0])  # 1000 V/s at 1 kHz = 1 V/sample
    assert rig.clamped_samples == 4
    rig.stop(False)
    assert rig.last_applied == 0.0
