"""What the output-domain loop sees beyond the model's dynamics and a lag, as frequency responses.

The PID adds its correction to the reference before the inverse, so its loop runs through two
things the model's linear dynamics do not describe:

- **the rig over the model** (:func:`rig_over_model`): whatever linear dynamics the rig has and the
  model lacks (a mechanical resonance, an amplifier's bandwidth). A single lag fitted to the
  training runs (:func:`hilbench.online.feedback_design.identify_loop`) describes them below the
  drive rates; near a lightly damped resonance the rig's response rises and its phase falls far
  faster than any lag says. The model is run on the recorded command, so the ratio of the measured
  to the modelled output's spectra is the rig's response after the model's (H1: the sum of ``Y X*``
  over the sum of ``|X|^2``, whole runs under one window). Only frequency lines where the model's
  output stands SNR_MIN in power above the sensor's noise enter; harmonics of a hysteretic output
  are lines too, which is how a slow triangle shows a resonance far above its fundamental.
- **the compensator's own response to a correction** (:func:`compensator_response`, measured by
  :meth:`hilbench.online.inverse.Compensator.correction_response`): the inverse is exact for the
  drives it is given, but a correction of a few noise sigma is a small, fast signal, and an inverse
  solved per sample answers it with its own dynamics: rate terms read on the rate so far (a
  low-pass of the command's rate) make a second-order recursion that rings a few hundred Hz below
  the Nyquist frequency (decision 0123). The response is measured by simulation: the training
  runs' static targets with and without a white correction, through the compensator and the
  fitted model's static part (the rig as far as the model knows it).

Both pool neighbouring frequency lines only as far as the estimate's standard error needs (at most
MAX_STANDARD_ERROR of unit response), so a lightly damped resonance keeps its peak. :func:`response_at` gives a
response on any grid, interpolated in log frequency (log magnitude and unwrapped phase) and held
at its end values beyond the measured bins: near a resonance measured on its rising side the loop
is charged with the largest rise measured, not with none.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "MAX_STANDARD_ERROR",
    "SNR_MIN",
    "MeasuredResponse",
    "compensator_response",
    "response_at",
    "rig_over_model",
]

#: a frequency line enters when the model output's power there is this many times the noise's
SNR_MIN = 30.0
#: a grid bin is kept when the standard error of its estimate is at most this (of unit response)
MAX_STANDARD_ERROR = 0.1
#: the window's taper at each end of a run (fraction of its length)
TAPER = 0.05
#: log bins per decade the compensator's response is pooled on (every line is excited)
BINS_PER_DECADE = 24
#: a line is left out when this share of its power comes from the tapers
TAPERED_SHARE = 0.1
#: lines that do not reach MAX_STANDARD_ERROR together within this fraction of their frequency are
#: dropped
GROUP_WIDTH = 0.02
#: fewer pooled groups than this: nothing measured (a lag says as much)
MIN_BINS = 3


@dataclass
class MeasuredResponse:
    """A response on the bins where it was measured: ``frequency_hz`` (bin centres, ascending),
    ``response`` (complex), ``standard_error`` (absolute)."""

    frequency_hz: np.ndarray
    response: np.ndarray
    standard_error: np.ndarray

    def peak(self) -> tuple[float, float]:
        """(largest |response|, its frequency in Hz)."""
        k = int(np.argmax(np.abs(self.response)))
        return float(abs(self.response[k])), float(self.frequency_hz[k])

    def describe(self) -> dict[str, float | int]:
        top, at = self.peak()
        return {"bins": int(self.frequency_hz.size), "from_hz": float(self.frequency_hz[0]),
                "up_to_hz": float(self.frequency_hz[-1]), "peak_gain": top, "peak_hz": at}


def _pool(pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]) -> MeasuredResponse | None:
    """H1 from (frequencies Hz, excitation X, response Y, noise power per line of Y) per run: the
    lines of all runs in order of frequency, pooled from each line on until the estimate's standard
    error is at most MAX_STANDARD_ERROR (a strong line stands alone: a lightly damped resonance keeps
    its peak); lines that reach it only over more than GROUP_WIDTH of their frequency are dropped.
    None when fewer than MIN_BINS groups are left."""
    f = np.concatenate([p[0] for p in pieces])
    order = np.argsort(f, kind="stable")
    f = f[order]
    X = np.concatenate([p[1] for p in pieces])[order]
    Y = np.concatenate([p[2] for p in pieces])[order]
    noise = np.concatenate([p[3] for p in pieces])[order]
    power = np.abs(X) ** 2
    cross = Y * np.conj(X)
    centres, responses, errors = [], [], []
    start, P, N, C, F = 0, 0.0, 0.0, 0j, 0.0
    for i in range(f.size):
        if f[i] > f[start] * (1.0 + GROUP_WIDTH):
            start, P, N, C, F = i, 0.0, 0.0, 0j, 0.0  # too weak over that width: dropped
        P += power[i]
        N += noise[i] * power[i]  # the estimate's variance times P^2
        C += cross[i]
        F += f[i] * power[i]
        se = math.sqrt(N) / P if P > 0.0 else math.inf
        if se <= MAX_STANDARD_ERROR:
            centres.append(F / P)
            responses.append(C / P)
            errors.append(se)
            start, P, N, C, F = i + 1, 0.0, 0.0, 0j, 0.0
    if len(centres) < MIN_BINS:
        return None
    return MeasuredResponse(np.asarray(centres), np.asarray(responses, complex), np.asarray(errors))


def _spectra(x: np.ndarray, y: np.ndarray, rate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Spectra of x and y windowed alike at the lines whose excitation lies in the window's flat part
    (the frequencies in Hz, X, Y) and the window's sum of squares. The window is flat but for TAPER of
    the run at each end: Y = H X holds under a window only where it is flat over the response's group
    delay, and a chirp puts its top frequencies at the run's end (a Hann window biased a resonance's
    peak by 10 %); a line with more than TAPERED_SHARE of its power in the tapers is left out."""
    from scipy.signal.windows import tukey

    n = x.size
    window = tukey(n, 2.0 * TAPER)
    x0, y0 = x - float(np.mean(x)), y - float(np.mean(y))
    X = np.fft.rfft(window * x0)
    Y = np.fft.rfft(window * y0)
    edge = math.ceil(TAPER * n)
    ends = np.zeros(n)
    ends[:edge], ends[n - edge:] = window[:edge], window[n - edge:]
    tapered = np.abs(np.fft.rfft(ends * x0)) ** 2
    keep = tapered <= TAPERED_SHARE * np.abs(X) ** 2
    f = np.fft.rfftfreq(n, 1.0 / rate)
    return f[keep], X[keep], Y[keep], float(np.sum(window * window))


def rig_over_model(runs: list[tuple[np.ndarray, np.ndarray, float, float]], fs: float) -> MeasuredResponse | None:
    """The rig's response after the model's from ``runs`` ((modelled output um, measured output um,
    the run's rate Hz, the sensor noise um rms) per run), on bins up to the loop's Nyquist frequency
    ``fs`` / 2, normalised to the response at the drives' dominant bin (the loop's local gain range
    already holds the rig's gain over the model's). None when fewer than MIN_BINS bins are measured
    well enough."""
    pieces = []
    for y_mod, y_meas, run_fs, noise in runs:
        ok = np.isfinite(y_mod) & np.isfinite(y_meas)
        if np.count_nonzero(ok) < 64 or not (noise > 0.0 and math.isfinite(noise)):
            continue
        f, X, Y, w2 = _spectra(y_mod[ok], y_meas[ok], run_fs)
        noise_power = noise * noise * w2  # E|N(k)|^2 of white noise through the window
        keep = (f > 0.0) & (f < 0.5 * min(fs, run_fs)) & (np.abs(X) ** 2 >= SNR_MIN * noise_power)
        if np.any(keep):
            pieces.append((f[keep], X[keep], Y[keep], np.full(np.count_nonzero(keep), noise_power)))
    if not pieces:
        return None
    # normalised by the response where the drives put most of their power (the fundamental)
    allx = np.concatenate([p[1] for p in pieces])
    ally = np.concatenate([p[2] for p in pieces])
    k = int(np.argmax(np.abs(allx)))
    scale = abs(ally[k] / allx[k])
    if not (scale > 0.0 and math.isfinite(scale)):
        return None
    pieces = [(f, X * scale, Y, n) for f, X, Y, n in pieces]  # H / scale, its error / scale
    return _pool(pieces)


def compensator_response(runs: list[tuple[np.ndarray, np.ndarray]], fs: float) -> MeasuredResponse | None:
    """The compensator's response to a correction from simulated ``runs`` ((correction um, the static
    model's output with it minus without it, um) per run, at the loop's rate ``fs``), on
    BINS_PER_DECADE log bins: H1 over each bin's lines, its standard error from the scatter of the
    lines' own ratios (the simulation has no noise: what scatters is what is not linear in the
    correction, hysteresis and the rate terms' power law). A constant correction passes an inverse
    exactly (it solves the static map), so the response starts from one at the lowest line."""
    pieces = []
    longest = 0.0
    for p, d in runs:
        if p.size < 64:
            continue
        f, X, Y, _ = _spectra(p, d, fs)
        keep = f > 0.0
        pieces.append((f[keep], X[keep], Y[keep]))
        longest = max(longest, p.size / fs)
    if not pieces:
        return None
    f = np.concatenate([q[0] for q in pieces])
    X = np.concatenate([q[1] for q in pieces])
    Y = np.concatenate([q[2] for q in pieces])
    lowest = 1.0 / longest
    edges = np.geomspace(lowest, 0.5 * fs, max(int(BINS_PER_DECADE * math.log10(0.5 * fs / lowest)), 1) + 1)
    k = np.clip(np.searchsorted(edges, f, side="right") - 1, 0, edges.size - 2)
    centres, responses, errors = [lowest], [1.0 + 0j], [0.0]
    for b in np.unique(k):
        at = k == b
        if np.count_nonzero(at) < 4:
            continue
        h = complex(np.sum(Y[at] * np.conj(X[at])) / np.sum(np.abs(X[at]) ** 2))
        ratios = Y[at] / X[at]
        se = math.sqrt(float(np.mean(np.abs(ratios - h) ** 2)) / (np.count_nonzero(at) - 1))
        if se <= MAX_STANDARD_ERROR and float(np.sqrt(edges[b] * edges[b + 1])) > lowest:
            centres.append(float(np.sqrt(edges[b] * edges[b + 1])))
            responses.append(h)
            errors.append(se)
    if len(centres) <= MIN_BINS:
        return None
    return MeasuredResponse(np.asarray(centres), np.asarray(responses, complex), np.asarray(errors))


def response_at(measured: MeasuredResponse, f_hz: np.ndarray, lag_s: float = 0.0) -> np.ndarray:
    """``measured`` over a lag's ``exp(-j 2 pi f lag_s)`` at ``f_hz`` (Hz): log magnitude and unwrapped
    phase interpolated in log frequency, held at the end values outside the measured bins."""
    c = measured.response * np.exp(2j * np.pi * measured.frequency_hz * lag_s)
    logf = np.log(measured.frequency_hz)
    mag = np.log(np.maximum(np.abs(c), 1e-12))
    phase = np.unwrap(np.angle(c))
    at = np.log(np.maximum(np.asarray(f_hz, float), 1e-300))
    return np.exp(np.interp(at, logf, mag) + 1j * np.interp(at, logf, phase))
