"""No silent blow-ups: a fitted model whose free run or weights are out of all proportion to the data.

Two checks, each with the numbers in its reason (``fit`` and ``evaluate`` put them in the notes,
the JSON's ``health`` and the model file, so ``diagnose``, ``show`` and a later ``fit --model``
see them):

* **free run**: the simulated output leaves the measured output's range by more than
  :data:`ESCAPE_SPANS` spans of it (max - min of the measured output) on any scored run, or is not
  finite. No model error is that large; it is an unstable filter, an operator fitted on a few
  samples, or a polynomial far outside its inputs.
* **weights**: a weight's lever, |w_j| times the largest span over the training rows of the columns of
  its block (a block's columns share a unit: the operators of one state, the powers of one input),
  exceeds :data:`LEVER_SPANS` output spans. Such a weight rests on rows where its column barely
  moves; on an input that moves the column further the output jumps by orders of magnitude. On the
  public Bouc-Wen benchmark ``duhem-d+dynamics`` fits g[r=-46.93] at -151,530 um/N: lever ~10^4 spans,
  a 1.24 m spike on the multisine test (issue 63); the other weights of that fit stay below 15 spans.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: a free run farther than this many measured spans beyond the measured range has diverged (the
#: bound ``online`` uses too)
ESCAPE_SPANS = 10.0
#: a weight whose lever exceeds this many output spans is extreme for the data's scale
LEVER_SPANS = 1000.0


def escape_spans(measured: np.ndarray, simulated: np.ndarray) -> float:
    """How far ``simulated`` leaves the range of ``measured``, in spans of it (0: within; inf: not finite)."""
    measured = measured[np.isfinite(measured)]
    if simulated.size == 0 or measured.size == 0:
        return 0.0
    if not np.all(np.isfinite(simulated)):
        return math.inf
    lo, hi = float(np.min(measured)), float(np.max(measured))
    span = max(hi - lo, 1e-12 * max(abs(lo), abs(hi), 1.0))
    return max(0.0, (float(np.max(simulated)) - hi) / span, (lo - float(np.min(simulated))) / span)


def weight_levers(model: Any, runs: list[Any], masks: list[np.ndarray]) -> list[tuple[str, float, float]]:
    """(name, weight, lever in output units) of every weight, from the training rows of ``runs``."""
    if model.weights is None or model.structure is not None or not len(model.weights):
        return []
    spans = np.zeros(len(model.weights))
    for run, mask in zip(runs, masks):
        if not mask.any():
            continue
        first = 0
        for block in model.static_columns(run):
            rows = block.matrix[mask]
            p = rows.shape[1]
            widest = float(np.max(np.ptp(rows, axis=0))) if rows.size else 0.0
            spans[first:first + p] = np.maximum(spans[first:first + p], widest)
            first += p
    return [(name, float(w), abs(float(w)) * float(s)) for name, w, s in zip(model.weight_names, model.weights, spans)]


def check(model: Any, runs: list[Any], output_unit: str = "um") -> dict[str, Any]:
    """The health of a fitted ``model`` on ``runs`` (:class:`hilbench.identify.dataset.FitRun` with
    ``simulated`` set): ``status`` ``ok`` or ``flagged``, ``reasons``, and the figures."""
    measured = [r.data.output[np.isfinite(r.data.output)] for r in runs if len(r.data)]
    every = np.concatenate(measured) if measured else np.zeros(0)
    reasons: list[str] = []
    worst_escape, worst_run = 0.0, ""
    for r in runs:
        scored = r.train | r.validation
        if r.simulated is None or not scored.any() or r.simulated.shape != r.data.output.shape:
            continue
        esc = escape_spans(every, r.simulated[scored])
        if esc > worst_escape:
            worst_escape, worst_run = esc, r.key
    if worst_escape > ESCAPE_SPANS:
        sim = next(r.simulated for r in runs if r.key == worst_run)
        peak = float(np.max(np.abs(sim[np.isfinite(sim)]), initial=0.0))
        what = "is not finite" if math.isinf(worst_escape) else f"leaves the measured range by {worst_escape:.3g} spans"
        reasons.append(f"the free run of run {worst_run} {what} (measured {float(every.min()):.4g}..{float(every.max()):.4g} "
                       f"{output_unit}, |y| up to {peak:.3g} {output_unit}; bound {ESCAPE_SPANS:g} spans)")
    span = float(np.ptp(every)) if every.size else 0.0
    levers = weight_levers(model, [r.data for r in runs], [r.train for r in runs])
    worst = max(levers, key=lambda t: t[2], default=None)
    lever_spans = worst[2] / span if worst is not None and span > 0 else 0.0
    if worst is not None and lever_spans > LEVER_SPANS:
        reasons.append(f"weight {worst[0]} = {worst[1]:.6g} is extreme for the data: its column moves so little on "
                       f"the training rows that it can move the output {lever_spans:.3g} output spans "
                       f"({span:.4g} {output_unit}) where the column is fully driven (bound {LEVER_SPANS:g})")
    return {"status": "flagged" if reasons else "ok", "reasons": reasons,
            "free_run_escape_spans": worst_escape if math.isfinite(worst_escape) else None,
            "largest_weight_lever_spans": lever_spans, "largest_lever_weight": worst[0] if worst else None}
