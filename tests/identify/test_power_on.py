"""The power-on step of a capture read as a step response (issue 11, item 4): its dead time and ringing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilbench.identify.power_on import power_on_step

FS = 10_000.0


def _sopdt(n: int, dead_s: float, f_hz: float, zeta: float, y0: float, y1: float) -> np.ndarray:
    t = np.arange(n) / FS
    tau = np.clip(t - dead_s, 0.0, None)
    wn = 2 * math.pi * f_hz
    wd = wn * math.sqrt(1 - zeta**2)
    unit = 1 - np.exp(-zeta * wn * tau) * (np.cos(wd * tau) + zeta * wn / wd * np.sin(wd * tau))
    return y0 + (y1 - y0) * unit


@pytest.mark.parametrize("dead_s, f_hz, zeta", [(0.0001, 700.0, 0.03), (0.00037, 300.0, 0.2), (0.0008, 1500.0, 0.5)])
def test_dead_time_and_ringing_are_read_off_the_power_on_transient(dead_s, f_hz, zeta):
    rng = np.random.default_rng(1)
    y = _sopdt(15_000, dead_s, f_hz, zeta, 0.1, -3.4) + rng.normal(0, 0.002, 15_000)
    step = power_on_step(y, FS, 15_000)
    assert step is not None and step.r2 > 0.99
    assert step.dead_time_s == pytest.approx(dead_s, abs=0.15 / FS)  # within a sixth of a sample
    assert step.natural_frequency_hz == pytest.approx(f_hz, rel=0.05)
    assert step.y_settled == pytest.approx(-3.4, abs=0.01)


def test_no_step_when_the_output_rests_or_wanders():
    rng = np.random.default_rng(2)
    assert power_on_step(rng.normal(0, 0.01, 5000), FS, 5000) is None  # only noise
    walk = np.cumsum(rng.normal(0, 0.01, 5000))  # drift, no step response shape
    step = power_on_step(walk, FS, 5000)
    assert step is None or step.r2 >= 0.95  # whatever it returns must explain the rise it fitted
