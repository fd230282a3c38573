"""Is a refit's validation error lower than the old one's by more than chance? Tests over blocks.

The residuals of a hysteresis model are strongly autocorrelated, so the tests compare contiguous
blocks of rows, not rows. Two alternatives matter and no single test has power against both
(docs/decisions/0022):

* a gain **spread** over the record (a lag, a temperature drift): most blocks improve a little.
  The Wilcoxon signed-rank test over N_BLOCKS equal blocks (:func:`block_test`) sees it; a test of
  the summed difference does too, but is noisier on heavy-tailed block differences.
* a gain **concentrated** where the effect acts (saturation at the largest drive, a resonance rung
  by a triangle's corners, a velocity term on the fastest stretches): a few blocks improve a lot,
  the rest do not change. The signed-rank test counts those few blocks as few and misses it; the
  sum of the block differences, tested by random sign flips (:func:`sum_test`), does not.

:func:`improvement_test` takes the smaller of the two p-values with a Bonferroni factor of two, so
the chance that noise passes stays under the one test's level.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from hilbench.diagnosis import thresholds as T


#: Squared-error differences below this fraction of the old mean square are floating-point
#: rounding (a refit that returned the same model), not a gain in either direction.
ROUNDING = 1e-9


def _squared_differences(e_old: np.ndarray, e_new: np.ndarray) -> np.ndarray:
    """Per row, old minus new squared error, with rounding-level differences set to zero."""
    e_old, e_new = np.asarray(e_old, float), np.asarray(e_new, float)
    d = e_old**2 - e_new**2
    if d.size:
        d[np.abs(d) <= ROUNDING * float(np.mean(e_old**2))] = 0.0
    return d


def block_test(e_old: np.ndarray, e_new: np.ndarray, n_blocks: int = T.N_BLOCKS) -> tuple[float, int, int]:
    """One-sided Wilcoxon signed-rank p-value that the new squared error is lower, over ``n_blocks``
    contiguous blocks; and how many blocks improved, of how many."""
    d_rows = _squared_differences(e_old, e_new)
    if d_rows.size < 5:
        return 1.0, 0, 0
    blocks = [b for b in np.array_split(np.arange(d_rows.size), min(n_blocks, d_rows.size)) if b.size]
    d = np.array([np.mean(d_rows[b]) for b in blocks])
    if d.size < 5 or not np.any(d != 0):
        return 1.0, int(np.sum(d > 0)), int(d.size)
    p = float(stats.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue)
    return p, int(np.sum(d > 0)), int(d.size)


def correlation_length(x: np.ndarray) -> int:
    """Lag (samples) at which the autocorrelation of ``x`` first falls below 1/e (``x.size`` if never)."""
    x = np.asarray(x, float) - float(np.mean(x))
    n = x.size
    if n < 2:
        return 1
    spectrum = np.fft.rfft(x, 2 * n)  # zero-padded: the linear, not the circular, autocorrelation
    ac = np.fft.irfft(spectrum * np.conj(spectrum))[:n]
    if ac[0] <= 0:
        return 1
    below = np.flatnonzero(ac < ac[0] * math.exp(-1))
    return int(below[0]) if below.size else n


def sum_test(e_old: np.ndarray, e_new: np.ndarray) -> tuple[float, int]:
    """One-sided sign-flip randomization p-value that the summed squared-error difference is
    positive, over contiguous blocks SUM_TEST_BLOCK_CORRELATIONS correlation lengths long (so the
    blocks are nearly independent and, under no effect, their differences symmetric about zero);
    and the number of blocks. Seeded: the same data give the same p."""
    d_rows = _squared_differences(e_old, e_new)
    if d_rows.size < 5:
        return 1.0, 0
    length = T.SUM_TEST_BLOCK_CORRELATIONS * correlation_length(d_rows)
    n_blocks = int(np.clip(d_rows.size // max(length, 1), T.N_BLOCKS, T.SUM_TEST_MAX_BLOCKS))
    blocks = [b for b in np.array_split(np.arange(d_rows.size), min(n_blocks, d_rows.size)) if b.size]
    d = np.array([np.mean(d_rows[b]) for b in blocks])
    if d.size < 5 or not np.any(d != 0):
        return 1.0, int(d.size)
    signs = np.random.default_rng(0).choice(np.array([-1.0, 1.0]), size=(T.SUM_TEST_FLIPS, d.size))
    exceed = int(np.sum(signs @ d >= d.sum() - 1e-12 * np.abs(d).sum()))
    return (1 + exceed) / (1 + T.SUM_TEST_FLIPS), int(d.size)


def improvement_test(e_old: np.ndarray, e_new: np.ndarray) -> tuple[float, int, int]:
    """p-value that the new error is lower, against a spread or a concentrated gain: twice the
    smaller of :func:`block_test`'s and :func:`sum_test`'s (Bonferroni), at most 1; and the signed-rank
    test's blocks improved, of how many."""
    p_spread, better, blocks = block_test(e_old, e_new)
    p_concentrated, _ = sum_test(e_old, e_new)
    return min(1.0, 2.0 * min(p_spread, p_concentrated)), better, blocks
