"""`hilbench.diagnosis.input_motion`: holds in a noisy measured input, reversals and drive frequencies."""

from __future__ import annotations

import numpy as np

from hilbench.diagnosis.input_motion import (excitation_summary, half_cycle_frequencies, hold_band, input_noise, motion,
                                             rate_spread)

FS = 1000.0


def _trapezoid(noise_v: float, seed: int = 0) -> np.ndarray:
    """0 V for 1 s, a 10 ms ramp to 1000 V, held 2 s, a ramp back, held 1 s; plus sensor noise."""
    rng = np.random.default_rng(seed)
    parts = [np.zeros(1000), np.linspace(0, 1000, 10), np.full(2000, 1000.0), np.linspace(1000, 0, 10),
             np.zeros(1000)]
    u = np.concatenate(parts)
    return u + rng.normal(0, noise_v, u.size)


def test_input_noise_from_second_differences() -> None:
    assert abs(input_noise(_trapezoid(1.0)) - 1.0) < 0.1
    assert input_noise(_trapezoid(0.0)) < 1e-9
    t = np.arange(4000) / FS
    assert input_noise(90 * np.sin(2 * np.pi * 20 * t)) < 0.01  # a smooth digital drive: ~A (w dt)^4


def test_noisy_holds_are_holds() -> None:
    u = _trapezoid(1.0)
    m = motion(u, FS, float(np.ptp(u)))
    assert m["still"][100:1000].mean() > 0.99 and m["still"][1100:3000].mean() > 0.99
    assert not m["still"][1001:1009].any()  # the ramp moves
    assert abs(m["since"][2999] - 1.9) < 0.1  # held since the end of the ramp, s
    assert set(m["direction"][1100:3000]) == {"hold"}
    # without the dead band, noise would be read as ~1900 reversals during the hold
    assert m["flips"].size <= 2
    summary = excitation_summary([u], FS)
    assert summary["longest_hold_s"] > 1.8 and summary["reversals"] <= 1


def test_a_noisy_drive_does_not_become_holds() -> None:
    """The dead band is capped at 1 % of the span: band-limited noise and triangles keep moving."""
    rng = np.random.default_rng(1)
    u = np.convolve(rng.normal(0, 1, 20000), np.ones(5) / 5, mode="same")
    assert hold_band(u, float(np.ptp(u))) <= 0.01 * np.ptp(u) + 1e-12
    m = motion(u, FS, float(np.ptp(u)))
    assert m["still"].mean() < 0.2
    tri = np.abs((np.arange(4000) % 100) - 50.0) * 2 - 50  # 10 Hz triangle, exact
    m = motion(tri, FS, float(np.ptp(tri)))
    assert not m["still"].any()
    f = half_cycle_frequencies(m["flips"], FS)
    assert np.allclose(f, 10.0)
    assert set(np.unique(m["direction"])) == {"rising", "falling", "turning"}


def _triangle(f_hz: float, cycles: int, amplitude: float) -> np.ndarray:
    t = np.arange(int(round(cycles * FS / f_hz))) / FS
    return amplitude * (2.0 / np.pi) * np.arcsin(np.sin(2 * np.pi * f_hz * t))


def test_a_few_loops_at_a_second_rate_are_a_second_rate() -> None:
    # three loops at 9 Hz fill 4 % of a record spent at 0.7 Hz: over time one rate, counted in loops two
    # (randomized seed 1079: a frequency-gain rate dependence untestable before decision 0040)
    sine = 5.0 * np.sin(2 * np.pi * 0.7 * np.arange(int(6 / 0.7 * FS)) / FS)
    u = np.concatenate([_triangle(9.0, 3, 5.0), sine])
    assert excitation_summary([u], FS)["frequency_spread"] > 10
    # one loop at 9 Hz is not yet a rate a rate term could be fitted on
    assert excitation_summary([np.concatenate([_triangle(9.0, 1, 5.0), sine])], FS)["frequency_spread"] < 1.5


def test_small_loops_make_no_second_rate() -> None:
    # three fast loops over 5 % of the input span (a ripple, not a loop a rate term is fitted on)
    sine = 5.0 * np.sin(2 * np.pi * 0.7 * np.arange(int(6 / 0.7 * FS)) / FS)
    assert excitation_summary([np.concatenate([_triangle(9.0, 3, 0.25), sine])], FS)["frequency_spread"] < 1.5
    assert excitation_summary([np.concatenate([_triangle(9.0, 3, 2.5), sine])], FS)["frequency_spread"] > 10


def test_one_frequency_at_several_amplitudes_is_several_rates() -> None:
    """A 2 Hz sine whose amplitude falls from 1 to 0.2 holds one drive frequency but several rates
    (what a velocity damping acts on, decision 0064); at a constant amplitude both spreads are 1."""
    t = np.arange(int(4 * FS)) / FS
    ramped = (1.0 - 0.2 * t) * np.sin(2 * np.pi * 2.0 * t)
    summary = excitation_summary([ramped], FS)
    assert summary["frequency_spread"] < 1.5 < summary["rate_spread"]
    assert 2.5 < summary["rate_spread"] < 5.0  # the 90th over the 10th percentile over time: ~0.9 / 0.3
    steady = excitation_summary([np.sin(2 * np.pi * 2.0 * t)], FS)
    assert steady["frequency_spread"] < 1.5 and steady["rate_spread"] < 1.1
    # half cycles below LOOP_MIN_SPAN of the span are wiggles, not rates
    assert rate_spread(np.array([2.0, 2.0, 2.0, 2.0]), np.array([1.0, 1.0, 0.01, 0.01]), 1.0) == 1.0


def test_a_step_faster_than_the_loops_is_another_rate() -> None:
    """Decision 0074: a 2 Hz sine at one amplitude has one rate, and no stretch of it moves faster
    than pi/2 x its mean rate; a step slewed over 5 samples beside it moves tens of times faster."""
    t = np.arange(int(3 * FS)) / FS
    sine = np.sin(2 * np.pi * 2.0 * t)
    assert excitation_summary([sine], FS)["step_rate_ratio"] == 1.0
    part = sine[int(0.458 * FS):int(0.541 * FS)]  # -30 to +30 degrees: the sine's fastest stretch
    assert excitation_summary([sine, part], FS, 2.0)["step_rate_ratio"] == 1.0
    step = np.concatenate([np.zeros(500), np.linspace(0.0, 0.8, 6)[1:], np.full(500, 0.8), sine + 0.8])
    with_step = excitation_summary([step], FS)
    assert with_step["rate_spread"] < 1.5 and with_step["frequency_spread"] < 1.5  # one rate by the loops ...
    assert with_step["step_rate_ratio"] > 10.0  # ... and a step: 0.8 in 5 ms against 8 per s at most
    small = np.concatenate([np.zeros(500), np.linspace(0.0, 0.1, 6)[1:], np.full(500, 0.1), sine + 0.1])
    assert excitation_summary([small], FS)["step_rate_ratio"] == 1.0  # under LOOP_MIN_SPAN of the span: a wiggle


def test_one_short_reversal_is_no_drive_rate() -> None:
    """Decision 0078: a hold, a jump slewed over 4 samples down to where a 3.6 Hz triangle starts
    (11 % of the span, randomized seed 9107), then the triangle. The jump is a half cycle of 100 Hz
    at 1 kHz; the drive frequencies stay at the triangle's. Three loops at 9 Hz still are a rate."""
    hold = np.full(700, 0.6)
    jump = np.linspace(0.6, 0.52, 5)[1:]
    t = np.arange(int(4 / 3.6 * FS)) / FS
    tri = 0.52 + 0.39 * (2.0 / np.pi) * np.arcsin(np.sin(2 * np.pi * 3.6 * t))
    u = np.concatenate([np.zeros(600), hold, jump, tri])
    m = motion(u, FS, float(np.ptp(u)))
    assert half_cycle_frequencies(m["flips"], FS).max() >= 90  # the jump is read as a reversal
    lo, hi = excitation_summary([u], FS)["frequencies_hz"]
    assert 3.0 < lo <= hi < 8.0, (lo, hi)  # a quarter cycle at the start reads 7.2 Hz
    sine = 5.0 * np.sin(2 * np.pi * 0.7 * np.arange(int(6 / 0.7 * FS)) / FS)
    lo, hi = excitation_summary([np.concatenate([_triangle(9.0, 3, 5.0), sine])], FS)["frequencies_hz"]
    assert abs(lo - 0.7) < 0.1 and abs(hi - 9.0) < 0.5, (lo, hi)
