"""The Preisach plane of the simulated plant: a weighted grid of relay hysterons and its density.

A relay hysteron R(alpha, beta) switches up to +1 when the input reaches alpha and down to -1 when it
falls to beta (alpha >= beta), and holds its state in between. The Preisach model sums them with a
density mu(alpha, beta) over the half plane alpha >= beta (Preisach 1935; Mayergoyz, *Mathematical
Models of Hysteresis*, ch. 1): its major loop, minor loops that close (return-point memory) and the
wiping-out of inner reversals by a larger one follow from the relays alone.

The density is written in the coordinates a magnetics lab reads a Preisach (FORC) diagram in: the
coercive field r = (alpha - beta) / 2 (half the relay's width) and the interaction field
c = (alpha + beta) / 2 (its centre), both in normalised input units, as a factorised Gaussian

    mu(alpha, beta) ~ exp(-(r - coercive_mean)^2 / (2 coercive_std^2)) exp(-c^2 / (2 interaction_std^2)),

on an ``levels`` x ``levels`` grid of cells over ``switching_range`` (cells with alpha >= beta only),
weights normalised to sum 1 (so the relays' part of the output spans -1..+1 once the drive has swept
the whole range). A wide interaction spread (much wider than the drive) makes the model the
Prandtl-Ishlinskii operator, whose density is constant along c; a narrow one gives the sigmoid loops
of a soft ferromagnet or a poled piezoceramic.

With switching fields at the cell centres, every hysteron of a grid row switches at once and the
output moves in steps of a row's weight; ``scatter_seed`` > 0 scatters each hysteron's two fields
uniformly within its cell (a seeded draw, the same for a seed), a sampled continuum: steps of one
hysteron's weight.
"""

from __future__ import annotations

import numpy as np

from hilbench.errors import ConfigError


def preisach_grid(h: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(alpha, beta, weights, demagnetised states) of the relays of a checked ``[plant.hysteresis]``
    table with ``model = 'preisach'`` (normalised input units; weights sum to 1).

    The demagnetised state (an AC-demagnetised sample at zero input): relays below the line
    alpha = -beta are up, those above it down (Mayergoyz ch. 1, the staircase of a decaying
    alternating input), a relay exactly on the line at 0, the mean of the two, since a decaying
    input leaves half of such relays up.
    """
    n = int(h["levels"])
    lo, hi = (float(x) for x in h["switching_range"])
    step = (hi - lo) / n
    i, j = np.tril_indices(n)  # i >= j: alpha index >= beta index
    alpha = lo + (i + 0.5) * step
    beta = lo + (j + 0.5) * step
    seed = int(h["scatter_seed"])
    if seed > 0:
        rng = np.random.default_rng([seed, 7])
        alpha = alpha + (rng.random(alpha.size) - 0.5) * step
        beta = beta + (rng.random(beta.size) - 0.5) * step
        # a diagonal cell may draw beta above alpha: a relay then has no width, not a negative one
        beta = np.minimum(beta, alpha)
    r = 0.5 * (alpha - beta)
    c = 0.5 * (alpha + beta)
    w = np.exp(-0.5 * ((r - h["coercive_mean"]) / h["coercive_std"]) ** 2
               - 0.5 * (c / h["interaction_std"]) ** 2)
    total = float(w.sum())
    if not total > 0.0:
        raise ConfigError("[plant.hysteresis] the Preisach density has no weight on the grid: expected "
                          "coercive_mean within a few coercive_std of the switching_range's half-width")
    w /= total
    state = -np.sign(alpha + beta)
    return alpha, beta, w, state
