"""Training and validation gains agree (verdict.gains_agree): in relative rmse, or on validation in
explained mean square when another missing effect dilutes the validation gain (decision 0030), or by
where the refit moves the simulation on validation rows that hold less of the effect (decision 0033).
Figures are the refits of randomized benchmark cases (old, new rmse in um)."""

from __future__ import annotations

import numpy as np
import pytest

from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.verdict import change_explained, check_reason, explained_power, gains_agree


def test_a_gain_diluted_on_validation_by_another_effect_agrees_in_explained_power():
    # seed 181: a resonance near the drive explains 95 % of training's rmse; a temperature ramp in the
    # test run leaves its own error, so validation falls 30 %, removing 9.1 of training's 17.0 um^2
    train, validation = (4.133, 0.2234), (4.226, 2.964)
    assert explained_power(*validation) >= T.AGREE_VALIDATION_OVER_TRAIN * explained_power(*train)
    assert gains_agree(train, validation)


def test_more_parameters_disagree_in_both_measures():
    # training learned, validation barely moved: neither the relative gain nor the power carried over
    assert not gains_agree((1.0, 0.3), (1.0, 0.9))
    # on a larger validation error the same power would agree (the dilution above); a third of it does not
    assert not gains_agree((1.0, 0.3), (3.0, 2.95))
    assert gains_agree((1.0, 0.3), (3.0, 2.6))


def test_a_gain_on_validation_only_stays_chance_extrapolation_whatever_the_power():
    # seed 146: a knee explains 11 % of training and 77 % of validation (1.1 against 2.3 um^2) on a rig
    # whose hidden effects are creep and load: the refit moved the base's extrapolation
    assert not gains_agree((2.247, 1.992), (1.571, 0.3608))
    assert not gains_agree((1.0, 1.01), (1.0, 0.5))  # training worse
    assert gains_agree((1.0, 0.5), (1.0, 0.6))


@pytest.mark.parametrize(("train", "validation", "words"), [
    ((1.0, 0.3), (1.0, 0.9), "more parameters, not physics"),
    ((2.247, 1.992), (1.571, 0.3608), "chance extrapolation"),
])
def test_the_reason_names_the_direction_and_the_figures(train, validation, words):
    ev = {"train_rmse": list(train), "validation_rmse": list(validation), "checks": {}}
    reason = check_reason("train_and_validation_agree", ev, "um")
    assert words in reason["text"]
    assert reason["measured"]["validation_explained_ms"] == pytest.approx(explained_power(*validation))
    assert "explained mean square" in reason["required"]


def test_the_text_output_names_each_figure_of_the_check():
    """The text summary's "also failed" part names every figure of a check with several (not a row
    of numbers joined by slashes)."""
    from hilbench.cli.summaries import _measured

    ev = {"train_rmse": [1.0, 0.3], "validation_rmse": [1.0, 0.9], "checks": {}}
    text = _measured(check_reason("train_and_validation_agree", ev)["measured"])
    assert text.startswith("training_gain=0.7, validation_gain=0.1") and "validation_explained_ms=0.19" in text


def test_change_explained_tells_a_change_towards_the_data_from_an_unrelated_one():
    rng = np.random.default_rng(0)
    e_old = rng.normal(0, 1, 20_000)
    assert change_explained(e_old, np.zeros_like(e_old)) == pytest.approx(1.0)  # the change is the error
    # a change in the error's direction, a third of it: removes more than its own power
    assert change_explained(e_old, e_old * (2 / 3)) == pytest.approx(5.0)
    # a change the error knows nothing of only adds its power
    assert change_explained(e_old, e_old + rng.normal(0, 0.3, e_old.size)) == pytest.approx(-1.0, abs=0.05)
    assert np.isnan(change_explained(e_old, e_old))  # nothing changed: no evidence either way


def test_validation_rows_that_hold_less_of_the_effect_still_confirm_it():
    # seed 149: a resonance rung by the training's steps explains 80 % of training's rmse and 17 % of
    # validation's, where the drive barely excites it: neither relative gain nor mean square carries
    # over, but on validation rows the refit's change is error it removes (2.7x its own power)
    train, validation = (0.9004, 0.1836), (0.1736, 0.1441)
    assert not gains_agree(train, validation)
    assert gains_agree(train, validation, carried=2.7)
    assert not gains_agree(train, validation, carried=-0.9)  # the change went anywhere: fitted, not learned
    assert not gains_agree((1.0, 1.01), (1.0, 0.8), carried=3.0)  # training did not learn it: still chance
    ev = {"train_rmse": list(train), "validation_rmse": list(validation), "change_explained": -0.9, "checks": {}}
    reason = check_reason("train_and_validation_agree", ev, "um")
    assert reason["measured"]["validation_change_explained"] == -0.9 and "-0.9x is error removed" in reason["text"]


def test_a_channel_that_reaches_further_on_validation_needs_less_training_gain():
    # seed 1394: a temperature gain; training ramps 20.5-25.3 degC, validation 28-43 degC. Training
    # rmse fell 3.4 % (its error is mostly noise there), validation 72 %: what the channel shows
    train, validation = (0.2283, 0.2204), (2.414, 0.6684)
    assert not gains_agree(train, validation)
    assert gains_agree(train, validation, reach=9.0)
    assert not gains_agree(train, validation, reach=2.0)  # a little further does not make up for it
    assert not gains_agree((1.0, 1.01), (1.0, 0.5), reach=100.0)  # training must still improve
    ev = {"train_rmse": list(train), "validation_rmse": list(validation), "channel_reach": 2.0}
    assert "the channel reaches 2x further on validation" in check_reason("train_and_validation_agree", ev)["text"]


def test_channel_reach_from_the_training_and_validation_rows():
    from types import SimpleNamespace

    from hilbench.diagnosis.testability import channel_reach

    rng = np.random.default_rng(0)
    n = 4000
    train = np.arange(n) < n // 2

    def result(temperature: np.ndarray) -> SimpleNamespace:
        run = SimpleNamespace(data=SimpleNamespace(aux={"temperature": temperature}), train=train, validation=~train)
        return SimpleNamespace(runs=[run])

    ramp = np.concatenate([np.linspace(20.0, 25.0, n // 2), np.linspace(28.0, 43.0, n // 2)])
    reach = channel_reach(result(ramp + rng.normal(0, 0.01, n)), "temperature")
    assert 8.0 < reach < 12.0, reach  # rms deviation from 22.5 degC: ~13 degC against 1.44
    same = np.concatenate([np.linspace(20.0, 25.0, n // 2), np.linspace(25.0, 20.0, n // 2)])
    assert channel_reach(result(same), "temperature") == pytest.approx(1.0, abs=0.01)
    # a channel that does not move in training (noise only) reaches nowhere: no coefficient was learned
    flat = np.concatenate([np.full(n // 2, 22.0), np.linspace(22.0, 40.0, n // 2)]) + rng.normal(0, 0.01, n)
    assert channel_reach(result(flat), "temperature") == 1.0
    assert channel_reach(result(ramp), "load") == 1.0  # no such channel
