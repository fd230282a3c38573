"""What tells two look-alike effects apart, measured on the base's residual (issue 62 item 2).

Two pairs of effects explain much the same residual, and their refits can validate alike:

* **saturation against asymmetry.** A saturation flattens both branches at large |output|: the
  model overshoots at the top and undershoots at the bottom, so the residual (model - measured) is
  odd in the output, about the output's zero. An even polynomial bends both ends of the input the
  same way: the residual is even in the input. :func:`parity` fits the residual both ways and
  compares what each leaves over contiguous blocks; it reports the residual at the two ends of the
  output and of the input against their middles (the rows in the top and bottom END_SHARE of the
  range), with standard errors from the spread between visits to an end (contiguous stretches of
  rows there), which are nearly independent where neighbouring rows are not.
* **rate-dependence against a delay.** A delay tau shifts the output: e = model(t) - model(t - tau)
  ~ tau dm/dt, a phase lag 2 pi f tau on every frequency component of the model's output (linear in
  frequency), whatever the input's rate there. A rate-dependent loop widens with the input's rate:
  e ~ -b |du/dt|^m sign(du/dt) (velocity damping, paper 003's widths), growing with the rate as the
  rate's power m, not with the output's slope. :func:`lags_by_rate` fits the residual both ways and
  compares what each leaves over contiguous blocks, and reports the loop's half width (the
  residual's mean times the direction of motion) in terciles of the input rate.

Both give a verdict (``favours``) only where the difference stands CONFUSABLE_Z standard errors
clear of zero; the ranking (:mod:`hilbench.diagnosis.ranking`) lets it order the pair when the
validation rows cannot. Units: output unit (um) for residual means, s for lags, input unit / s for rates.
"""

from __future__ import annotations

import copy
import math
import weakref
from typing import Any

import numpy as np

from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.evidence import parity_overlap
from hilbench.diagnosis.rows import ResidualRows

#: the share of rows at each end of a range (by quantile) whose residual is an end's
END_SHARE = 0.1
#: the fewest rows of a visit that count, and the fewest visits for a standard error
MIN_VISIT_ROWS = 3
MIN_VISITS = 3
#: the input-rate bins of the lag: terciles of the moving rows' |du/dt|
RATE_BINS = 3

PAIRS = {"parity": frozenset({"saturation", "asymmetry"}), "lag": frozenset({"delay", "rate-dependence"})}


def _visits(mask: np.ndarray, run: np.ndarray) -> list[np.ndarray]:
    """The contiguous stretches (row indices) of ``mask``, split where the run changes."""
    idx = np.flatnonzero(mask)
    if not idx.size:
        return []
    cut = np.flatnonzero((np.diff(idx) > 1) | (np.diff(run[idx]) != 0)) + 1
    return [v for v in np.split(idx, cut) if v.size >= MIN_VISIT_ROWS]


def _mean_se(e: np.ndarray, mask: np.ndarray, run: np.ndarray) -> tuple[float, float, int]:
    """The mean of ``e`` over the visits to ``mask`` (each visit one value) and its standard error."""
    visits = _visits(mask, run)
    rows = np.concatenate(visits) if visits else np.zeros(0, dtype=int)
    starts = np.cumsum([0] + [v.size for v in visits[:-1]])
    means = np.add.reduceat(e[rows], starts) / np.array([v.size for v in visits]) if visits else np.zeros(0)
    if means.size < MIN_VISITS:
        return (float(np.mean(means)) if means.size else math.nan), math.inf, int(means.size)
    return float(np.mean(means)), float(np.std(means, ddof=1) / math.sqrt(means.size)), int(means.size)


def _ends(e: np.ndarray, x: np.ndarray, run: np.ndarray) -> dict[str, Any]:
    """The residual's mean at the high and low END_SHARE of ``x`` and in its middle (the rows between
    the 40th and 60th percentiles), and each end's departure from the middle in standard errors
    (``high_z``, ``low_z``): an end bent away from the middle."""
    lo_q, mid_lo, mid_hi, hi_q = np.quantile(x, [END_SHARE, 0.4, 0.6, 1.0 - END_SHARE])
    hi, se_hi, n_hi = _mean_se(e, x >= hi_q, run)
    lo, se_lo, n_lo = _mean_se(e, x <= lo_q, run)
    mid, se_mid, n_mid = _mean_se(e, (x >= mid_lo) & (x <= mid_hi), run)
    return {"high": hi, "low": lo, "middle": mid, "high_z": (hi - mid) / math.hypot(se_hi, se_mid),
            "low_z": (lo - mid) / math.hypot(se_lo, se_mid), "visits": [n_hi, n_mid, n_lo]}


def _centred(x: np.ndarray) -> np.ndarray:
    lo, hi = float(np.min(x)), float(np.max(x))
    return (x - 0.5 * (lo + hi)) / max(0.5 * (hi - lo), 1e-12)


def _fit_residual(e: np.ndarray, cols: list[np.ndarray]) -> np.ndarray:
    """What a least-squares fit of ``e`` on ``cols`` and a constant leaves."""
    A = np.column_stack([np.ones_like(e), *cols])
    coef, *_ = np.linalg.lstsq(A, e, rcond=None)
    return e - A @ coef


def _block_z(a: np.ndarray, b: np.ndarray, run: np.ndarray) -> float:
    """The mean over N_BLOCKS contiguous blocks (within runs) of mean(a^2) - mean(b^2), in standard
    errors of that mean (blocks long against the residual's correlation: nearly independent)."""
    d = []
    for k in np.unique(run):
        idx = np.flatnonzero(run == k)
        n = max(1, round(T.N_BLOCKS * idx.size / run.size))
        d += [float(np.mean(a[blk] ** 2) - np.mean(b[blk] ** 2)) for blk in np.array_split(idx, n) if blk.size]
    d_arr = np.array(d)
    if d_arr.size < MIN_VISITS or np.std(d_arr, ddof=1) == 0:
        return math.nan
    return float(np.mean(d_arr) / (np.std(d_arr, ddof=1) / math.sqrt(d_arr.size)))


def parity(rows: ResidualRows) -> dict[str, Any]:
    """The saturation-against-asymmetry signature of the residual on ``rows`` (module docstring).

    A saturation's residual is odd in the model's output m about the output's zero (it flattens the
    top and the bottom alike, wherever the drive's range lies), an asymmetry's is even in the input u
    about the input's zero. The residual is fitted both ways with the same number of columns (a
    constant and m, the gain and offset any refit moves, and m^3, m^5 or u^2, u^4, each scaled by its
    largest magnitude), and ``odd_output_over_even_input_z`` is how much less the odd fit leaves, in
    standard errors over N_BLOCKS contiguous blocks. ``favours`` is saturation or asymmetry when that
    reaches CONFUSABLE_Z one way; None otherwise or when the drive cannot tell even from odd
    (:func:`hilbench.diagnosis.evidence.parity_overlap` within SIGNATURE_MARGIN of 1). Reported beside
    it: the residual at both ends of m and of u against their middles (``output_ends``,
    ``input_ends``: a saturation's model runs above the measurement at the top and below it at the
    bottom; an even term bends both ends of the input one way) and the variance shares of each fit."""
    e, run = rows.e, rows.run
    m = rows.y + rows.e  # the model's output: noise-free, and what a saturation compresses (the
    # measured output is flat at the ends, where model outputs of many heights meet)
    w = m / max(float(np.max(np.abs(m))), 1e-12)
    v = rows.u / max(float(np.max(np.abs(rows.u))), 1e-12)
    odd, even = _fit_residual(e, [w, w**3, w**5]), _fit_residual(e, [w, v**2, v**4])
    z = _block_z(even, odd, run)
    overlap = parity_overlap(rows.u)
    favours = None
    if math.isfinite(z) and 1.0 - overlap >= T.SIGNATURE_MARGIN:
        favours = "saturation" if z >= T.CONFUSABLE_Z else "asymmetry" if z <= -T.CONFUSABLE_Z else None
    var = float(np.var(e)) or 1.0
    return {"output_ends": _ends(e, m, run), "input_ends": _ends(e, rows.u, run),
            "odd_in_output": 1.0 - float(np.var(odd)) / var, "even_in_input": 1.0 - float(np.var(even)) / var,
            "odd_output_over_even_input_z": z, "parity_overlap": overlap, "favours": favours}


def _model_rate(rows: ResidualRows) -> np.ndarray:
    """d(model)/dt (output unit / s) within contiguous rows: the model is noise-free, so its derivative
    needs no smoothing (which would bias a lag measured at the fastest rates)."""
    m = rows.e + rows.y
    out = np.zeros_like(m)
    dt = np.diff(rows.t)
    step = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    cut = np.flatnonzero((np.abs(dt - step) > 0.5 * step) | (np.diff(rows.run) != 0)) + 1
    for seg in np.split(np.arange(m.size), cut):
        if seg.size >= 2:
            out[seg] = np.gradient(m[seg]) / step
    return out


def _lag(e: np.ndarray, s: np.ndarray, dm: np.ndarray, run: np.ndarray) -> tuple[float, float]:
    """The lag tau (s) of the fit e ~ c + a s + tau dm on all rows, and its standard error from the
    spread of the same fit over N_BLOCKS contiguous blocks."""
    def tau(rows: np.ndarray) -> float:
        A = np.column_stack([np.ones(rows.size), s[rows], dm[rows]])
        return float(np.linalg.lstsq(A, e[rows], rcond=None)[0][2]) if np.ptp(dm[rows]) > 0 else math.nan

    taus = []
    for k in np.unique(run):
        idx = np.flatnonzero(run == k)
        n = max(1, round(T.N_BLOCKS * idx.size / run.size))
        taus += [tau(blk) for blk in np.array_split(idx, n) if blk.size > 3]
    t = np.array([x for x in taus if math.isfinite(x)])
    se = float(np.std(t, ddof=1) / math.sqrt(t.size)) if t.size >= MIN_VISITS else math.inf
    return tau(np.arange(e.size)), se


#: the exponents m of the rate fit's width |du/dt|^m searched (velocity damping's span, 003's
#: frequency polynomials of order 1 and below)
RATE_EXPONENTS = (0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0)


def lags_by_rate(rows: ResidualRows) -> dict[str, Any]:
    """The rate-dependence-against-delay signature of the residual on ``rows``' moving rows (module
    docstring). Both fits keep a constant and a rate-independent half width a sign(du/dt) (what the
    base's hysteresis took of either); a delay adds tau dm/dt (a phase lag 2 pi f tau on every
    component of the model's output), a rate-dependent width b |du/dt|^m sign(du/dt), m searched
    over RATE_EXPONENTS. ``rate_over_delay_z``: how much less the rate fit leaves, in standard
    errors over N_BLOCKS contiguous blocks; ``favours`` rate-dependence or delay where that reaches
    CONFUSABLE_Z one way. Reported beside it: ``lag_s`` (the delay fit's tau), ``exponent`` (the rate
    fit's m) and per tercile of the input rate the loop's half width (the residual's mean times the
    direction of motion, output unit) with its standard error over visits. A delay only lags: a
    ``lag_s`` CONFUSABLE_Z standard errors below zero (``lag_standard_error_s``, over blocks) favours
    rate-dependence too."""
    moving = (rows.direction == "rising") | (rows.direction == "falling")
    out: dict[str, Any] = {"bins": [], "rate_over_delay_z": math.nan, "favours": None}
    if moving.sum() < RATE_BINS * MIN_VISITS * MIN_VISIT_ROWS:
        return out
    dm = _model_rate(rows)[moving]
    e, run, du = rows.e[moving], rows.run[moving], rows.du[moving]
    s = np.sign(du)
    rate = np.abs(du) / max(float(np.max(np.abs(du))), 1e-12)
    scale = max(float(np.max(np.abs(dm))), 1e-12)
    delay = _fit_residual(e, [s, dm / scale])
    lag, lag_se = _lag(e, s, dm, run)
    out["lag_s"], out["lag_standard_error_s"] = lag, lag_se
    fits = [(_fit_residual(e, [s, s * rate**m]), m) for m in RATE_EXPONENTS]
    widening, out["exponent"] = min(fits, key=lambda f: float(np.sum(f[0] ** 2)))
    z = _block_z(delay, widening, run)
    out["rate_over_delay_z"] = z
    # a delay can only lag: a lead of CONFUSABLE_Z standard errors is no delay, however it fits
    leads = lag_se > 0 and lag / lag_se <= -T.CONFUSABLE_Z
    if leads or z >= T.CONFUSABLE_Z:
        out["favours"] = "rate-dependence"
    elif z <= -T.CONFUSABLE_Z:
        out["favours"] = "delay"
    edges = np.quantile(np.abs(du), np.linspace(0.0, 1.0, RATE_BINS + 1))
    for k in range(RATE_BINS):
        inside = (np.abs(du) >= edges[k]) & ((np.abs(du) <= edges[k + 1]) if k == RATE_BINS - 1 else (np.abs(du) < edges[k + 1]))
        width, se, n = _mean_se(e * s, inside, run)
        out["bins"].append({"rate": float(np.median(np.abs(du[inside]))) if inside.any() else math.nan,
                            "half_width": width, "half_width_standard_error": se, "visits": n})
    return out


#: (id of the rows, entry) -> (a weak reference to the rows, the entry): both members of a pair are
#: judged on the same rows, and on 2e5 rows an entry costs about half a second
_MEASURED: dict[tuple[int, str], tuple[weakref.ref, dict[str, Any]]] = {}


def signature(effect: str, rows: ResidualRows) -> dict[str, Any]:
    """The evidence entries of ``effect`` when it belongs to a confusable pair (none otherwise),
    measured once per rows object."""
    entry, measure = (("parity", parity) if effect in PAIRS["parity"] else
                      ("lag_by_rate", lags_by_rate) if effect in PAIRS["lag"] else (None, None))
    if entry is None or measure is None:
        return {}
    key = (id(rows), entry)
    held = _MEASURED.get(key)
    if held is None or held[0]() is not rows:
        for k in [k for k, (ref, _) in _MEASURED.items() if ref() is None]:
            del _MEASURED[k]
        held = (weakref.ref(rows), measure(rows))
        _MEASURED[key] = held
    return {entry: copy.deepcopy(held[1])}


def sentence(effect: str, ev: dict[str, Any], unit: str = "") -> str:
    """A clause for the explanation stating the pair's signature and what it favours."""
    u = f" {unit}" if unit else ""
    if "parity" in ev:
        p = ev["parity"]
        o, i = p["output_ends"], p["input_ends"]
        say = {"saturation": "odd in the output: saturation", "asymmetry": "even in the input: asymmetry",
               None: "neither clearly"}[p["favours"]]
        return (f"; against its middle the error is {o['high'] - o['middle']:+.3g} and {o['low'] - o['middle']:+.3g}{u} "
                f"at the model output's top and bottom, {i['high'] - i['middle']:+.3g} and "
                f"{i['low'] - i['middle']:+.3g}{u} at the input's; odd in the output it explains "
                f"{100 * p['odd_in_output']:.2g} %, even in the input {100 * p['even_in_input']:.2g} % "
                f"({p['odd_output_over_even_input_z']:.2g} standard errors apart): {say}")
    if "lag_by_rate" in ev and len(ev["lag_by_rate"]["bins"]) >= 2:
        L = ev["lag_by_rate"]
        b = L["bins"]
        say = {"rate-dependence": "a width growing with the rate: rate-dependence",
               "delay": "a lag on the output's own motion: a delay", None: "neither clearly"}[L["favours"]]
        return (f"; the loop's half width is {b[0]['half_width']:.3g}{u} at the slowest input rates and "
                f"{b[-1]['half_width']:.3g}{u} at the fastest; a width growing as the rate^{L['exponent']:.3g} "
                f"fits the error {L['rate_over_delay_z']:.2g} standard errors better than a lag of "
                f"{1e3 * L['lag_s']:.3g} ms: {say}")
    return ""


def pair_of(a: str, b: str) -> str | None:
    """The name of the confusable pair ``a`` and ``b`` make (``parity``, ``lag``), or None."""
    return next((name for name, pair in PAIRS.items() if frozenset({a, b}) == pair), None)


def decides(a: str, b: str, ev_a: dict[str, Any], ev_b: dict[str, Any]) -> bool | None:
    """Whether the pair's signature puts ``a`` before ``b`` (True), ``b`` before ``a`` (False), or
    does not speak (None: not a confusable pair, or no verdict)."""
    entry = {"parity": "parity", "lag": "lag_by_rate"}.get(pair_of(a, b) or "")
    if entry is None or entry not in ev_a:
        return None
    favours = ev_a[entry]["favours"]
    return None if favours is None else favours == a
