"""Preisach and Bouc-Wen hysteresis in the simulated plant: the loop shapes a lab checks them by, and
the schema's one-line refusals.

Preisach (relay hysterons; Mayergoyz, *Mathematical Models of Hysteresis*, ch. 1): a minor loop
closes where it started (return-point memory), and a reversal larger than an earlier one wipes out the
memory of the reversals inside it. Bouc-Wen (Ismail, Ikhouane, Rodellar 2009): z stays within
(A / (beta + gamma))^(1/n), the loop is traversed so that it dissipates (the output lags the input:
the falling branch lies above the rising one), and for n = 1 it agrees with the fit base's exact
per-sample solution (hilbench.models.kernels.bouc_wen_block), an independent integration.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import pytest

from hilbench.errors import ConfigError
from hilbench.models import kernels as MK
from hilbench.sim import kernels as K
from hilbench.sim.plant import Plant
from hilbench.sim.schema import SensorModel, check_plant

FS = 1000.0
PREISACH = {"model": "preisach", "levels": 50, "coercive_mean": 0.25, "coercive_std": 0.15,
            "interaction_std": 0.4, "scatter_seed": 5}


def plant(**h: Any) -> Plant:
    return Plant(check_plant({"hysteresis": h}, "<test>", FS), FS, [SensorModel("output")])


def path(*corners: float, step: float = 0.002) -> np.ndarray:
    """A piecewise-linear drive through the corners (normalised input units), ~step per sample."""
    parts = [np.linspace(a, b, max(int(abs(b - a) / step), 2))[1:] for a, b in itertools.pairwise(corners)]
    return np.concatenate(parts)


def drive(p: Plant, *corners: float) -> np.ndarray:
    return p.simulate(path(*corners)).output


# -- Preisach ------------------------------------------------------------------------------------
def test_preisach_major_loop_saturates_and_lags():
    p = plant(**PREISACH)
    drive(p, 0.0, 1.2)
    falling, rising = drive(p, 1.2, -1.2), drive(p, -1.2, 1.2)
    assert falling[-1] == pytest.approx(-1.0) and rising[-1] == pytest.approx(1.0)  # every relay switched
    v = path(1.2, -1.2)  # both branches sampled at the same inputs (rising reversed)
    mid = np.argmin(np.abs(v))
    assert falling[mid] > rising[::-1][mid] + 0.2  # at zero input the falling branch lies above the rising one


def test_preisach_minor_loop_closes_and_a_larger_reversal_wipes_out_the_inner_ones():
    inner = plant(**PREISACH)
    drive(inner, 0.0, 0.8, -0.2, 0.5)
    at_first = inner.op_state.copy()
    y_first = drive(inner, 0.5, 0.1, 0.5)[-1]
    np.testing.assert_array_equal(inner.op_state, at_first)  # the minor loop 0.5 -> 0.1 -> 0.5 closes
    assert y_first == pytest.approx(inner.simulate(np.array([0.5])).output[0])
    drive(inner, 0.5, 0.9)  # above the earlier maximum 0.8: the reversals 0.8, -0.2, 0.5, 0.1 are wiped out
    direct = plant(**PREISACH)
    drive(direct, 0.0, 0.9)
    np.testing.assert_array_equal(inner.op_state, direct.op_state)
    np.testing.assert_array_equal(drive(inner, 0.9, 0.3, 0.6), drive(direct, 0.9, 0.3, 0.6))
    # a smaller reversal does not wipe them: the memory is there to be wiped
    kept = plant(**PREISACH)
    drive(kept, 0.0, 0.8, -0.2, 0.5, 0.1, 0.7)
    short = plant(**PREISACH)
    drive(short, 0.0, 0.7)
    assert np.sum(kept.op_state != short.op_state) > 10


def test_preisach_starts_demagnetised_and_reset_restores_it():
    p = plant(**PREISACH)
    assert abs(p.simulate(np.zeros(3)).output[-1]) < 0.05  # AC-demagnetised: near zero at zero input
    first = drive(p, 0.0, 0.6, -0.4)
    p.reset()
    np.testing.assert_array_equal(drive(p, 0.0, 0.6, -0.4), first)


# -- Bouc-Wen ------------------------------------------------------------------------------------
@pytest.mark.parametrize(("a", "beta", "gamma", "n"), [(1.0, 2.0, 0.5, 1.0), (2.0, 3.0, -1.0, 2.0),
                                                        (0.5, 8.0, 8.0, 1.5)])
def test_bouc_wen_z_bounded_even_under_full_range_steps(a, beta, gamma, n):
    p = plant(model="bouc-wen", a=a, beta=beta, gamma=gamma, n=n)
    rng = np.random.default_rng(3)
    u = np.concatenate([path(0.0, 3.0, -3.0, 2.0), rng.choice([-4.0, 4.0], 50), rng.uniform(-5, 5, 500)])
    z = p.simulate(u).output  # linear_gain 0: the output is z
    z_max = K.bouc_wen_z_max(a, beta, gamma, n)
    assert np.all(np.isfinite(z))
    assert np.max(np.abs(z)) <= z_max * (1 + 1e-9)
    assert np.max(np.abs(z)) > 0.9 * z_max  # and the large drive reaches near the bound


def test_bouc_wen_loop_sign():
    """y = k u + z: z is a stop (elastoplastic) operator, its loop clockwise in (u, z), the energy
    dissipated per cycle (closed integral of z du) positive. y = k u - z (z_weight -1, the piezo form):
    the output lags, the falling branch above the rising one (the loop counter-clockwise)."""
    u = np.sin(2 * np.pi * np.arange(3001) / 1000.0)  # three cycles; the last one is the steady loop
    last = slice(2000, 3001)

    def loop(z_weight: float) -> tuple[float, float, float]:
        p = plant(model="bouc-wen", a=1.0, beta=3.0, gamma=1.0, n=1.0, linear_gain=0.5, z_weight=z_weight)
        y = p.simulate(u).output[last]
        z = z_weight * (y - 0.5 * u[last])
        return float(np.sum(0.5 * (z[1:] + z[:-1]) * np.diff(u[last]))), float(y[0]), float(y[500])

    work, rising, falling = loop(1.0)  # u = 0 rising at t = 2 s, falling at 2.5 s
    assert work > 0.05 and rising > falling + 0.2
    work, rising, falling = loop(-1.0)
    assert work > 0.05 and falling > rising + 0.2


def test_bouc_wen_n1_matches_the_fit_bases_exact_solution():
    a, beta, gamma = 1.7, 2.5, -0.8
    p = plant(model="bouc-wen", a=a, beta=beta, gamma=gamma, n=1.0)
    u = path(0.0, 1.0, -0.6, 0.4, -1.0, 0.9, step=0.01)
    z = p.simulate(u).output
    ref = np.empty_like(u)
    # the fit's kernel has A = 1; z with A is A z(A = 1) for n = 1 (z -> z / A rescales the equation)
    MK.bouc_wen_block(u, beta, gamma, 1.0, np.array([0.0, u[0]]), ref)  # from rest at the first input
    # exact while z keeps its sign; in the samples where it changes sign (a kink of |z|) the fit's
    # kernel takes 8 midpoint sub-steps and the plant RK4 ones: ~1e-5 of z_max = A / (beta + gamma) = 1
    np.testing.assert_allclose(z, a * ref, rtol=0, atol=1e-4)
    assert np.max(np.abs(z)) > 0.5


def test_bouc_wen_and_preisach_step_mode_equals_block_mode():
    u = path(0.0, 0.9, -0.7, 0.5, step=0.01)
    for h in (PREISACH, {"model": "bouc-wen", "beta": 2.0, "gamma": 0.5, "n": 2.0, "linear_gain": 0.3}):
        block, step = plant(**h), plant(**h)
        np.testing.assert_array_equal(np.array([step.step_value(x) for x in u]), block.simulate(u).output)


# -- schema --------------------------------------------------------------------------------------
@pytest.mark.parametrize(("h", "says"), [
    ({"model": "bouc-wen", "beta": 0.2, "gamma": 0.5}, "beta = 0.2 < |gamma| = 0.5"),
    ({"model": "bouc-wen", "beta": 0.5, "gamma": -0.5}, "beta + gamma = 0.0"),
    ({"model": "bouc-wen"}, "missing key 'beta'"),
    ({"model": "bouc-wen", "beta": 1.0, "n": 0.5}, "n"),
    ({"model": "bouc-wen", "beta": 1.0, "a": 0.0}, "a"),
    ({"model": "preisach", "levels": 1}, "levels"),
    ({"model": "preisach", "switching_range": [1.0, -1.0]}, "switching_range = [1.0, -1.0]: expected low < high"),
    ({"model": "preisach", "interaction_std": 0.0}, "interaction_std"),
    ({"model": "preisach", "coercive_mean": 50.0, "coercive_std": 0.01}, "no weight on the grid"),
])
def test_schema_refuses_bad_hysteresis_tables_in_one_line(h, says):
    with pytest.raises(ConfigError) as exc:
        check_plant({"hysteresis": h}, "<test>", FS)
    assert says in exc.value.message and "\n" not in exc.value.message
    assert "[plant.hysteresis]" in exc.value.message
