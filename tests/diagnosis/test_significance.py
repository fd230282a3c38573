"""The block tests of a refit's validation error (hilbench/diagnosis/significance.py, decisions 0022, 0032)."""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.significance import block_count, block_tests, correlation_length, improvement_test


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


def _ar1_unscaled(rng: np.random.Generator, n: int, pole: float) -> np.ndarray:
    """AR(1) noise of unit stationary variance whose sample variance scatters as a residual's does
    (scaling each draw to its own std would make two draws' summed squares equal by construction)."""
    return lfilter([1.0], [1.0, -pole], rng.normal(0, 1, n)) * np.sqrt(1.0 - pole**2)


def test_gain_confined_to_a_few_stretches_is_found():
    """Saturation on a ramped sine: only the peaks of the last part of the record reach the
    knee, and there the refit removes most of the error; elsewhere it keeps the error up to its
    own scatter. The signed ranks see a few blocks improve among many that change at random and
    miss it; the sum over blocks a few cycles long does not, and the joint p keeps its power."""
    rng = np.random.default_rng(4)
    n, period = 20_000, 200
    t = np.arange(n)
    drive = (t / n) * np.sin(2 * np.pi * t / period)  # amplitude ramps 0 -> 1
    knee = 0.05 * np.sign(drive) * np.clip(np.abs(drive) - 0.6, 0, None) / 0.4  # beyond 60 % of full drive
    noise = _ar1(rng, n, 0.95, 0.01)
    e_old = noise + knee
    e_new = noise + 0.1 * knee + _ar1(rng, n, 0.95, 0.003)  # 90 % of the knee gone, a little error added
    assert np.sqrt(np.mean(e_new**2)) < 0.8 * np.sqrt(np.mean(e_old**2))  # a gain the diagnosis must see
    t = block_tests(e_old, e_new)
    assert t.p_ranks > T.P_MAX and t.better < t.blocks
    assert t.p_sum < 1e-3 and t.blocks > T.N_BLOCKS
    assert t.p < T.P_MAX and min(t.p_ranks, t.p_sum) <= t.p <= 2 * min(t.p_ranks, t.p_sum)
    assert improvement_test(e_old, e_new) == (t.p, t.better, t.blocks)


def test_gain_spread_over_the_record_is_still_found():
    rng = np.random.default_rng(5)
    e_old = _ar1(rng, 10_000, 0.9)
    p, better, blocks = improvement_test(e_old, 0.8 * e_old)
    assert p < T.P_MAX and better == blocks


def test_joint_p_is_below_bonferroni_when_the_two_statistics_agree():
    """A gain on most blocks moves both statistics: their p-values are nearly the same event, and
    the joint p, calibrated on the same flips, is close to the smaller one rather than twice it
    (the Bonferroni factor of decision 0022 counted one piece of evidence twice)."""
    rng = np.random.default_rng(9)
    e_old = _ar1(rng, 20_000, 0.9)
    e_new = 0.97 * e_old + _ar1(rng, 20_000, 0.9, 0.05)
    t = block_tests(e_old, e_new)
    assert t.p < 2 * min(t.p_ranks, t.p_sum) and t.p >= min(t.p_ranks, t.p_sum)


def test_noise_alone_passes_at_the_tests_level():
    """Two refits as good as each other, on autocorrelated residuals: the joint test flags a gain
    at about its level (1 % per test, here 400 pairs: at most a few), not at the rate of a
    per-sample test that ignores the correlation (which flags about half)."""
    rng = np.random.default_rng(6)
    trials, flagged = 400, 0
    for _ in range(trials):
        e_old, e_new = _ar1_unscaled(rng, 20_000, 0.9), _ar1_unscaled(rng, 20_000, 0.9)
        flagged += improvement_test(e_old, e_new)[0] < T.P_MAX
    assert flagged <= 0.025 * trials


def test_blocks_are_several_correlation_lengths_long():
    rng = np.random.default_rng(10)
    d = _ar1(rng, 40_000, 0.99) ** 2  # squared difference: correlated over ~50 rows
    assert T.N_BLOCKS <= block_count(d) <= T.SUM_TEST_MAX_BLOCKS
    assert 40_000 / block_count(d) >= 0.5 * T.SUM_TEST_BLOCK_CORRELATIONS * correlation_length(d)
    assert block_count(rng.normal(0, 1, 1_000_000)) == T.SUM_TEST_MAX_BLOCKS
    assert block_count(np.ones(8)) == 8  # never more blocks than rows


def test_tests_are_reproducible_and_bounded():
    rng = np.random.default_rng(7)
    e_old, e_new = _ar1(rng, 5_000, 0.9), _ar1(rng, 5_000, 0.9)
    assert block_tests(e_old, e_new) == block_tests(e_old, e_new)
    t = block_tests(e_old, e_new)
    assert 0 < t.p <= 1 and 0 < t.p_ranks <= 1 and 0 < t.p_sum <= 1
    assert T.N_BLOCKS <= t.blocks <= T.SUM_TEST_MAX_BLOCKS
    assert block_tests(e_old, e_old).p == 1.0  # no difference: nothing to test


def test_a_refit_that_returned_the_same_model_is_no_gain():
    """Differences at floating-point rounding (a refit whose new term got zero weight) are neither a
    gain nor a loss: p = 1, not whatever the signs of the rounding happen to give."""
    rng = np.random.default_rng(8)
    e_old = _ar1(rng, 5_000, 0.9)
    e_new = e_old * (1.0 - 1e-14)  # lower everywhere, by rounding only
    t = block_tests(e_old, e_new)
    assert t.p == 1.0 and t.p_ranks == 1.0 and t.p_sum == 1.0
    assert improvement_test(np.array([]), np.array([]))[0] == 1.0
