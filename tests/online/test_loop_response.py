"""What the output-domain loop sees beyond the model's dynamics and a lag (decision 0123): the rig's
response over the model's, measured from the training runs, and the compensator's own response to a
correction, simulated. Generated rigs with a resonance the model lacks, and compensators with and
without rate terms."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from hilbench.models import Model
from hilbench.models.stepping import compile_model
from hilbench.online import feedback_design as FD
from hilbench.online import inverse_kernels as K
from hilbench.online.inverse import Compensator
from hilbench.online.loop_response import response_at, rig_over_model
from hilbench.online.pid import PID
from hilbench.online.tracking import track
from tests.online.swept_rigs import sweep_and_fit

FS = 5000.0


def _pi_model(fs: float = FS) -> Model:
    model = Model("pi(n=3)")
    model.norm = {"u_scale": 1.0}
    model.sample_rate_hz = fs
    model.base.constants["thresholds"] = [0.0, 0.2, 0.4]
    model.weights = np.array([0.0, 10.0, 5.0, 2.0])
    return model


def _resonance(fs: float, fn: float, zeta: float) -> tuple[np.ndarray, np.ndarray]:
    w = 2 * np.pi * fn
    b, a = signal.cont2discrete(([w * w], [1.0, 2 * zeta * w, w * w]), 1.0 / fs, method="zoh")[:2]
    b = np.ravel(b)
    return b / (b.sum() / np.sum(a)), np.ravel(a)


def _training(model: Model, fs: float, fn: float, zeta: float, noise: float, seed: int) -> list:
    """Two runs as a sweep plan drives them (a 40 Hz triangle, a log chirp to a third of fs/2) through
    a rig that is the model followed by a resonance at ``fn`` (Hz) with damping ``zeta``."""
    rng = np.random.default_rng(seed)
    b, a = _resonance(fs, fn, zeta)
    t = np.arange(int(1.5 * fs)) / fs
    triangle = 0.9 * signal.sawtooth(2 * np.pi * 40.0 * t, 0.5)
    chirp = 0.4 * signal.chirp(t, 5.0, t[-1], fs / 6, method="logarithmic")
    runs = []
    for u in (triangle, chirp):
        y_mod = compile_model(model, fs).block(u)
        y = signal.lfilter(b, a, y_mod - y_mod[0]) + y_mod[0] + rng.normal(0.0, noise, u.size)
        runs.append((u, y, {}, fs))
    return runs


@pytest.mark.parametrize("seed", range(4))
def test_the_rig_over_the_model_shows_a_resonance_the_model_lacks(seed: int) -> None:
    """Random resonances (fn 400-1200 Hz, zeta 0.05-0.3) behind a PI model: the measured response
    follows the resonance wherever it was measured, within its own standard error (4.5 sigma over
    some two thousand groups of lines) and 10 % (the drive's last lines, near the window's taper),
    and finds its peak within 5 %."""
    rng = np.random.default_rng(100 + seed)
    fn, zeta = float(rng.uniform(400.0, 1200.0)), float(np.exp(rng.uniform(np.log(0.05), np.log(0.3))))
    model = _pi_model()
    runs = _training(model, FS, fn, zeta, 0.002, seed)
    pairs = [(compile_model(model, FS).block(u), y, FS, 0.002) for u, y, _, _ in runs]
    measured = rig_over_model(pairs, FS)
    assert measured is not None and measured.frequency_hz[-1] > fn
    b, a = _resonance(FS, fn, zeta)
    _, truth = signal.freqz(b, a, worN=2 * np.pi * measured.frequency_hz / FS)
    assert np.all(np.abs(measured.response - truth) <= 4.5 * measured.standard_error + 0.1 * np.abs(truth))
    near = np.abs(measured.frequency_hz / fn - 1.0) < 0.2
    assert np.max(np.abs(measured.response[near])) == pytest.approx(np.max(np.abs(truth[near])), rel=0.05)
    # between the measured bins the response is interpolated, beyond them held at the end values
    inside = response_at(measured, np.array([measured.frequency_hz[0], measured.frequency_hz[-1], 1e6]))
    assert inside[0] == pytest.approx(measured.response[0], rel=1e-9)
    assert inside[2] == pytest.approx(measured.response[-1], rel=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_the_margins_hold_on_the_rig_with_the_resonance(seed: int) -> None:
    """The highest integral gain the margins allow, on the loop identified from the runs, keeps the
    rig's loop (the resonance in it) stable with its gain margin within the estimate's scatter
    (1.5 dB) of 6 dB; on the lag alone (as before decision 0123) that gain made the rig unstable."""
    rng = np.random.default_rng(200 + seed)
    fn, zeta = float(rng.uniform(400.0, 900.0)), float(np.exp(rng.uniform(np.log(0.05), np.log(0.15))))
    model = _pi_model()
    loop = FD.identify_loop(model, FS, runs=_training(model, FS, fn, zeta, 0.002, seed))
    assert loop.measured is not None
    b, a = _resonance(FS, fn, zeta)
    rig = FD.IdentifiedLoop(FS, b, a, 0, 0.0, loop.gain_range, "the rig as it is")
    ceiling = FD.design(loop)[1]["ki_max_per_s"]
    on_rig = FD.margins(PID(0.0, ceiling, 0.0), rig)
    assert on_rig["stable"] and on_rig["gain_margin_db"] >= FD.MIN_GAIN_MARGIN_DB - 1.5
    loop.measured = None
    lag_only = FD.design(loop)[1]["ki_max_per_s"]
    assert not FD.margins(PID(0.0, lag_only, 0.0), rig)["stable"]


def test_a_compensator_without_rate_terms_answers_a_correction_as_asked() -> None:
    """An exact inverse (PI) passes a correction through whole: unit response at every frequency (the
    reversal guard, which holds a correction against the reference's direction, is not counted on)."""
    model = _pi_model()
    comp = Compensator(model, FS, (-1.0, 1.0))
    runs = _training(model, FS, 800.0, 0.2, 0.002, 0)
    runs = [(u, y, aux, fs, u.size) for u, y, aux, fs in runs]
    response = comp.correction_response(runs, 0.002)
    assert response is not None and response.frequency_hz[-1] > 0.4 * FS
    assert np.max(np.abs(response.response - 1.0)) < 1e-6
    assert comp.CP[K.C_GUARD] == 1.0  # the compensator's own setting is left as it was


# ==================================================================================================
# a rate-dependent model on a rig with a resonance it lacks
# ==================================================================================================

RESONANT_RIG = """
[rig]
name = "resonant-magnetostrictive"
description = "Duhem hysteresis, creep and a 637 Hz mechanical resonance (zeta 0.25) sampled at 2 kHz"
sample_rate_hz = 2000.0
seed = 3

[actuator]
driver = "sim"
kind = "magnetostrictive actuator"
unit = "A"
min = -0.692
max = 0.692
max_rate = 4617.0
rest = 0.0

[[sensors]]
channel = "output"
unit = "um"
driver = "sim"
noise_std = 0.48

[plant.hysteresis]
model = "duhem"
input_scale = 0.692
alpha = 2.48922
beta = 3.40051
shape = "tanh"
k1 = 0.584309
k2 = 1.1588
mu = [0.371321, 0.126368]
output_scale = 71.8041

[plant.dynamics]
kind = "second-order"
natural_frequency_hz = 636.8
zeta = 0.248

[plant.creep]
gains = [0.07702, 0.03787]
time_constants_s = [0.01766, 0.2062]

[[plan.runs]]
label = "sine"
kind = "sine"
offset = 0.0
phase_deg = -90.0
frequency_hz = 1.594
cycles = 2
sweep = { amplitude = [0.237356, 0.474712, 0.67816] }

[[plan.runs]]
label = "triangle"
kind = "triangle"
offset = 0.0
amplitude = 0.67816
phase_deg = -90.0
duration_s = 1.25471
sweep = { frequency_hz = [1.594, 8.929, 50.0] }

[[plan.runs]]
label = "triangle-staircase"
kind = "triangle"
offset = 0.0
phase_deg = 0.0
frequency_hz = 3.188
amplitudes = [0.67816, 0.50862, 0.33908, 0.203448, 0.101724]

[[plan.runs]]
label = "chirp"
kind = "chirp"
offset = 0.0
amplitude = 0.33908
f_start_hz = 8.929
f_end_hz = 150.0
method = "logarithmic"
duration_s = 1.25471
"""


@pytest.fixture(scope="module")
def resonant(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    """The rig swept with its plan and fitted with the model ``diagnose --auto`` gives there (Duhem
    with 003's velocity damping standing in for the resonance on the training drives)."""
    return sweep_and_fit(tmp_path_factory.mktemp("resonant"), RESONANT_RIG, "duhem-m+rate-dependence(form=damping)")


def test_feedback_through_a_rate_dependent_inverse_does_not_ring(resonant) -> None:
    """The inverse reads the rate terms on the rate so far, a recursion that answers a correction with
    a peak of about 2.5x near 270 Hz: designed without it, the loop crossed over at 218 Hz and rang
    at 330 Hz rail to rail on a staircase (34 % against feed-forward's 2.2 %)."""
    rig, model = resonant
    reference = "step:levels=34/31.4/49.4/-42.3,hold_s=0.106,rise_s=0.0077"
    ff = track(str(rig), model, reference)
    fb = track(str(rig), model, reference, feedback=True)
    loop = fb.compensator["checks"]["closed_loop"]["loop"]
    assert loop["compensator_response"]["peak_gain"] > 1.5
    assert fb.metrics["erms_pct"] <= ff.metrics["erms_pct"]
    # no ringing: above 150 Hz the error's power is at most what the margins allow the sensitivity to
    # raise it (|S| <= 2 at 6 dB of gain margin: 4x); ringing at the rails it was a thousand times
    def high(e: np.ndarray) -> float:
        spectrum = np.abs(np.fft.rfft(e - e.mean())) ** 2
        return float(np.sum(spectrum[np.fft.rfftfreq(e.size, 1 / 2000.0) > 150.0]))
    assert high(fb.error) <= 4.0 * high(ff.error)
