"""The plant's step function: plant_block is plant_step in a loop, the fast step path draws the same
noise and trajectories as block mode across batch boundaries and run restarts, and plant_step is
callable from other numba code."""

from __future__ import annotations

import numpy as np
from numba import njit

from hilbench.rig.config import load_rig
from hilbench.sim import kernels as K
from hilbench.sim.plant import Plant
from tests.sim.test_plant import ALL_EFFECTS, make_plant, sine

CURRENT_SENSOR = """
[[sensors]]
channel = "current"
unit = "A"
driver = "sim"
noise_std = 0.002
quantization = 0.001
"""


def test_fast_steps_mixed_with_blocks_equal_one_block_across_batches_and_run_restarts(write_rig):
    block = make_plant(write_rig, ALL_EFFECTS + CURRENT_SENSOR)
    mixed = make_plant(write_rig, ALL_EFFECTS + CURRENT_SENSOR)
    n = Plant.STEP_BATCH
    u = sine(3 * n + 500)
    cuts = [0, 700, n + 3, n + 10, 2 * n + 100, 3 * n + 500]  # steps, block, steps, block, steps
    expected_parts, got_parts, aux_expected, aux_got = [], [], [], []
    for k in range(len(cuts) - 1):
        part = u[cuts[k] : cuts[k + 1]]
        if k == 2:  # a new run: the trajectories start again, the memory and noise streams go on
            block.start_run()
            mixed.start_run()
        ref = block.simulate(part)
        expected_parts.append(ref.output)
        aux_expected.append(ref.aux["current"])
        if k % 2 == 0:
            outs = [mixed.step(x) for x in part]
            got_parts.append(np.concatenate([o.output for o in outs]))
            aux_got.append(np.concatenate([o.aux["current"] for o in outs]))
            if k == 2:
                assert mixed.time_s == len(part) / mixed.sample_rate_hz  # the run clock restarted
        else:
            res = mixed.simulate(part)
            got_parts.append(res.output)
            aux_got.append(res.aux["current"])
    np.testing.assert_array_equal(np.concatenate(got_parts), np.concatenate(expected_parts))
    np.testing.assert_array_equal(np.concatenate(aux_got), np.concatenate(aux_expected))


def test_step_value_is_the_measured_output_of_step(write_rig):
    a = make_plant(write_rig, ALL_EFFECTS)
    b = make_plant(write_rig, ALL_EFFECTS)
    u = sine(1500)
    fast = np.array([a.step_value(x) for x in u])
    full = np.array([b.step(x).output[0] for x in u])
    np.testing.assert_array_equal(fast, full)
    assert a.samples == 1500 and a.time_s == 1.5


def test_plant_step_called_from_numba_equals_block_mode(write_rig):
    p = make_plant(write_rig, ALL_EFFECTS)
    q = make_plant(write_rig, ALL_EFFECTS)
    u = sine(2000)
    ref = p.simulate(u)
    # the inputs block mode used: the noise stream and trajectories of the same run clock
    noise = np.random.default_rng([q.seed, 1]).standard_normal(u.size)
    t = np.arange(u.size) / q.sample_rate_hz
    from hilbench.sim import trajectories

    temperature = trajectories.evaluate(q.tables["temperature"]["trajectory"], t)
    load = trajectories.evaluate(q.tables["load"]["trajectory"], t)
    F, L = q.step_arrays()

    @njit(_nrt=False)
    def closed(F, L, u, temperature, load, noise, B, out):  # no allocation without NRT: B from outside
        for n in range(u.shape[0]):
            B[K.B_NOISE, 0] = noise[n]
            B[K.B_TEMPERATURE, 0] = temperature[n]
            B[K.B_LOAD, 0] = load[n]
            out[n] = K.plant_step_flat(F, L, B, 0, u[n])

    out = np.empty(u.size)
    closed(F, L, u, temperature, load, noise, np.empty((3, 1)), out)
    np.testing.assert_array_equal(out, ref.output)
    np.testing.assert_array_equal(q.X, p.X)  # the Plant's own state arrays were stepped


def test_block_kernel_is_step_in_a_loop(write_rig):
    p = make_plant(write_rig, ALL_EFFECTS)
    args = [getattr(p, name) for name in K.PLANT_ARRAYS[:-1]]
    u = sine(50)
    temp = np.full(u.size, 24.0)
    load = np.linspace(0.0, 10.0, u.size)
    noise = np.linspace(-1.0, 1.0, u.size)
    saved = [a.copy() for a in args]
    outs = [np.empty(u.size) for _ in range(3)]
    K.plant_block(u, temp, load, noise, *args, *outs)
    for a, s in zip(args, saved):
        a[:] = s
    for n in range(u.size):
        m, y, d = K.plant_step(u[n], temp[n], load[n], noise[n], *args)
        assert (m, y, d) == (outs[0][n], outs[1][n], outs[2][n])


def test_reset_keeps_step_and_block_in_step(write_rig):
    p = Plant.from_rig(load_rig(write_rig()))
    u = sine(300)
    first = np.array([p.step_value(x) for x in u])
    p.reset()
    np.testing.assert_array_equal(p.simulate(u).output, first)
