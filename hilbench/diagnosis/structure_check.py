"""The hysteresis inside the mechanics is a finding too: when the data show mechanics, try the structure.

Every base and effect the diagnosis tries is a static hysteresis followed by linear dynamics. When
the hysteretic element is the spring of a mass-spring-damper (``bouc-wen+restoring-force``,
:mod:`hilbench.models.restoring_force`; the public Bouc-Wen benchmark), no effect on such a model can
make the loop change with frequency as the oscillator makes it: on the benchmark ``bouc-wen``
validates at 5.8e-4 m, with ``dynamics`` 1.75e-4 m, and the structure at 8.7e-6 m (the sensor noise
is 8e-6 m). So, as another base is tried when the loop has the wrong shape
(:mod:`hilbench.diagnosis.base_check`), the structure is tried when the data show mechanics
(:func:`mechanics`):

* a second-order dynamics identified on the data (the base's own, or the diagnosis's refit with
  ``dynamics``, which must have lowered the training error) is a resonance, zeta below 1/sqrt(2);
* the drive excites it: at least MECHANICS_DRIVE_SHARE of the input's power lies within an octave
  of the natural frequency (a triangle whose corners ring a resonance 30 times faster than it puts
  ~1e-4 there; below resonance the oscillator is its static map and the structures agree);
* the residual follows it: the current model's error holds at least as large a share of its power
  within that octave as the drive (on the benchmark 0.82-0.91 against 0.42). A resonance the model
  already describes leaves its error elsewhere.

As for another base, the structure is tried only on a base with memory whose validation error
exceeds WRONG_BASE_NOISE_FACTOR noise floors, and it is significant when it lowers the validation
rmse WRONG_BASE_RATIO times, and as much against the best single effect on the current model, with
training lower too, the block test significant and its free run healthy
(:mod:`hilbench.identify.health`). It is the candidate ``restoring-force`` whose spec replaces the
model, so ``--auto`` switches to it; the structure is a whole model, so nothing is added after it.
Decision 0103.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hilbench import progress
from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.significance import improvement_test
from hilbench.diagnosis.verdict import Candidate, relative_gain, validation_errors
from hilbench.errors import UserError
from hilbench.identify.fitting import FitResult, fit
from hilbench.identify.resonance import contiguous_stretches, residual_spectrum
from hilbench.models.model import Model, split_spec
from hilbench.models.restoring_force import RestoringForce

#: the candidate's name: the model effect that puts the base's hysteresis inside the mechanics
STRUCTURE = RestoringForce.name


def whole_model(spec: str) -> str | None:
    """The name of the structure that makes ``spec`` one state equation (``restoring-force``), else None."""
    structure = Model(spec).structure
    return structure.name if structure is not None else None


def structure_spec(spec: str) -> str:
    """The structure for a model ``spec``: its base inside the mechanics when the kernel has that law
    (``bouc-wen(n=2)`` keeps its options), else the first law built (``pi`` -> ``bouc-wen``)."""
    base = spec.split("+")[0].strip()
    law = base if split_spec(spec)[0][0] in RestoringForce.LAWS else RestoringForce.LAWS[0]
    return f"{law}+{STRUCTURE}"


def resonance_of(model: Any) -> tuple[float, float] | None:
    """(natural frequency Hz, zeta) of a model's second-order dynamics; None without one."""
    dyn = model.effect("dynamics")
    if dyn is None or str(dyn.options.get("kind", "second-order")) != "second-order":
        return None
    names = {p.name for p in dyn.params}
    if not {"natural_frequency_hz", "zeta"} <= names:
        return None
    return float(dyn.param("natural_frequency_hz")), float(dyn.param("zeta"))


def octave_share(stretches: Sequence[np.ndarray], fs: float, f_hz: float) -> float:
    """The share of the power of ``stretches`` (Welch, :func:`hilbench.identify.resonance.residual_spectrum`)
    within an octave either side of ``f_hz`` (f_hz / 2 .. 2 f_hz), 0 Hz left out; NaN when too short."""
    spectrum = residual_spectrum(stretches, fs)
    if spectrum is None:
        return math.nan
    freqs, psd = spectrum
    total = float(np.sum(psd[freqs > 0]))
    if not total > 0:
        return math.nan
    return float(np.sum(psd[(freqs >= f_hz / 2) & (freqs <= 2 * f_hz)])) / total


@dataclass
class Mechanics:
    """Whether the data show mechanics (module docstring), with the figures; ``reason`` when they do not."""

    applies: bool
    reason: str = ""
    evidence: dict[str, Any] = field(default_factory=dict)


def _scored_stretches(result: FitResult) -> tuple[list[np.ndarray], list[np.ndarray], float]:
    """The input and the model's error on the scored rows (training and validation), by contiguous stretch."""
    inputs, errors = [], []
    fs = math.nan
    for r in result.runs:
        if r.simulated is None or r.simulated.shape != r.data.output.shape:
            continue
        rows = np.flatnonzero((r.train | r.validation) & np.isfinite(r.data.output) & np.isfinite(r.simulated))
        if rows.size == 0:
            continue
        fs = float(r.data.sample_rate_hz)
        inputs += contiguous_stretches(r.data.input[rows], rows)
        errors += contiguous_stretches((r.simulated - r.data.output)[rows], rows)
    return inputs, errors, fs


def mechanics(base: FitResult, cands: Sequence[Candidate]) -> Mechanics:
    """Do the data show a resonance the drive excites and the model's error follows (module docstring)?"""
    found, source = resonance_of(base.model), "the model's own dynamics"
    if found is None:
        dyn = next((c for c in cands if c.effect == "dynamics" and c.fitted is not None), None)
        if dyn is not None and dyn.fitted.metrics["train"]["rmse"] < base.metrics["train"]["rmse"]:
            found, source = resonance_of(dyn.fitted.model), "the refit with dynamics"
    if found is None:
        return Mechanics(False, "no second-order dynamics identified on the data (the model has none and a "
                                "refit with dynamics was not tried or did not lower the training error)")
    fn, zeta = found
    ev: dict[str, Any] = {"natural_frequency_hz": fn, "zeta": zeta, "identified_by": source}
    where = f"{source} put the natural frequency at {fn:.4g} Hz, zeta {zeta:.3g}"
    if not zeta < T.MECHANICS_MAX_ZETA:
        return Mechanics(False, f"{where}: no resonance (zeta >= {T.MECHANICS_MAX_ZETA:.3g})", ev)
    inputs, errors, fs = _scored_stretches(base)
    if not math.isfinite(fs):
        return Mechanics(False, "no scored rows to look at", ev)
    drive, residual = octave_share(inputs, fs, fn), octave_share(errors, fs, fn)
    ev.update({"drive_power_share": drive, "residual_power_share": residual})
    if not drive >= T.MECHANICS_DRIVE_SHARE:
        return Mechanics(False, f"{where}, outside the drive's band: {100 * drive:.2g} % of the input's power lies "
                                f"within an octave of it, under the {100 * T.MECHANICS_DRIVE_SHARE:g} % that excites "
                                "the mechanics", ev)
    if not residual >= drive:
        return Mechanics(False, f"{where}, but the error does not follow it: {100 * residual:.2g} % of its power lies "
                                f"within an octave of it, against {100 * drive:.2g} % of the input's", ev)
    sentence = (f"{where}; {100 * drive:.2g} % of the input's power and {100 * residual:.2g} % of the error's lie "
                "within an octave of it")
    ev["sentence"] = sentence
    return Mechanics(True, "", ev)


def worth_trying(base: FitResult, noise: float) -> bool:
    """As for another base: a base with memory whose validation error is well above the noise."""
    current = split_spec(base.spec)[0][0]
    return current != "linear" and base.metrics["validation"]["rmse"] > T.WRONG_BASE_NOISE_FACTOR * noise


def fit_structure(paths: Any, base: FitResult, kw: dict[str, Any]) -> FitResult | None:
    """The structure for ``base`` fitted on the user's split; None when it cannot be fitted."""
    spec = structure_spec(base.spec)
    try:
        with progress.task(f"diagnose {base.spec}: the structure {spec}", total=1) as advance:
            fitted = fit(paths, spec, **kw)
            advance(1, f"{spec} done")
        return fitted
    except UserError:
        return None  # e.g. a drive the output does not follow (the linear start's gain not positive)


def structure_candidate(base: FitResult, fitted: FitResult, found: Mechanics, noise: float,
                        effect_rmse: Sequence[float] = ()) -> Candidate:
    """The candidate ``restoring-force``: ``fitted`` (the structure) judged against ``base`` and the
    best single effect's validation rmse ``effect_rmse`` (module docstring)."""
    old_v, old_t = base.metrics["validation"]["rmse"], base.metrics["train"]["rmse"]
    new_v, new_t = fitted.metrics["validation"]["rmse"], fitted.metrics["train"]["rmse"]
    p, better, blocks = improvement_test(validation_errors(base), validation_errors(fitted))
    best_effect = min([old_v, *[v for v in effect_rmse if math.isfinite(v)]])
    health = fitted.health or {"status": "ok", "reasons": []}
    ratio = T.WRONG_BASE_RATIO
    checks = {
        f"validation_{ratio:g}x_lower": new_v * ratio <= old_v,
        f"{ratio:g}x_lower_than_any_effect": new_v * ratio <= best_effect,
        "training_lower_too": new_t < old_t,
        "blocks_p_below_0.01": p < T.P_MAX,
        "fit_healthy": health.get("status") == "ok",
    }
    sentence = (f"the hysteresis sits inside the mechanics: {found.evidence['sentence']}; the structure {fitted.spec!r} "
                f"(the hysteresis as the spring of a mass-spring-damper) fits with validation rmse {new_v:.4g} against "
                f"{old_v:.4g} ({old_v / max(new_v, 1e-300):.3g}x lower; the best single effect on {base.spec!r} reaches "
                f"{best_effect:.4g})")
    evidence = {"validation_rmse": [old_v, new_v], "train_rmse": [old_t, new_t], "p_value": p,
                "best_effect_rmse": best_effect, "blocks_improved": [better, blocks], "noise_floor": noise,
                "checks": checks, "spec": fitted.spec, "mechanics": {k: v for k, v in found.evidence.items()
                                                                      if k != "sentence"},
                "health": health, "replacement": "the structure"}
    return Candidate(STRUCTURE, fitted.spec, all(checks.values()), relative_gain(old_v, new_v), sentence, evidence,
                     fitted=fitted, unit=base.output_unit, replaces_model=True)


def structure_check(paths: Any, base: FitResult, cands: Sequence[Candidate], noise: float, kw: dict[str, Any],
                    untestable: list[dict[str, str]]) -> Candidate | None:
    """The structure candidate when the data show mechanics; else None, and the reason appended to
    ``untestable`` when the question was open (:func:`worth_trying`)."""
    if whole_model(base.spec) is not None or not worth_trying(base, noise):
        return None
    found = mechanics(base, cands)
    if not found.applies:
        untestable.append({"effect": STRUCTURE, "reason": found.reason})
        return None
    fitted = fit_structure(paths, base, kw)
    if fitted is None:
        untestable.append({"effect": STRUCTURE, "reason": f"{structure_spec(base.spec)!r} could not be fitted"})
        return None
    effect_rmse = [c.evidence["validation_rmse"][1] for c in cands if "validation_rmse" in c.evidence]
    return structure_candidate(base, fitted, found, noise, effect_rmse)
