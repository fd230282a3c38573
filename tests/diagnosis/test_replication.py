"""`hilbench.diagnosis.replication`: a gain the validation rows are too short to confirm alone is
tested again on held-back training rows, and is significant when both block tests reach sqrt(P_MAX)
(decision 0052). End to end on randomized cases: tests/diagnosis/test_random_cases.py (2801, 3076)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.replication import (BLOCK_CHECK, HELD_BACK_CHECK, REPLICATION_FOLDS, held_back_folds,
                                            needs_replication, replication_level, settle)
from hilbench.diagnosis.significance import block_tests
from hilbench.diagnosis.verdict import Candidate, check_reason


def _candidate(checks: dict[str, bool], p: float, effect: str = "creep", **evidence) -> Candidate:
    # the base check and the structure check replace the model, as base_check and structure_check build them
    return Candidate(effect, f"pi+{effect}", all(checks.values()), 0.2, "", {"checks": checks, "p_value": p, **evidence},
                     fitted=object(), replaces_model=effect in ("base", "restoring-force"))


FAILED_BLOCKS = {"gain_over_10pct": True, "train_and_validation_agree": True, BLOCK_CHECK: False, "error_above_noise": True}


def test_the_level_of_each_test_makes_the_pair_of_them_a_one_percent_test():
    assert replication_level() ** 2 == pytest.approx(T.P_MAX)


def test_only_a_candidate_that_failed_the_block_test_alone_near_the_level_is_replicated():
    assert needs_replication(_candidate(FAILED_BLOCKS, 0.05))
    assert not needs_replication(_candidate(FAILED_BLOCKS, 0.2)), "validation p beyond sqrt(P_MAX): no evidence there"
    assert not needs_replication(_candidate({**FAILED_BLOCKS, "gain_over_10pct": False}, 0.05)), "another check failed"
    assert not needs_replication(_candidate({**FAILED_BLOCKS, "train_and_validation_agree": False}, 0.05))
    assert not needs_replication(_candidate({k: True for k in FAILED_BLOCKS}, 0.005)), "already significant"
    assert not needs_replication(_candidate(FAILED_BLOCKS, 0.05, effect="base"))
    assert not needs_replication(_candidate(FAILED_BLOCKS, 0.05, effect="restoring-force"))
    assert not needs_replication(_candidate(FAILED_BLOCKS, 0.05, rate_calibration={}))
    pair = _candidate({**FAILED_BLOCKS, "pair_over_each_single": True}, 0.03, effect="creep+load")
    assert needs_replication(pair), "a pair is judged by the same checks"


def test_under_no_effect_two_independent_block_tests_both_pass_the_level_about_one_time_in_a_hundred():
    """The joint level is exact only if each test's p is (close to) uniform under no effect: white
    residual differences of two models that are equally good, 400 draws of two independent records."""
    rng = np.random.default_rng(7)
    both = 0
    draws = 400
    for _ in range(draws):
        p = [block_tests(rng.normal(size=400), rng.normal(size=400)).p for _ in range(2)]
        both += max(p) < replication_level()
    # binomial(400, 0.01): mean 4, P(X >= 12) < 0.1 %
    assert both < 12, both


def test_the_reason_names_both_p_values_when_the_replication_fails():
    ev = {"checks": dict(FAILED_BLOCKS), "p_value": 0.25, "blocks_improved": [16, 20],
          "replication": {"validation_p": 0.05, "held_back_p": 0.5, "held_back_blocks_improved": [9, 20],
                          "held_back_rows": 4000, "held_back_rmse": [1.0, 0.99], "level_each": math.sqrt(T.P_MAX)}}
    reason = check_reason(BLOCK_CHECK, ev)
    assert "0.05 on validation" in reason["text"] and "0.5 on held-back training rows" in reason["text"], reason
    assert reason["measured"] == 0.25


def test_a_replication_whose_held_back_gain_is_small_names_it():
    """The held-back rows must show a gain over MIN_GAIN as validation must (clean seed 3571: a knee
    on a one-sided PI, held-back rmse 8 % lower at p 1e-4)."""
    ev = {"checks": {**FAILED_BLOCKS, BLOCK_CHECK: True, "held_back_gain_over_10pct": False}, "p_value": 0.0093,
          "replication": {"validation_p": 0.0966, "held_back_p": 1e-4, "held_back_blocks_improved": [149, 187],
                          "held_back_rows": 1876, "held_back_rmse": [0.0601, 0.0551], "level_each": 0.1}}
    reason = check_reason("held_back_gain_over_10pct", ev)
    assert reason["measured"] == pytest.approx(1 - 0.0551 / 0.0601)
    assert "held-back training rows" in reason["text"] and "8.3 %" in reason["text"], reason


def test_a_candidate_the_held_back_rows_make_significant_says_so_in_its_explanation():
    """Issue item 8: the text gives the reason of a verdict as the JSON does, for a significant one
    too: both p-values, the blocks and the joint p (the failed-check sentence covers the other way)."""
    c = _candidate(FAILED_BLOCKS, 0.05, blocks_improved=[15, 20])
    c.explanation = "drift after input changes"
    rng = np.random.default_rng(3)
    noise = rng.normal(size=4000)
    held = block_tests(noise + 0.5 * np.sign(noise), noise)  # the refit removes a clear part of the error
    assert held.p < replication_level()
    settle(c, held, 1.0, 0.7, 4000)
    assert c.significant and c.evidence["checks"][HELD_BACK_CHECK]
    assert c.evidence["p_value"] == pytest.approx(0.05**2)
    text = c.reasoned_explanation()
    assert text.startswith("drift after input changes; significant on two block tests together")
    assert "p = 0.05 on validation (15 of 20 blocks improved)" in text and "30.0 % lower" in text, text
    assert "jointly p = 0.0025" in text, text

    refused = _candidate(FAILED_BLOCKS, 0.05, blocks_improved=[15, 20])
    settle(refused, held, 1.0, 0.95, 4000)  # 5 % on the held-back rows: under MIN_GAIN
    assert not refused.significant and "significant on two" not in refused.reasoned_explanation()


def test_the_folds_hold_back_every_training_row_but_the_first_blocks_once():
    """Cross-validation over the training rows (decision 0056): each fold holds back about 1 -
    INNER_SPLIT of them in interleaved blocks, neighbouring blocks in different folds, the first
    block (where the model's memory starts) in none; rows outside training are never held back."""
    train = np.zeros(1100, bool)
    train[:1000] = True
    folds = held_back_folds(train)
    assert len(folds) == REPLICATION_FOLDS == 5
    count = np.sum(folds, axis=0)
    assert count.max() == 1 and not count[:100].any() and count[100:1000].all() and not count[1000:].any()
    assert [int(f.sum()) for f in folds] == [200, 200, 200, 200, 100]
    assert np.flatnonzero(folds[0])[[0, -1]].tolist() == [100, 699]  # blocks 1 and 6: it spans the record
    assert not any(f.any() for f in held_back_folds(np.ones(5, bool)))  # fewer rows than blocks: none
