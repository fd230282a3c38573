"""Refitting a model with one more effect, in the form the data choose.

An effect of the registry (:data:`hilbench.effects.EFFECTS`) lists the forms it is tried in and how
the diagnosis chooses among them (``form_choice``):

* ``train``: every form is fitted and the best training fit is kept, so the validation comparison
  that judges the effect stays fair (saturation: a tanh or a knee of the hysteresis output; which
  describes the plant is not known beforehand);
* ``inner-split``: a richer form has many more weights, so training always prefers it; an inner
  split of the training rows (its first INNER_SPLIT part fits, the rest judges) tells whether the
  extra weights carry over, and a richer form must win by RICHER_FORM_MARGIN (creep after the
  hysteresis, ``creep(form=output)``). The user's validation rows stay untouched.
* ``inner-split-both``: as ``inner-split``, and the richer form must fit the inner fit's own rows
  better too (hysteresis on a memoryless base: a family that describes the loop fits every stretch).
* ``inner-range``: as ``inner-split``, but the held-back rows are the training rows at the largest
  inputs (beyond INNER_SPLIT of training's largest |input|): a memoryless polynomial of the input
  fails where it extrapolates in input (asymmetry: v^2 alone, or v^2..v^4). Only when validation
  drives beyond training's reach; inside it, as ``train`` (decision 0069).
* ``inner-blocks``: as ``inner-split``, but the held-back rows are interleaved blocks spread over
  the training rows (:func:`hilbench.identify.sweep.interleaved`): a rate form is about rates, and
  the end of a training run holds only its last ones (rate-dependence: velocity damping, or the
  frequency polynomials of 003 with many more weights); a richer form must also fit the training
  rows better than the first, and among forms that fit them alike (FORM_TIE) the one with the fewest
  free parameters is the one checked (the polynomials of order 1 before order 3, decision 0063).

With a rate plan (one training rate, several validation rates) the effect's shape is calibrated
across drive rates first and fixed (:mod:`hilbench.diagnosis.rate_calibration`).

A joint candidate (two effects that act together, :mod:`hilbench.diagnosis.pairs`) is written as
its parts joined by ``+``, each in the form its single fit chose (``creep(form=output)+load``); it
is fitted as written, with no choice of form.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from hilbench import effects as E
from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.rate_calibration import RatePlan, calibrated_spec
from hilbench.errors import UserError
from hilbench.identify.dataset import as_dataset
from hilbench.identify.fitting import FitResult, assign_roles, fit
from hilbench.identify.sweep import interleaved, reversals
from hilbench.models.model import split_spec


def _memoryless_base_effect(part: str) -> E.Effect | None:
    """The registry entry of an effect that needs a memoryless base, when ``part`` names it or one
    of its forms (a base: ``duhem-d`` is a form of ``hysteresis``); else None."""
    name = split_spec(part)[0][0]
    for entry in E.EFFECTS.values():
        if E.MEMORYLESS_BASE in entry.requires and (name == entry.name or part in entry.forms):
            return entry
    return None


def spec_with(spec: str, effect: str) -> str:
    """``spec`` plus ``effect``; an effect that needs a memoryless base (``hysteresis``) replaces
    the ``linear`` base with its component (``pi``), or with the base its form names (``duhem-d``)."""
    entry = _memoryless_base_effect(effect)
    if entry is not None:
        name = split_spec(effect)[0][0]
        parts = [p.strip() for p in spec.split("+")]
        if split_spec(spec)[0][0] != "linear":
            raise UserError(f"{entry.name!r} needs a linear base; {spec!r} already has memory")
        return "+".join([str(entry.component) if name == entry.name else effect, *parts[1:]])
    return f"{spec}+{effect}"


def spec_parts(spec: str) -> list[str]:
    """``"pi(n=8)+creep(form=output)+load"`` -> its parts, split at the ``+`` outside parentheses."""
    parts, depth, current = [], 0, ""
    for ch in spec:
        depth += (ch == "(") - (ch == ")")
        if ch == "+" and depth == 0:
            parts.append(current.strip())
            current = ""
        else:
            current += ch
    return [*parts, current.strip()]


def spec_with_all(spec: str, effects: Sequence[str]) -> str:
    """``spec`` plus every one of ``effects`` (:func:`spec_with` in turn)."""
    for effect in effects:
        spec = spec_with(spec, effect)
    return spec


def added_parts(base_spec: str, spec: str, effect: str) -> list[str]:
    """What ``spec``, a refit of ``base_spec`` with ``effect``, adds: the effect in the form its fit
    chose (``creep(form=output)``, ``delay(seconds=0.004)``); the base it chose when it replaced the
    base (``hysteresis`` on ``linear``: ``duhem-d``, a form :func:`spec_with` reads back)."""
    old, new = spec_parts(base_spec), spec_parts(spec)
    if new[0] != old[0]:
        return [new[0]]
    return [p for p in new[1:] if p not in old[1:]] or [effect]


def is_joint(effect: str) -> bool:
    """Whether ``effect`` names several effects fitted together (``creep+load``)."""
    return len(spec_parts(effect)) > 1


def effect_specs(spec: str, effect: str) -> list[str]:
    """The specs a candidate effect is tried as: one per form of its registry entry; a joint
    candidate as written."""
    if is_joint(effect):
        return [spec_with_all(spec, spec_parts(effect))]
    return [spec_with(spec, part) for part in E.effect(effect).spec_parts()] if effect in E.EFFECTS \
        else [spec_with(spec, effect)]


def free_parameters(model: Any) -> int:
    """Weights plus searched shape parameters of a fitted model."""
    return len(model.weights) + sum(1 for p in model.shape_params() if p.upper > p.lower)


def inner_rmse(result: FitResult, held_back: list[np.ndarray]) -> float:
    """rmse on ``held_back`` rows (one mask per run) of an inner fit's free run."""
    parts = []
    for r, rows in zip(result.runs, held_back):
        if r.simulated is None or r.simulated.size == 0 or not rows.any():
            continue
        e = (r.simulated - r.data.output)[rows]
        parts.append(e[np.isfinite(e)])
    e = np.concatenate(parts) if parts else np.zeros(0)
    return float(np.sqrt(np.mean(e**2))) if e.size else float("inf")


def choose_by_inner_blocks(paths: Any, specs: list[str], kw: dict[str, Any], start_from: Any = None) -> str:
    """The first spec, unless a richer one predicts held-back training rows better by
    RICHER_FORM_MARGIN; the inner fits train on the user's training rows but the
    :func:`~hilbench.identify.sweep.validation_blocks` of 10 interleaved blocks (1 - INNER_SPLIT of
    them, never the first) and are scored on those. The user's validation rows stay untouched."""
    if len(specs) == 1:
        return specs[0]
    dataset = as_dataset(paths)
    user = dataset.fit_runs()
    assign_roles(user, kw.get("train"), kw.get("test"), float(kw.get("train_fraction", 0.7)), dataset.keep)
    held_back = [interleaved(u.train, T.INNER_SPLIT)[1] for u in user]
    if not any(h.any() for h in held_back):
        return specs[0]
    inner_data = replace(dataset, keep=[u.train & ~h for u, h in zip(user, held_back)])
    scored = within_inner_rates(user, held_back)
    fits = [fit(inner_data, s, train_fraction=1.0, start_from=start_from) for s in specs]
    scores = [inner_rmse(f, scored) for f in fits]
    best = min(range(1, len(specs)), key=lambda k: scores[k])
    return specs[best] if scores[best] < (1.0 - T.RICHER_FORM_MARGIN) * scores[0] else specs[0]


def within_inner_rates(user: list[Any], held_back: list[np.ndarray]) -> list[np.ndarray]:
    """The held-back rows whose drive frequency (the turning-point estimate the rate forms use)
    lies within the frequencies of the rows the inner fit trains on (INNER_RATE_TOLERANCE for the
    estimator's jitter), or that have no estimate yet; all held-back rows when none does.

    Interleaved blocks of a program of a few segments can hold all of one drive rate: the inner fit
    never sees it and its frequency polynomials are held at the largest rate they saw (they have no
    physical extrapolation), so on those rows it is judged on an extrapolation the form does not
    claim, against a damping that extrapolates as its power law (on a frequency gain, for example,
    the polynomials lowered the user's validation rmse 10x and lost the inner check on a block
    at up to 21 Hz, the inner fit's rows reaching 5.4 Hz; decision 0050). The user's validation
    judges rates beyond training."""
    from hilbench.models.kernels import turning_point_frequency
    from hilbench.sim.kernels import N_TP

    out = []
    for u, h in zip(user, held_back):
        if not h.any():
            out.append(h)
            continue
        v = np.ascontiguousarray(u.data.input, dtype=float)
        f, a = np.empty_like(v), np.empty_like(v)
        turning_point_frequency(v, float(u.data.sample_rate_hz), np.zeros(N_TP), f, a)
        seen = f[u.train & ~h]
        seen = seen[seen > 0.0]
        if seen.size == 0:
            out.append(h & (f == 0.0))
            continue
        lo, hi = float(seen.min()) / T.INNER_RATE_TOLERANCE, float(seen.max()) * T.INNER_RATE_TOLERANCE
        out.append(h & ((f == 0.0) | ((f >= lo) & (f <= hi))))
    return out if any(o.any() for o in out) else held_back


def validation_beyond_training_reach(paths: Any, kw: dict[str, Any]) -> bool:
    """Whether the user's validation rows drive beyond training's largest |input| by more than
    REACH_MARGIN of it: only then must a memoryless polynomial of the input extrapolate, and
    ``inner-range`` judges its order where it does (decision 0069).

    Inside training's reach the inner-range check measures the base more than the polynomial: the
    rows above INNER_SPLIT of the reach are where the base's top operators act, and held back from
    the inner fit, nothing fits them (an even v^4 on a one-sided drive validated within
    training's range: v^2 and v^2..v^4 left 0.1115 and 0.1110 um there, so v^2
    was kept; on validation it gave 0.044 um, v^2..v^4 0.029 and a saturation 0.034). Only the
    inputs of validation are read, the drive the user chose, never its response."""
    dataset = as_dataset(paths)
    user = dataset.fit_runs()
    assign_roles(user, kw.get("train"), kw.get("test"), float(kw.get("train_fraction", 0.7)), dataset.keep)

    def reach(rows: str) -> float:
        return max((float(np.nanmax(np.abs(u.data.input[getattr(u, rows)]))) for u in user
                    if getattr(u, rows).any()), default=0.0)

    return reach("validation") > (1.0 + T.REACH_MARGIN) * reach("train")


def choose_by_inner_range(paths: Any, specs: list[str], kw: dict[str, Any], start_from: Any = None) -> str:
    """The first spec, unless a richer one predicts the training rows at the largest inputs better
    by RICHER_FORM_MARGIN: the inner fits train on the user's training rows whose |input| stays within
    INNER_SPLIT of training's largest and are scored on the rest. A
    memoryless polynomial of the input fails where it extrapolates in input: higher powers fitted
    over one range swing beyond it, and a test run often drives further than training (an even
    v^2 on a one-sided drive: v^2..v^4 validated 0.175 um where v^2 alone gave
    0.040, the test run reaching 1.23x training's drive; decision 0046). The user's validation rows
    stay untouched."""
    if len(specs) == 1:
        return specs[0]
    dataset = as_dataset(paths)
    user = dataset.fit_runs()
    assign_roles(user, kw.get("train"), kw.get("test"), float(kw.get("train_fraction", 0.7)), dataset.keep)
    reach = max((float(np.max(np.abs(u.data.input[u.train]))) for u in user if u.train.any()), default=0.0)
    held_back = [u.train & (np.abs(u.data.input) > T.INNER_SPLIT * reach) for u in user]
    inner = [u.train & ~h for u, h in zip(user, held_back)]
    if not any(h.any() for h in held_back) or not any(k.any() for k in inner):
        return specs[0]
    inner_data = replace(dataset, keep=inner)
    scores = [inner_rmse(fit(inner_data, s, train_fraction=1.0, start_from=start_from), held_back) for s in specs]
    best = min(range(1, len(specs)), key=lambda k: scores[k])
    return specs[best] if scores[best] < (1.0 - T.RICHER_FORM_MARGIN) * scores[0] else specs[0]


def choose_by_inner_split(paths: Any, specs: list[str], kw: dict[str, Any], start_from: Any = None,
                          fit_rows_too: bool = False) -> str:
    """The first spec, unless a richer one (later in ``specs``) predicts held-back training rows
    better by RICHER_FORM_MARGIN. The inner fits train on the first INNER_SPLIT of the user's
    training rows and are scored on the training rows they did not see: with a fraction split, the
    first INNER_SPLIT of the training fraction fits (for a run split in interleaved blocks,
    :mod:`hilbench.identify.sweep`, the blocks between the two splits are held back); with runs in
    roles (``train`` / ``test``), the first INNER_SPLIT of each training run's rows fits and the rest
    of it is held back. The user's validation rows stay untouched either way.

    ``fit_rows_too``: a richer form must also fit the inner fit's own rows better than the first
    (``inner-split-both``, the loop families of hysteresis). A loop shape is what every stretch of
    a run shows, so a family that describes it better fits both the rows it saw and those it did
    not; one that fits its own rows worse and the held-back rows better stopped in a poorer
    optimum whose extrapolation happened to suit the run's end (on play loops, ``pmpi``
    0.61 against ``pi``'s 0.55 um on its rows, 0.40 against 0.62 held back, and 2.9 against
    0.96 um on the test run)."""
    if len(specs) == 1:
        return specs[0]
    dataset = as_dataset(paths)
    user = dataset.fit_runs()
    train_fraction = float(kw.get("train_fraction", 0.7))
    roles = bool(kw.get("train") or kw.get("test"))
    assign_roles(user, kw.get("train"), kw.get("test"), train_fraction, dataset.keep)
    if roles:
        # whole runs train: the inner fit sees only the training runs' rows, split by time in each
        inner_data, inner = replace(dataset, keep=[u.train.copy() for u in user]), T.INNER_SPLIT
    else:
        inner_data, inner = dataset, T.INNER_SPLIT * train_fraction
        if not 0.0 < inner < train_fraction:
            return specs[0]
    scores, fitted = [], []
    for s in specs:
        result = fit(inner_data, s, train_fraction=inner, start_from=start_from)
        if fit_rows_too and not scores and not inner_rows_loop(result, user):
            return specs[0]
        held_back = [r.validation & u.train for r, u in zip(result.runs, user)]
        scores.append(inner_rmse(result, held_back))
        fitted.append(result.metrics["train"]["rmse"])
    richer = [k for k in range(1, len(specs)) if not fit_rows_too or fitted[k] < fitted[0]]
    if not richer:
        return specs[0]
    best = min(richer, key=lambda k: scores[k])
    return specs[best] if scores[best] < (1.0 - T.RICHER_FORM_MARGIN) * scores[0] else specs[0]


def inner_rows_loop(result: FitResult, user: list[Any]) -> bool:
    """Whether the inner fit's rows (``result``'s training rows) turn the input INNER_MIN_REVERSALS
    times in some run, counted against the span of the user's training rows: a loop family shows
    its shape on loops. An inner fit that saw a power-on step and a hold predicts the held-back
    rows by whatever each family makes of a step, not by the loop's shape (for example,
    play loops from a linear start, training a step, a hold and the first cycle of a sine; ``duhem-d``
    won the held-back cycle and validated at 2.41 um against the linear base's 2.16, where ``pi``
    validates at 0.093 um; decision 0057)."""
    for r, u in zip(result.runs, user):
        rows = r.train & u.train
        if not rows.any() or not u.train.any():
            continue
        x = u.data.input[u.train]
        span = float(np.ptp(x[np.isfinite(x)])) if np.isfinite(x).any() else 0.0
        if reversals(u.data.input[rows], span) >= T.INNER_MIN_REVERSALS:
            return True
    return False


def fit_effect(paths: Any, base: FitResult, effect: str, kw: dict[str, Any], plan: RatePlan | None) -> FitResult:
    """``base`` refitted with ``effect`` on the user's split, in the form the data choose (a joint
    candidate in the forms it names). Every refit starts from ``base``'s fitted shape (a warm
    start: the global scan spreads only the new effect's parameters)."""
    kw = {**kw, "start_from": base.model}
    if is_joint(effect):
        return fit(paths, effect_specs(base.spec, effect)[0], **kw)
    if plan is not None:
        spec, _ = calibrated_spec(paths, base.spec, effect, plan)
        return fit(paths, spec, **kw)
    specs = effect_specs(base.spec, effect)
    choice = E.effect(effect).form_choice
    if choice == "inner-range" and not validation_beyond_training_reach(paths, kw):
        # nothing extrapolates in input: the forms are chosen as any effect's (decision 0069)
        choice = "train"
    if choice == "inner-range":
        return fit(paths, choose_by_inner_range(paths, specs, kw, base.model), **kw)
    if choice in ("inner-split", "inner-split-both"):
        return fit(paths, choose_by_inner_split(paths, specs, kw, base.model, choice == "inner-split-both"), **kw)
    fits = [fit(paths, spec, **kw) for spec in specs]
    # choose among the forms on training rows only, so the validation comparison stays fair; forms
    # that fit them equally well go to the one with the fewest free parameters (decision 0043)
    train = [f.metrics["train"]["rmse"] for f in fits]
    best = min(range(len(fits)), key=lambda k: train[k])
    if choice in ("train", "inner-blocks"):
        # equal: within FORM_TIE of what the best form explains, not of the whole training error,
        # which other effects may dominate (a saturation beside a resonance that left 1.54 um in
        # training: the saturation forms differed by 0.005 um and the one that fitted better
        # validated 30 % lower)
        band = T.FORM_TIE * max(base.metrics["train"]["rmse"] - train[best], 0.0)
        tied = [k for k in range(len(fits)) if train[k] - train[best] <= band]
        best = min(tied, key=lambda k: (free_parameters(fits[k].model), k))
    if choice == "inner-blocks" and best > 0:
        # a richer form must fit the training rows better and predict held-back blocks of them
        # better too (decision 0034)
        chosen = choose_by_inner_blocks(paths, [specs[0], specs[best]], kw, base.model)
        best = best if chosen == specs[best] else 0
    return fits[best]
