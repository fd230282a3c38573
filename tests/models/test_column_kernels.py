"""The column-assembly kernels equal the numpy they replace, bit for bit, in block and split calls."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilbench.models import kernels as MK


@pytest.fixture()
def columns() -> np.ndarray:
    rng = np.random.default_rng(7)
    return np.cumsum(rng.normal(size=(3001, 5)), axis=0)


def _lowpass_drift(x: np.ndarray, alpha: float, start: np.ndarray) -> np.ndarray:
    """Each column through lowpass_block, minus the column (the reference)."""
    out = np.empty_like(x)
    for j in range(x.shape[1]):
        col = np.ascontiguousarray(x[:, j])
        lp = np.empty_like(col)
        MK.lowpass_block(col, alpha, np.array([start[j]]), lp)
        out[:, j] = lp - col
    return out


def test_scale_columns_scales_the_marked_columns_only(columns: np.ndarray) -> None:
    gain = np.linspace(0.5, 1.5, columns.shape[0])
    marked = np.array([True, False, True, True, False])
    expected = columns.copy()
    expected[:, marked] *= gain[:, None]
    got = columns.copy()
    MK.scale_columns(got, gain, marked)
    assert np.array_equal(got, expected)


def test_lowpass_drift_into_writes_the_drift_at_its_columns(columns: np.ndarray) -> None:
    alpha = 1.0 - math.exp(-1.0 / 37.0)
    expected = _lowpass_drift(columns, alpha, columns[0])
    out = np.full((columns.shape[0], 2 + columns.shape[1]), np.nan)
    state = columns[0].copy()
    MK.lowpass_drift_into(columns, alpha, state, out, 2)
    assert np.array_equal(out[:, 2:], expected)
    assert np.isnan(out[:, :2]).all()  # the other columns are left alone


def test_lowpass_drift_sum_in_two_calls_equals_one(columns: np.ndarray) -> None:
    alphas = np.array([1.0 - math.exp(-1.0 / t) for t in (3.0, 40.0, 900.0)])
    weights = np.array([0.2, 0.7, 1.3])
    expected = np.zeros_like(columns)
    for a, w in zip(alphas, weights):  # the bank's order: the sum is added in the same order
        expected += w * _lowpass_drift(columns, a, columns[0])
    whole = np.zeros((columns.shape[0], 1 + columns.shape[1]))
    MK.lowpass_drift_sum(columns, alphas, weights, np.repeat(columns[:1], 3, axis=0), whole, 1)
    assert np.array_equal(whole[:, 1:], expected)
    # step mode: the state carries the memory from one block to the next
    split = np.zeros_like(whole)
    state = np.repeat(columns[:1], 3, axis=0)
    MK.lowpass_drift_sum(columns[:1234], alphas, weights, state, split[:1234], 1)
    MK.lowpass_drift_sum(columns[1234:], alphas, weights, state, split[1234:], 1)
    assert np.array_equal(split, whole)


def test_gather_rows_into_equals_fancy_indexing(columns: np.ndarray) -> None:
    rows = np.flatnonzero(np.arange(columns.shape[0]) % 3 != 1)
    out = np.zeros((rows.size, columns.shape[1] + 3))
    MK.gather_rows_into(columns, rows, out, 3)
    assert np.array_equal(out[:, 3:], columns[rows])
    assert not out[:, :3].any()
