"""The wrong base is an effect too: when the hysteresis itself has the wrong shape, say which base fits.

Small effects added on top of a base of the wrong family cannot fix its loop shape (a PMPI base on a
rig whose loops are Duhem-like stays at tens of percent, where ``duhem-d`` reaches the noise). When
the current validation error is far above the noise floor, the same spec is refitted with each base
of another family (:data:`ALTERNATIVE_BASES`), keeping its effects; a base that lowers the
validation error by WRONG_BASE_RATIO or more, and by as much against the best single effect on the
current base, with training improving too and the block test significant, is reported as the candidate ``base`` (its spec switches the base), so ``--auto``
switches to it before adding effects.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from hilbench import effects as E
from hilbench import progress
from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.significance import improvement_test
from hilbench.diagnosis.verdict import Candidate, relative_gain, validation_errors
from hilbench.errors import UserError
from hilbench.identify.fitting import FitResult, fit
from hilbench.models.model import split_spec
from hilbench.models.spec import SpecError

#: one base per family of loop shape (play operators, M-play with polynomial, ISSF-Duhem with a
#: dead-zone and with a Gompertz shape, Bouc-Wen): the forms hysteresis takes on a memoryless base
ALTERNATIVE_BASES = E.EFFECTS["hysteresis"].forms


def with_base(spec: str, base: str) -> str:
    """``spec`` with its base replaced (its options dropped: they belong to the old base)."""
    parts = spec.split("+")
    return "+".join([base, *parts[1:]])


def alternatives(base: FitResult, noise: float) -> list[str]:
    """The specs :func:`wrong_base` fits: ``base.spec`` on every base of another family, none when the
    validation error is near the noise (the loop shape is right enough), the base is memoryless
    (it needs hysteresis, not another loop) or the model is a structure (restoring-force)."""
    current = split_spec(base.spec)[0][0]
    if not base.metrics["validation"]["rmse"] > T.WRONG_BASE_NOISE_FACTOR * noise or current == "linear":
        return []
    if base.model.structure is not None:
        return []  # the structure's kernel holds one law (Bouc-Wen): no other family to put in its place
    return [with_base(base.spec, b) for b in ALTERNATIVE_BASES if b != current]


def fit_alternative(paths: Any, base: FitResult, spec: str, kw: dict[str, Any]) -> FitResult | None:
    """``spec`` (an :func:`alternatives` spec) fitted; None when its base cannot carry the effects."""
    try:
        # the effects start from their fitted shape; only the new base is searched globally
        return fit(paths, spec, **kw, start_from=base.model)
    except UserError:
        return None  # an effect the alternative cannot carry (e.g. asymmetry on pmpi's polynomial)


def wrong_base(base: FitResult, fitted: Sequence[FitResult | None], noise: float,
               effect_rmse: Sequence[float] = ()) -> Candidate | None:
    """The best base of another family when it fits far better (module docstring); else None.

    ``fitted``: the :func:`alternatives` of ``base`` as :func:`fit_alternative` returned them.
    ``effect_rmse``: the validation rmse each single effect reached on the current base. Another
    base must beat the best of them by WRONG_BASE_RATIO too: a base whose terms include an effect
    (PMPI's cubic polynomial is asymmetry) is no evidence that the loop shape is wrong when adding
    that effect does as well."""
    current = split_spec(base.spec)[0][0]
    old_v, old_t = base.metrics["validation"]["rmse"], base.metrics["train"]["rmse"]
    tried: dict[str, float] = {}
    best: FitResult | None = None
    for f in fitted:
        if f is None:
            continue
        tried[split_spec(f.spec)[0][0]] = f.metrics["validation"]["rmse"]
        if best is None or f.metrics["validation"]["rmse"] < best.metrics["validation"]["rmse"]:
            best = f
    if best is None:
        return None
    new_v, new_t = best.metrics["validation"]["rmse"], best.metrics["train"]["rmse"]
    e_old, e_new = validation_errors(base), validation_errors(best)
    p, better, blocks = improvement_test(e_old, e_new)
    gain = relative_gain(old_v, new_v)
    best_effect = min([old_v, *[v for v in effect_rmse if v == v]])
    checks = {
        f"validation_{T.WRONG_BASE_RATIO:g}x_lower": new_v * T.WRONG_BASE_RATIO <= old_v,
        f"{T.WRONG_BASE_RATIO:g}x_lower_than_any_effect": new_v * T.WRONG_BASE_RATIO <= best_effect,
        "training_lower_too": new_t < old_t,
        "blocks_p_below_0.01": p < T.P_MAX,
    }
    name = split_spec(best.spec)[0][0]
    sentence = (f"the loop itself has another shape: the base {name!r} fits with validation rmse {new_v:.4g} against "
                f"{old_v:.4g} ({old_v / max(new_v, 1e-300):.3g}x lower), which no effect on {current!r} can reach; "
                f"start from {best.spec!r}")
    evidence = {"validation_rmse": [old_v, new_v], "train_rmse": [old_t, new_t], "p_value": p,
                "best_effect_rmse": best_effect,
                "blocks_improved": [better, blocks], "noise_floor": noise, "checks": checks, "spec": best.spec,
                "bases_tried": tried, "current_base": current, "suggested_base": name, "replacement": "the other base"}
    return Candidate("base", best.spec, all(checks.values()), gain, sentence, evidence, fitted=best,
                     replaces_model=True)


def finer_base_check(paths: Any, base: FitResult, other: Candidate, cands: Sequence[Candidate],
                     kw: dict[str, Any]) -> None:
    """A significant wrong-base candidate ``other`` must also beat, by WRONG_BASE_RATIO, the best
    refit on the current base at a finer resolution (decision 0077); in place, as one more check.

    An operator base places its thresholds evenly, so a rig whose few operators sit between them
    leaves a loop the base cannot bend to, and any base with a searched shape (PMPI's etas move
    where its operators turn) fits that better. That is the current family at too coarse a
    resolution, not another family (for example four play operators and an even v^2
    under ``pi``: ``pi+asymmetry(order=2)`` validated at 0.726 um, ``pmpi`` at 0.360, 2.02x lower,
    and the base was reported wrong; ``pi(n=30)+asymmetry(order=2)`` validates at 0.389). The
    spec refitted is the one of the candidate that validates best on the current base (the base
    itself if none does better), on :func:`hilbench.diagnosis.resolution.finer_spec`'s base;
    a base the user gave an ``n`` keeps its resolution and is not checked."""
    from hilbench.diagnosis.resolution import finer_spec  # resolution imports the ranking, which this module must not

    if not other.significant:
        return
    refits = [c for c in cands if c.fitted is not None and not c.replaces_model]
    best = min(refits, key=lambda c: c.fitted.metrics["validation"]["rmse"], default=None)
    better = best is not None and best.fitted.metrics["validation"]["rmse"] < base.metrics["validation"]["rmse"]
    spec = finer_spec(best.fitted.spec if better else base.spec)
    if spec is None:
        return
    try:
        with progress.task(f"diagnose {base.spec}: the other base against {spec}", total=1) as advance:
            finer = fit(paths, spec, **kw)
            advance(1, f"{spec} done")
    except (SpecError, UserError) as e:
        # past the memory limit the finer base cannot be fitted: the check is recorded as skipped
        other.evidence["finer_base"] = {"spec": spec, "skipped": str(e)}
        return
    v_finer, v_other = finer.metrics["validation"]["rmse"], other.fitted.metrics["validation"]["rmse"]
    key = f"{T.WRONG_BASE_RATIO:g}x_lower_than_a_finer_{split_spec(base.spec)[0][0]}"
    other.evidence["finer_base"] = {"spec": spec, "validation_rmse": v_finer}
    other.evidence["checks"][key] = v_other * T.WRONG_BASE_RATIO <= v_finer
    other.significant = all(other.evidence["checks"].values())
