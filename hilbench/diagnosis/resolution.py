"""The base's resolution must not choose between two effects: the leader and its closest rival are
refitted on a finer base when the leader leaves much of the training error unexplained.

A play-operator base (``pi``, ``pi1``, ``mpi``, ``pd``) places its n thresholds evenly, 10 by
default; between two of them the model's loop is straight where a real loop bends. That residual
is structured in the input, and an effect with columns in the input or in the hysteresis output
(an even term, a saturation of the output or of the drive) takes it up together with its own share.
Which of two such effects validates better can then depend on n rather than on the physics
(decision 0054's table: an even v^4 on ``pi1`` ranks behind a saturation at 10 and 20 operators and
ahead of it at 30, where the truth reaches the noise). Judging every effect on a finer base moved
as many cases one way as the other (0054); this check only asks whether the *order of the two
leaders* survives a finer base, when the data say the base's resolution may matter:

* the leader's refit still trains above the noise band (:func:`hilbench.diagnosis.verdict.noise_band`,
  the test a validation error passes to hold anything to explain: a refit at the noise has no
  structured error left for the resolution to shape), and
* the rival, the next significant single effect, validates within TIE_MEAN_SQUARE_RATIO of the
  leader's mean square (a decisive lead is not a question of resolution).

Both effects are then refitted on the base at RESOLUTION_FACTOR x its operators, each in the form
the data choose there, and the rival goes first when its finer refit validates more than MIN_GAIN
below the leader's, on the finer base and on the user's (decision 0070: a finer base that only
makes the leader worse has not shown its lead to be the base's). When the finer base validates the
two alike (the rival within PARSIMONY_MARGIN of the leader), the lead was the base's resolution too,
and the ranking's tie rules decide between them: the residual's pattern, then the fewer free
parameters (decision 0076). The user's base is unchanged: the finer refits only order the
candidates (docs/decisions/0060).

A delay and a lag on a ``pmpi`` base are checked so whatever their margins (decision 0068). The
M-play operator's eta is a delay coefficient of its own (004 eq. 6): at the reversals it bends the
loop as a dead time or a lag would, and with ten thresholds placed evenly the searched etas also
stand in for the plant's operators between them. What that leaves at the reversals, a lag takes up
with the delay's share: on a 1 ms amplifier delay on an M-play rig, for example, the lag
validated at 0.023 um against the delay's 0.060 on ten operators, and at 0.046 against 0.015 on
twenty. The training condition does not apply (the lag trained at the noise there), nor the tie:
the lag's lead is the base's mismatch, however large. ``pmpi`` is refitted at
PMPI_RESOLUTION_FACTOR x its operators. A leader that the error at the input's fastest changes put
first (:func:`hilbench.diagnosis.ranking._delay_or_lag_by_the_fast_error`) keeps its place: that is
where the two differ, and the finer base compares what both share.
"""

from __future__ import annotations

from functools import partial
from typing import Any

from hilbench import progress
from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.ranking import (DELAY_AND_LAG, free_parameters, pattern_decides_for, reorderable,
                                        trains_far_better)
from hilbench.diagnosis.refit import fit_effect, spec_parts
from hilbench.diagnosis.verdict import Candidate, relative_gain, rms, validation_errors
from hilbench.diagnosis.workers import run_tasks
from hilbench.identify.dataset import Dataset
from hilbench.identify.fitting import FitResult, fit
from hilbench.models.bases import BASES
from hilbench.models.spec import SpecError, split_spec

#: The bases whose resolution is their number of evenly placed thresholds, and nothing else searched
#: per operator, for close leaders of any kind (``pmpi`` carries one searched eta per operator).
FINER_BASES = ("pi", "pi1", "mpi", "pd")
#: Bases whose operators carry a searched delay coefficient (M-play's eta): a delay and a lag are
#: checked on a finer one whatever their margins (module doc).
ETA_BASES = ("pmpi",)
#: What put a check in motion, as its record says.
DELAY_OR_LAG = "a delay and a lag on an eta base"
CLOSE_LEADERS = "close leaders above the noise"


def finer_spec(spec: str) -> str | None:
    """``spec`` with its base at RESOLUTION_FACTOR x the default operators (``pi+saturation`` ->
    ``pi(n=30)+saturation``; ``pmpi`` at PMPI_RESOLUTION_FACTOR x); None when the base is in
    neither FINER_BASES nor ETA_BASES or the user set its ``n``."""
    parts = spec_parts(spec)
    name, options = split_spec(parts[0])[0]
    if name not in FINER_BASES + ETA_BASES or "n" in options:
        return None
    factor = T.PMPI_RESOLUTION_FACTOR if name in ETA_BASES else T.RESOLUTION_FACTOR
    n = factor * int(BASES[name].options_schema["n"].default)
    inner = ",".join([f"n={n}", *(f"{k}={v}" for k, v in options.items())])
    return "+".join([f"{name}({inner})", *parts[1:]])


def _delay_or_lag_rival(base_spec: str, cands: list[Candidate]) -> Candidate | None:
    """On an ETA_BASES base whose leader is a delay or a lag, the other one when it is significant
    (a refit the ranking may reorder), unless the leader was put first by its fast error; else None."""
    leader = cands[0]
    if split_spec(base_spec)[0][0] not in ETA_BASES or leader.effect not in DELAY_AND_LAG:
        return None
    if "ranked_by_fast_error" in leader.evidence:
        # the error at the input's fastest changes already passed the bar of an effect for the leader
        # (decision 0066): that is where a delay and a lag differ, and a finer base's slow part is not
        # evidence against it (a delay behind a lag: on pmpi(n=20) the lag validates 0.30 um against
        # the delay's 0.44, while the delay's fast error stands at the noise's)
        return None
    partner = next(iter(DELAY_AND_LAG - {leader.effect}))
    return next((c for c in cands[1:] if c.effect == partner and reorderable(c)), None)


def check_resolution(paths: Dataset, base: FitResult, cands: list[Candidate], noise: float, kw: dict[str, Any],
                     jobs: int = 1) -> None:
    """Reorder ranked ``cands``, refits of ``base``, in place when the finer base puts the rival first (module doc);
    the leader's evidence records the check either way (``resolution_check``)."""
    if not cands or not reorderable(cands[0]) or not noise > 0.0:
        return
    leader = cands[0]
    leader_train = leader.fitted.metrics["train"]["rmse"]
    band = float(leader.evidence.get("noise_band", T.NOISE_FACTOR * noise))
    spec = finer_spec(base.spec)
    if spec is None:
        return
    rival = _delay_or_lag_rival(base.spec, cands)
    trigger = DELAY_OR_LAG if rival is not None else CLOSE_LEADERS
    v_leader = rms(validation_errors(leader.fitted))
    if rival is None:
        if not leader_train > band:
            return
        rival = next((c for c in cands[1:] if reorderable(c) and c.effect != leader.effect), None)
        if rival is None or split_spec(base.spec)[0][0] not in FINER_BASES:
            return
        if not rms(validation_errors(rival.fitted))**2 <= T.TIE_MEAN_SQUARE_RATIO * v_leader**2:
            return
    v_rival = rms(validation_errors(rival.fitted))
    # each effect in the form the data choose on the finer base: a form chosen at 10 operators may
    # owe the choice to them as well (an even term behind a saturation: v^2 alone chosen at 10; at
    # 30 v^2..v^4, which validates 0.112 against v^2's 0.175 um there)
    try:
        with progress.task(f"diagnose {base.spec}: {leader.effect} and {rival.effect} on {spec}", total=3) as advance:
            finer = fit(paths, spec, **kw)
            advance(1, f"{spec} done")
            fine: list[FitResult] = run_tasks(
                [partial(fit_effect, paths, finer, c.effect, kw, None) for c in (leader, rival)], jobs, advance,
                [f"{spec}: {c.effect}" for c in (leader, rival)], shared=paths.runs)
    except SpecError as e:
        # the finer base needs 2-3x the columns: past the memory limit (--memory-limit) the order stands
        leader.evidence["resolution_check"] = {"over": rival.effect, "skipped": str(e)}
        return
    specs = [f.spec for f in fine]
    factor = T.PMPI_RESOLUTION_FACTOR if split_spec(base.spec)[0][0] in ETA_BASES else T.RESOLUTION_FACTOR
    f_leader, f_rival = (rms(validation_errors(f)) for f in fine)
    record = {"over": rival.effect, "trigger": trigger, "specs": specs, "training_rmse": leader_train, "noise_band": band,
              "validation_rmse": {leader.effect: v_leader, rival.effect: v_rival},
              "finer_validation_rmse": {leader.effect: f_leader, rival.effect: f_rival}}
    # the rival must validate below the leader's best showing, on either base: where the finer base
    # only made the leader worse, its extra operators took up something besides the loop's shape and
    # the order is no question of resolution (a saturation with a sensor delay unmodelled, for
    # example: at 30 operators the saturation validated 0.339 against its 0.260 um at 10, and v^2..v^4
    # 0.286 ranked first; decision 0070)
    if relative_gain(min(f_leader, v_leader), f_rival) > T.MIN_GAIN:
        cands.remove(rival)
        cands.insert(0, rival)
        rival.evidence["ranked_by_resolution"] = {**record, "over": leader.effect}
        rival.explanation += (
            f"; ranked before {leader.effect}, which validated {v_leader:.4g} against its {v_rival:.4g}: on a base "
            f"of {factor}x the operators it validates at {f_rival:.4g} against {f_leader:.4g}, so "
            f"{leader.effect}'s lead came from the base's resolution")
    elif trigger == CLOSE_LEADERS and (reason := _tie_on_the_finer_base(leader, rival, min(f_leader, v_leader), f_rival)):
        cands.remove(rival)
        cands.insert(0, rival)
        rival.evidence["ranked_by_resolution"] = {**record, "over": leader.effect, "tie_broken_by": reason}
        rival.explanation += (
            f"; ranked before {leader.effect}, which validated {v_leader:.4g} against its {v_rival:.4g}: on a base "
            f"of {factor}x the operators the two validate alike ({f_rival:.4g} against {f_leader:.4g}), and "
            + ("the error's pattern fits it better" if reason == "signature" else
               f"it needs fewer parameters ({free_parameters(rival)} against {free_parameters(leader)})"))
    else:
        leader.evidence["resolution_check"] = record


def _tie_on_the_finer_base(leader: Candidate, rival: Candidate, best_leader: float, f_rival: float) -> str | None:
    """``signature`` or ``parsimony`` when the finer base cannot tell the two leaders apart and the
    ranking's tie rules (:func:`hilbench.diagnosis.ranking.rank`, 1 and 2) choose the rival; else None.

    The user's base put the leader ahead by more than the tie margins; if the finer base validates
    the rival within PARSIMONY_MARGIN of the leader's best showing on either base (``best_leader``,
    as decision 0070 compares), that lead was the base's resolution, and the
    two explain the data alike: then what decides a tie on any base decides here, the residual's
    pattern first, then the fewer free parameters (decision 0076; an even v^2 on a one-sided
    drive under ``pi1``, for example: a saturation with 25 parameters validated 0.0118 um
    against v^2's 0.0125 with 12, and on 30 operators 0.00694 against 0.00702, at the noise's
    0.0063)."""
    if f_rival > best_leader * (1.0 + T.PARSIMONY_MARGIN):
        return None
    if pattern_decides_for(rival, leader):
        return "signature"
    if pattern_decides_for(leader, rival) or trains_far_better(leader, rival):
        return None
    return "parsimony" if free_parameters(rival) < free_parameters(leader) else None
