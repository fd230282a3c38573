"""Excitations: the papers' signals, chunked generation equal to whole-array generation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbench.errors import ConfigError
from hilbench.excitation.signals import KINDS, make_excitation

FS = 1000.0

EXAMPLES = {
    "sine": {"kind": "sine", "amplitude": 2.0, "frequency_hz": 3.0, "offset": 1.0, "cycles": 4},
    "ramped-sine": {"kind": "ramped-sine", "amplitude_start": 0.3, "amplitude_end": 3.0, "frequency_hz": 1.0, "cycles": 10},
    "triangle": {"kind": "triangle", "frequency_hz": 1.0, "amplitudes": [6.0, 5.0, 4.0, 3.0, 2.0, 1.0]},
    "noise": {"kind": "noise", "rms": 0.2, "band_hz": [1.0, 50.0], "duration_s": 20.0, "seed": 3},
    "step": {"kind": "step", "levels": [0.0, 0.726, 0.0], "hold_s": [0.1, 0.5, 0.5]},
    "multitone": {"kind": "multitone", "amplitudes": [4.0, 2.5], "omegas_rad_s": [8.80, 2.51],
                  "phases_rad": [0.0, np.pi / 2], "duration_s": 5.0},
    "chirp": {"kind": "chirp", "amplitude": 1.0, "f_start_hz": 1.0, "f_end_hz": 100.0, "duration_s": 2.0},
    "attenuated-triangle": {"kind": "attenuated-triangle", "amplitude_start": 100.0, "amplitude_end": 20.0,
                            "frequency_start_hz": 0.5, "frequency_end_hz": 2.0, "cycles": 5},
}


def test_every_kind_has_an_example():
    assert set(EXAMPLES) == set(KINDS)


@pytest.mark.parametrize("kind", sorted(EXAMPLES))
def test_chunks_equal_whole(kind):
    exc = make_excitation(EXAMPLES[kind])
    whole = exc.generate(FS)
    chunked = np.concatenate(list(exc.chunks(FS, chunk=777)))
    assert whole.shape == (exc.n_samples(FS),)
    np.testing.assert_allclose(chunked, whole, rtol=0, atol=1e-12)
    assert np.all(np.isfinite(whole))


def test_sine_values():
    x = make_excitation(EXAMPLES["sine"]).generate(FS)
    t = np.arange(x.size) / FS
    np.testing.assert_allclose(x, 1.0 + 2.0 * np.sin(2 * np.pi * 3.0 * t), atol=1e-12)


def test_ramped_sine_peaks_are_arithmetic():
    x = make_excitation(EXAMPLES["ramped-sine"]).generate(FS)
    peaks = np.array([x[int(k * FS): int((k + 1) * FS)].max() for k in range(10)])
    steps = np.diff(peaks)
    assert peaks[0] == pytest.approx(0.3, abs=0.01) and peaks[-1] == pytest.approx(3.0, abs=0.01)
    assert np.ptp(steps) < 0.02 and steps.mean() == pytest.approx(0.3, rel=0.02)


def test_triangle_staircase_maxima_and_linearity():
    x = make_excitation(EXAMPLES["triangle"]).generate(FS)
    maxima = [x[int(k * FS): int((k + 1) * FS)].max() for k in range(6)]
    np.testing.assert_allclose(maxima, [6, 5, 4, 3, 2, 1], atol=0.03)
    slope = np.diff(x[10:240]) * FS  # rising edge of the first cycle: 6 A per quarter second
    assert np.ptp(slope) < 1e-6 and slope[0] == pytest.approx(24.0, rel=1e-3)


def test_noise_rms_band_and_seed():
    exc = make_excitation(EXAMPLES["noise"])
    x = exc.generate(FS)
    assert x.std() == pytest.approx(0.2, rel=0.1)
    spectrum = np.abs(np.fft.rfft(x)) ** 2
    f = np.fft.rfftfreq(x.size, 1 / FS)
    in_band = spectrum[(f > 2) & (f < 45)].sum()
    assert in_band / spectrum.sum() > 0.8
    assert spectrum[f > 150].sum() / spectrum.sum() < 1e-3
    np.testing.assert_array_equal(x, make_excitation(EXAMPLES["noise"]).generate(FS))
    other = make_excitation({**EXAMPLES["noise"], "seed": 4}).generate(FS)
    assert not np.allclose(x, other)


def test_multitone_is_papers_two_tone():
    x = make_excitation(EXAMPLES["multitone"]).generate(FS)
    t = np.arange(x.size) / FS
    np.testing.assert_allclose(x, 4 * np.sin(8.80 * t) + 2.5 * np.sin(2.51 * t + np.pi / 2), atol=1e-12)


def test_step_levels_and_holds():
    x = make_excitation(EXAMPLES["step"]).generate(FS)
    assert x[50] == 0.0 and x[300] == 0.726 and x[-1] == 0.0
    assert np.count_nonzero(x == 0.726) == pytest.approx(500, abs=1)


def test_step_rise_time_limits_the_slope():
    x = make_excitation({"kind": "step", "levels": [0.0, 1.0, -1.0], "hold_s": 0.5, "rise_s": 0.1}).generate(FS)
    assert np.max(np.abs(np.diff(x))) * FS == pytest.approx(20.0, rel=1e-6)  # 2 units in 0.1 s
    assert x[550] == pytest.approx(0.5) and x[620] == pytest.approx(1.0) and x[1200] == pytest.approx(-1.0) and x[1050] == pytest.approx(0.0)


def test_chirp_sweeps_frequency():
    x = make_excitation(EXAMPLES["chirp"]).generate(FS)
    early = np.count_nonzero(np.diff(np.sign(x[:200])))
    late = np.count_nonzero(np.diff(np.sign(x[-200:])))
    assert late > 10 * max(early, 1)


def test_attenuated_triangle_decays_and_speeds_up():
    exc = make_excitation(EXAMPLES["attenuated-triangle"])
    x = exc.generate(FS)
    assert x.min() == pytest.approx(0.0, abs=1e-9) and x.max() == pytest.approx(100.0, rel=1e-3)
    assert exc.duration_s() == pytest.approx(sum(1 / f for f in np.linspace(0.5, 2.0, 5)))
    assert x[-int(0.5 * FS / 2):].max() == pytest.approx(20.0, rel=0.02)


@pytest.mark.parametrize(
    "table, fragment",
    [
        ({"kind": "sinus"}, "kind: expected one of"),
        ({"kind": "sine", "amplitude": 1.0, "frequency_hz": 1.0}, "either 'cycles' or 'duration_s'"),
        ({"kind": "sine", "amplitude": "a", "frequency_hz": 1.0, "cycles": 1}, "amplitude: expected a finite number"),
        ({"kind": "sine", "amplitude": 1.0, "frequency_hz": -1.0, "cycles": 1}, "frequency_hz: expected a finite number > 0"),
        ({"kind": "noise", "rms": 1.0, "band_hz": [50.0, 10.0], "duration_s": 1.0}, "low < high"),
        ({"kind": "step", "levels": [1.0, 2.0], "hold_s": [1.0]}, "'hold_s' has 1 entries"),
    ],
)
def test_bad_excitations(table, fragment):
    with pytest.raises(ConfigError) as info:
        make_excitation(table)
    assert fragment in info.value.line()


@settings(max_examples=30, deadline=None)
@given(amplitude=st.floats(0, 10), frequency=st.floats(0.1, 50), offset=st.floats(-5, 5), chunk=st.integers(1, 5000))
def test_sine_chunking_any_size(amplitude, frequency, offset, chunk):
    exc = make_excitation({"kind": "sine", "amplitude": amplitude, "frequency_hz": frequency, "offset": offset, "cycles": 2})
    whole = exc.generate(FS)
    np.testing.assert_allclose(np.concatenate(list(exc.chunks(FS, chunk))), whole, atol=1e-12)
    assert whole.max() <= offset + amplitude + 1e-9 and whole.min() >= offset - amplitude - 1e-9
