"""Creep's signature along holds (decision 0059): the residual's drift per hold, and what a refit
did to it. Synthetic rows: four holds of 1 s at 1 kHz after steps, sensor noise 0.01 um."""

from __future__ import annotations

import numpy as np
import pytest

from hilbench.diagnosis.evidence import EVIDENCE_CHECKS, HOLD_END_ROWS, drift_after_refit, hold_drifts
from hilbench.diagnosis.rows import ResidualRows

FS = 1000.0
NOISE = 0.01


def _rows(e: np.ndarray, n_holds: int = 4) -> ResidualRows:
    """Rows of ``n_holds`` holds of 1 s each, 0.2 s of motion before each; residual ``e``."""
    per = int(1.2 * FS)
    n = per * n_holds
    direction = np.empty(n, dtype=object)
    since = np.zeros(n)
    for k in range(n_holds):
        direction[k * per: k * per + int(0.2 * FS)] = "rising"
        direction[k * per + int(0.2 * FS): (k + 1) * per] = "hold"
        since[k * per + int(0.2 * FS): (k + 1) * per] = np.arange(int(FS)) / FS
    z = np.zeros(n)
    return ResidualRows(e=e, u=z, du=z, y=z, dy=z, d2y=z, since=since, direction=direction,
                        run=np.zeros(n, int), t=np.arange(n) / FS, aux={}, keys=["run"])


def _creep(n_holds: int = 4, size: float = 0.3) -> np.ndarray:
    """A residual that decays along every hold (a creep the model lacks), alternating in sign."""
    per, e = int(1.2 * FS), []
    for k in range(n_holds):
        t = np.arange(int(FS)) / FS
        e += [np.zeros(int(0.2 * FS)), (-1) ** k * size * np.exp(-t / 0.4)]
    return np.concatenate(e)


def test_hold_drifts_are_the_ends_of_each_hold_after_the_settling():
    e = _creep()
    d = hold_drifts(_rows(e))
    assert d.shape == (4,)
    # from the first HOLD_END_ROWS rows after 0.1 s to the last HOLD_END_ROWS of the hold
    t_first = (0.1 + (HOLD_END_ROWS - 1) / 2 / FS)
    t_last = (1.0 - 1 / FS - (HOLD_END_ROWS - 1) / 2 / FS)
    expected = 0.3 * (np.exp(-t_last / 0.4) - np.exp(-t_first / 0.4))
    assert d[0] == pytest.approx(expected, rel=1e-3) and d[1] == pytest.approx(-expected, rel=1e-3)
    # the same holds for any residual on the same rows
    assert hold_drifts(_rows(e), np.zeros_like(e)).tolist() == [0.0] * 4


def test_a_refit_that_removes_the_drift_stands_for_creep_and_one_that_leaves_it_does_not():
    rng = np.random.default_rng(0)
    e = _creep() + rng.normal(0.0, NOISE, _creep().size)
    rows = _rows(e)
    removed = drift_after_refit(rows, rng.normal(0.0, NOISE, e.size), NOISE)
    assert removed["drift_over_noise"] > 50 and removed["drift_removed"] > 0.9
    left = drift_after_refit(rows, 0.8 * e, NOISE)  # a refit that keeps 80 % of the drift
    assert left["drift_removed"] == pytest.approx(0.2, abs=0.01)
    rule = EVIDENCE_CHECKS["drift-on-holds"]
    small = {"drift_over_rms": 0.1}  # other errors fill the rms
    assert rule.holds({**small, **removed}) and not rule.holds({**small, **left})


def test_noise_alone_does_not_drift():
    rng = np.random.default_rng(1)
    rows = _rows(rng.normal(0.0, NOISE, 4 * int(1.2 * FS)))
    ev = drift_after_refit(rows, rng.normal(0.0, NOISE, rows.e.size), NOISE)
    # a difference of two means of HOLD_END_ROWS noise samples: about 0.8 standard errors on average
    assert ev["drift_over_noise"] < 3.0
    assert not EVIDENCE_CHECKS["drift-on-holds"].holds({"drift_over_rms": 0.05, **ev})
    # a drift within the noise is no drift, however small the rms beside it (decision 0061)
    assert not EVIDENCE_CHECKS["drift-on-holds"].holds({"drift_over_rms": 0.25, **ev})
    assert EVIDENCE_CHECKS["drift-on-holds"].holds({**ev, "drift_over_rms": 0.25, "drift_over_noise": 3.0})
