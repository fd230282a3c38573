"""The verdict on a candidate effect: refit with it, judge the change, rank the candidates.

An effect is significant when (a) the validation rmse drops by more than MIN_GAIN, (b) training
improves too and the two relative gains agree (neither an artefact of more parameters nor chance
extrapolation), (c) a one-sided Wilcoxon signed-rank test on the per-block squared-error
differences of N_BLOCKS contiguous validation blocks gives p < P_MAX, (d) the current validation
error is above NOISE_FACTOR times the noise floor, and (e) the effect's evidence check, if its
registry entry names one, holds. Thresholds: :mod:`hilbench.diagnosis.thresholds`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from hilbench import effects as E
from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.evidence import EVIDENCE_CHECKS, explain
from hilbench.diagnosis.rate_calibration import RatePlan
from hilbench.diagnosis.refit import fit_effect
from hilbench.diagnosis.rows import ResidualRows
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

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.effect, "significant": self.significant, "expected_gain": self.expected_gain,
                "explanation": self.explanation, "evidence": self.evidence}


def validation_errors(result: FitResult, keys: Sequence[str] | None = None) -> np.ndarray:
    """Model minus measured on the validation rows (of the runs ``keys``, default all), output unit."""
    return np.concatenate([(r.simulated - r.data.output)[r.validation & np.isfinite(r.data.output)]
                           for r in result.runs if r.validation.any() and r.simulated is not None
                           and r.simulated.size and (keys is None or r.key in keys)])


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


def relative_gain(old: float, new: float) -> float:
    return 1.0 - new / old if old > 0 else 0.0


def block_test(e_old: np.ndarray, e_new: np.ndarray, n_blocks: int = T.N_BLOCKS) -> tuple[float, int, int]:
    """One-sided Wilcoxon signed-rank p-value that the new squared error is lower, over contiguous
    blocks; and how many blocks improved, of how many."""
    blocks = [b for b in np.array_split(np.arange(e_old.size), min(n_blocks, e_old.size)) if b.size]
    d = np.array([np.mean(e_old[b] ** 2) - np.mean(e_new[b] ** 2) for b in blocks])
    if d.size < 5 or not np.any(d != 0):
        return 1.0, int(np.sum(d > 0)), int(d.size)
    p = float(stats.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue)
    return p, int(np.sum(d > 0)), int(d.size)


def judge(paths: Any, base: FitResult, effect: str, rows: ResidualRows, noise: float, kw: dict[str, Any],
         plan: RatePlan | None = None) -> Candidate:
    """Refit with ``effect`` and judge it (module docstring). With a rate ``plan`` the gain is
    measured on the confirming runs and must agree with the calibrating runs' instead of training's."""
    new = fit_effect(paths, base, effect, kw, plan)
    old_v, new_v = base.metrics["validation"]["rmse"], new.metrics["validation"]["rmse"]
    old_t, new_t = base.metrics["train"]["rmse"], new.metrics["train"]["rmse"]
    gain_t = relative_gain(old_t, new_t)
    extra: dict[str, Any] = {}
    if plan is None:
        gain, learned = relative_gain(old_v, new_v), gain_t
        e_old, e_new = validation_errors(base), validation_errors(new)
        agree = "train_and_validation_agree"
    else:
        e_old, e_new = validation_errors(base, plan.confirm), validation_errors(new, plan.confirm)
        c_old, c_new = rms(validation_errors(base, plan.calibrate)), rms(validation_errors(new, plan.calibrate))
        gain, learned = relative_gain(rms(e_old), rms(e_new)), relative_gain(c_old, c_new)
        agree = "calibration_and_confirmation_agree"
        extra = {"rate_calibration": plan.to_json(), "confirmation_rmse": [rms(e_old), rms(e_new)],
                 "calibration_rmse": [c_old, c_new], "calibration_gain": learned}
    p, better, blocks = block_test(e_old, e_new)
    checks = {
        "gain_over_10pct": gain > T.MIN_GAIN,
        # a real effect is learned from one set of rows and holds on unseen rows: neither gain may
        # be a small fraction of the other (a gain on validation only is chance extrapolation)
        agree: learned > 0 and gain >= T.AGREE_VALIDATION_OVER_TRAIN * learned
        and learned >= T.AGREE_TRAIN_OVER_VALIDATION * gain,
        "blocks_p_below_0.01": p < T.P_MAX,
        "error_above_noise": rms(e_old) > T.NOISE_FACTOR * noise,
    }
    if plan is not None:
        checks["training_not_worse"] = new_t <= old_t * (1.0 + T.TRAINING_WORSE_TOLERANCE)
    sentence, evidence = explain(effect, rows)
    check = E.effect(effect).evidence_check
    if check is not None:
        rule = EVIDENCE_CHECKS[check]
        checks[rule.key] = rule.holds(evidence)
        if checks[rule.key] and not all(checks.values()):
            # the physical signature is there; say so, since the refit's verdict alone would hide it
            sentence += (f"; {rule.present}, but adding {effect} alone changes the validation error by "
                         f"{-100 * gain:+.2g} %: another missing effect may mask it")
    if plan is not None:
        sentence += (f"; calibrated at {'/'.join(f'{f:.3g}' for f in plan.calibrate_hz)} Hz, it changes the error at "
                     f"{'/'.join(f'{f:.3g}' for f in plan.confirm_hz)} Hz by {-100 * gain:+.2g} %")
    evidence = {
        "validation_rmse": [old_v, new_v], "train_rmse": [old_t, new_t], "train_gain": gain_t,
        "p_value": p, "blocks_improved": [better, blocks], "noise_floor": noise, "checks": checks,
        "spec": new.spec, **extra, **evidence,
    }
    return Candidate(effect, new.spec, all(checks.values()), gain, sentence, evidence, fitted=new)


def rank(cands: list[Candidate]) -> None:
    """Order candidates in place: significant first, then by expected gain. When the best one's
    validation error cannot be told from another significant candidate's (block test both ways,
    p >= P_MAX) the two refits explain the data equally well, and the residual's own pattern
    decides: the candidate whose ``signature`` (fraction of the error's variance its physical
    pattern explains, e.g. even in the input for asymmetry, odd for saturation) is higher by at
    least SIGNATURE_MARGIN goes first. A cubic term mimics saturation on a bipolar drive, so
    without this asymmetry and saturation are a coin toss on saturating data."""
    cands.sort(key=lambda c: (not c.significant, -c.expected_gain))
    if not cands or not cands[0].significant or cands[0].fitted is None:
        return
    top = cands[0]
    if "signature" not in top.evidence:
        return  # no pattern to weigh against (rate-dependence, creep): gain order stands
    e_top = validation_errors(top.fitted)
    best, best_p = top, 1.0
    for c in cands[1:]:
        if not c.significant or c.fitted is None or "rate_calibration" in c.evidence or "rate_calibration" in top.evidence:
            continue
        e_c = validation_errors(c.fitted)
        if e_c.size != e_top.size:
            continue
        p_top_better, _, _ = block_test(e_c, e_top)
        if p_top_better < T.P_MAX:
            continue  # the data tell them apart: gain order stands
        if "signature" in c.evidence and c.evidence["signature"] >= best.evidence["signature"] + T.SIGNATURE_MARGIN:
            best, best_p = c, p_top_better
    if best is not top:
        cands.remove(best)
        cands.insert(0, best)
        best.evidence["ranked_by_signature"] = {
            "over": top.effect, "p_value_of_difference": best_p,
            "signatures": {top.effect: top.evidence.get("signature"), best.effect: best.evidence.get("signature")}}
        best.explanation += (f"; its validation error cannot be told from {top.effect}'s (p {best_p:.2g}) and the "
                             f"error's pattern fits {best.effect} better")
