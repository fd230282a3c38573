"""The frequency response of the linear part: the H1 estimate with coherence (MATLAB ``tfestimate``)
and the 3-sigma confidence band of its magnitude (paper 000 sec. 2.2, Fig. 2d); the first resonant
peak is paper 002's ADT Step 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import signal as sps

from hilbench.errors import UserError
from hilbench.identify.array_checks import (
    as_1d,
    require_finite,
    require_positive,
    same_length,
)
from hilbench.identify.peaks import moving_average, quad_vertex


# ------------------------------------------------------------------------------------------------
# frequency response (000 Fig. 2d, 002 ADT Step 1)
# ------------------------------------------------------------------------------------------------
@dataclass
class FrequencyResponse:
    """H1 frequency-response estimate ``H = P_uy / P_uu`` with its coherence and 3-sigma band.

    frequency_hz (Hz); magnitude (output unit per input unit, um/A); phase_rad (unwrapped, rad);
    coherence (magnitude-squared, 0..1); lower/upper: |H| -+ 3 sigma_|H| (clipped at 0), with the
    normalised random error of the H1 magnitude (Bendat & Piersol)
    ``sigma_|H| / |H| = sqrt(1 - gamma^2) / (|gamma| sqrt(2 n_d))``, n_d = n_segments averaged.
    """

    frequency_hz: np.ndarray
    response: np.ndarray  # complex H1
    magnitude: np.ndarray
    phase_rad: np.ndarray
    coherence: np.ndarray
    relative_sigma: np.ndarray  # sigma_|H| / |H|
    lower: np.ndarray
    upper: np.ndarray
    n_segments: int
    nperseg: int
    sample_rate_hz: float

    @property
    def magnitude_db(self) -> np.ndarray:
        return 20 * np.log10(np.maximum(self.magnitude, 1e-300))

    def resonant_frequency_hz(self, *, min_coherence: float = 0.5, prominence_db: float = 2.0,
                              smooth_bins: int | None = None) -> float:
        """The first resonant peak of the magnitude (Hz): the lowest-frequency local maximum of the
        magnitude (dB, moving average over ``smooth_bins`` bins against the estimate's scatter;
        default about 1/64 of the bins) that stands ``prominence_db`` above the lowest point on
        each side before a higher value, among bins with coherence >= min_coherence; refined by a
        least-squares parabola through the raw dB values around it."""
        ok = self.coherence >= min_coherence
        if ok.sum() < 5:
            raise UserError(f"no resonant peak: fewer than 5 frequencies with coherence >= {min_coherence:g}")
        f = self.frequency_hz[ok]
        db = self.magnitude_db[ok]
        w = smooth_bins if smooth_bins is not None else max(3, (f.size // 64) | 1)
        smooth = moving_average(db, int(w))
        peaks, _ = sps.find_peaks(smooth, prominence=prominence_db)
        if peaks.size == 0:
            raise UserError(f"no resonant peak in the magnitude (prominence >= {prominence_db:g} dB where "
                            f"coherence >= {min_coherence:g}); the dynamics may be overdamped")
        k = int(peaks[0])
        half = max(1, int(w))
        lo, hi = max(0, k - half), min(f.size, k + half + 1)
        vertex = quad_vertex(f[lo:hi], db[lo:hi], True)
        return vertex[0] if vertex is not None else float(f[k])

    def natural_frequency_hz(self, zeta: float | None = None, **kwargs: Any) -> float:
        """002 ADT Step 1: omega_n / 2 pi (Hz) read from the first resonant peak of the magnitude.

        Without ``zeta`` this is the peak frequency itself, as the paper reads it. The magnitude of
        a second-order plant peaks at f_n sqrt(1 - 2 zeta^2), below f_n (8 % below at zeta = 0.28),
        so with ``zeta`` (e.g. from :func:`step_response`, ADT Step 4) the peak is converted to f_n."""
        fr = self.resonant_frequency_hz(**kwargs)
        if zeta is None:
            return fr
        if not 0 <= zeta < 1 / math.sqrt(2):
            raise UserError(f"zeta = {zeta:g}: a second-order magnitude has a resonant peak only for zeta < 0.707")
        return fr / math.sqrt(1 - 2 * zeta**2)

    def to_dict(self) -> dict[str, Any]:
        return {
            "frequency_hz": self.frequency_hz.tolist(), "magnitude": self.magnitude.tolist(),
            "phase_rad": self.phase_rad.tolist(), "coherence": self.coherence.tolist(),
            "lower": self.lower.tolist(), "upper": self.upper.tolist(),
            "n_segments": self.n_segments, "nperseg": self.nperseg, "sample_rate_hz": self.sample_rate_hz,
        }


def frequency_response(
    u: np.ndarray,
    y: np.ndarray,
    fs: float,
    *,
    nperseg: int | None = None,
    band_hz: tuple[float, float] | None = None,
) -> FrequencyResponse:
    """H1 estimate of the frequency response from input u (A or V) to output y (um), like MATLAB
    ``tfestimate``: Welch averages (Hann window, 50 % overlap, per-segment mean removed) of the cross
    and auto spectra, ``H1 = P_uy / P_uu``, coherence ``|P_uy|^2 / (P_uu P_yy)``, and the 3-sigma band
    of the magnitude (000 Fig. 2d). fs: sample rate (Hz). nperseg: samples per segment (default the
    largest power of two not above n / 8, at most 2^16: about 15 averaged segments). band_hz: keep
    only frequencies in [low, high] (Hz), e.g. the excitation band; the DC bin is always left out.
    """
    u = as_1d(u, "u")
    y = as_1d(y, "y")
    n = same_length(u=u, y=y)
    fs = require_positive(fs, "fs")
    if n < 64:
        raise UserError(f"too few samples for a frequency response: {n} (need at least 64)")
    require_finite(u, "u")
    require_finite(y, "y")
    if nperseg is None:
        nperseg = int(min(2**16, 2 ** int(math.floor(math.log2(max(16, n / 8))))))
    nperseg = int(nperseg)
    if not 8 <= nperseg <= n:
        raise UserError(f"nperseg = {nperseg}: expected 8 <= nperseg <= the number of samples ({n})")
    if np.ptp(u) == 0:
        raise UserError("u is constant: no excitation to estimate a frequency response from")
    noverlap = nperseg // 2
    kw = dict(fs=fs, window="hann", nperseg=nperseg, noverlap=noverlap, detrend="constant")
    f, puu = sps.welch(u, **kw)
    _, pyy = sps.welch(y, **kw)
    _, puy = sps.csd(u, y, **kw)  # conj(U) Y
    n_seg = 1 + (n - nperseg) // (nperseg - noverlap)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = puy / puu
        coh = np.abs(puy) ** 2 / (puu * pyy)
    coh = np.clip(np.nan_to_num(coh, nan=0.0), 0.0, 1.0)
    keep = (puu > 0) & (f > 0)
    if band_hz is not None:
        lo, hi = (float(v) for v in band_hz)
        if not 0 <= lo < hi:
            raise UserError(f"band_hz = {band_hz!r}: expected [low, high] with 0 <= low < high (Hz)")
        keep &= (f >= lo) & (f <= hi)
    if keep.sum() < 2:
        raise UserError("no frequencies left in band_hz with input power; widen the band or use more samples")
    f, h, coh = f[keep], h[keep], coh[keep]
    mag = np.abs(h)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.sqrt(1.0 - coh) / (np.sqrt(coh) * math.sqrt(2 * n_seg))
    rel = np.where(coh > 0, rel, np.inf)
    lower = np.clip(mag * (1 - 3 * rel), 0.0, None)
    upper = mag * (1 + 3 * rel)
    return FrequencyResponse(
        frequency_hz=f, response=h, magnitude=mag, phase_rad=np.unwrap(np.angle(h)), coherence=coh,
        relative_sigma=rel, lower=lower, upper=upper, n_segments=int(n_seg), nperseg=nperseg,
        sample_rate_hz=fs,
    )
