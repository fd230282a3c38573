"""Operator laws (hypothesis): rate independence, congruent minor loops (004 eq. 9-11), and the
one-sided play as a shifted play."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbench.models.kernels import mplay_block

levels = st.lists(st.floats(-10, 10, allow_nan=False), min_size=2, max_size=25)


def mplay(v: np.ndarray, r: np.ndarray, eta: np.ndarray, state: np.ndarray | None = None) -> np.ndarray:
    out = np.empty((v.size, r.size))
    mplay_block(np.ascontiguousarray(v, dtype=float), r, eta, np.zeros(r.size) if state is None else state, out)
    return out


def weighted(v: np.ndarray, r: np.ndarray, eta: np.ndarray, w: np.ndarray, p0: float) -> np.ndarray:
    return p0 * v + mplay(v, r, eta) @ w


operators = st.integers(1, 6).flatmap(lambda n: st.tuples(
    st.lists(st.floats(0.0, 4.0), min_size=n, max_size=n),
    st.lists(st.floats(-0.9, 1.5), min_size=n, max_size=n),
    st.lists(st.floats(0.0, 3.0), min_size=n, max_size=n),
))


@settings(max_examples=60, deadline=None)
@given(points=levels, ops=operators, factor=st.integers(2, 7))
def test_play_and_mplay_are_rate_independent(points, ops, factor):
    """Resampling the input (more samples along the same path) leaves the output at the original
    samples unchanged: the operators see the path, not its speed."""
    r, eta, _ = (np.asarray(x) for x in ops)
    v = np.asarray(points)
    fine = np.concatenate([np.linspace(a, b, factor, endpoint=False) for a, b in zip(v[:-1], v[1:])] + [v[-1:]])
    for e in (np.ones_like(eta), eta):  # play, M-play
        coarse_out = mplay(v, r, e)
        fine_out = mplay(fine, r, e)[::factor]
        np.testing.assert_allclose(fine_out, coarse_out, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(ops=operators, p0=st.floats(0.0, 3.0), history=levels,
       lo=st.floats(-3, 0), span=st.floats(0.1, 6.0))
def test_minor_loops_are_congruent_with_the_height_of_eq_11(ops, p0, history, lo, span):
    """Two different histories, then the same cycles between v_m and v_M: after one cycle both
    trace the same loop up to a vertical shift, of height p0 x + sum w max(x - (1 + eta) r, 0)."""
    r, eta, w = (np.asarray(x) for x in ops)
    hi = lo + span
    cycle = np.concatenate([np.linspace(lo, hi, 40), np.linspace(hi, lo, 40)[1:]])
    tail = np.concatenate([cycle] * 3)
    a = np.concatenate([[0.0], np.asarray(history), tail])
    b = np.concatenate([[0.0], -np.asarray(history)[::-1] * 0.7, tail])
    for e in (np.ones_like(eta), eta):  # PI, PMPI
        ya = weighted(a, r, e, w, p0)[-2 * cycle.size:]
        yb = weighted(b, r, e, w, p0)[-2 * cycle.size:]
        shift = ya - yb
        np.testing.assert_allclose(shift, shift[0], atol=1e-9)  # congruent: same shape
        # loop height at the turning point v_M relative to v_m (004 eq. 9-11 with the linear term)
        height = ya[-cycle.size + 39] - ya[-cycle.size]
        expected = p0 * span + np.sum(w * np.maximum(span - (1 + e) * r, 0.0))
        assert abs(height - expected) < 1e-9 * max(1.0, abs(expected))


@settings(max_examples=60, deadline=None)
@given(path=st.lists(st.floats(0, 10), min_size=2, max_size=30), r=st.floats(0.01, 4.0))
def test_one_sided_play_is_a_shifted_play(path, r):
    """For a nonnegative input that first rises above r: F1_r[v] = F_{r/2}[v] - r/2."""
    v = np.concatenate([[0.0, r + 0.5], np.asarray(path)])
    one_sided = mplay(v, np.array([r]), np.zeros(1))[:, 0]
    play = mplay(v, np.array([r / 2]), np.ones(1))[:, 0]
    np.testing.assert_allclose(one_sided[1:], play[1:] - r / 2, atol=1e-12)
