"""The loop family of a hysteresis candidate is chosen on an inner split of training only when the
inner fit's rows turn the input (decision 0057)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.refit import inner_rows_loop
from hilbench.identify.sweep import reversals


def test_two_turns_close_a_loop_and_a_step_with_a_hold_has_none():
    t = np.linspace(0.0, 1.0, 1000)
    step_hold = np.where(t < 0.1, 0.0, -0.28)
    assert reversals(step_hold, 1.0) == 0
    assert reversals(np.sin(2 * np.pi * 3 * t), 2.0) == 6  # 3 cycles: 3 maxima and 3 minima, each turned
    assert reversals(0.01 * np.sin(2 * np.pi * 3 * t), 2.0) == 0, "wiggles within the band of the span are no turns"
    assert reversals(np.array([0.0, np.nan, 1.0, 0.0, 1.0]), 1.0) == 2, "non-finite samples are left out"


def _run(u: np.ndarray, inner: np.ndarray, train: np.ndarray):
    return SimpleNamespace(train=inner), SimpleNamespace(train=train, data=SimpleNamespace(input=u))


def test_the_inner_rows_must_turn_the_input_in_some_run():
    """Randomized seed 4042: training a power-on step, a hold and the first cycle of a sine; the inner
    fit (its first INNER_SPLIT) holds the step and the hold only."""
    n = 2000
    t = np.arange(n) / 1000.0
    u = np.where(t < 0.3, 0.0, -0.284)
    u[1700:] = 0.5 * np.sin(2 * np.pi * 10 * (t[1700:] - t[1700]))
    train = np.ones(n, bool)
    inner = np.zeros(n, bool)
    inner[: int(T.INNER_SPLIT * n)] = True
    r, user = _run(u, inner, train)
    assert not inner_rows_loop(SimpleNamespace(runs=[r]), [user])
    looping = np.sin(2 * np.pi * 5 * t)
    r2, user2 = _run(looping, inner, train)
    assert inner_rows_loop(SimpleNamespace(runs=[r, r2]), [user, user2]), "one run that loops is enough"
