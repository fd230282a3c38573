"""Effects that act in the same stretches, judged together (issue item 7).

Creep after each load step: refitted alone, either effect soaks up the other in training (the creep
low-pass bends to the load steps, the load gain to the drift after them) and the gain does not carry
over to validation, so judging one effect at a time finds one or neither. When no single candidate
is significant, or the best one leaves most of the error (it lowers the validation rmse by less than
PAIR_TRIGGER_GAIN), and some singles improved training clearly (training gain over MIN_GAIN) but
failed a check on the validation rows (the validation gain, the agreement or the block test),
:func:`pair_candidates` refits pairs jointly: of the top PAIR_MAX_MEMBERS singles by the better of
their training and validation gains (over MIN_GAIN; a partner may gain little in training, where
the other soaked up its share, and show its gain on validation only; significant but weak singles
included), and the single with the best validation gain when those places leave it out (decision
0048), each pair holding at least one that improved training clearly but failed, each effect in
the form its single fit chose.

A pair is judged by the same checks as a single (:func:`hilbench.diagnosis.verdict.judge`, the
joint name fitted by :func:`hilbench.diagnosis.refit.fit_effect`), plus: the members' evidence
checks as their single verdicts found them (creep's drift on holds), and the pair must lower the
validation rmse by more than MIN_GAIN below the better member's own refit (else the second effect
adds nothing). It is reported as the candidate ``a+b``; with ``--auto`` a significant pair is added
as one step (the spec gains both effects). Thresholds: :mod:`hilbench.diagnosis.thresholds`.
"""

from __future__ import annotations

from functools import partial
from itertools import combinations
from typing import Any

from hilbench import effects as E
from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.evidence import EVIDENCE_CHECKS
from hilbench.diagnosis.refit import added_parts
from hilbench.diagnosis.rows import ResidualRows
from hilbench.diagnosis.verdict import Candidate, judge, relative_gain
from hilbench.diagnosis.workers import run_tasks
from hilbench.identify.dataset import Dataset
from hilbench.identify.fitting import FitResult

#: the checks of a single verdict that say whether its gain carried over to validation
VALIDATION_CHECKS = ("gain_over_10pct", "train_and_validation_agree", "blocks_p_below_0.01")
#: evidence keys the joint name's (meaningless) residual signature adds, dropped from a pair's evidence
_JOINT_SIGNATURE_KEYS = ("corr_e_channel", "explained_by_channel", "signature")


def _single(c: Candidate) -> bool:
    """A single effect judged on the user's split (not the base or structure check, not a rate calibration, not a pair)."""
    return (c.fitted is not None and not c.replaces_model and "+" not in c.effect
            and "rate_calibration" not in c.evidence and "train_gain" in c.evidence)


def _failed_validation(c: Candidate) -> bool:
    """Not significant because a check on the validation rows failed (gain, agreement, block test)."""
    checks = c.evidence.get("checks", {})
    return not c.significant and any(k in checks and not checks[k] for k in VALIDATION_CHECKS)


def _learned_but_failed(c: Candidate) -> bool:
    """Improved training clearly but did not carry over to validation: one half of an overlapping pair."""
    return c.evidence["train_gain"] > T.MIN_GAIN and _failed_validation(c)


def should_try(cands: list[Candidate]) -> list[Candidate]:
    """The singles to pair (module docstring), best training gain first; empty when pairs are not tried."""
    singles = [c for c in cands if _single(c)]
    significant = [c for c in singles if c.significant]
    if significant and max(c.expected_gain for c in significant) >= T.PAIR_TRIGGER_GAIN:
        return []  # a single effect explains most of the error
    if not any(_learned_but_failed(c) for c in singles):
        return []
    # the partner of a soaking effect may gain little in training (the other took its share there)
    # and show its gain on validation only: rank by the better of the two gains
    members = sorted((c for c in singles if _gain(c) > T.MIN_GAIN), key=lambda c: -_gain(c))
    chosen = members[: T.PAIR_MAX_MEMBERS]
    # the single that carries over best is the likeliest real half of a pair: singles that only
    # learned training can fill the places by training gain alone and leave it out (for example an
    # even v^6 and a saturation trained 66 %, a creep bank 31 %, and the temperature ramp that
    # validated 27 % was fourth; jointly with the v^6 it validates 83 %) (decision 0048)
    carries = max(members, key=lambda c: c.expected_gain, default=None)
    if carries is not None and all(carries is not c for c in chosen) and carries.expected_gain > T.MIN_GAIN:
        chosen.append(carries)
    return chosen


def delay_partners(cands: list[Candidate], base: FitResult, noise: float) -> list[tuple[Candidate, Candidate]]:
    """The delay with every other single, when no single carries over any of an error that stands
    far above the noise (whether or not the usual rule pairs others): no single lowers the validation
    rmse by MIN_GAIN, and it exceeds WRONG_BASE_NOISE_FACTOR noise floors (the same "far from the
    data" as the base check's). A dead time in the drive moves where every other effect acts: an effect acting at fast
    transitions (velocity damping at slewed steps) cannot fit where its output lands samples early,
    and a delay alone cannot make the transitions' error, so neither single learns anything, even
    training (for example an amplifier delay of 3 samples and a damping: every single
    within 2 % of the base, 24 um on validation with a 0.07 um noise floor; jointly 0.60 um;
    decision 0051). Empty otherwise."""
    singles = [c for c in cands if _single(c)]
    delay = next((c for c in singles if c.effect == "delay"), None)
    if delay is None or any(c.expected_gain > T.MIN_GAIN for c in singles):
        return []
    if not base.metrics["validation"]["rmse"] > T.WRONG_BASE_NOISE_FACTOR * noise:
        return []
    return [(delay, c) for c in singles if c is not delay]


def _gain(c: Candidate) -> float:
    """The better of a single's training and validation gains."""
    return max(c.evidence["train_gain"], c.expected_gain)


def _member_json(c: Candidate) -> dict[str, Any]:
    ev = c.evidence
    return {"spec": c.spec, "significant": c.significant, "expected_gain": c.expected_gain,
            "train_gain": ev["train_gain"], "validation_rmse": ev["validation_rmse"],
            "failed": sorted(k for k, v in ev.get("checks", {}).items() if not v)}


def judge_pair(paths: Any, base: FitResult, a: Candidate, b: Candidate, rows: ResidualRows, noise: float,
               kw: dict[str, Any]) -> Candidate:
    """Refit ``base`` with both effects, each in the form its single refit chose, and judge the pair."""
    joint = "+".join([*added_parts(base.spec, a.spec, a.effect), *added_parts(base.spec, b.spec, b.effect)])
    # the joint name has no registry entry of its own: judge's residual signature for it is the
    # (absent) channel's, all zeros, and is dropped; the members' signatures are checked below
    c = judge(paths, base, joint, rows, noise, kw)
    for key in _JOINT_SIGNATURE_KEYS:
        c.evidence.pop(key, None)
    checks = c.evidence["checks"]
    for m in (a, b):  # a member's physical signature, as its single verdict found it in the residual
        rule = E.effect(m.effect).evidence_check
        if rule is not None and EVIDENCE_CHECKS[rule].key in m.evidence.get("checks", {}):
            checks[EVIDENCE_CHECKS[rule].key] = bool(m.evidence["checks"][EVIDENCE_CHECKS[rule].key])
    new_v = c.evidence["validation_rmse"][1]
    best_member = min(a.evidence["validation_rmse"][1], b.evidence["validation_rmse"][1])
    over = relative_gain(best_member, new_v)
    checks["pair_over_each_single"] = over > T.MIN_GAIN
    old_v = c.evidence["validation_rmse"][0]
    gain, gain_t = c.expected_gain, c.evidence["train_gain"]

    def alone(m: Candidate) -> str:
        return (f"{m.effect} alone {-100 * m.expected_gain:+.2g} % on validation, "
                f"{-100 * m.evidence['train_gain']:+.2g} % in training")

    lone = "neither carries over alone" if not (a.significant or b.significant) else \
        f"alone only {a.effect if a.significant else b.effect} carries over, and leaves most of the error"
    sentence = (f"{a.effect} and {b.effect} act together: refitted jointly ({c.spec}) they change the validation "
                f"rmse by {-100 * gain:+.2g} % ({old_v:.4g} -> {new_v:.4g}) and training by {-100 * gain_t:+.2g} %, "
                f"while {lone} ({alone(a)}; {alone(b)})")
    c.effect = f"{a.effect}+{b.effect}"
    c.explanation = sentence
    c.significant = all(checks.values())
    c.evidence.update({"pair": [a.effect, b.effect], "members": {m.effect: _member_json(m) for m in (a, b)},
                       "gain_over_best_single": over})
    return c


def pairs_to_try(cands: list[Candidate], base: FitResult, noise: float) -> list[list[Candidate]]:
    """The pairs to refit jointly: of :func:`should_try`'s members, those holding one that learned
    training and failed on validation; and the delay with every other single when
    :func:`delay_partners` calls for it, whether or not the usual rule pairs others (a single that
    learned training and failed, a frequency gain's polynomial bending to the lagged loops, calls
    for the usual pairs, yet as long as the drive's dead time is missing no partner of it carries
    over; for example a frequency gain and a sensor delay: every single within 5 % of the
    base at 56 noise floors, the two jointly 80 % lower; decision 0056). Members keep the order of
    ``cands`` (the registry's); no pair twice."""
    members = should_try(cands)
    order = {id(c): k for k, c in enumerate(cands)}
    pairs: list[list[Candidate]] = []
    for a, b in combinations(members, 2):
        if _learned_but_failed(a) or _learned_but_failed(b):
            pairs.append(sorted((a, b), key=lambda m: order[id(m)]))
    named = {frozenset(m.effect for m in p) for p in pairs}
    pairs += [sorted(p, key=lambda m: order[id(m)]) for p in delay_partners(cands, base, noise)
              if frozenset(m.effect for m in p) not in named]
    return pairs


def pair_candidates(paths: Dataset, base: FitResult, cands: list[Candidate], rows: ResidualRows, noise: float,
                    kw: dict[str, Any], jobs: int = 1) -> list[Candidate]:
    """Pairs of overlapping effects judged jointly, when the singles call for it (module docstring,
    :func:`pairs_to_try`). The pairs' refits run in up to ``jobs`` processes
    (:mod:`hilbench.diagnosis.workers`)."""
    pairs = pairs_to_try(cands, base, noise)
    return run_tasks([partial(judge_pair, paths, base, a, b, rows, noise, kw) for a, b in pairs], jobs,
                     shared=paths.runs)
