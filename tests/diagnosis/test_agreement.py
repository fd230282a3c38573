"""Training and validation gains agree (verdict.gains_agree): in relative rmse, or on validation in
explained mean square when another missing effect dilutes the validation gain (decision 0030), or by
where the refit moves the simulation on validation rows that hold less of the effect (decision 0033).
Figures are the refits of randomized benchmark cases (old, new rmse in um)."""

from __future__ import annotations

import numpy as np
import pytest

from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.noise import NoiseFloor
from hilbench.diagnosis.verdict import change_explained, check_reason, explained_power, gains_agree, model_error_gain


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


def test_model_error_gain_takes_the_sensor_noise_out():
    # no noise: the relative rmse gain
    assert model_error_gain(1.0, 0.5) == pytest.approx(0.5)
    # rmse 1.25 -> 1.0 over a 0.75 noise floor: the model error 1.0 -> ~0.66 (its rms above the noise)
    assert model_error_gain(1.25, 1.0, 0.75, 0.05) == pytest.approx(1 - (1.0 - 0.5625) ** 0.5 / (1.5625 - 0.5625) ** 0.5)
    # all of the excess removed (or more: the refit fit noise): at most 1
    assert model_error_gain(1.25, 0.7, 0.75, 0.05) == pytest.approx(1.0)
    assert model_error_gain(1.0, 1.1, 0.5, 0.05) < 0  # worse stays worse
    # rows at (or under) the floor, or above it by less than the floor's own uncertainty: the excess
    # is not known, the plain relative gain
    assert model_error_gain(0.4446, 0.4439, 0.4466, 0.086) == pytest.approx(1 - 0.4439 / 0.4446)
    # seed 1740, a clean rig: training 0.1736 -> 0.1677 um over 0.1624 um, u = 0.28 (excess 0.0038 um^2
    # against a band of 0.0073 um^2): 3.4 %, and the 36 % on validation stays chance extrapolation
    assert model_error_gain(0.17364, 0.16768, 0.16239, 0.278) == pytest.approx(1 - 0.16768 / 0.17364)
    assert not gains_agree((0.17364, 0.16768), (0.81894, 0.53827), noise=0.16239, uncertainty=0.278)
    # a floor not known well enough (no spread of estimates): the plain relative gain
    assert model_error_gain(1.25, 1.0, 0.75, float("inf")) == pytest.approx(0.2)


def test_training_rows_mostly_noise_still_confirm_a_large_validation_gain():
    # seed 1518: a placed weight on a load cell; training's rmse 0.0686 -> 0.0641 um over a 0.0567 um
    # sensor floor (6.6 % of the rmse, 40 % of the mean square above the noise), validation 0.588 ->
    # 0.0597 um (90 %), the load cell reaching 1.8x further: refused as chance extrapolation before
    # decision 0044 (the model error's gains are 23 % against 97 %)
    train, validation = (0.06863, 0.06408), (0.5876, 0.05973)
    assert not gains_agree(train, validation, reach=1.8)
    assert gains_agree(train, validation, reach=1.8, noise=0.05674, uncertainty=0.068)
    # seed 1530: an output saturation, training 0.342 -> 0.307 um over 0.294 um, validation 1.0 -> 0.36 um
    assert gains_agree((0.3415, 0.3071), (0.9996, 0.3590), noise=0.2941, uncertainty=0.112)
    assert not gains_agree((0.3415, 0.3071), (0.9996, 0.3590))
    # seed 1449: training at the floor (0.4446 -> 0.4439 um under a 0.4466 um floor) shows nothing
    # the refit learned; a 23 % validation gain there stays chance extrapolation
    assert not gains_agree((0.4446, 0.4439), (45.72, 35.39), noise=0.4466, uncertainty=0.086)
    # seed 146's knee, whose training error is far above a small floor, stays refused
    assert not gains_agree((2.247, 1.992), (1.571, 0.3608), noise=0.05, uncertainty=0.05)


def test_the_noise_floor_knows_how_well_its_variance_is_known():
    floor = NoiseFloor(0.0567, {"differences_1": 0.0586, "differences_2": 0.0570, "spectrum": 0.0568,
                                "holds": 0.0567, "residual": 0.09, "chosen": "holds", "hold_samples": 7865})
    assert floor.variance_uncertainty() == pytest.approx((0.0586 / 0.0567) ** 2 - 1)  # the residual is no sensor estimate
    assert NoiseFloor(0.1, {"spectrum": 0.1}).variance_uncertainty() == float("inf")


def test_the_reason_gives_the_gains_above_the_noise_when_it_took_the_noise_out():
    ev = {"train_rmse": [0.4446, 0.4439], "validation_rmse": [45.72, 35.39], "checks": {},
          "model_error_gains": {"first": 0.016, "second": 0.23, "noise_variance_uncertainty": 0.086}}
    text = check_reason("train_and_validation_agree", ev, "um")["text"]
    assert "the training error above the sensor noise fell 1.6 % against 23 % on validation" in text
