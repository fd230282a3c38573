"""The block tests of a refit's validation error (hilbench/diagnosis/significance.py, decision 0022)."""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.significance import block_test, correlation_length, improvement_test, sum_test


def _ar1(rng: np.random.Generator, n: int, pole: float, std: float = 1.0) -> np.ndarray:
    """Autocorrelated noise like a model's residual: AR(1) with the given pole, unit-ish std."""
    x = lfilter([1.0], [1.0, -pole], rng.normal(0, 1, n))
    return std * x / np.std(x)


def test_correlation_length_of_ar1_is_its_time_constant():
    rng = np.random.default_rng(1)
    x = _ar1(rng, 200_000, 0.99)  # autocorrelation 0.99^k falls to 1/e at k = 1/-ln(0.99) ~ 99.5
    assert 80 <= correlation_length(x) <= 120
    assert correlation_length(rng.normal(0, 1, 10_000)) == 1
    assert correlation_length(np.ones(50)) == 1


def test_gain_confined_to_a_few_stretches_is_found():
    """Saturation on a ramped sine: only the peaks of the last part of the record reach the
    knee, and there the refit removes most of the error; elsewhere it keeps the error up to its
    own scatter. The signed-rank test over 20 blocks sees 5 blocks improve among 15 that change at
    random and misses it (p ~ 0.3); the sum test over blocks a few cycles long does not."""
    rng = np.random.default_rng(4)
    n, period = 20_000, 200
    t = np.arange(n)
    drive = (t / n) * np.sin(2 * np.pi * t / period)  # amplitude ramps 0 -> 1
    knee = 0.05 * np.sign(drive) * np.clip(np.abs(drive) - 0.6, 0, None) / 0.4  # beyond 60 % of full drive
    noise = _ar1(rng, n, 0.95, 0.01)
    e_old = noise + knee
    e_new = noise + 0.1 * knee + _ar1(rng, n, 0.95, 0.003)  # 90 % of the knee gone, a little error added
    assert np.sqrt(np.mean(e_new**2)) < 0.8 * np.sqrt(np.mean(e_old**2))  # a gain the diagnosis must see
    p_ranks, better, blocks = block_test(e_old, e_new)
    assert p_ranks > T.P_MAX and better < blocks
    p_sum, n_blocks = sum_test(e_old, e_new)
    assert p_sum < 1e-3 and n_blocks > T.N_BLOCKS
    p, better_reported, _ = improvement_test(e_old, e_new)
    assert p < T.P_MAX and p == min(1.0, 2 * min(p_ranks, p_sum)) and better_reported == better


def test_gain_spread_over_the_record_is_still_found():
    rng = np.random.default_rng(5)
    e_old = _ar1(rng, 10_000, 0.9)
    p, better, blocks = improvement_test(e_old, 0.8 * e_old)
    assert p < T.P_MAX and better == blocks


def test_noise_alone_rarely_passes():
    """Two refits as good as each other, on strongly autocorrelated residuals: the combined test
    flags a gain at about its level or less (Bonferroni over its two tests), not at the rate of a
    per-sample test that ignores the correlation."""
    rng = np.random.default_rng(6)
    trials, flagged = 200, 0
    for _ in range(trials):
        e_old, e_new = _ar1(rng, 4_000, 0.98), _ar1(rng, 4_000, 0.98)
        flagged += improvement_test(e_old, e_new)[0] < T.P_MAX
    assert flagged <= 0.03 * trials


def test_sum_test_is_reproducible_and_bounded():
    rng = np.random.default_rng(7)
    e_old, e_new = _ar1(rng, 5_000, 0.9), _ar1(rng, 5_000, 0.9)
    assert sum_test(e_old, e_new) == sum_test(e_old, e_new)
    p, blocks = sum_test(e_old, e_new)
    assert 0 < p <= 1 and T.N_BLOCKS <= blocks <= T.SUM_TEST_MAX_BLOCKS
    assert sum_test(e_old, e_old)[0] == 1.0  # no difference: nothing to test


def test_a_refit_that_returned_the_same_model_is_no_gain():
    """Differences at floating-point rounding (a refit whose new term got zero weight) are neither a
    gain nor a loss: p = 1, not whatever the signs of the rounding happen to give."""
    rng = np.random.default_rng(8)
    e_old = _ar1(rng, 5_000, 0.9)
    e_new = e_old * (1.0 - 1e-14)  # lower everywhere, by rounding only
    assert block_test(e_old, e_new)[0] == 1.0 and sum_test(e_old, e_new)[0] == 1.0
    assert improvement_test(np.array([]), np.array([]))[0] == 1.0
