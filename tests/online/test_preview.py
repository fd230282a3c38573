"""The dynamics and delay inverted with a preview of the whole reference (issue 58): on randomly drawn
linear dynamics (second and third order, ZOH and FOH holds, so with sampling zeros near -1 and zeros
outside the unit circle), fractional delays and references whose content lies below the dynamics'
bandwidth, the previewed target run through the dynamics and the delay gives the reference back,
where the reference itself would lag by percents."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from hilbench.online.preview import preview_with_lead, settling_samples


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
    with_preview = _through(preview_with_lead(r, b, a, delay)[1], b, a, delay) - r
    without = _through(r, b, a, delay) - r
    e_with = float(np.sqrt(np.mean(with_preview[skip:] ** 2))) / span
    e_without = float(np.sqrt(np.mean(without[skip:] ** 2))) / span
    assert e_with <= 0.005 and e_with <= 0.2 * e_without, (fs, fn, delay, e_with, e_without)


def test_without_dynamics_or_delay_the_target_is_the_reference_and_nan_holds() -> None:
    r = np.array([1.0, 2.0, np.nan, 4.0])
    lead, same = preview_with_lead(r, None, None, 0.0)
    np.testing.assert_array_equal(same, [1.0, 2.0, 2.0, 4.0])
    assert lead.size == 0
    lead, shifted = preview_with_lead(np.arange(100.0), None, None, 2.0)  # a pure delay: the reference 2 samples ahead
    np.testing.assert_allclose(shifted[10:90], np.arange(12.0, 92.0), atol=1e-6)
    np.testing.assert_allclose(lead, [1.0], atol=1e-3)  # its second sample delivered before it starts (the first is r0)


@pytest.mark.parametrize("seed", range(12))
def test_with_its_pre_actuation_the_reference_is_followed_from_its_first_sample(seed: int) -> None:
    """Stable inversion is non-causal even on minimum-phase dynamics (the hold's sample, a delay, the
    regularised inverse ringing both ways): played from rest with its pre-actuation before it, the
    target gives the reference from its very first sample. A reference that starts moving at once
    (a ramp from its first sample, as a triangle starting at a corner) without the pre-actuation
    starts late and rings; the static value is exact (no Tikhonov shrink at rest)."""
    rng = np.random.default_rng(100 + seed)
    fs = float(rng.choice([1000.0, 5000.0, 20000.0, 50000.0]))
    b, a, fn = _dynamics(rng, fs)
    delay = float(rng.choice([0.0, rng.uniform(0.3, 8.0)]))
    f = fn / rng.uniform(5.0, 20.0)  # a triangle from its lower corner, well below the resonance
    n = int(fs * rng.integers(2, 5) / f)
    r0 = rng.uniform(-20, 20)
    amplitude = rng.uniform(1.0, 10.0)
    r = r0 + amplitude * signal.sawtooth(2 * np.pi * f * np.arange(n) / fs, 0.5) + amplitude  # from r0 up
    span = float(np.ptp(r))
    lead, v = preview_with_lead(r, b, a, delay)
    rest = np.full(settling_samples(b, a) + 10, r0)
    y = _through(np.concatenate([rest, lead, v]), b, a, delay)[rest.size + lead.size:]
    y_without = _through(np.concatenate([rest, v]), b, a, delay)[rest.size:]
    start = int(fs / f / 2)  # up to the first corner: where the run starts moving
    start_with = float(np.max(np.abs(y - r)[:start])) / span
    later = float(np.max(np.abs(y - r)[start:])) / span  # the corners' error, which no pre-actuation changes
    start_without = float(np.max(np.abs(y_without - r)[:start])) / span
    assert lead.size > 0
    # with it the start is no worse than any later corner; without it, worse than with it
    assert later <= 0.02 and start_with <= later and start_with < start_without, \
        (fs, fn, delay, lead.size, start_with, later, start_without)
    flat = np.full(50, r0)  # a reference at rest needs no pre-actuation and is delivered exactly
    lead, v = preview_with_lead(flat, b, a, delay)
    assert lead.size == 0 and np.allclose(v, r0, rtol=0, atol=1e-12 * max(1.0, abs(r0)))
