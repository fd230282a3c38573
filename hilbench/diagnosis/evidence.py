"""The evidence of an effect: the residual pattern that is its physical signature.

Each effect of :data:`hilbench.effects.EFFECTS` names a ``signature``; :data:`SIGNATURES` turns the
residual rows into one sentence and the numbers behind it. A numeric ``signature`` entry in the
evidence (the fraction of the error's variance the pattern explains) lets the ranking break ties
between refits that explain the data equally well. An effect may also name an ``evidence_check``
(:data:`EVIDENCE_CHECKS`): a pattern that must be present before the effect can be significant.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hilbench import effects as E
from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.rows import ResidualRows


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.std(a[ok]) == 0 or np.std(b[ok]) == 0:
        return 0.0
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def explained(e: np.ndarray, cols: list[np.ndarray]) -> float:
    """Fraction of the residual's variance a least-squares fit on ``cols`` (plus a constant) explains."""
    A = np.column_stack([np.ones_like(e), *cols])
    ok = np.all(np.isfinite(A), axis=1) & np.isfinite(e)
    if ok.sum() <= A.shape[1] or np.var(e[ok]) == 0:
        return 0.0
    w, *_ = np.linalg.lstsq(A[ok], e[ok], rcond=None)
    r = e[ok] - A[ok] @ w
    return float(max(0.0, 1.0 - np.var(r) / np.var(e[ok])))



#: rows at each end of a hold whose mean residuals make its drift
HOLD_END_ROWS = 20


def hold_drifts(rows: ResidualRows, e: np.ndarray | None = None) -> np.ndarray:
    """The residual's drift along every hold (output unit, signed): the mean of ``e`` (default the
    rows' own residual) over the last HOLD_END_ROWS rows of the hold less that over its first, after
    the first T.CREEP_SETTLE_S; holds too short for both ends are left out. The same rows in the same
    order for any residual on ``rows``, so a refit's drifts pair with the base's."""
    e = rows.e if e is None else e
    hold = rows.direction == "hold"
    drift = []
    for k in np.unique(rows.run):
        idx = np.flatnonzero(hold & (rows.run == k))
        for seg in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
            # skip the first T.CREEP_SETTLE_S of a hold: a delay or a resonance settles there, while
            # creep (time constants of tenths of seconds and more) keeps drifting after it
            seg = seg[rows.since[seg] >= T.CREEP_SETTLE_S]
            if seg.size > 50:
                drift.append(float(np.mean(e[seg[-HOLD_END_ROWS:]]) - np.mean(e[seg[:HOLD_END_ROWS]])))
    return np.array(drift)


def _drift_on_holds(effect: str, rows: ResidualRows) -> tuple[str, dict[str, Any]]:
    e, e2 = rows.e, rows.e**2
    total = float(e2.sum()) or 1.0
    hold = rows.direction == "hold"
    early = hold & (rows.since < 1.0)
    late = hold & (rows.since >= 1.0)
    # drift: residual changes along a hold; its size relative to the rms error
    drift = np.abs(hold_drifts(rows))
    rms = math.sqrt(total / e.size)
    ev = {"hold_share": float(e2[hold].sum() / total), "hold_rows": float(hold.mean()),
          "drift_over_hold_um": float(np.mean(drift)) if drift.size else 0.0,
          "drift_over_rms": float(np.mean(drift) / rms) if drift.size and rms > 0 else 0.0,
          "first_second_vs_later_mse": float(np.mean(e2[early]) / max(np.mean(e2[late]), 1e-30))
          if early.any() and late.any() else float("nan")}
    return (f"the error drifts by {ev['drift_over_hold_um']:.3g} (output unit) while the input holds still "
            f"({ev['drift_over_rms']:.2g}x the rms error) and decays after each step: creep"), ev


def drift_after_refit(rows: ResidualRows, refit_e: np.ndarray, noise: float) -> dict[str, Any]:
    """What a refit did to the drift along holds: the base's mean absolute drift over the noise's
    standard error on it (a difference of two means of HOLD_END_ROWS samples of the sensor's noise),
    and the fraction of that drift the refit's residual ``refit_e`` (on the same rows) no longer has."""
    before, after = np.abs(hold_drifts(rows)), np.abs(hold_drifts(rows, refit_e))
    if not before.size or before.size != after.size:
        return {"drift_over_noise": 0.0, "drift_removed": 0.0}
    standard_error = float(noise) * math.sqrt(2.0 / HOLD_END_ROWS)
    mean = float(np.mean(before))
    return {"drift_over_noise": mean / standard_error if standard_error > 0 else math.inf,
            "drift_removed": 1.0 - float(np.mean(after)) / mean if mean > 0 else 0.0,
            "drift_after_refit_um": float(np.mean(after))}


#: the residual patterns of slow effects: creep's drift along holds and a recorded channel's trace
SLOW_SIGNATURES = ("drift-on-holds", "channel")


def slow_signatures(rows: ResidualRows, refit_e: np.ndarray, noise: float) -> dict[str, Any]:
    """What a slow effect's refit leaves of the slow effects' signatures (issue 62), on the rows of
    ``rows`` (the refit's residual ``refit_e`` on them, output unit; ``noise`` the sensor's floor):

    * ``drift_left_um`` and ``drift_left_over_noise``: the mean absolute drift of the refit's
      residual along the holds (:func:`hold_drifts`), and that over the noise's standard error on a
      drift (a difference of two means of HOLD_END_ROWS samples): creep keeps drifting along every
      hold whatever a channel does, so a channel term that leaves a drift beyond the noise leaves creep;
    * ``channel_trace``: per recorded channel a, the residual's part that a and a*u explain (a
      least-squares fit with a constant), as the fraction of its variance and that part's rms over
      the noise floor: a channel effect follows its channel, creep does not.

    Numbers to report beside the verdict; no check rests on them."""
    drifts = np.abs(hold_drifts(rows, refit_e))
    standard_error = float(noise) * math.sqrt(2.0 / HOLD_END_ROWS)
    out: dict[str, Any] = {"holds": int(drifts.size)}
    if drifts.size:
        mean = float(np.mean(drifts))
        out["drift_left_um"] = mean
        out["drift_left_over_noise"] = mean / standard_error if standard_error > 0 else math.inf
    trace: dict[str, dict[str, float]] = {}
    var = float(np.var(refit_e)) if refit_e.size else 0.0
    for channel, a in rows.aux.items():
        share = explained(refit_e, [a, a * rows.u])
        rms_part = math.sqrt(share * var)
        trace[channel] = {"explained": share,
                          "rms_over_noise": rms_part / float(noise) if noise > 0 else math.inf}
    out["channel_trace"] = trace
    return out


def slow_sentence(effect: str, ev: dict[str, Any], unit: str = "") -> str:
    """A clause for a slow effect's explanation when its refit leaves creep's signature beyond the
    noise (CREEP_MIN_DRIFT_OVER_NOISE standard errors, the bar creep's own drift must clear); empty
    otherwise."""
    z = ev.get("drift_left_over_noise", 0.0)
    if E.effect(effect).signature == "drift-on-holds" or not z >= T.CREEP_MIN_DRIFT_OVER_NOISE:
        return ""
    u = f" {unit}" if unit else ""
    return (f"; with {effect} the residual still drifts along holds by {ev['drift_left_um']:.3g}{u} "
            f"({z:.2g}x the noise's standard error on a drift): creep's signature, which {effect} does not take")


def _fast_vs_slow(effect: str, rows: ResidualRows) -> tuple[str, dict[str, Any]]:
    e2 = rows.e**2
    rate = np.abs(rows.du)
    moving = rate > 0
    hi = moving & (rate >= np.percentile(rate[moving], 67)) if moving.any() else moving
    lo = moving & (rate <= np.percentile(rate[moving], 33)) if moving.any() else moving
    ratio = float(np.mean(e2[hi]) / max(np.mean(e2[lo]), 1e-30)) if hi.any() and lo.any() else float("nan")
    ev = {"mse_fast_over_slow": ratio, "corr_e2_rate": correlation(e2, rate)}
    return (f"the squared error is {ratio:.2g}x larger at the fastest third of input rates than at the slowest: "
            "rate-dependence"), ev


def _derivatives(effect: str, rows: ResidualRows) -> tuple[str, dict[str, Any]]:
    e = rows.e
    c2 = correlation(e, rows.d2y)
    x = explained(e, [rows.dy, rows.d2y])
    ev = {"corr_e_d2y": c2, "explained_by_dy_d2y": x, "signature": x}
    return (f"the error follows the output's derivatives ({100 * x:.2g} % of its variance, correlation "
            f"with acceleration {c2:.2f}): a lag and ringing of linear dynamics"), ev


def _rate_of_change(effect: str, rows: ResidualRows) -> tuple[str, dict[str, Any]]:
    e = rows.e
    c1 = correlation(e, rows.dy)
    ev = {"corr_e_dy": c1, "explained_by_dy": explained(e, [rows.dy])}
    ev["signature"] = ev["explained_by_dy"]
    # measured y(t) = model(t - lag) gives e = model - y ~ lag * dy/dt: a positive lag means the
    # measurement trails the model
    lag = float(np.dot(e, rows.dy) / max(np.dot(rows.dy, rows.dy), 1e-30))
    ev["equivalent_lag_s"] = lag
    return (f"the error is proportional to the output's rate of change (correlation {c1:.2f}, "
            f"as a lag of {1e3 * lag:.3g} ms): a time delay"), ev


def parity_overlap(u: np.ndarray) -> float:
    """How far this drive can tell an even pattern from an odd one: the fraction of the even
    regressor's variance (the centred input squared) the odd regressors (u, u^3, about zero) explain.
    Near 0 on a drive that swings about zero; near 1 on a one-sided drive, where a cubic in u is as
    good a fit to a parabola as the parabola itself, so even and odd residual patterns are the same."""
    span = max(float(np.ptp(u)), 1e-12)
    v = (u - u.mean()) / (span / 2)
    s = u / max(float(np.max(np.abs(u))), 1e-12)
    return explained(v**2, [s, s**3])


def _even_input(effect: str, rows: ResidualRows) -> tuple[str, dict[str, Any]]:
    e, u = rows.e, rows.u
    span = max(float(np.ptp(u)), 1e-12)
    v = (u - u.mean()) / (span / 2)
    even = explained(e, [v**2, v**4])
    ev = {"explained_by_even_input": even, "corr_e_u2": correlation(e, v**2), "signature": even,
          "parity_overlap": parity_overlap(u)}
    return (f"{100 * even:.2g} % of the error's variance is an even function of the input: the loops are "
            "not centrally symmetric (asymmetry)"), ev


def _odd_input(effect: str, rows: ResidualRows) -> tuple[str, dict[str, Any]]:
    e, u, e2 = rows.e, rows.u, rows.e**2
    total = float(e2.sum()) or 1.0
    a = np.abs(u - np.median(u))
    outer = a >= np.percentile(a, 80)
    share = float(e2[outer].sum() / total)
    odd = explained(e, [u, u**3])
    ev = {"outer_20pct_share": share, "explained_by_odd_input": odd, "signature": odd,
          "parity_overlap": parity_overlap(u)}
    return (f"{100 * share:.2g} % of the squared error lies in the outer fifth of the input range: the loops "
            "flatten at large drive (saturation)"), ev


def _direction(effect: str, rows: ResidualRows) -> tuple[str, dict[str, Any]]:
    e = rows.e
    s = np.where(rows.direction == "rising", 1.0, np.where(rows.direction == "falling", -1.0, 0.0))
    x = explained(e, [s])
    ev = {"explained_by_direction": x, "corr_e_direction": correlation(e, s), "signature": x}
    return (f"the error's sign depends on the direction of motion ({100 * x:.2g} % of its variance): "
            "rate-independent memory (hysteresis)"), ev


def _channel(effect: str, rows: ResidualRows) -> tuple[str, dict[str, Any]]:
    e, u = rows.e, rows.u
    a = rows.aux.get(effect)
    c = correlation(e, a) if a is not None else 0.0
    ev = {"corr_e_channel": c, "explained_by_channel": explained(e, [a, a * u]) if a is not None else 0.0}
    ev["signature"] = ev["explained_by_channel"]
    return (f"the error follows the {effect} channel (correlation {c:.2f}, {100 * ev['explained_by_channel']:.2g} % "
            f"of its variance with the input): dependence on {effect}"), ev


#: signature name (hilbench.effects) -> pattern(effect name, rows) -> (sentence, evidence)
SIGNATURES: dict[str, Callable[[str, ResidualRows], tuple[str, dict[str, Any]]]] = {
    "drift-on-holds": _drift_on_holds,
    "fast-vs-slow": _fast_vs_slow,
    "derivatives": _derivatives,
    "rate-of-change": _rate_of_change,
    "even-input": _even_input,
    "odd-input": _odd_input,
    "direction": _direction,
    "channel": _channel,
}

#: signature -> the signatures whose regressors it contains. A nested pattern explains at least as
#: much of any residual (the derivatives' fit includes the rate of change's column), so its larger
#: fraction says nothing about which effect is there: a tie between the two stays in gain order.
NESTED_SIGNATURES: dict[str, frozenset[str]] = {"derivatives": frozenset({"rate-of-change"})}


def nested(a: str | None, b: str | None) -> bool:
    """Whether one of the signatures ``a``, ``b`` contains the other's regressors."""
    return (a is not None and b is not None
            and (b in NESTED_SIGNATURES.get(a, frozenset()) or a in NESTED_SIGNATURES.get(b, frozenset())))


@dataclass(frozen=True)
class EvidenceCheck:
    key: str  # the name of the check in a verdict's ``checks``
    holds: Callable[[dict[str, Any]], bool]  # test on the evidence
    present: str  # what to say when the pattern is there but the refit alone does not pay
    #: evidence from the base's rows, the refit's residual on the same rows and the noise floor
    #: (output unit), added before ``holds`` is asked
    after_refit: Callable[[ResidualRows, np.ndarray, float], dict[str, Any]] | None = None


#: check name (hilbench.effects) -> the check
EVIDENCE_CHECKS: dict[str, EvidenceCheck] = {
    # creep's physical signature, which a refit alone can fake (the creep low-pass also buys phase
    # lag on delay or dynamics data): the residual drifts along holds beyond the noise, and by a good
    # part of its rms, or, where other errors fill the rms, the creep refit is what removes that
    # drift (a ringing, a temperature or a load drifts along holds too, and creep's refit leaves most
    # of it; decision 0059). A drift within the noise is no drift, however small the rms beside it
    # (on a clean rig, a drift of 0.25x the rms and 1.0x the noise's standard error; decision 0061)
    "drift-on-holds": EvidenceCheck(
        "drift_on_holds",
        lambda ev: (ev["drift_over_noise"] >= T.CREEP_MIN_DRIFT_OVER_NOISE
                    and (ev["drift_over_rms"] >= T.CREEP_MIN_DRIFT or ev["drift_removed"] >= T.CREEP_MIN_DRIFT_REMOVED)),
        "the drift is there", after_refit=drift_after_refit),
}


def explain(effect: str, rows: ResidualRows) -> tuple[str, dict[str, Any]]:
    """One sentence from residual statistics, and the numbers behind it."""
    signature = E.effect(effect).signature
    assert signature is not None, effect
    return SIGNATURES[signature](effect, rows)
