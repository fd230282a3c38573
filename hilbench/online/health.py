"""A tracking run's own health (DESIGN.md, "The closed loop on any rig"): is the result what the
model promised, or did the loop run out of actuator?

Three figures, each a share or a percentage of the run:

``at_limit_pct``     samples whose command sat at an end of the compensator's command range (the
                     rig's ``min``/``max``, or the model's operating range for the general inverse):
                     the inverse wanted more than it may ask for, the output cannot follow.
``slew_limited_pct`` samples the rig's safety path slew-limited (:func:`hilbench.rig.safety.command_path`:
                     the applied command differs from the command clamped to the limits), counted
                     apart from the limit: a reference too fast for the amplifier, not too large.
``erms_pct``         the tracking error (rms e over the reference's span, the metric key) against
                     the model's own validation error (its ``metrics.validation``, else
                     ``metrics.train``) from the fit, *on the same span*: the model's rmse (um) over
                     the reference's span, ``model_erms_on_reference_pct``. The model's ``erms_pct``
                     is over the span of the data it was scored on, usually the whole recorded
                     range; a reference over half of it would double the ratio of the same error in
                     um (decision 0116).

A run is *degraded* when

- more than :data:`MAX_LIMITED_PCT` (1 %) of its samples sat at a limit, or more than 1 % were
  slew-limited. A sine touching its peak command for a handful of samples is normal; 1 % of a
  1 Hz cycle (10 ms around each peak at 1 kHz) is already a visibly flattened peak, and a
  reference that needs the rail for longer cannot be tracked whatever the model;
- or the tracking ``erms_pct`` exceeds ``max(ERROR_FACTOR x m, m + ERROR_MARGIN_PCT)`` with ``m`` the
  model's error on the reference's span (2x, +0.3 points). The factor is the usual "within twice
  the model's error" of measurement practice (the inverse adds the solver's and the plant's noise
  to the model's error); the margin keeps a very good model (0.04 % validation error) from flagging
  a run whose error is dominated by sensor noise and quantisation. A model file without its rmse
  (none written by hilbench) is compared by its ``erms_pct`` as it stands.

``--strict`` (CLI) turns a degraded run into exit status :data:`DEGRADED_EXIT` (3; 2 is for errors
the user can fix before the run, this run happened and is recorded).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["run_health", "health_line", "MAX_LIMITED_PCT", "MAX_SLEW_PCT", "ERROR_FACTOR", "ERROR_MARGIN_PCT", "DEGRADED_EXIT",
           "model_validation_erms_pct", "model_validation_metric"]

MAX_LIMITED_PCT = 1.0
MAX_SLEW_PCT = 1.0
ERROR_FACTOR = 2.0
ERROR_MARGIN_PCT = 0.3
DEGRADED_EXIT = 3


def model_validation_metric(model: Any, key: str) -> tuple[float | None, str]:
    """The model's own metric ``key`` from its fit, validation split first: (value, which split), or
    (None, "") when unknown."""
    metrics = (getattr(model, "info", {}) or {}).get("metrics", {}) or {}
    for split in ("validation", "train"):
        value = (metrics.get(split) or {}).get(key)
        if value is not None and np.isfinite(float(value)):
            return float(value), split
    return None, ""


def model_validation_erms_pct(model: Any) -> tuple[float | None, str]:
    """The model's own erms_pct from its fit: (value, which split), or (None, "") when unknown."""
    return model_validation_metric(model, "erms_pct")


def run_health(command: np.ndarray, applied: np.ndarray, command_range: tuple[float, float],
               limits: tuple[float, float], erms_pct: float, model: Any,
               reference_span_um: float | None = None) -> dict[str, Any]:
    """The health figures and verdict of a run (see the module docstring); JSON-ready.
    ``erms_pct``: the tracking rmse over ``reference_span_um`` (the reference's peak-to-peak, um)."""
    n = max(int(command.size), 1)
    lo, hi = command_range
    tol = 1e-9 * (hi - lo)
    at_limit = int(np.count_nonzero((command <= lo + tol) | (command >= hi - tol)))
    # the slew limiter acted where the applied command is not the command clamped to the limits
    clamped = np.clip(np.where(np.isfinite(command), command, applied), limits[0], limits[1])
    slewed = int(np.count_nonzero(applied != clamped))
    model_erms, split = model_validation_erms_pct(model)
    model_rmse, rmse_split = model_validation_metric(model, "rmse")
    # the model's error on the reference's span: the same denominator as the tracking erms_pct
    on_reference = None
    if model_rmse is not None and rmse_split == split and reference_span_um and reference_span_um > 0:
        on_reference = 100.0 * model_rmse / float(reference_span_um)
    yardstick = on_reference if on_reference is not None else model_erms
    allowed = None if yardstick is None else max(ERROR_FACTOR * yardstick, yardstick + ERROR_MARGIN_PCT)
    health: dict[str, Any] = {
        "samples": int(command.size),
        "at_limit_samples": at_limit, "at_limit_pct": 100.0 * at_limit / n,
        "slew_limited_samples": slewed, "slew_limited_pct": 100.0 * slewed / n,
        "command_range": [float(lo), float(hi)],
        "erms_pct": float(erms_pct), "model_erms_pct": model_erms, "model_erms_split": split or None,
        "model_rmse_um": model_rmse if on_reference is not None else None,
        "model_erms_on_reference_pct": on_reference,
        "erms_allowed_pct": allowed,
        "thresholds": {"at_limit_pct": MAX_LIMITED_PCT, "slew_limited_pct": MAX_SLEW_PCT,
                       "erms_factor": ERROR_FACTOR, "erms_margin_pct": ERROR_MARGIN_PCT},
    }
    reasons = []
    if health["at_limit_pct"] > MAX_LIMITED_PCT:
        reasons.append(f"{health['at_limit_pct']:.3g} % of samples at a command limit (> {MAX_LIMITED_PCT:g} %)")
    if health["slew_limited_pct"] > MAX_SLEW_PCT:
        reasons.append(f"{health['slew_limited_pct']:.3g} % of samples slew-limited (> {MAX_SLEW_PCT:g} %)")
    if allowed is not None and not erms_pct <= allowed:
        reasons.append(f"tracking erms {erms_pct:.3g} % > {allowed:.3g} % allowed by the model's {split} error "
                       f"({_model_error(health)})")
    health["degraded"] = bool(reasons)
    health["reasons"] = reasons
    return health


def _model_error(health: dict[str, Any]) -> str:
    """The model's own error as the verdict compares it: on the reference's span when known."""
    if health.get("model_erms_on_reference_pct") is not None:
        return (f"rmse {health['model_rmse_um']:.3g} um, {health['model_erms_on_reference_pct']:.3g} % of the "
                f"reference's span; {health['model_erms_pct']:.3g} % of its own data's span")
    return f"erms {health['model_erms_pct']:.3g} %"


def health_line(health: dict[str, Any]) -> str:
    """One line for the text output."""
    model = (f" (model's {health['model_erms_split']} {_model_error(health)}; allowed "
             f"{health['erms_allowed_pct']:.3g} %)" if health.get("model_erms_pct") is not None else
             " (the model's own error is unknown)")
    verdict = "DEGRADED: " + "; ".join(health["reasons"]) if health["degraded"] else "ok"
    return (f"health: {health['at_limit_pct']:.3g} % of samples at a limit, {health['slew_limited_pct']:.3g} % "
            f"slew-limited, erms {health['erms_pct']:.3g} %{model} - {verdict}")
