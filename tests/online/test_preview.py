"""The dynamics and delay inverted with a preview of the whole reference (issue 58): on randomly drawn
linear dynamics (second and third order, ZOH and FOH holds, so with sampling zeros near -1 and zeros
outside the unit circle), fractional delays and references whose content lies below the dynamics'
bandwidth, the previewed target run through the dynamics and the delay gives the reference back,
where the reference itself would lag by percents."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from hilbench.online.preview import preview_target, settling_samples


def _dynamics(rng: np.random.Generator, fs: float) -> tuple[np.ndarray, np.ndarray, float]:
    """A physical actuator's dynamics: a resonance (100 Hz-5 kHz, zeta 0.05-0.8) below Nyquist, sometimes
    with a first-order pole (an amplifier's bandwidth), discretised with a ZOH or a FOH; unit static gain."""
    fn = float(np.exp(rng.uniform(np.log(100.0), np.log(min(5000.0, fs / 8)))))
    zeta = float(rng.uniform(0.05, 0.8))
    wn = 2 * np.pi * fn
    num, den = [wn * wn], [1.0, 2 * zeta * wn, wn * wn]
    if rng.random() < 0.5:  # an amplifier pole a few times above the resonance: relative degree 3
        wa = wn * rng.uniform(2.0, 6.0)
        num, den = [wn * wn * wa], np.polymul(den, [1.0, wa])
    method = "zoh" if rng.random() < 0.6 else "foh"
    b, a, _ = signal.cont2discrete((num, den), 1.0 / fs, method=method)
    b, a = np.ravel(b), np.ravel(a)
    b = b / (b.sum() / a.sum())
    return b, a, fn


def _reference(rng: np.random.Generator, fs: float, f_max: float) -> np.ndarray:
    n = int(fs * rng.uniform(0.2, 0.6))
    t = np.arange(n) / fs
    r = np.full(n, rng.uniform(-20, 20))
    for _ in range(int(rng.integers(1, 4))):
        r += rng.uniform(1, 10) * np.sin(2 * np.pi * rng.uniform(0.02, 1.0) * f_max * t + rng.uniform(0, 2 * np.pi))
    return r


def _through(v: np.ndarray, b: np.ndarray, a: np.ndarray, delay: float) -> np.ndarray:
    y = signal.lfilter(b, a, v, zi=signal.lfilter_zi(b, a) * v[0])[0]
    k = np.arange(v.size, dtype=float)
    return np.interp(k - delay, k, y, left=y[0])


@pytest.mark.parametrize("seed", range(12))
def test_the_previewed_target_through_the_dynamics_and_delay_gives_the_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    fs = float(rng.choice([1000.0, 5000.0, 20000.0, 50000.0]))
    b, a, fn = _dynamics(rng, fs)
    delay = float(rng.choice([0.0, rng.uniform(0.3, 8.0)]))
    r = _reference(rng, fs, 0.2 * fn)  # content up to a fifth of the resonance
    span = float(np.ptp(r))
    skip = settling_samples(b, a) // 50 + int(delay) + 2  # the first samples: the dynamics' own start
    with_preview = _through(preview_target(r, b, a, delay), b, a, delay) - r
    without = _through(r, b, a, delay) - r
    e_with = float(np.sqrt(np.mean(with_preview[skip:] ** 2))) / span
    e_without = float(np.sqrt(np.mean(without[skip:] ** 2))) / span
    assert e_with <= 0.005 and e_with <= 0.2 * e_without, (fs, fn, delay, e_with, e_without)


def test_without_dynamics_or_delay_the_target_is_the_reference_and_nan_holds() -> None:
    r = np.array([1.0, 2.0, np.nan, 4.0])
    np.testing.assert_array_equal(preview_target(r, None, None, 0.0), [1.0, 2.0, 2.0, 4.0])
    shifted = preview_target(np.arange(100.0), None, None, 2.0)  # a pure delay: the reference 2 samples ahead
    np.testing.assert_allclose(shifted[10:90], np.arange(12.0, 92.0), atol=1e-6)
