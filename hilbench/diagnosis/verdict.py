"""The verdict on a candidate effect: refit with it and judge the change (their order: :mod:`hilbench.diagnosis.ranking`).

An effect is significant when (a) the validation rmse drops by more than MIN_GAIN, (b) training
improves too and the two relative gains agree (neither an artefact of more parameters nor chance
extrapolation), (c) the block tests of :func:`hilbench.diagnosis.significance.improvement_test` on
the squared-error differences of contiguous validation blocks (a gain spread over the record or
concentrated in a few stretches) give p < P_MAX, (d) the current validation error holds model error
above the sensor noise, beyond the noise floor's own uncertainty (:func:`error_above_noise`), and (e)
the effect's evidence check, if its registry entry names one, holds. Thresholds: :mod:`hilbench.diagnosis.thresholds`.

Every verdict gives its reason: ``evidence["failed_checks"]`` of :meth:`Candidate.to_json` lists each failed check with what was
measured, what was required and a sentence (:func:`failed_checks`), and the explanation of a
candidate that is not significant ends with the first failed check's sentence.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hilbench import effects as E
from hilbench.diagnosis import confusable
from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.evidence import (
    EVIDENCE_CHECKS,
    SLOW_SIGNATURES,
    explain,
    slow_sentence,
    slow_signatures,
)
from hilbench.diagnosis.rate_calibration import RatePlan
from hilbench.diagnosis.refit import fit_effect
from hilbench.diagnosis.rows import ResidualRows, residual_errors
from hilbench.diagnosis.significance import improvement_test
from hilbench.diagnosis.testability import channel_reach
from hilbench.identify.fitting import FitResult


@dataclass
class Candidate:
    effect: str
    spec: str
    significant: bool
    expected_gain: float
    explanation: str
    evidence: dict[str, Any]
    fitted: FitResult | None = field(default=None, repr=False)  # the refit, reused by --auto
    unit: str = field(default="", repr=False)  # the output's unit, for the reasons' text
    #: the spec replaces the model (another base, another structure) instead of adding one effect
    #: to it: never paired, reordered by the tie rules nor replicated
    replaces_model: bool = field(default=False, repr=False)

    def failed_checks(self) -> list[dict[str, Any]]:
        """Why the verdict is what it is: :func:`failed_checks` of the checks as they stand now (a
        caller may add checks after judging, e.g. a pair's)."""
        return failed_checks(self.evidence, self.unit)

    def reasoned_explanation(self) -> str:
        """The explanation; when not significant, ending with the first failed check's sentence."""
        failed = self.failed_checks()
        if self.significant or not failed or self.explanation.endswith(failed[0]["text"]):
            return self.explanation
        return f"{self.explanation}; not significant: {failed[0]['text']}"

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.effect, "significant": self.significant, "expected_gain": self.expected_gain,
                "explanation": self.reasoned_explanation(),
                "evidence": {**self.evidence, "failed_checks": self.failed_checks()}}


def validation_errors(result: FitResult, keys: Sequence[str] | None = None) -> np.ndarray:
    """Model minus measured on the validation rows (of the runs ``keys``, default all), output unit."""
    return np.concatenate([(r.simulated - r.data.output)[r.validation & np.isfinite(r.data.output)]
                           for r in result.runs if r.validation.any() and r.simulated is not None
                           and r.simulated.size and (keys is None or r.key in keys)])


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


def relative_gain(old: float, new: float) -> float:
    return 1.0 - new / old if old > 0 else 0.0


def model_error_gain(old: float, new: float, noise: float = 0.0, uncertainty: float = 0.0) -> float:
    """Relative gain of the model's error above the sensor's noise (rmse ``old`` -> ``new``, noise
    std ``noise``, all output unit): the mean square removed, old^2 - new^2, over the mean square
    above the noise, old^2 - noise^2, as a relative rms gain 1 - sqrt(1 - that fraction).

    No model removes sensor noise, so rows whose error is mostly noise show a small relative rmse
    gain whatever the model learned there (a load effect, for example, removed 40 % of the
    training's mean square above the noise, 6.6 % of its rmse). Only where the excess is known: it
    must exceed ``uncertainty`` x noise^2 (:meth:`hilbench.diagnosis.noise.NoiseFloor.variance_uncertainty`).
    Rows whose excess is within the floor's own uncertainty cannot tell what a refit learned from
    noise and show the plain relative gain (a clean rig 1.07x the floor in training, u =
    0.28: a saturation refit removed 27 % of the uncertainty band there and 34 % of validation's
    rmse, a wrong base's shape, not an effect). With no noise this is :func:`relative_gain`."""
    if not old > 0:
        return 0.0
    excess = old * old - noise * noise
    if not math.isfinite(uncertainty) or not excess > uncertainty * noise * noise:
        return relative_gain(old, new)  # the floor not known, or the rows within its uncertainty
    fraction = min((old * old - new * new) / excess, 1.0)
    return 1.0 - math.sqrt(1.0 - fraction)


def noise_band(noise: float, uncertainty: float) -> float:
    """The rmse (output unit) up to which an error may be the sensor's noise alone: the floor's mean
    square widened by its own variance uncertainty, at most by the NOISE_FACTOR band when the floor
    is less certain than that or its uncertainty unknown (docs/decisions/0045)."""
    widen = T.NOISE_FACTOR**2 - 1.0
    if math.isfinite(uncertainty) and uncertainty >= 0.0:
        widen = min(uncertainty, widen)
    return float(noise) * math.sqrt(1.0 + widen)


def error_above_noise(old: float, noise: float, uncertainty: float) -> bool:
    """Does a validation rmse ``old`` hold model error above the sensor noise? Its mean square must
    exceed the floor's by more than the floor's own variance uncertainty (:func:`noise_band`).

    A fixed NOISE_FACTOR x the floor refused errors of 1.2-1.4x a well-known floor, where a refit
    took the error down to the floor with p = 1e-4 (a resonance and a lag, 0.5 and 0.9 of the noise
    variance above a floor known to 0.1-0.3 of it). That excess is model error whenever the floor is
    known better than that; when it is not, the excess may be the floor's error and the band stays."""
    return float(old) > noise_band(noise, uncertainty)


def explained_power(old: float, new: float) -> float:
    """The mean square a refit explained: old rmse^2 - new rmse^2 (output unit^2)."""
    return old * old - new * new


def change_explained(e_old: np.ndarray, e_new: np.ndarray) -> float:
    """On these rows, the mean square a refit removed over the mean square of its change
    (``e_old - e_new``, what the refit moved the simulation by): 1 when the change is exactly error
    it removes, above 1 when it removes part of a larger error in the same direction, -1 when the
    change is unrelated to the error (it only adds its own power). NaN when nothing changed."""
    e_old, e_new = np.asarray(e_old, float), np.asarray(e_new, float)
    ok = np.isfinite(e_old) & np.isfinite(e_new)
    change = float(np.mean((e_old[ok] - e_new[ok]) ** 2)) if ok.any() else 0.0
    if not change > 0:
        return math.nan
    return float(np.mean(e_old[ok] ** 2) - np.mean(e_new[ok] ** 2)) / change


def gains_agree(first: Sequence[float], second: Sequence[float], carried: float = math.nan, reach: float = 1.0,
                noise: float = 0.0, uncertainty: float = 0.0) -> bool:
    """Whether a gain learned on ``first`` (old, new rmse: training) holds on ``second`` (validation):
    the first improved, the second gain is not a small fraction of the first (AGREE_VALIDATION_OVER_TRAIN)
    in relative rmse or in explained mean square, or the refit's change on the second rows is mostly
    error it removes (``carried``, :func:`change_explained`, at least AGREE_CHANGE_EXPLAINED); and the
    first is not a small fraction of the second (AGREE_TRAIN_OVER_VALIDATION) in relative rmse.

    Relative gains on validation are diluted by error the effect has nothing to do with: a second
    missing effect that acts on the validation rows (a temperature ramp in the test run) leaves the
    error it causes there, so a resonance explaining 95 % of training's rmse lowers validation's by
    30 % while removing about half as much mean square there as in training (17.0 against 9.1 um^2).
    Another error adds its mean square and does not change what the effect removes, so agreement in
    explained power is not diluted, while an effect that learned the training rows only (more
    parameters) removes little mean square on validation.

    Both fall short when the validation rows hold less of the effect than training's: a resonance rung
    by the training's steps, on validation rows the drive barely excites (in one such case 80 % of
    training's rmse, 17 % of validation's). What still tells a learned effect from a fitted one is
    where the refit moves the simulation on rows it never saw: towards the data (the change is error it removes,
    about 1) or anywhere (a change unrelated to the error adds its own power, about -1). Decision 0033.

    The converse is not admitted: a small training gain with a large validation gain is what a
    refit that changed the base's extrapolation produces, and explained power is no guard there,
    since a base's errors beyond its training rows are usually larger than on them (for example a
    knee explaining 11 % of training and 77 % of validation, 1.1 against 2.3 um^2, on a rig whose
    hidden effects were creep and load). Decision 0030.

    Except by what a measured channel shows: an effect that follows a recorded channel acts in
    proportion to the channel's excursion, so where the validation rows take it ``reach`` times
    further than the training rows (:func:`hilbench.diagnosis.testability.channel_reach`) the
    training gain needs only 1/``reach`` of the fraction. Decision 0042.

    And the converse compares what each set of rows can show: the gains of the model's error above
    the sensor's noise (``noise``, its variance known to ``uncertainty``; :func:`model_error_gain`),
    since training rows whose error is mostly noise cannot show a large relative gain. Decision 0044."""
    learned, gain = relative_gain(*first[:2]), relative_gain(*second[:2])
    if not learned > 0:
        return False
    learned_model = model_error_gain(first[0], first[1], noise, uncertainty)
    gain_model = model_error_gain(second[0], second[1], noise, uncertainty)
    if learned_model < T.AGREE_TRAIN_OVER_VALIDATION * gain_model / max(reach, 1.0):
        return False
    powered = explained_power(*second[:2]) >= T.AGREE_VALIDATION_OVER_TRAIN * explained_power(*first[:2])
    towards = carried >= T.AGREE_CHANGE_EXPLAINED  # False for NaN
    return gain >= T.AGREE_VALIDATION_OVER_TRAIN * learned or powered or towards


def _pct(x: float) -> str:
    return f"{100 * abs(x):.2g} %"


def _change(name: str, gain: float) -> str:
    """'validation rmse fell 6.2 %' / 'rose 3 %' for a relative gain (a fraction, > 0 = lower error)."""
    if not math.isfinite(gain):
        return f"{name} rmse could not be compared"
    if abs(gain) < 5e-5:
        return f"{name} rmse did not change"
    return f"{name} rmse {'fell' if gain > 0 else 'rose'} {_pct(gain)}"


def _short_of_fall(gain: float) -> str:
    """What a gain below MIN_GAIN misses: 'less than the 10 % required' reads wrong after a rise."""
    if math.isfinite(gain) and gain > 0:
        return f"less than the {100 * T.MIN_GAIN:g} % required"
    return f"where a fall of {100 * T.MIN_GAIN:g} % is required"


def check_reason(key: str, ev: dict[str, Any], unit: str = "") -> dict[str, Any]:
    """Why check ``key`` failed, from a verdict's evidence: ``{"check", "measured", "required",
    "text"}``. ``measured`` is a number (or a dict of numbers), ``required`` the condition on it as
    text; gains are fractions of the rmse (> 0: lower error)."""
    u = f" {unit}" if unit else ""
    old_v, new_v = (ev.get("confirmation_rmse") or ev.get("validation_rmse") or [math.nan, math.nan])[:2]
    gain = relative_gain(old_v, new_v)
    if key == "gain_over_10pct":
        where = "validation at the confirming rates" if "confirmation_rmse" in ev else "validation"
        return {"check": key, "measured": gain, "required": f"> {T.MIN_GAIN:g}",
                "text": f"{_change(where, gain)}, {_short_of_fall(gain)}"}
    if key in ("train_and_validation_agree", "calibration_and_confirmation_agree"):
        calibrated = key.startswith("calibration")
        first, second = ("calibration", "confirmation") if calibrated else ("training", "validation")
        pair = ev.get("calibration_rmse") if calibrated else ev.get("train_rmse")
        learned = relative_gain(*pair[:2]) if pair else math.nan
        measured = {f"{first}_gain": learned, f"{second}_gain": gain}
        required = (f"{first}_gain > 0, {second}_gain >= {T.AGREE_VALIDATION_OVER_TRAIN:g} x {first}_gain, "
                    f"{first}_gain >= {T.AGREE_TRAIN_OVER_VALIDATION:g} x {second}_gain")
        p1 = explained_power(*pair[:2]) if pair else math.nan
        p2 = explained_power(old_v, new_v)
        carried = float(ev.get("change_explained", math.nan))
        measured.update({f"{first}_explained_ms": p1, f"{second}_explained_ms": p2})
        if math.isfinite(carried):
            measured[f"{second}_change_explained"] = carried
        required += (f" (the {second} gain in relative rmse or in explained mean square, or {second}_change_explained"
                     f" >= {T.AGREE_CHANGE_EXPLAINED:g})")
        sq = f" {unit}^2" if unit else ""
        power = f"; in mean square {p2:.3g} against {p1:.3g}{sq}"
        if math.isfinite(carried):
            power += f"; of the refit's change on {second} rows {carried:.2g}x is error removed"
        if not learned > 0:
            text = f"{_change(first, learned)} while {_change(second, gain)}: a gain on {second} only is chance"
        elif gain < T.AGREE_VALIDATION_OVER_TRAIN * learned:
            text = (f"{_change(second, gain)} against {_pct(learned)} on {first}{power}, less than the "
                    f"{T.AGREE_VALIDATION_OVER_TRAIN:g}x of it required: more parameters, not physics")
        else:
            reach = float(ev.get("channel_reach", 1.0))
            fraction = f"{T.AGREE_TRAIN_OVER_VALIDATION / reach:.2g}x of it required (the channel reaches {reach:.2g}x " \
                       "further on validation)" if reach > 1.0 else f"{T.AGREE_TRAIN_OVER_VALIDATION:g}x of it required"
            model = ev.get("model_error_gains") or {}
            if model and model.get("noise_variance_uncertainty") is not None:
                text = (f"the {first} error above the sensor noise fell {_pct(model['first'])} against "
                        f"{_pct(model['second'])} on {second}, less than the {fraction}: chance extrapolation")
            else:
                text = (f"{_change(first, learned)} against {_pct(gain)} on {second}, less than the "
                        f"{fraction}: chance extrapolation")
        return {"check": key, "measured": measured, "required": required, "text": text}
    if key == "blocks_p_below_0.01":
        p = float(ev.get("p_value", math.nan))
        better, blocks = (ev.get("blocks_improved") or [0, 0])[:2]
        rep = ev.get("replication")
        if rep:  # decision 0052: the validation p and the held-back training p, each to reach sqrt(P_MAX)
            hb, hn = rep["held_back_blocks_improved"][:2]
            return {"check": key, "measured": p, "required": f"< {T.P_MAX:g}",
                    "text": f"the block test gives p = {rep['validation_p']:.2g} on validation ({better} of {blocks} "
                            f"blocks improved) and {rep['held_back_p']:.2g} on held-back training rows ({hb} of {hn}), "
                            f"not both below the {rep['level_each']:.2g} that makes them significant together"}
        return {"check": key, "measured": p, "required": f"< {T.P_MAX:g}",
                "text": f"the block test gives p = {p:.2g} ({better} of {blocks} validation blocks improved), "
                        f"not below the {T.P_MAX:g} required"}
    if key == "held_back_gain_over_10pct":  # decision 0052
        old_h, new_h = (ev.get("replication") or {}).get("held_back_rmse") or [math.nan, math.nan]
        g = relative_gain(old_h, new_h)
        return {"check": key, "measured": g, "required": f"> {T.MIN_GAIN:g}",
                "text": f"{_change('on the held-back training rows the', g)}, {_short_of_fall(g)}"}
    if key == "error_above_noise":
        noise = float(ev.get("noise_floor", math.nan))
        ratio = old_v / noise if noise > 0 else math.inf
        band = float(ev.get("noise_band", T.NOISE_FACTOR * noise))
        need = band / noise if noise > 0 else T.NOISE_FACTOR
        return {"check": key, "measured": ratio, "required": f"> {need:.3g}",
                "text": f"the current error ({old_v:.3g}{u} rms) is {ratio:.3g}x the sensor noise floor "
                        f"({noise:.3g}{u}), within the {need:.3g}x the floor's own uncertainty allows: "
                        "nothing left to explain"}
    if key == "training_not_worse":
        old_t, new_t = (ev.get("train_rmse") or [math.nan, math.nan])[:2]
        worse = new_t / old_t - 1.0 if old_t > 0 else math.nan
        return {"check": key, "measured": worse, "required": f"<= {T.TRAINING_WORSE_TOLERANCE:g}",
                "text": f"training rmse rose {_pct(worse)} with the calibrated shape, more than the "
                        f"{100 * T.TRAINING_WORSE_TOLERANCE:g} % allowed"}
    if key == "training_cost_small":
        old_t, new_t = (ev.get("train_rmse") or [math.nan, math.nan])[:2]
        worse = new_t / old_t - 1.0 if old_t > 0 else math.nan
        return {"check": key, "measured": {"training_rise": worse, "validation_gain": gain},
                "required": f"training_rise <= {T.AGREE_TRAIN_OVER_VALIDATION:g} x validation_gain",
                "text": f"training rmse rose {_pct(worse)} with the shape of the power-on step, more than "
                        f"{T.AGREE_TRAIN_OVER_VALIDATION:g}x the {_pct(gain)} validation gain: the training rows "
                        "contradict it"}
    if key == "drift_on_holds":
        drift = float(ev.get("drift_over_rms", math.nan))
        z, removed = float(ev.get("drift_over_noise", math.nan)), float(ev.get("drift_removed", math.nan))
        required = (f"drift_over_noise >= {T.CREEP_MIN_DRIFT_OVER_NOISE:g}, and drift_over_rms >= "
                    f"{T.CREEP_MIN_DRIFT:g} or drift_removed >= {T.CREEP_MIN_DRIFT_REMOVED:g}")
        if not math.isfinite(drift):  # carried over from a member's verdict (a pair)
            return {"check": key, "measured": None, "required": required,
                    "text": "the residual does not drift along holds as creep's signature needs"}
        if math.isfinite(z) and z < T.CREEP_MIN_DRIFT_OVER_NOISE and drift >= T.CREEP_MIN_DRIFT:
            text = (f"the residual drifts along holds by {drift:.2g}x its rms but only {z:.2g}x the noise's "
                    f"standard error on a drift, less than the {T.CREEP_MIN_DRIFT_OVER_NOISE:g}x creep's signature needs")
            return {"check": key, "measured": {"drift_over_rms": drift, "drift_over_noise": z, "drift_removed": removed},
                    "required": required, "text": text}
        text = (f"the residual drifts along holds by {drift:.2g}x its rms, less than the {T.CREEP_MIN_DRIFT:g}x "
                "creep's signature needs")
        if math.isfinite(z) and z < T.CREEP_MIN_DRIFT_OVER_NOISE:
            text += (f", and by {z:.2g}x the noise's standard error on a drift, less than the "
                     f"{T.CREEP_MIN_DRIFT_OVER_NOISE:g}x that could stand for it")
        elif math.isfinite(removed):
            text += (f"; creep's refit removes {100 * removed:.2g} % of that drift, less than the "
                     f"{100 * T.CREEP_MIN_DRIFT_REMOVED:g} % that could stand for it")
        return {"check": key, "measured": {"drift_over_rms": drift, "drift_over_noise": z, "drift_removed": removed},
                "required": required, "text": text}
    other = str(ev.get("replacement", "the other base"))  # the wrong-base and the structure checks
    if key.startswith("validation_") and key.endswith("x_lower"):  # the wrong-base check
        ratio = old_v / new_v if new_v > 0 else math.inf
        return {"check": key, "measured": ratio, "required": f">= {T.WRONG_BASE_RATIO:g}",
                "text": f"{other} lowers the validation rmse {ratio:.2g}x, less than the "
                        f"{T.WRONG_BASE_RATIO:g}x required"}
    if key.endswith("x_lower_than_any_effect") and "best_effect_rmse" in ev:  # the wrong-base check
        best = float(ev["best_effect_rmse"])
        ratio = best / new_v if new_v > 0 else math.inf
        return {"check": key, "measured": ratio, "required": f">= {T.WRONG_BASE_RATIO:g}",
                "text": f"the best single effect's validation rmse ({best:.3g}{u}) is {ratio:.2g}x {other}'s "
                        f"({new_v:.3g}{u}), less than the {T.WRONG_BASE_RATIO:g}x required"}
    if key == "fit_healthy":  # the structure check: its free run or weights flagged (hilbench.identify.health)
        reasons = (ev.get("health") or {}).get("reasons") or []
        return {"check": key, "measured": reasons, "required": "no health flag",
                "text": f"{other}'s fit is flagged: {reasons[0] if reasons else 'see its health'}"}
    if "x_lower_than_a_finer_" in key and "finer_base" in ev:  # the wrong-base check on a finer current base
        finer = float(ev["finer_base"]["validation_rmse"])
        ratio = finer / new_v if new_v > 0 else math.inf
        return {"check": key, "measured": ratio, "required": f">= {T.WRONG_BASE_RATIO:g}",
                "text": f"the current family at a finer resolution ({ev['finer_base']['spec']}) validates at "
                        f"{finer:.3g}{u}, {ratio:.2g}x the other base's ({new_v:.3g}{u}), less than the "
                        f"{T.WRONG_BASE_RATIO:g}x required: the lead is the current base's resolution"}
    if key == "pair_over_each_single" and "gain_over_best_single" in ev:  # a pair of effects
        over = float(ev["gain_over_best_single"])
        return {"check": key, "measured": over, "required": f"> {T.MIN_GAIN:g}",
                "text": f"the pair's validation rmse is {_pct(over)} {'below' if over > 0 else 'above'} the best single "
                        f"effect's, less than the {100 * T.MIN_GAIN:g} % required"}
    if key == "training_lower_too":
        old_t, new_t = (ev.get("train_rmse") or [math.nan, math.nan])[:2]
        g = relative_gain(old_t, new_t)
        return {"check": key, "measured": g, "required": "> 0", "text": f"{_change('training', g)}, where it must fall"}
    return {"check": key, "measured": None, "required": "true", "text": f"the check {key} does not hold"}


def failed_checks(ev: dict[str, Any], unit: str = "") -> list[dict[str, Any]]:
    """:func:`check_reason` of every failed check of ``ev["checks"]``, in the order they were checked."""
    return [check_reason(k, ev, unit) for k, ok in (ev.get("checks") or {}).items() if not ok]


def judge(paths: Any, base: FitResult, effect: str, rows: ResidualRows, noise: float, kw: dict[str, Any],
         plan: RatePlan | None = None) -> Candidate:
    """Refit with ``effect`` and judge it (module docstring). With a rate ``plan`` the gain is
    measured on the confirming runs and must agree with the calibrating runs' instead of training's."""
    return verdict(base, effect, fit_effect(paths, base, effect, kw, plan), rows, noise, plan)


def verdict(base: FitResult, effect: str, new: FitResult, rows: ResidualRows, noise: float,
            plan: RatePlan | None = None) -> Candidate:
    """Judge ``new``, a refit with ``effect``, against ``base`` (module docstring; :func:`judge`)."""
    old_v, new_v = base.metrics["validation"]["rmse"], new.metrics["validation"]["rmse"]
    old_t, new_t = base.metrics["train"]["rmse"], new.metrics["train"]["rmse"]
    gain_t = relative_gain(old_t, new_t)
    extra: dict[str, Any] = {}
    if plan is None:
        gain, learned = relative_gain(old_v, new_v), gain_t
        e_old, e_new = validation_errors(base), validation_errors(new)
        agree = "train_and_validation_agree"
    elif plan.step is not None:
        # the shape comes from the power-on step, which no fit saw: every validation run confirms it
        e_old, e_new = validation_errors(base, plan.confirm), validation_errors(new, plan.confirm)
        gain, learned = relative_gain(rms(e_old), rms(e_new)), gain_t
        agree = ""
        extra = {"rate_calibration": plan.to_json(), "confirmation_rmse": [rms(e_old), rms(e_new)]}
    else:
        e_old, e_new = validation_errors(base, plan.confirm), validation_errors(new, plan.confirm)
        c_old, c_new = rms(validation_errors(base, plan.calibrate)), rms(validation_errors(new, plan.calibrate))
        gain, learned = relative_gain(rms(e_old), rms(e_new)), relative_gain(c_old, c_new)
        agree = "calibration_and_confirmation_agree"
        extra = {"rate_calibration": plan.to_json(), "confirmation_rmse": [rms(e_old), rms(e_new)],
                 "calibration_rmse": [c_old, c_new], "calibration_gain": learned}
    p, better, blocks = improvement_test(e_old, e_new)
    uncertainty = noise.variance_uncertainty() if hasattr(noise, "variance_uncertainty") else math.inf
    checks = {"gain_over_10pct": gain > T.MIN_GAIN}
    if agree:
        # a real effect is learned from one set of rows and holds on unseen rows: neither gain may
        # be a small fraction of the other (a gain on validation only is chance extrapolation)
        first = extra["calibration_rmse"] if plan is not None else [old_t, new_t]
        second = extra["confirmation_rmse"] if plan is not None else [old_v, new_v]
        carried = change_explained(e_old, e_new)
        extra["change_explained"] = carried
        reach = channel_reach(base, effect) if plan is None and effect not in E.EFFECTS else 1.0
        if reach > 1.0:
            extra["channel_reach"] = reach
        extra["model_error_gains"] = {"first": model_error_gain(first[0], first[1], noise, uncertainty),
                                      "second": model_error_gain(second[0], second[1], noise, uncertainty),
                                      "noise_variance_uncertainty": uncertainty if math.isfinite(uncertainty) else None}
        checks[agree] = gains_agree(first, second, carried, reach, noise, uncertainty)
    checks["blocks_p_below_0.01"] = p < T.P_MAX
    checks["error_above_noise"] = error_above_noise(rms(e_old), noise, uncertainty)
    extra["noise_band"] = noise_band(noise, uncertainty)
    if plan is not None and plan.step is not None:
        # At one drive rate the training fit absorbs a lag into the loop width, so a lag fixed from
        # the step may cost training a little; the training rows may not object by more than the
        # agreement ratio of the validation gain (what they would have to show to count as learning it).
        checks["training_cost_small"] = -gain_t <= T.AGREE_TRAIN_OVER_VALIDATION * gain
    elif plan is not None:
        checks["training_not_worse"] = new_t <= old_t * (1.0 + T.TRAINING_WORSE_TOLERANCE)
    sentence, evidence = explain(effect, rows)
    # what tells this effect from its look-alike, if it has one (issue 62): reported, and the ranking's
    evidence.update(confusable.signature(effect, rows))
    sentence += confusable.sentence(effect, evidence, base.output_unit)
    signature = E.effect(effect).signature
    check = E.effect(effect).evidence_check
    refit_e = residual_errors(new, "all") if check is not None or signature in SLOW_SIGNATURES else None
    if signature in SLOW_SIGNATURES:
        # what the refit leaves of creep's drift and of the channels' traces (issue 62): reported
        evidence["slow_signatures"] = slow_signatures(rows, refit_e, float(noise))
        sentence += slow_sentence(effect, evidence["slow_signatures"], base.output_unit)
    if check is not None:
        rule = EVIDENCE_CHECKS[check]
        if rule.after_refit is not None:
            evidence.update(rule.after_refit(rows, refit_e, float(noise)))
        checks[rule.key] = rule.holds(evidence)
        if checks[rule.key] and not all(checks.values()):
            # the physical signature is there; say so, since the refit's verdict alone would hide it
            sentence += (f"; {rule.present}, but adding {effect} alone changes the validation error by "
                         f"{-100 * gain:+.2g} %: another missing effect may mask it")
    if plan is not None:
        sentence += (f"; calibrated on {plan.calibrated_by}, it changes the error at "
                     f"{'/'.join(f'{f:.3g}' for f in plan.confirm_hz)} Hz by {-100 * gain:+.2g} %")
    evidence = {
        "validation_rmse": [old_v, new_v], "train_rmse": [old_t, new_t], "train_gain": gain_t,
        "p_value": p, "blocks_improved": [better, blocks], "noise_floor": noise, "checks": checks,
        "spec": new.spec, **extra, **evidence,
    }
    if hasattr(noise, "estimates"):  # how the floor was estimated (the old residual-based one among them)
        evidence["noise_floor_estimates"] = dict(noise.estimates)
    return Candidate(effect, new.spec, all(checks.values()), gain, sentence, evidence, fitted=new,
                     unit=base.output_unit)
