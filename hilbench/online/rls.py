"""Recursive least squares as one numba kernel over explicit state (block and step mode).

The estimator minimises the exponentially weighted a-priori error of ``y(k) = theta' phi(k) + e(k)``
(paper 000 eq. 10-13). One step function, :func:`rls_step`, updates caller-owned state arrays;
:func:`rls_block` loops over samples calling it, so a block of n samples and n single steps give
bit-identical results (tested).

State (all float64 arrays the caller owns, see :func:`new_state`):

* ``theta`` (n,)   parameter estimate
* ``P`` (n, n)     covariance (scaled by the noise variance: the inverse information matrix)
* ``g`` (n,)       work vector (P phi), kept in the state so a step allocates nothing
* ``cfg`` (N_CFG,) settings, indices ``C_*``
* ``st`` (N_ST,)   counters, robust scale, status of the last sample, indices ``ST_*``

Numerics, and why:

* **Symmetric update.** P is updated as a symmetric rank-1 correction ``P[i, j] -= c (g_i g_j)``
  over the whole matrix: ``g_i g_j`` and ``g_j g_i`` are the same IEEE product, so a symmetric P
  stays symmetric to the last bit without mirroring, and each row is one contiguous pass the
  compiler vectorises (no ``fastmath``: no reassociation, the same bits in block and step mode;
  ``g = P phi`` is summed column by column for the same reason). The textbook form ``P - P phi phi' P / (...)``
  evaluated as matrix products accumulates an antisymmetric rounding error that forgetting
  (division by lambda) amplifies every sample: it diverges after ~1e4-1e5 samples at lambda = 0.999.
  In exact arithmetic the update equals the Joseph form
  ``(I - k phi') P (I - k phi')' / lambda + k k' / lambda`` (expand it: the k-terms collapse to the
  rank-1 correction), at O(n^2) instead of O(n^3) per sample.
* **Bounded covariance.** After each update the trace is capped at ``trace_max`` (default: the
  initial trace n * delta, "never more uncertain than at the start") by scaling P; a non-finite or
  non-positive diagonal (loss of positive definiteness) resets P to delta I. Both are counted.
* **No wind-up.** Default forgetting is *directional* (after Kulhavy 1987): information is
  forgotten only along the current regressor direction, in information form
  ``R+ = R - mu phi phi' / xi + q phi phi'`` with ``xi = phi' P phi``, i.e. the fraction mu of what
  is known along phi is replaced by the new sample. Directions the data do not excite keep their
  information, so P cannot grow while the excitation has stopped (a held input, a constant
  regressor). In covariance form ``P+ = P - (q - mu/xi) g g' / (1 - mu + q xi)``; the denominator
  is > 0 for mu < 1, so P stays positive definite. ``mu = n (1 - lambda)`` (at most 0.5) removes
  as much information per sample as exponential forgetting does (``trace(P dR) = n (1 - lambda)``
  in both), so lambda means the same memory, about 1 / (1 - lambda) samples under rich
  excitation, in both kinds (with mu = 1 - lambda, Kulhavy's choice, tracking is n times slower,
  and slower still along weakly excited directions). Forgetting is also suspended on samples that
  carry little information, ``xi <= forget_threshold mu`` (directional forgetting settles at
  xi ~ mu under rich excitation): P is frozen and theta still corrected with it (counted as
  ``frozen``). Forgetting on such samples, an excitation that drops to noise level (input
  switched off, output noise still exciting the output lags) would replace what was learnt by
  noise-level information and let P grow by orders of magnitude; learning from them without
  forgetting would pile up information over a long pause, so that the estimator turns stiff in
  directions the pause happened to excite. A regressor with ``xi <= xi_min`` (default 0: phi = 0)
  is not used at all. ``forgetting="exponential"`` gives the classical
  ``P+ = (P - q g g'/(lambda + q xi)) / lambda`` with the same suspension on uninformative samples;
  it still winds up (to the trace cap) under a held input, whose constant regressor excites one
  direction only.
* **Guards.** A sample with a non-finite regressor or output is skipped (counted); its prediction
  is returned (NaN when the regressor is not finite). The a-priori error is compared with a robust
  running scale sigma_hat (a winsorised running mean of |e|, times sqrt(pi/2) so it estimates the
  standard deviation of Gaussian noise; plain mean over the first ``warmup`` samples). An error
  beyond ``outlier_k`` sigma_hat is an outlier (counted): ``outlier="skip"`` ignores the sample,
  ``outlier="huber"`` (default) weights it by ``q = outlier_k sigma_hat / |e|``, the Huber
  M-estimator as a weighted least-squares sample, so its influence on theta and P is bounded; an
  error beyond ``reject_k`` sigma_hat (default 50, a gross error: a sensor spike, not the plant) is
  skipped in Huber mode too. The
  scale takes in winsorised errors, so a lasting change of the plant (not a spike) raises sigma_hat
  by a few per cent per sample until its errors are accepted again.

Status of the last sample, ``st[ST_STATUS]``: ``UPDATED``, ``NONFINITE``, ``OUTLIER_SKIPPED``,
``OUTLIER_WEIGHTED`` (updated with Huber weight) or ``FROZEN`` (little or no excitation: P
frozen, theta corrected; or not used at all when phi = 0). ``st[ST_CLEAN]`` is
the output value the estimator believes: y, the prediction for a skipped sample, or the Huber-clipped
``y_hat + q e``; the OIIR puts it into its output history in place of a skipped or non-finite
measurement (a Huber-weighted one is kept: it is most likely the plant, see hilbench.online.oiir).

Speed: :func:`_core` is the sample; it takes the settings and scalar state as arguments and returns
what changed, so :func:`rls_block` reads ``cfg`` once per block and keeps counters in locals, and
:func:`rls_step` reads and writes ``st`` around one call. ``error_model="numpy"`` (no Python
division checks).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

__all__ = [
    "RLS",
    "rls_step",
    "rls_block",
    "new_state",
    "make_config",
    "counters",
]

# -- cfg indices -------------------------------------------------------------------------------
C_LAMBDA = 0  # forgetting factor, 0 < lambda <= 1
C_DELTA = 1  # initial covariance P0 = delta I (and after a reset)
C_FORGET = 2  # 0 exponential, 1 directional
C_TRACE_MAX = 3  # cap of trace(P)
C_XI_MIN = 4  # phi' P phi at or below this: sample not used (phi = 0)
C_OUTLIER = 5  # 0 off, 1 skip, 2 Huber weight
C_OUTLIER_K = 6  # outlier threshold, robust standard deviations
C_SCALE_ALPHA = 7  # per-sample weight of the running scale estimate (1 / memory in samples)
C_WARMUP = 8  # samples averaged before outliers are judged
C_SCALE_MIN = 9  # floor of the scale estimate, output units
C_XI_FORGET = 10  # forgetting only when phi' P phi exceeds this (informative samples)
C_MU = 11  # directional forgetting: fraction of the information along phi forgotten per sample
C_REJECT_K = 12  # huber: an error beyond this many robust standard deviations is skipped (gross error)
N_CFG = 13

# -- st indices --------------------------------------------------------------------------------
ST_SAMPLES = 0
ST_UPDATES = 1
ST_NONFINITE = 2
ST_OUTLIERS = 3
ST_FROZEN = 4
ST_CAPPED = 5
ST_RESETS = 6
ST_SCALE = 7  # robust standard deviation of the a-priori error, output units
ST_STATUS = 8
ST_CLEAN = 9
ST_WARM = 10  # samples taken into the warm-up mean
N_ST = 11

# -- status codes ------------------------------------------------------------------------------
UPDATED = 0.0
NONFINITE = 1.0
OUTLIER_SKIPPED = 2.0
OUTLIER_WEIGHTED = 3.0
FROZEN = 4.0

_SIGMA_PER_MAD = math.sqrt(math.pi / 2.0)  # E|e| = sigma sqrt(2/pi) for Gaussian e

FORGETTING = {"exponential": 0.0, "directional": 1.0}
OUTLIER = {"off": 0.0, "skip": 1.0, "huber": 2.0}


# -- what a sample did, as bits of the ``flags`` the core returns --------------------------------
_F_UPDATED = 1  # theta corrected
_F_NONFINITE = 2
_F_OUTLIER = 4
_F_FROZEN = 8
_F_CAPPED = 16
_F_RESET = 32


@njit(cache=True, inline="always", error_model="numpy")
def _core(
    phi: np.ndarray, y: float, theta: np.ndarray, P: np.ndarray, g: np.ndarray,
    lam: float, inv_lam: float, mu: float, directional: bool, mode: float, k_out: float, k_reject: float,
    alpha: float,
    warmup: float, scale_min: float, xi_min: float, xi_forget: float, trace_max: float, delta: float,
    scale: float, warm: float,
) -> tuple[float, float, float, float, float, int]:
    """One RLS sample on theta, P and g; settings and the scalar state come in as locals, and what
    the sample did goes out as values: ``(y_hat, status, clean, scale, warm, flags)``.

    Nothing here writes ``st`` or reads ``cfg``: :func:`rls_step` does that around one call,
    :func:`rls_block` once per block (a store to ``st`` between the loops over P would make the
    compiler reload every array after it: it cannot rule out aliasing). Both call this same code,
    so block and step mode give the same bits.
    """
    n = theta.shape[0]
    y_hat = 0.0
    for i in range(n):
        y_hat += theta[i] * phi[i]
    # A NaN/inf anywhere in phi makes y_hat non-finite (0 * inf is NaN too): one test covers both.
    if not (math.isfinite(y_hat) and math.isfinite(y)):
        return y_hat, NONFINITE, y_hat, scale, warm, _F_NONFINITE
    e = y - y_hat
    # g = P phi by columns (P is symmetric to the bit, so column j is row j): the inner loop runs
    # over contiguous memory with independent sums, which vectorises without reassociation, and
    # each g[i] is summed over j in order, as a row-by-row dot product would sum it.
    p0 = phi[0]
    for i in range(n):
        g[i] = P[0, i] * p0
    for j in range(1, n):
        pj = phi[j]
        for i in range(n):
            g[i] += P[j, i] * pj
    xi = 0.0
    for i in range(n):
        xi += phi[i] * g[i]
    if not math.isfinite(xi):  # finite but huge regressor: its square overflows
        return y_hat, NONFINITE, y_hat, scale, warm, _F_NONFINITE

    # -- robust scale and outlier weight q -------------------------------------------------------
    q = 1.0
    outlier = 0
    if mode != 0.0:
        ae = abs(e)
        if warm < warmup:
            warm += 1.0
            scale += (_SIGMA_PER_MAD * ae - scale) / warm
        else:
            limit = k_out * scale
            if ae > limit:
                outlier = _F_OUTLIER
                # skip mode, or a gross error in Huber mode (a sensor spike, not the plant): skipped
                q = 0.0 if (mode == 1.0 or ae > k_reject * scale) else limit / ae
            # winsorised: a spike moves the scale by at most (k - 1) alpha of itself
            scale += alpha * (_SIGMA_PER_MAD * min(ae, limit) - scale)
        scale = max(scale, scale_min)
        if q == 0.0:
            return y_hat, OUTLIER_SKIPPED, y_hat, scale, warm, _F_OUTLIER
    if xi <= xi_min:
        # phi = 0 (or P singular along it): there is nothing to learn from this sample
        return y_hat, FROZEN, y, scale, warm, _F_FROZEN
    if xi <= xi_forget:
        # Little excitation (phi small against what is already known): theta is still corrected
        # with the current P, but P is frozen. Forgetting along phi would replace good information
        # by noise-level information (P winds up); learning without forgetting would pile up
        # information over a long pause (P winds down and the estimator turns stiff).
        k_e = q * e / (1.0 + q * xi)
        for i in range(n):
            theta[i] += g[i] * k_e
        status = FROZEN if q == 1.0 else OUTLIER_WEIGHTED
        return y_hat, status, y_hat + q * e, scale, warm, _F_UPDATED | _F_FROZEN | outlier

    # -- parameter update: theta += q e P+ phi, with P+ phi = g / den in both forgetting kinds ------
    den = (1.0 - mu + q * xi) if directional else (lam + q * xi)  # > 0: mu < 1, lam > 0
    inv_den = 1.0 / den
    k_e = (q * e) * inv_den
    for i in range(n):
        theta[i] += g[i] * k_e

    # -- covariance: symmetric rank-1 correction ------------------------------------------------
    # P[i, j] - c (g_i g_j): g_i g_j and g_j g_i are the same IEEE product, so a symmetric P stays
    # symmetric to the bit without mirroring, and every row is one contiguous vectorisable pass.
    if directional:
        c = (q - mu / xi) * inv_den
        for i in range(n):
            gi = g[i]
            for j in range(n):
                P[i, j] -= c * (gi * g[j])
    else:
        c = q * inv_den
        for i in range(n):
            gi = g[i]
            for j in range(n):
                P[i, j] = (P[i, j] - c * (gi * g[j])) * inv_lam
    trace = 0.0
    bad = False
    for i in range(n):
        d = P[i, i]
        trace += d
        if not d > 0.0:  # also catches NaN
            bad = True
    flags = _F_UPDATED | outlier
    if bad or not math.isfinite(trace):
        for i in range(n):
            for j in range(n):
                P[i, j] = 0.0
            P[i, i] = delta
        flags |= _F_RESET
    elif trace > trace_max:
        s = trace_max / trace
        for i in range(n):
            for j in range(n):
                P[i, j] *= s
        flags |= _F_CAPPED
    status = UPDATED if q == 1.0 else OUTLIER_WEIGHTED
    return y_hat, status, y_hat + q * e, scale, warm, flags


@njit(cache=True, inline="always", error_model="numpy")
def rls_step(
    phi: np.ndarray, y: float, theta: np.ndarray, P: np.ndarray, g: np.ndarray, cfg: np.ndarray, st: np.ndarray
) -> float:
    """One RLS sample: returns the a-priori prediction theta' phi, then updates the state in place."""
    y_hat, status, clean, scale, warm, flags = _core(
        phi, y, theta, P, g, cfg[C_LAMBDA], 1.0 / cfg[C_LAMBDA], cfg[C_MU], cfg[C_FORGET] == 1.0, cfg[C_OUTLIER],
        cfg[C_OUTLIER_K], cfg[C_REJECT_K], cfg[C_SCALE_ALPHA], cfg[C_WARMUP], cfg[C_SCALE_MIN], cfg[C_XI_MIN], cfg[C_XI_FORGET],
        cfg[C_TRACE_MAX], cfg[C_DELTA], st[ST_SCALE], st[ST_WARM],
    )
    st[ST_SAMPLES] += 1.0
    st[ST_UPDATES] += flags & _F_UPDATED
    st[ST_NONFINITE] += (flags & _F_NONFINITE) >> 1
    st[ST_OUTLIERS] += (flags & _F_OUTLIER) >> 2
    st[ST_FROZEN] += (flags & _F_FROZEN) >> 3
    st[ST_CAPPED] += (flags & _F_CAPPED) >> 4
    st[ST_RESETS] += (flags & _F_RESET) >> 5
    st[ST_STATUS] = status
    st[ST_CLEAN] = clean
    st[ST_SCALE] = scale
    st[ST_WARM] = warm
    return y_hat


@njit(cache=True, error_model="numpy")
def rls_block(
    Phi: np.ndarray,
    Y: np.ndarray,
    theta: np.ndarray,
    P: np.ndarray,
    g: np.ndarray,
    cfg: np.ndarray,
    st: np.ndarray,
    y_hat: np.ndarray,
    theta_hist: np.ndarray,
    decimate: int,
) -> int:
    """:func:`rls_step` over the rows of Phi (m, n) and Y (m,); returns the history rows written.

    ``y_hat`` (m,) receives the a-priori predictions; ``theta_hist`` (rows, n) receives theta after
    every ``decimate``-th sample of the block (samples decimate-1, 2 decimate-1, ...) until full;
    ``decimate <= 0`` records nothing. Settings are read and the counters, scale and status kept
    in locals for the whole block, and written to ``st`` once at its end: the same values as
    ``m`` calls of :func:`rls_step` (counts are exact in float64).
    """
    lam = cfg[C_LAMBDA]
    inv_lam = 1.0 / lam
    mu = cfg[C_MU]
    directional = cfg[C_FORGET] == 1.0
    mode = cfg[C_OUTLIER]
    k_out = cfg[C_OUTLIER_K]
    k_reject = cfg[C_REJECT_K]
    alpha = cfg[C_SCALE_ALPHA]
    warmup = cfg[C_WARMUP]
    scale_min = cfg[C_SCALE_MIN]
    xi_min = cfg[C_XI_MIN]
    xi_forget = cfg[C_XI_FORGET]
    trace_max = cfg[C_TRACE_MAX]
    delta = cfg[C_DELTA]
    scale = st[ST_SCALE]
    warm = st[ST_WARM]
    status = st[ST_STATUS]
    clean = st[ST_CLEAN]
    n_updated = 0
    n_nonfinite = 0
    n_outlier = 0
    n_frozen = 0
    n_capped = 0
    n_reset = 0
    m = Y.shape[0]
    rows = 0
    max_rows = theta_hist.shape[0] if decimate > 0 else 0
    countdown = decimate  # a counter, not (k + 1) % decimate: no integer division per sample
    for k in range(m):
        y_hat[k], status, clean, scale, warm, flags = _core(
            Phi[k], Y[k], theta, P, g, lam, inv_lam, mu, directional, mode, k_out, k_reject, alpha, warmup, scale_min,
            xi_min, xi_forget, trace_max, delta, scale, warm,
        )
        n_updated += flags & _F_UPDATED
        n_nonfinite += (flags & _F_NONFINITE) >> 1
        n_outlier += (flags & _F_OUTLIER) >> 2
        n_frozen += (flags & _F_FROZEN) >> 3
        n_capped += (flags & _F_CAPPED) >> 4
        n_reset += (flags & _F_RESET) >> 5
        if rows < max_rows:
            countdown -= 1
            if countdown == 0:
                countdown = decimate
                for i in range(theta.shape[0]):
                    theta_hist[rows, i] = theta[i]
                rows += 1
    st[ST_SAMPLES] += m
    st[ST_UPDATES] += n_updated
    st[ST_NONFINITE] += n_nonfinite
    st[ST_OUTLIERS] += n_outlier
    st[ST_FROZEN] += n_frozen
    st[ST_CAPPED] += n_capped
    st[ST_RESETS] += n_reset
    st[ST_STATUS] = status
    st[ST_CLEAN] = clean
    st[ST_SCALE] = scale
    st[ST_WARM] = warm
    return rows


def make_config(
    n_params: int,
    *,
    lam: float = 0.999,
    delta: float = 1.0e3,
    forgetting: str = "directional",
    trace_max: float | None = None,
    xi_min: float = 0.0,
    outlier: str = "huber",
    outlier_k: float = 5.0,
    reject_k: float = 50.0,
    scale_memory: float = 500.0,
    warmup: int | None = None,
    scale_min: float = 1.0e-12,
    forget_threshold: float = 0.1,
) -> np.ndarray:
    """The ``cfg`` array of the kernel, validated (see :class:`RLS` for the meaning)."""
    if not 0.0 < lam <= 1.0:
        raise ValueError(f"forgetting factor lam={lam}: expected 0 < lam <= 1")
    if not delta > 0.0:
        raise ValueError(f"delta={delta}: expected > 0")
    if forgetting not in FORGETTING:
        raise ValueError(f"forgetting={forgetting!r}: expected one of {', '.join(FORGETTING)}")
    if outlier not in OUTLIER:
        raise ValueError(f"outlier={outlier!r}: expected one of {', '.join(OUTLIER)}")
    if not outlier_k > 1.0:
        raise ValueError(f"outlier_k={outlier_k}: expected > 1 (robust standard deviations)")
    if not reject_k >= outlier_k:
        raise ValueError(f"reject_k={reject_k}: expected >= outlier_k={outlier_k}")
    if not scale_memory >= 1.0:
        raise ValueError(f"scale_memory={scale_memory}: expected >= 1 sample")
    cfg = np.zeros(N_CFG)
    cfg[C_LAMBDA] = lam
    cfg[C_DELTA] = delta
    cfg[C_FORGET] = FORGETTING[forgetting]
    cfg[C_TRACE_MAX] = n_params * delta if trace_max is None else float(trace_max)
    cfg[C_XI_MIN] = xi_min
    cfg[C_OUTLIER] = OUTLIER[outlier]
    cfg[C_OUTLIER_K] = outlier_k
    cfg[C_REJECT_K] = reject_k
    cfg[C_SCALE_ALPHA] = 1.0 / scale_memory
    cfg[C_WARMUP] = float(10 * n_params if warmup is None else warmup)
    cfg[C_SCALE_MIN] = scale_min
    # Under rich excitation directional forgetting settles at phi' P phi ~ (1 - lam): a sample far
    # below that carries far less information than the estimate already holds.
    # Directional forgetting removes, per sample, the fraction mu of what is known along phi. With
    # mu = n (1 - lam) it removes as much information per sample as exponential forgetting does
    # (trace(P dR) = n (1 - lam) in both), so lam means the same memory, ~1 / (1 - lam) samples
    # under rich excitation, in both kinds; capped at 0.5 (mu < 1 keeps P positive definite).
    cfg[C_MU] = min(n_params * (1.0 - lam), 0.5)
    # Under rich excitation directional forgetting settles at phi' P phi ~ mu: a sample far below
    # that carries far less information than the estimate already holds.
    cfg[C_XI_FORGET] = forget_threshold * cfg[C_MU]
    return cfg


def new_state(n_params: int, delta: float, theta0: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Fresh state arrays: theta = theta0 (or 0), P = delta I, counters 0."""
    theta = np.zeros(n_params) if theta0 is None else np.array(theta0, dtype=np.float64).reshape(n_params)
    return {"theta": theta, "P": np.eye(n_params) * delta, "g": np.zeros(n_params), "st": np.zeros(N_ST)}


def counters(st: np.ndarray) -> dict[str, Any]:
    """The counters and scale of a state vector as a dict (JSON-ready)."""
    return {
        "samples": int(st[ST_SAMPLES]),
        "updates": int(st[ST_UPDATES]),
        "nonfinite_skipped": int(st[ST_NONFINITE]),
        "outliers": int(st[ST_OUTLIERS]),
        "frozen": int(st[ST_FROZEN]),
        "trace_capped": int(st[ST_CAPPED]),
        "covariance_resets": int(st[ST_RESETS]),
        "scale": float(st[ST_SCALE]),
    }


class RLS:
    """Recursive least squares for ``y = theta' phi + noise`` with n parameters.

    Parameters
    ----------
    n_params : number of parameters n.
    lam : forgetting factor (paper 000 uses 1; < 1 tracks changes with a memory of about
        1 / (1 - lam) samples under rich excitation, in both forgetting kinds).
    delta : initial covariance P0 = delta I (000: 1e5); large = little trust in theta0.
    forgetting : ``"directional"`` (default, no wind-up) or ``"exponential"``.
    trace_max : cap of trace(P); default n delta.
    xi_min : a regressor with phi' P phi at or below this is not used at all (default 0: phi = 0).
    forget_threshold : forgetting only on samples with phi' P phi > forget_threshold n (1 - lam);
        on less informative samples P is frozen and theta still corrected (counted as ``frozen``).
    outlier : ``"huber"`` (default), ``"skip"`` or ``"off"``.
    outlier_k : outlier threshold in robust standard deviations of the a-priori error.
    reject_k : ``"huber"``: errors beyond this many robust standard deviations are skipped (>= outlier_k).
    scale_memory : memory of the running scale estimate, samples.
    warmup : samples averaged into the scale before outliers are judged (default 10 n).
    scale_min : floor of the scale estimate, output units (noise-free data).
    theta0 : initial parameters (default 0).
    """

    def __init__(self, n_params: int, *, lam: float = 0.999, delta: float = 1.0e3, forgetting: str = "directional",
                 trace_max: float | None = None, xi_min: float = 0.0, outlier: str = "huber",
                 outlier_k: float = 5.0, reject_k: float = 50.0, scale_memory: float = 500.0,
                 warmup: int | None = None,
                 scale_min: float = 1.0e-12, forget_threshold: float = 0.1, theta0: np.ndarray | None = None):
        if n_params < 1:
            raise ValueError(f"n_params={n_params}: expected >= 1")
        self.n = int(n_params)
        self.cfg = make_config(self.n, lam=lam, delta=delta, forgetting=forgetting, trace_max=trace_max,
                               xi_min=xi_min, outlier=outlier, outlier_k=outlier_k, reject_k=reject_k,
                               scale_memory=scale_memory,
                               warmup=warmup, scale_min=scale_min, forget_threshold=forget_threshold)
        self._theta0 = theta0
        self.reset()

    def reset(self) -> None:
        """Back to theta0, P0 = delta I, counters 0."""
        s = new_state(self.n, float(self.cfg[C_DELTA]), self._theta0)
        self.theta, self.P, self.g, self.st = s["theta"], s["P"], s["g"], s["st"]

    def step(self, phi: np.ndarray, y: float) -> float:
        """One sample (step mode): the a-priori prediction theta' phi, then the update."""
        phi = np.ascontiguousarray(phi, dtype=np.float64)
        if phi.shape != (self.n,):
            raise ValueError(f"phi has shape {phi.shape}, expected ({self.n},)")
        return rls_step(phi, float(y), self.theta, self.P, self.g, self.cfg, self.st)

    def run(self, Phi: np.ndarray, Y: np.ndarray, decimate: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Block mode over the rows of Phi (m, n): a-priori predictions (m,) and theta after every
        ``decimate``-th sample (m // decimate, n). State carries on from, and into, step mode."""
        Phi = np.ascontiguousarray(Phi, dtype=np.float64)
        Y = np.ascontiguousarray(Y, dtype=np.float64).reshape(-1)
        if Phi.ndim != 2 or Phi.shape[1] != self.n or Phi.shape[0] != Y.shape[0]:
            raise ValueError(f"Phi {Phi.shape} and Y {Y.shape}: expected (m, {self.n}) and (m,)")
        m = Y.shape[0]
        y_hat = np.empty(m)
        hist = np.empty((m // decimate if decimate > 0 else 0, self.n))
        rls_block(Phi, Y, self.theta, self.P, self.g, self.cfg, self.st, y_hat, hist, int(decimate))
        return y_hat, hist

    @property
    def status(self) -> float:
        """Status code of the last sample (UPDATED, NONFINITE, OUTLIER_SKIPPED, ...)."""
        return float(self.st[ST_STATUS])

    @property
    def scale(self) -> float:
        """Robust standard deviation of the a-priori error, output units."""
        return float(self.st[ST_SCALE])

    def counters(self) -> dict[str, Any]:
        return counters(self.st)
