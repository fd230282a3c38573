"""Where a resonance rings, read off a residual's spectrum (hilbench/identify/resonance.py), and the
natural-frequency search started there (decision 0023)."""

from __future__ import annotations

import numpy as np

from hilbench.identify.resonance import contiguous_stretches, ringing_frequencies

FS = 2000.0


def _ringing_residual(f_ring: float, zeta: float, drive_hz: float, seconds: float, seed: int = 0) -> np.ndarray:
    """What a model without a resonance leaves: base-model error at the drive's odd harmonics
    (stronger than the ringing), decaying ringing after each corner of a triangle drive, noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * FS)) / FS
    r = sum(0.5 / k**2 * np.sin(2 * np.pi * k * drive_hz * t + k) for k in (1, 3, 5, 7))
    w = 2 * np.pi * f_ring
    for corner in np.arange(0.0, seconds, 0.5 / drive_hz):
        after = t >= corner
        tau = t[after] - corner
        r[after] += 0.1 * np.exp(-zeta * w * tau) * np.sin(w * np.sqrt(1 - zeta**2) * tau)
    return r + rng.normal(0.0, 0.02, t.size)


def test_the_ringing_is_among_the_peaks_despite_stronger_drive_harmonics():
    residual = _ringing_residual(f_ring=260.0, zeta=0.04, drive_hz=4.0, seconds=6.0)
    peaks = ringing_frequencies([residual], FS)
    assert any(abs(f - 260.0) < 5.0 for f in peaks), peaks


def test_stretches_cut_where_rows_jump_and_short_ones_give_no_spectrum():
    rows = np.array([0, 1, 2, 10, 11, 30])
    parts = contiguous_stretches(np.arange(6.0), rows)
    assert [p.tolist() for p in parts] == [[0.0, 1.0, 2.0], [3.0, 4.0], [5.0]]
    assert ringing_frequencies(parts, FS) == []  # nothing long enough for one Welch segment


def test_white_noise_has_no_prominent_ringing_close_to_zero():
    noise = np.random.default_rng(1).normal(0.0, 1.0, 20_000)
    peaks = ringing_frequencies([noise], FS)
    assert all(f >= 3 * FS / 4096 for f in peaks)  # no slow drift counted as a ringing
