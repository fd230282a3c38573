"""Is a refit's validation error lower than the old one's by more than chance? Tests over blocks.

The residuals of a hysteresis model are strongly autocorrelated, so the tests compare contiguous
blocks of rows, not rows. Two alternatives matter and no single test has power against both
(docs/decisions/0022):

* a gain **spread** over the record (a lag, a temperature drift): most blocks improve a little.
  The Wilcoxon signed-rank statistic sees it; the summed difference does too, but is noisier on
  heavy-tailed block differences.
* a gain **concentrated** where the effect acts (saturation at the largest drive, a resonance rung
  by a triangle's corners, a velocity term on the fastest stretches): a few blocks improve a lot,
  the rest do not change. The signed ranks count those few blocks as few and miss it; the sum of
  the block differences does not.

Both statistics are taken over one partition into blocks SUM_TEST_BLOCK_CORRELATIONS correlation
lengths of the squared-error difference long (:func:`block_count`), and both are referred to the
same random sign flips of the block differences: under no effect the blocks are nearly independent
and their differences symmetric, so every flip is as likely as the data. :func:`block_tests` takes
the smaller of the two p-values and calibrates it on the flips themselves (how often a flip's
smaller p is as small): an exact level for the pair, where a Bonferroni factor of two over-counts
two tests that mostly agree (docs/decisions/0032).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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


def block_count(d_rows: np.ndarray) -> int:
    """Contiguous blocks for the tests: each SUM_TEST_BLOCK_CORRELATIONS correlation lengths of the
    squared-error difference long (neighbours nearly independent, so under no effect the block
    differences are symmetric about zero and their signs exchangeable), N_BLOCKS to SUM_TEST_MAX_BLOCKS."""
    length = T.SUM_TEST_BLOCK_CORRELATIONS * correlation_length(d_rows)
    return int(min(np.clip(d_rows.size // max(length, 1), T.N_BLOCKS, T.SUM_TEST_MAX_BLOCKS), d_rows.size))


@dataclass(frozen=True)
class BlockTests:
    """The improvement tests over one partition into blocks (module docstring)."""

    p: float  #: the joint p-value: the chance that noise gives a smaller of the two p-values this small
    p_ranks: float  #: the signed-rank statistic's own sign-flip p-value (a spread gain)
    p_sum: float  #: the summed difference's own sign-flip p-value (a concentrated gain)
    better: int  #: blocks whose squared error fell
    blocks: int


def block_tests(e_old: np.ndarray, e_new: np.ndarray) -> BlockTests:
    """One-sided sign-flip tests that the new squared error is lower, over :func:`block_count`
    contiguous blocks: the Wilcoxon signed-rank statistic and the summed difference, each with its
    own p-value, and their joint p-value calibrated on the same flips (module docstring). Seeded:
    the same data give the same p."""
    d_rows = _squared_differences(e_old, e_new)
    if d_rows.size < 5:
        return BlockTests(1.0, 1.0, 1.0, 0, 0)
    blocks = [b for b in np.array_split(np.arange(d_rows.size), block_count(d_rows)) if b.size]
    d = np.array([np.mean(d_rows[b]) for b in blocks])
    better = int(np.sum(d > 0))
    if d.size < 5 or not np.any(d != 0):
        return BlockTests(1.0, 1.0, 1.0, better, int(d.size))
    flips = T.SUM_TEST_FLIPS
    flipped = np.random.default_rng(0).choice(np.array([-1.0, 1.0]), size=(flips, d.size)) * d
    ranks = stats.rankdata(np.abs(d))
    ranks_null = (flipped > 0) @ ranks  # a flip only moves a block between the signs; its rank stays
    sums_null = flipped.sum(axis=1)
    tolerance = 1e-12 * float(np.abs(d).sum())

    def p_of(null: np.ndarray, observed: np.ndarray, tol: float) -> np.ndarray:
        ordered = np.sort(null)  # (1 + flips at least as large) / (1 + flips): the observed counts once
        return (1 + flips - np.searchsorted(ordered, observed - tol, side="left")) / (1 + flips)

    p_ranks = float(p_of(ranks_null, np.array([ranks[d > 0].sum()]), 1e-9)[0])
    p_sum = float(p_of(sums_null, np.array([d.sum()]), tolerance)[0])
    smaller_null = np.minimum(p_of(ranks_null, ranks_null, 1e-9), p_of(sums_null, sums_null, tolerance))
    p = float((1 + np.sum(smaller_null <= min(p_ranks, p_sum))) / (1 + flips))
    return BlockTests(min(p, 1.0), p_ranks, p_sum, better, int(d.size))


def improvement_test(e_old: np.ndarray, e_new: np.ndarray) -> tuple[float, int, int]:
    """The joint p-value of :func:`block_tests` that the new error is lower, against a spread or a
    concentrated gain; and how many blocks improved, of how many."""
    t = block_tests(e_old, e_new)
    return t.p, t.better, t.blocks
