"""The search's column cache (identify/separable.py, _ColumnCache) gives the matrix a fresh
computation gives, bit for bit, while a Jacobian moves one shape parameter at a time and back:
reused blocks are the ones computed for the same shape, and a block a later component scales in
place (a loop gain: rate-dependence, a recorded channel) is not scaled twice."""

from __future__ import annotations

import numpy as np
import pytest

from hilbench.identify.separable import _Problem
from hilbench.models.model import Model, RunData

FS = 1000.0


def _run() -> RunData:
    t = np.arange(6000) / FS
    u = 8.0 * np.sin(2 * np.pi * 1.5 * t) * (t < 3.0) + np.where(t >= 3.0, np.round(4 * np.sin(t)), 0.0)
    temperature = 25.0 + 0.5 * t
    y = 0.9 * u + 0.3 * np.tanh(u / 4) + 0.01 * (temperature - 25.0) * u
    return RunData(u, y, {"temperature": temperature}, FS)


@pytest.mark.parametrize("spec", ["pi+rate-dependence(form=damping)", "pi+rate-dependence(form=frequency)",
                                  "pi+asymmetry+creep(form=output)+temperature", "pi+saturation(form=output)+temperature",
                                  "pi+creep(form=output)+dynamics", "pmpi(n=4)+creep(form=log-output)",
                                  "pmpi(n=4)+creep(form=bank)+dynamics", "pmpi(n=4)+creep"])
def test_cached_matrix_equals_a_fresh_one_as_each_parameter_moves(spec: str) -> None:
    run = _run()
    mask = np.ones(len(run.input), dtype=bool)
    model = Model(spec)
    model.prepare([run])
    cached = _Problem(model, [run], [mask])
    lo, hi = cached.bounds_x()
    x0 = cached.to_x(np.array([p.value for p in cached.params]))
    steps = [x0]
    for k in range(x0.size):  # as a finite-difference Jacobian: one parameter moved, then the next
        x = x0.copy()
        x[k] = x[k] + 0.05 * (hi[k] - lo[k]) if x[k] + 0.05 * (hi[k] - lo[k]) <= hi[k] else x[k] - 0.05 * (hi[k] - lo[k])
        steps += [x, x0]
    assert len(steps) > 3, spec
    for x in steps:
        got = cached.residual(x)
        fresh = _Problem(model, [run], [mask]).residual(x)
        assert np.array_equal(got, fresh), spec


@pytest.mark.parametrize("spec", ["pmpi(n=4)+creep(form=output)", "pmpi(n=4)+creep(form=log-output)+dynamics",
                                  "pi+saturation(form=hammerstein)+creep"])
def test_chained_runs_cached_equal_the_models_own_walk(spec: str) -> None:
    """Runs chained through the rig's ramps: the cache keeps the ramps' blocks and the signals (with
    what components keep on them, Signals.memo) and gives the matrix the model's own design gives
    (Model._walk, fresh signals at every call), as each parameter moves and back."""
    first = _run()
    second = RunData(first.input[::-1] * 0.7 + 1.0, first.output[::-1], {"temperature": first.aux["temperature"]},
                     FS, chain=True)
    third = RunData(first.input * 0.5, first.output, {"temperature": first.aux["temperature"]}, FS,
                    approach_from=0.0)
    runs = [first, second, third]
    masks = [np.ones(len(r.input), dtype=bool) for r in runs]
    model = Model(spec)
    model.prepare(runs)
    cached = _Problem(model, runs, masks)
    lo, hi = cached.bounds_x()
    x0 = cached.to_x(np.array([p.value for p in cached.params]))
    steps = [x0]
    for k in range(x0.size):
        x = x0.copy()
        x[k] = x[k] + 0.05 * (hi[k] - lo[k]) if x[k] + 0.05 * (hi[k] - lo[k]) <= hi[k] else x[k] - 0.05 * (hi[k] - lo[k])
        steps += [x, x0]
    for x in steps:
        cached.solve(cached.to_theta(x))
        got, _, _, _ = cached.design()
        walked = []
        for run, states in model._walk(runs):
            blocks = model.static_columns(run, states)
            walked.append(model.apply_dynamics(run, blocks)[0])
        assert np.array_equal(got, np.vstack(walked)), spec
