"""A compensator's operating range: the commands the model knows and the outputs it can reach.

A fitted model is only known over the inputs it was fitted on (``model.norm["u_min"]`` and
``["u_max"]``, set by :meth:`hilbench.models.Model.prepare` from the training rows). Models saved
before those keys existed fall back to ``[-u_scale, u_scale]`` (``u_scale`` = max |u| of training),
which is exact for the bipolar drives of the shipped rigs and too wide for a unipolar one; the
fallback is named in the compensator's notes.

The *static map* is the model with its ``dynamics`` and ``delay`` switched off and its auxiliary
channels held at their references (the compensator inverts exactly that; a tracking run inverts
the dynamics and the delay over its whole reference beforehand, :mod:`hilbench.online.preview`). Its *major loop* over a
command range ``[a, b]`` is traced as the rig would: from rest to ``a``, up to ``b``, down to ``a``
(which wipes the model's memory), then the ascending branch ``a -> b`` and the descending branch
``b -> a`` are kept (:data:`BRANCH_SAMPLES` samples each, at the model's sample rate; a model with
rate-dependence or creep is traced as a 1 Hz loop, :data:`SLOW_BRANCH_S` per branch, and so evaluated
at that ramp's rate: traced fast, its branch keeps rising after a reversal).

A branch *rises* when, walked with increasing command, it never falls by more than
:data:`FALL_TOLERANCE` of the loop's output span below its running maximum: a dip that small
moves the solver's root by less than that share of the output and is within a fit's error, a
larger one means two commands give one output and the solver may land on the falling part (the
general inverse's failure this module was written for: a pmpi fitted on +-6 A whose cubic turns
over beyond, solved on the rig's +-6.5 A, sat at the rail).

A map may also *fall* (a magnetostrictive rod whose strain shrinks with the current over its bias):
a branch then is walked the same way on the negated output, and the compensator solves on the map
with its sign (``direction`` -1). Where the loop over the fitted range is monotone in neither
direction (a figure eight: paper 001's D-model as the gmm-issf-duhem rig simulates it, whose
branches turn over inside the range), the operating range is the sub-range of the fitted inputs,
on a grid of :data:`SUBRANGE_STEPS`, whose own major loop is monotone and reaches the widest span
of outputs: only there does one output have one command; the reachable output range says how
little that may be, and a reference beyond it is refused naming it.

The operating range is the fitted range within the rig's limits, widened towards each limit in
:data:`WIDEN_STEPS` equal steps only while the loop over the widened range still rises on both
branches and falls nowhere more than it did over the fitted range (extrapolating a model is safe
only as far as it stays monotone; the tolerance is for the data the model has seen, not for its
extrapolation). The reachable output
range is the range of that loop's outputs (um).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hilbench.errors import UserError
from hilbench.models import stepping as ST

__all__ = ["OperatingRange", "fitted_input_range", "static_major_loop", "branch_fall", "branch_samples",
           "operating_range", "BRANCH_SAMPLES", "SLOW_BRANCH_S", "FALL_TOLERANCE", "WIDEN_STEPS", "SUBRANGE_STEPS"]

#: samples per branch of the traced major loop
BRANCH_SAMPLES = 400
#: a model with memory in time (rate-dependence, creep) is traced at least this slowly (s per branch:
#: a 1 Hz loop, the quasi-static drive of most plans): traced fast, a rate-dependent branch keeps
#: rising after its reversal, a fall that is the ramp's, not the map's, and creep has no time to act
SLOW_BRANCH_S = 0.5
#: largest accepted fall of a branch below its running maximum, share of the loop's output span
FALL_TOLERANCE = 0.005
#: steps in which the fitted range is widened towards each rig limit
WIDEN_STEPS = 8
#: grid (intervals over the fitted range) on which a monotone sub-range is searched when the loop over
#: the whole fitted range is not monotone: ends to 1/24 of the range (0.5 A of +-6 A)
SUBRANGE_STEPS = 24


@dataclass
class OperatingRange:
    """Where a compensator works: command ranges (command units) and the reachable outputs (um)."""

    fitted: tuple[float, float]  # the inputs the model was fitted on (within the rig's limits)
    source: str  # where ``fitted`` came from
    command: tuple[float, float]  # ``fitted`` widened towards the rig's limits while the map rises
    output: tuple[float, float]  # reachable outputs: the static major loop's range over ``command``, um
    rising: bool  # both branches of the loop over ``fitted`` are monotone (in ``direction``)
    fall_um: float = 0.0  # the largest fall found over ``fitted`` (um) ...
    fall_from: tuple[float, float] = (0.0, 0.0)  # ... from (command, output) ...
    fall_to: tuple[float, float] = (0.0, 0.0)  # ... to (command, output), on ...
    fall_branch: str = ""  # ... this branch
    limits: tuple[float, float] = (0.0, 0.0)
    slope: float = 0.0  # mean slope of the ascending branch over ``command``, um per command unit
    direction: int = 1  # +1: the output rises with the command over ``command``; -1: it falls
    sub_range: bool = False  # ``command`` is the monotone part of a fitted range that is not
    loop_output: tuple[float, float] = (0.0, 0.0)  # the range of the loop over ``fitted`` (um), overshoots included
    planned: bool = False  # ``command`` is ``fitted`` again and ``output`` its loop's: a planned path runs there
    notes: list[str] = field(default_factory=list)

    def plan_over_fitted(self) -> None:
        """Work over the whole fitted range with a path planned over a known reference
        (:mod:`hilbench.online.path_plan`): what it reaches is the loop's whole range."""
        self.command, self.output, self.planned = self.fitted, self.loop_output, True

    @property
    def invertible(self) -> bool:
        """One output has one command over ``command``: the loop there is monotone."""
        return self.rising or self.sub_range

    def describe(self, unit: str = "") -> dict[str, Any]:
        return {"fitted_input": list(self.fitted), "fitted_input_source": self.source,
                "command": list(self.command), "reachable_output_um": list(self.output), "rising": self.rising,
                "direction": "rising" if self.direction > 0 else "falling", "monotone_sub_range": self.sub_range,
                "largest_fall_um": self.fall_um, "planned_path": self.planned, "unit": unit}

    def not_rising(self, spec: str, unit: str = "") -> str:
        """The refusal's message when the loop over the fitted range is not monotone and no sub-range
        of it is (one line)."""
        (u0, y0), (u1, y1) = self.fall_from, self.fall_to
        lo, hi = self.fitted
        way = "falls" if self.direction > 0 else "rises"
        return (f"the static map of {spec!r} is not monotone over its operating range [{lo:.4g}, {hi:.4g}] {unit} "
                f"({self.source}) nor over any part of it: its {self.fall_branch} branch {way} by {self.fall_um:.4g} "
                f"um, from {y0:.4g} um at {u0:.4g} {unit} to {y1:.4g} um at {u1:.4g} {unit} (more than "
                f"{100 * FALL_TOLERANCE:g} % of the loop's span); two commands give one output there, so the inverse "
                "is not defined").replace("  ", " ")

    def sub_range_note(self, unit: str = "") -> str:
        """What the compensator says when it works on a monotone part of the fitted range."""
        u0, u1 = self.fall_from[0], self.fall_to[0]
        way = "falls" if self.direction > 0 else "rises"
        return (f"the static map is not monotone over the fitted [{self.fitted[0]:.4g}, {self.fitted[1]:.4g}] {unit} "
                f"(its {self.fall_branch} branch {way} back by {self.fall_um:.4g} um from {u0:.4g} to {u1:.4g} {unit}): "
                f"the compensator works on [{self.command[0]:.4g}, {self.command[1]:.4g}] {unit}, the part whose loop "
                f"is monotone with the widest reach, [{self.output[0]:.4g}, {self.output[1]:.4g}] um").replace("  ", " ")


def fitted_input_range(model: Any, limits: tuple[float, float]) -> tuple[tuple[float, float], str]:
    """The input range the model was fitted on, within ``limits``, and where it came from."""
    lo, hi = limits
    norm = model.norm
    if "u_min" in norm and "u_max" in norm:
        a, b = float(norm["u_min"]), float(norm["u_max"])
        source = "the inputs it was fitted on"
    else:
        us = float(norm.get("u_scale", max(abs(lo), abs(hi))))
        a, b = -us, us
        source = "+-u_scale: the model file predates the recorded fitted range"
    if a < lo or b > hi:
        source += f", cut to the rig's [{lo:.4g}, {hi:.4g}]"
    a, b = max(a, lo), min(b, hi)
    if not b > a:
        raise UserError(f"model {model.spec!r} was fitted on inputs [{norm.get('u_min', a):.4g}, "
                        f"{norm.get('u_max', b):.4g}], which the rig's command range [{lo:.4g}, {hi:.4g}] "
                        "does not overlap: the model knows nothing of this rig's commands",
                        hint="fit the model on a recording of this rig")
    return (a, b), source


def static_major_loop(I: np.ndarray, P: np.ndarray, aux_ref: np.ndarray, a: float, b: float,
                      n: int = BRANCH_SAMPLES) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(u, y_up, y_down)``: the static model's major loop over ``[a, b]`` (command units), both
    branches on the same ascending grid ``u`` (um). ``I`` must have dynamics and delay off."""
    X = np.zeros(int(I[ST.I_NX]))
    aux = np.ascontiguousarray(np.broadcast_to(aux_ref, (n, aux_ref.size)))
    out = np.empty(n)
    start = min(max(0.0, a), b)
    for u0, u1 in ((start, a), (a, b), (b, a)):  # from rest, then one full cycle wipes the memory
        ST.model_block(I, P, X, np.linspace(u0, u1, n), aux, out)
    u = np.linspace(a, b, n)
    ST.model_block(I, P, X, u, aux, out)
    y_up = out.copy()
    ST.model_block(I, P, X, np.ascontiguousarray(u[::-1]), aux, out)
    return u, y_up, out[::-1].copy()


def branch_fall(u: np.ndarray, y: np.ndarray) -> tuple[float, int, int]:
    """The largest fall of ``y`` below its running maximum along increasing ``u``: (um, from, to)."""
    peak = np.maximum.accumulate(y)
    k = int(np.argmax(peak - y))
    fall = float(peak[k] - y[k])
    j = int(np.argmax(y[: k + 1])) if k > 0 else 0
    return fall, j, k


def branch_samples(I: np.ndarray, sample_rate_hz: float | None) -> int:
    """Samples per traced branch: :data:`BRANCH_SAMPLES`, or :data:`SLOW_BRANCH_S` at the model's rate
    for a model with rate-dependence or creep."""
    timed = int(I[ST.I_RATE]) != 0 or int(I[ST.I_NCREEP]) != 0
    if not timed or not sample_rate_hz:
        return BRANCH_SAMPLES
    return max(BRANCH_SAMPLES, int(SLOW_BRANCH_S * sample_rate_hz))


def _loop_monotone(I: np.ndarray, P: np.ndarray, aux_ref: np.ndarray, a: float, b: float,
                   n: int = BRANCH_SAMPLES, direction: int = 0) -> tuple[bool, dict[str, Any]]:
    """Whether the major loop over ``[a, b]`` is monotone on both branches, and where it turns most.
    ``direction`` +1 / -1 asks for that sense; 0 takes the sense of the ascending branch's ends."""
    u, up, down = static_major_loop(I, P, aux_ref, a, b, n)
    y_lo, y_hi = float(min(up.min(), down.min())), float(max(up.max(), down.max()))
    span = max(y_hi - y_lo, 1e-300)
    slope = (float(up[-1]) - float(up[0])) / (b - a)
    sense = direction or (1 if slope >= 0.0 else -1)
    worst: dict[str, Any] = {"fall": -1.0}
    for name, y in (("ascending", up), ("descending", down)):
        fall, j, k = branch_fall(u, sense * y)
        if fall > worst["fall"]:
            worst = {"fall": fall, "branch": name, "from": (float(u[j]), float(y[j])), "to": (float(u[k]), float(y[k]))}
    finite = bool(np.all(np.isfinite(up)) and np.all(np.isfinite(down)))
    worst.update(output=(y_lo, y_hi), slope=slope, direction=sense)
    return finite and worst["fall"] <= FALL_TOLERANCE * span and sense * slope > 0.0, worst


def _monotone_sub_range(I: np.ndarray, P: np.ndarray, aux_ref: np.ndarray, a: float, b: float,
                        n: int) -> tuple[tuple[float, float], dict[str, Any]] | None:
    """The sub-range of ``[a, b]`` on a :data:`SUBRANGE_STEPS` grid whose major loop is monotone (either
    sense) and reaches the widest output span; None when no interval of two grid steps is. An
    interval is grown from each start until its loop stops being monotone (a loop that turns over on
    [c, d] turns over on the wider ones too: the turn is inside)."""
    grid = np.linspace(a, b, SUBRANGE_STEPS + 1)
    best: tuple[float, tuple[float, float], dict[str, Any]] | None = None
    for i in range(grid.size - 2):
        for sense in (1, -1):
            for j in range(i + 2, grid.size):
                ok, found = _loop_monotone(I, P, aux_ref, float(grid[i]), float(grid[j]), n, sense)
                if not ok:
                    break
                reach = found["output"][1] - found["output"][0]
                if best is None or reach > best[0]:
                    best = (reach, (float(grid[i]), float(grid[j])), found)
    return None if best is None else (best[1], best[2])


def _aux_values(aux_ref: Any) -> np.ndarray:
    """The aux channels' reference values as a flat float array (one 0 for a model without any)."""
    return np.asarray(aux_ref, float).ravel() if np.size(aux_ref) else np.zeros(1)


def narrowed(found: OperatingRange, I: np.ndarray, P: np.ndarray, aux_ref: np.ndarray, command: tuple[float, float],
             sample_rate_hz: float | None = None) -> OperatingRange | None:
    """``found`` with its command range narrowed to ``command`` (inside it) and the reach traced again
    there; None when the loop over ``command`` is not monotone in ``found``'s direction."""
    ok, worst = _loop_monotone(I, P, _aux_values(aux_ref), command[0], command[1], branch_samples(I, sample_rate_hz),
                               found.direction)
    if not ok:
        return None
    return replace(found, command=(float(command[0]), float(command[1])), output=worst["output"],
                   slope=worst["slope"], notes=list(found.notes))


def operating_range(model: Any, I: np.ndarray, P: np.ndarray, aux_ref: np.ndarray,
                    limits: tuple[float, float], *, widen: bool = True,
                    sample_rate_hz: float | None = None) -> OperatingRange:
    """The model's operating range on a rig with command ``limits`` (see the module docstring).
    ``I, P``: the compiled model with dynamics and delay off; ``aux_ref``: the aux channels' values;
    ``sample_rate_hz``: the model's rate (a model with memory in time is traced slowly at it)."""
    (a, b), source = fitted_input_range(model, limits)
    aux_ref = _aux_values(aux_ref)
    n = branch_samples(I, sample_rate_hz)
    rises, worst = _loop_monotone(I, P, aux_ref, a, b, n)
    result = OperatingRange((a, b), source, (a, b), worst["output"], rises, max(worst["fall"], 0.0),
                            worst.get("from", (a, 0.0)), worst.get("to", (b, 0.0)), worst.get("branch", ""),
                            (float(limits[0]), float(limits[1])), worst["slope"], worst["direction"])
    result.loop_output = worst["output"]
    if not rises:
        part = _monotone_sub_range(I, P, aux_ref, a, b, n)
        if part is not None:
            result.command, found = part
            result.output, result.slope, result.direction = found["output"], found["slope"], found["direction"]
            result.sub_range = True
        return result
    if not widen:
        return result
    lo, hi = limits
    sense = result.direction
    for side in ("low", "high"):
        limit = lo if side == "low" else hi
        edge = a if side == "low" else b
        if edge == limit:
            continue
        for step in range(1, WIDEN_STEPS + 1):
            trial = edge + (limit - edge) * step / WIDEN_STEPS
            c, d = (trial, b) if side == "low" else (a, trial)
            ok, found = _loop_monotone(I, P, aux_ref, c, d, n, sense)
            # beyond the fitted range the model is extrapolated: no fall at all is accepted there
            # (a cubic turning over near the rail, 0.4 um on a 95 um loop, is where a solve goes wrong)
            span = found["output"][1] - found["output"][0]
            if not ok or found["fall"] > result.fall_um + 1e-9 * span:
                break
            a, b = c, d
            result.command, result.output = (a, b), found["output"]
            result.slope = found["slope"]
    if result.command != result.fitted:
        result.notes.append(f"operating range widened from the fitted [{result.fitted[0]:.4g}, {result.fitted[1]:.4g}] "
                            f"to [{a:.4g}, {b:.4g}] within the rig's limits, where the static map stays monotone")
    return result
