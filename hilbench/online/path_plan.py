"""A command path planned over a whole reference, for a static map that is not monotone.

Where the model's loop over its fitted inputs turns over (a figure eight: paper 001's D-model, whose
output keeps moving the same way for a while after the command reverses; a fractional polynomial
whose root terms turn a branch back after every reversal), one output has several commands and a
per-sample solve cannot tell which one the reference needs: the monotone part of the range
(:mod:`hilbench.online.operating_range`) reaches little of what the rig records. The overshoot after
a reversal is part of what the actuator can do, and a reference known before the run can use it:
reverse *before* the reference turns, so that the output's overshoot lands on the reference's
extremum.

The planner walks the model's static map over the reference's targets (the preview's, when the
model has dynamics), sample by sample, keeping the direction the command moves in:

* **move**: from the last command along that direction (at most the rig's slew per sample, inside
  the command range), the first command where the model's output crosses the target (a marched
  search, then an Illinois solve inside the crossing). A crossing beyond one sample's reach (past an
  overshoot that first takes the output away) is headed for at the slew rate once the error left
  where the command is exceeds :data:`PASS_TOLERANCE` of the loop's span, and then kept until met;
  with no crossing, the marched command with the smallest error (it holds when moving does not help);
* **turn with the reference**: when moving on does not meet the target this sample, moving back is
  tried too, and each choice is rolled out without turning over the samples either takes to meet
  it; the cheaper is kept (every reversal of a monotone map happens here, at the extremum);
* **turn early**: when the output heads for the reference's coming extremum, the command reverses
  at the first sample whose overshoot, if it reversed now, reaches that extremum (marched along the
  reversed direction until the output turns, and by no more than a few samples' worth of the
  reference's motion: more is another route, over a lobe's top). The turn is bisected between the
  last command and this one so the overshoot lands on the extremum; the direction is then kept
  until the reference has passed it.

For each sample it keeps the command, the model's output, the direction, and the stretch around the
command on which the model's output (from that sample's memory) is monotone, and the output's slope
there: at run time feed-forward replays the plan, and feedback adds its correction over that slope
inside that stretch (:mod:`hilbench.online.inverse_kernels`), so it moves the command only where one
output has one command (and only where :func:`feedback_samples` lets it). All of it is numba over explicit state, scratch passed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from hilbench.online.inverse_kernels import model_step

__all__ = ["MARCH_STEPS", "PASS_TOLERANCE", "STRETCH_STEPS", "PathPlan", "feedback_samples", "plan_path", "turning_points"]

#: the marched search's step: the command range over this many steps
MARCH_STEPS = 400
#: an error within this share of the loop's span is held rather than left through an overshoot (the
#: output first moves away there): the detour is for an error that grows
PASS_TOLERANCE = 1e-3
#: the monotone stretch around a planned command is searched this many march steps each way
STRETCH_STEPS = 16


@njit(cache=True, _nrt=False)
def _probe(I: np.ndarray, P: np.ndarray, X: np.ndarray, S: np.ndarray, u: float, aux: np.ndarray) -> float:
    """The model's output for command ``u`` from memory ``X`` (``S`` is overwritten, ``X`` is not)."""
    for i in range(X.size):
        S[i] = X[i]
    return model_step(I, P, S, u, aux)


@njit(cache=True, _nrt=False)
def _crossing(I: np.ndarray, P: np.ndarray, X: np.ndarray, S: np.ndarray, aux: np.ndarray, target: float,
              a: float, fa: float, b: float, fb: float, tol_u: float, tol_y: float) -> float:
    """Illinois regula falsi for ``f(u) = out(u) - target`` between ``a`` and ``b`` of opposite signs."""
    side = 0
    for _ in range(80):
        c = b - fb * (b - a) / (fb - fa) if fb != fa else 0.5 * (a + b)
        if not (min(a, b) < c < max(a, b)):
            c = 0.5 * (a + b)
        fc = _probe(I, P, X, S, c, aux) - target
        if abs(fc) <= tol_y or abs(b - a) <= tol_u:
            return c
        if fc * fb < 0.0:
            a, fa = b, fb
            b, fb = c, fc
            side = 0
        else:
            b, fb = c, fc
            side += 1
            if side >= 2:
                fa *= 0.5
    return b


@njit(cache=True, _nrt=False)
def _move(I: np.ndarray, P: np.ndarray, X: np.ndarray, S: np.ndarray, aux: np.ndarray, u: float, d: float,
          target: float, reach: float, h: float, lo: float, hi: float, tol_u: float,
          tol_y: float, tol_pass: float) -> tuple[float, float, float]:
    """From ``u`` along ``d``: the first command where the output crosses ``target`` and how far it
    is (command units; inf when the output does not cross it before the range ends). Within
    ``reach`` the crossing is the command; beyond it the command moves ``reach`` towards it (through
    an overshoot that first takes the output away) unless the command within reach with the
    smallest error (``u`` included) is within ``tol_pass`` of the target, which it then is; with no
    crossing, that command. Returns (command, its error, distance)."""
    e0 = _probe(I, P, X, S, u, aux) - target
    if abs(e0) <= tol_y:
        return u, e0, 0.0
    end = hi if d > 0.0 else lo
    best_u, best_e = u, e0
    prev_u, prev_e = u, e0
    step = min(h, reach) / 8.0  # small first steps: most samples move a little
    v = u
    while (end - v) * d > 0.0:
        v = v + d * step
        if (v - end) * d > 0.0:
            v = end
        e = _probe(I, P, X, S, v, aux) - target
        if e * e0 <= 0.0:
            c = _crossing(I, P, X, S, aux, target, prev_u, prev_e, v, e, tol_u, tol_y)
            if abs(c - u) <= reach:
                return c, _probe(I, P, X, S, c, aux) - target, abs(c - u)
            if abs(best_e) <= tol_pass:  # near enough where it is: no detour through an overshoot
                return best_u, best_e, abs(c - u)
            w = u + d * reach
            return w, _probe(I, P, X, S, w, aux) - target, abs(c - u)
        if abs(v - u) <= reach and abs(e) < abs(best_e):
            best_u, best_e = v, e
        prev_u, prev_e = v, e
        step = min(2.0 * step, h)
    return best_u, best_e, math.inf


@njit(cache=True, _nrt=False)
def _overshoot(I: np.ndarray, P: np.ndarray, X: np.ndarray, S: np.ndarray, aux: np.ndarray, u: float, d: float,
               s: float, h: float, lo: float, hi: float, tol_y: float) -> float:
    """How far the output goes on in direction ``s`` when the command reverses now (from ``u`` along
    ``d``): its extreme times ``s``, marched until the output has turned by more than ``tol_y``;
    -inf when it reaches the range's end without turning (a branch, not an overshoot)."""
    best = s * _probe(I, P, X, S, u, aux)
    v = u
    while True:
        nv = min(max(v + d * h, lo), hi)
        if nv == v:
            return -math.inf
        v = nv
        y = s * _probe(I, P, X, S, v, aux)
        if y > best:
            best = y
        elif y < best - tol_y:
            return best


@njit(cache=True, _nrt=False)
def _monotone_end(I: np.ndarray, P: np.ndarray, X: np.ndarray, S: np.ndarray, aux: np.ndarray, u: float, y0: float,
                  step: float, sense: float, lo: float, hi: float, steps: int) -> float:
    """From ``u`` (output ``y0``) in steps of ``step`` (signed), at most ``steps`` of them: the last
    command up to which the output keeps moving with ``sense`` (times the step's sign)."""
    end = u
    prev = y0
    way = sense if step > 0.0 else -sense
    for _ in range(steps):
        v = min(max(end + step, lo), hi)
        if v == end:
            break
        y = _probe(I, P, X, S, v, aux)
        if way * (y - prev) < 0.0:
            break
        end, prev = v, y
    return end


@njit(cache=True, _nrt=False)
def _stretch(I: np.ndarray, P: np.ndarray, X: np.ndarray, S: np.ndarray, aux: np.ndarray, u: float, d: float,
             h: float, lo: float, hi: float, steps: int) -> tuple[float, float, float]:
    """The stretch around ``u`` on which the output (from memory ``X``) is monotone, searched
    ``steps`` steps of ``h`` each way, and the output's slope there (um per command unit; its sign
    the stretch's sense, 0 where the output is flat)."""
    eps = 1e-3 * h
    y0 = _probe(I, P, X, S, u, aux)
    ua = max(u - eps, lo)
    ub = min(u + eps, hi)
    ya = _probe(I, P, X, S, ua, aux)
    yb = _probe(I, P, X, S, ub, aux)
    # the slope the way the command moves (behind it, a reversal's kink may lie within eps)
    uf, yf = (ub, yb) if d > 0.0 else (ua, ya)
    if uf == u:  # at the range's end: the other side
        uf, yf = (ua, ya) if d > 0.0 else (ub, yb)
    slope = (yf - y0) / (uf - u) if uf != u else 0.0
    sense = 1.0 if slope > 0.0 else (-1.0 if slope < 0.0 else d)  # flat here: the way the command moves
    top = _monotone_end(I, P, X, S, aux, u, y0, h, sense, lo, hi, steps)
    bottom = _monotone_end(I, P, X, S, aux, u, y0, -h, sense, lo, hi, steps)
    return bottom, top, slope


@njit(cache=True, _nrt=False)
def _rollout(I: np.ndarray, P: np.ndarray, X: np.ndarray, R: np.ndarray, S: np.ndarray, aux: np.ndarray, u: float,
             d: float, targets: np.ndarray, k: int, horizon: int, reach: float, h: float, lo: float, hi: float,
             tol_u: float, tol_y: float, tol_pass: float) -> float:
    """Sum of squared errors of moving along ``d`` only, from sample ``k`` for ``horizon`` samples, from
    memory ``X`` (``R``, ``S``: scratch): what one choice at a turn costs before the next."""
    for i in range(X.size):
        R[i] = X[i]
    cost = 0.0
    stop = min(targets.size, k + horizon)
    for j in range(k, stop):
        v, e, _ = _move(I, P, R, S, aux, u, d, targets[j], reach, h, lo, hi, tol_u, tol_y, tol_pass)
        cost += e * e
        model_step(I, P, R, v, aux)
        u = v
    return cost


@njit(cache=True, _nrt=False)
def plan_kernel(I: np.ndarray, P: np.ndarray, X: np.ndarray, S: np.ndarray, R: np.ndarray, Q: np.ndarray,
                aux: np.ndarray, u0: float,
                targets: np.ndarray, turns: np.ndarray, lo: float, hi: float, max_step: float, h: float,
                tol_y: float, tol_pass: float, out_u: np.ndarray, out_y: np.ndarray, out_dir: np.ndarray, out_lo: np.ndarray,
                out_hi: np.ndarray, out_slope: np.ndarray) -> None:
    """Plan the commands for ``targets`` from memory ``X`` and command ``u0`` (``X`` is advanced along
    the plan). ``turns[k]``: the index of the extremum the target heads for at sample k (k itself
    when it is one, n-1 for the end). ``max_step``: the largest command change per sample."""
    n = targets.size
    tol_u = 1e-12 * (hi - lo)
    u = min(max(u0, lo), hi)
    # the first direction: the one whose output meets the first target nearer
    d = 1.0 if _move(I, P, X, S, aux, u, 1.0, targets[0], max_step, h, lo, hi, tol_u, tol_y, tol_pass)[2] <= \
        _move(I, P, X, S, aux, u, -1.0, targets[0], max_step, h, lo, hi, tol_u, tol_y, tol_pass)[2] else -1.0
    keep_until = -1  # an early reversal is kept until the reference has passed its extremum
    short_of = -1  # the extremum whose overshoot was last seen falling short of it
    passing = False  # the command is passing an overshoot towards a crossing beyond one sample's reach
    for k in range(n):
        r = targets[k]
        v, e, far = _move(I, P, X, S, aux, u, d, r, max_step, h, lo, hi, tol_u, tol_y, tol_pass)
        if far > max_step and k > keep_until and not (passing and far < math.inf):
            # on along d, the output does not meet the target this sample: back, when that costs less
            # over the samples either takes to meet it (each choice rolled out without turning)
            vb, eb, farb = _move(I, P, X, S, aux, u, -d, r, max_step, h, lo, hi, tol_u, tol_y, tol_pass)
            if far == math.inf and farb == math.inf:
                turn = abs(eb) < abs(e) - tol_y
            else:
                longest = max(far if far < math.inf else 0.0, farb if farb < math.inf else 0.0)
                horizon = 8 + 4 * int(math.ceil(longest / max_step))
                turn = _rollout(I, P, X, R, S, aux, u, -d, targets, k, horizon, max_step, h, lo, hi, tol_u, tol_y, tol_pass) < \
                    _rollout(I, P, X, R, S, aux, u, d, targets, k, horizon, max_step, h, lo, hi, tol_u, tol_y, tol_pass)
            if turn:
                v, e, d, far = vb, eb, -d, farb
        # once through an overshoot, on until its crossing: turning back midway starts another one
        passing = max_step < far < math.inf and abs(e) > tol_pass
        out_lo[k], out_hi[k], out_slope[k] = _stretch(I, P, X, S, aux, v, d, h, lo, hi, STRETCH_STEPS)
        # where the output heads when the command goes on along d (0 at the range's end)
        on = min(max(v + d * 1e-3 * h, lo), hi)
        heading = _probe(I, P, X, S, on, aux) - _probe(I, P, X, S, v, aux) if on != v else 0.0
        out_u[k] = v
        out_dir[k] = d
        for i in range(X.size):
            Q[i] = X[i]  # the memory before this sample, for a refined early turn
        out_y[k] = model_step(I, P, X, v, aux)
        u = v
        j = turns[k]
        s = 1.0 if targets[j] > r else -1.0
        # an early turn is for a command whose output heads for the extremum (sense times direction);
        # one heading away turns with the reference above, at once
        if k > keep_until and j > k and j < n - 1 and heading * s > 0.0:
            # the first sample whose overshoot reaches the extremum: one that already did at the first
            # look is past it (reversing would overshoot it), and another route (a branch, a lobe's top)
            margin = 4.0 * abs(r - targets[k - 1]) + tol_y if k > 0 else tol_y
            reach = _overshoot(I, P, X, S, aux, u, -d, s, h, lo, hi, tol_y) - s * targets[j]
            if -tol_y <= reach <= margin:
                if short_of == j and k > 0 and (v - out_u[k - 1]) * d > 0.0:
                    # the turn falls between the last sample's command and this one's: this sample's
                    # command is moved there (bisected) so that the overshoot lands on the extremum,
                    # not up to one sample's worth of it beyond
                    u_prev = out_u[k - 1]
                    lam_short, lam_reach = 0.0, 1.0
                    for _ in range(24):
                        lam = 0.5 * (lam_short + lam_reach)
                        ur = u_prev + lam * (v - u_prev)
                        for i in range(X.size):
                            R[i] = Q[i]
                        model_step(I, P, R, ur, aux)
                        if _overshoot(I, P, R, S, aux, ur, -d, s, h, lo, hi, tol_y) >= s * targets[j] - tol_y:
                            lam_reach = lam
                        else:
                            lam_short = lam
                    u = u_prev + lam_reach * (v - u_prev)
                    out_lo[k], out_hi[k], out_slope[k] = _stretch(I, P, Q, S, aux, u, d, h, lo, hi, STRETCH_STEPS)
                    for i in range(X.size):
                        X[i] = Q[i]
                    out_u[k] = u
                    out_y[k] = model_step(I, P, X, u, aux)
                    d = -d
                    keep_until = j
                elif short_of == j:
                    d = -d
                    keep_until = j
            elif reach < -tol_y:
                short_of = j


def feedback_samples(plan: PathPlan, targets: np.ndarray, command_range: tuple[float, float]) -> np.ndarray:
    """Where feedback may move the command off the plan (bool per sample): where the monotone stretch
    around the planned command reaches a march step (:data:`MARCH_STEPS`) beyond it on both sides,
    so that a correction either way stays where one output has one command, away from the kinks a
    reversal leaves (a hysteretic model's memory is its turning points: a plan replayed after
    feedback moved one starts from a memory it was not planned from); and not from a reversal made
    before the reference turns to as long again after the turn (the output overshoots there,
    command and output move opposite ways and the local gain passes through zero: outside the loop
    the gains were designed on)."""
    n = targets.size
    room = (command_range[1] - command_range[0]) / MARCH_STEPS
    ok = (plan.command - plan.stretch_lo >= room) & (plan.stretch_hi - plan.command >= room)
    turns = turning_points(targets, 1e-9 * max(float(np.ptp(targets)) if n else 0.0, 1e-12))
    flips = np.flatnonzero(np.diff(plan.direction) != 0.0) + 1
    for f in flips:
        j = int(turns[f - 1])
        if j > f:  # reversed before the reference turned: the overshoot runs to j and back
            ok[f - 1 : min(n, j + (j - f) + 1)] = False
    return ok


def turning_points(targets: np.ndarray, tolerance: float) -> np.ndarray:
    """For each sample, the index of the extremum the targets head for (a change of direction by
    more than ``tolerance`` um; n-1 for the end)."""
    n = targets.size
    turns = np.full(n, n - 1, dtype=np.int64)
    if n < 3:
        return turns
    # runs of one direction, steps within the tolerance joining the run they sit in
    way = np.sign(np.diff(targets))
    way[np.abs(np.diff(targets)) <= tolerance] = 0.0
    nxt = n - 1
    current = 0.0
    for k in range(n - 2, -1, -1):
        w = way[k]
        if w != 0.0 and current != 0.0 and w != current:
            nxt = k + 1  # the sample where the direction changes
        if w != 0.0:
            current = w
        turns[k] = nxt
    turns[n - 1] = n - 1
    return turns


@dataclass
class PathPlan:
    """A planned command path (see the module docstring): per sample the command, the model's output
    (um), the command's direction (+1/-1) and the monotone stretch ``[lo, hi]`` around the command
    with the output's slope at the command (um per command unit, its sign the stretch's sense)."""

    command: np.ndarray
    output: np.ndarray
    direction: np.ndarray
    stretch_lo: np.ndarray
    stretch_hi: np.ndarray
    slope: np.ndarray

    def error(self, targets: np.ndarray) -> np.ndarray:
        return self.output - targets


def plan_path(I: np.ndarray, P: np.ndarray, X: np.ndarray, aux: np.ndarray, u0: float, targets: np.ndarray,
              command_range: tuple[float, float], max_step: float, output_span: float) -> PathPlan:
    """Plan the commands for ``targets`` (um) on the static model ``I, P`` from memory ``X`` (advanced
    along the plan) at command ``u0``; ``command_range``: where the model is known; ``max_step``: the
    rig's slew per sample (command units, inf for none); ``output_span``: the loop's output span (um),
    the scale of the tolerances."""
    lo, hi = float(command_range[0]), float(command_range[1])
    t = np.ascontiguousarray(targets, dtype=np.float64)
    n = t.size
    h = (hi - lo) / MARCH_STEPS
    tol_y = 1e-9 * max(output_span, 1e-12)
    step = float(max_step) if math.isfinite(max_step) and max_step > 0 else hi - lo
    out = [np.empty(n) for _ in range(6)]
    S = np.empty_like(X)
    R = np.empty_like(X)
    Q = np.empty_like(X)
    plan_kernel(I, P, X, S, R, Q, np.ascontiguousarray(aux, dtype=np.float64), float(u0), t,
                turning_points(t, 1e-9 * max(output_span, 1e-12)), lo, hi, step, h, tol_y, PASS_TOLERANCE * output_span,
                *out)
    u, y, d, blo, bhi, slope = out
    return PathPlan(u, y, d, blo, bhi, slope)
