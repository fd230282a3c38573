"""Where a fitted model fails and which effect of DESIGN.md is missing (``hilbench diagnose``).

:func:`diagnose` fits a spec (or evaluates a saved model), then

* splits the squared validation error ``e = model - measured`` (output unit, um) into shares by run,
  time window, input range x direction (rising / falling / turning / hold), |input rate| and the
  range of every auxiliary channel (``where``);
* refits the spec with every effect it lacks and the data can test, on the same split, and calls an
  effect significant when (a) validation rmse drops by more than 10 %, (b) training improves too and
  the two relative gains agree (validation at least half of training's, training at least a quarter
  of validation's: neither an artefact of more parameters nor chance extrapolation), (c) a
  one-sided Wilcoxon signed-rank test on the per-block squared-error differences of ~20 contiguous
  validation blocks gives p < 0.01, and (d) the current validation error is above the noise floor
  (noise estimated from sample-to-sample residual differences);
* tries rate-dependence in both forms (the better training fit is kept) and creep in the form that
  predicts held-back training rows better (:func:`_creep_form`); with one training drive rate,
  calibrates delay and dynamics across the validation rates (:mod:`hilbench.rate_calibration`);
* explains each effect in one sentence from residual statistics (``evidence``), ranks them by the
  measured fractional drop of validation rmse (``expected_gain``; a tie is decided by the residual's
  pattern, :func:`rank`), and lists the effects the data cannot test with the reason;
* with ``add`` refits with that effect, with ``auto`` adds the best significant effect while one
  remains (``steps``).

Units: input in the command unit (V or A), errors in the output unit, rates in input units per s,
times in s, gains as fractions.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from hilbench.errors import UserError
from hilbench.fitting import FitResult, PathLike, _finite, fit, fit_or_evaluate
from hilbench.input_motion import excitation_summary, motion
from hilbench.rate_calibration import RatePlan, calibrated_spec, rate_plan
from hilbench.models.model import split_spec

#: thresholds of significance (see the module docstring)
MIN_GAIN = 0.10
P_MAX = 0.01
N_BLOCKS = 20
NOISE_FACTOR = 1.5
#: creep is significant only if the residual drifts along holds by this fraction of its rms (after
#: the first CREEP_SETTLE_S s of each hold): the physical signature, which a refit alone can fake
#: (the creep low-pass also buys phase lag on delay or dynamics data)
CREEP_MIN_DRIFT = 0.2
CREEP_SETTLE_S = 0.1
#: creep's form is chosen on an inner split: the first CREEP_INNER of the training rows fit, the rest
#: judge; the output form must lower that error by CREEP_OUTPUT_MARGIN
CREEP_INNER = 0.8
CREEP_OUTPUT_MARGIN = 0.1
#: a tie on validation error is broken by the residual's pattern when signatures differ this much
SIGNATURE_MARGIN = 0.2
#: an auxiliary channel is tried when its smoothed range exceeds this many noise stds
AUX_MIN_VARIATION = 3.0
#: effects tried, in DESIGN.md order; aux channels are added by name
CANDIDATES = ("hysteresis", "asymmetry", "saturation", "rate-dependence", "dynamics", "creep", "delay")
MEMORYLESS_BASES = ("linear",)


@dataclass
class Candidate:
    effect: str
    spec: str
    significant: bool
    expected_gain: float
    explanation: str
    evidence: dict[str, Any]
    fitted: FitResult | None = field(default=None, repr=False)  # the refit, reused by --auto

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.effect, "significant": self.significant, "expected_gain": self.expected_gain,
                "explanation": self.explanation, "evidence": self.evidence}


@dataclass
class Diagnosis:
    spec: str
    result: FitResult
    where: list[dict[str, Any]]
    effects: list[Candidate]
    untestable: list[dict[str, str]]
    steps: list[dict[str, Any]] = field(default_factory=list)
    noise: float = float("nan")
    rounds: list[Diagnosis] = field(default_factory=list)  # with add/auto: the diagnosis of every step

    @property
    def metrics(self) -> dict[str, dict[str, float]]:
        return self.result.metrics

    @property
    def best(self) -> Candidate | None:
        return self.effects[0] if self.effects else None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "spec": self.spec,
            "metrics": {"train": self.metrics["train"], "validation": self.metrics["validation"]},
            "where": self.where,
            "effects": [c.to_json() for c in self.effects],
            "untestable": self.untestable,
        }
        if self.steps:
            out["steps"] = self.steps
        return _finite(out)


# -- helpers ------------------------------------------------------------------------------------


def spec_with(spec: str, effect: str) -> str:
    """``spec`` plus ``effect``; ``hysteresis`` turns a ``linear`` base into ``pi``."""
    if effect == "hysteresis":
        parts = [p.strip() for p in spec.split("+")]
        if split_spec(spec)[0][0] != "linear":
            raise UserError(f"'hysteresis' needs a linear base; {spec!r} already has memory")
        return "+".join(["pi", *parts[1:]])
    return f"{spec}+{effect}"


def _names(spec: str) -> set[str]:
    return {name for name, _ in split_spec(spec)}


@dataclass
class _Rows:
    """Validation rows of every run, concatenated, with what the statistics need."""

    e: np.ndarray  # model - measured
    u: np.ndarray
    du: np.ndarray  # input rate, input unit / s
    y: np.ndarray  # measured
    dy: np.ndarray
    d2y: np.ndarray
    since: np.ndarray  # time since the input last changed (s), inf-free
    direction: np.ndarray  # "rising", "falling", "turning", "hold"
    run: np.ndarray  # run index
    t: np.ndarray  # time in the run (s)
    aux: dict[str, np.ndarray]
    keys: list[str]


def _smooth(x: np.ndarray, k: int) -> np.ndarray:
    if k <= 1 or x.size < k:
        return x
    return np.convolve(x, np.ones(k) / k, mode="same")


def _rows(result: FitResult, rows: str = "validation") -> _Rows:
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("e", "u", "du", "y", "dy", "d2y", "since", "direction",
                                                             "run", "t")}
    aux: dict[str, list[np.ndarray]] = {}
    span = max(float(np.ptp(np.concatenate([r.data.input for r in result.runs if len(r.data)]))), 1e-12)
    common = None
    for r in result.runs:
        if len(r.data):
            common = set(r.data.aux) if common is None else common & set(r.data.aux)
    keys = []
    for k, r in enumerate(result.runs):
        m = (r.validation if rows == "validation" else r.validation | r.train) & np.isfinite(r.data.output)
        if not m.any() or r.simulated is None or r.simulated.size == 0:
            continue
        fs = r.data.sample_rate_hz
        sig = motion(r.data.input, fs, span)
        y = r.data.output
        ys = _smooth(np.nan_to_num(y), max(int(fs / 200), 1))
        dy = np.gradient(ys) * fs
        d2y = np.gradient(_smooth(dy, max(int(fs / 200), 1))) * fs
        parts["e"].append((r.simulated - y)[m])
        parts["u"].append(r.data.input[m])
        parts["du"].append(sig["du"][m])
        parts["y"].append(y[m])
        parts["dy"].append(dy[m])
        parts["d2y"].append(d2y[m])
        parts["since"].append(sig["since"][m])
        parts["direction"].append(sig["direction"][m])
        parts["run"].append(np.full(int(m.sum()), len(keys)))
        parts["t"].append(np.arange(len(r.data))[m] / fs)
        for c in common or ():
            aux.setdefault(c, []).append(r.data.aux[c][m])
        keys.append(r.key)
    if not keys:
        raise UserError("no validation rows: name runs with --test, or use a training fraction below 1")
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    return _Rows(**cat, aux={c: np.concatenate(v) for c, v in aux.items()}, keys=keys)


def noise_floor(e: np.ndarray, run: np.ndarray) -> float:
    """Noise std from sample-to-sample differences of the residual (robust: MAD), output unit."""
    d = np.concatenate([np.diff(e[run == k]) for k in np.unique(run)])
    if d.size < 3:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


# -- where the error is -------------------------------------------------------------------------


def _shares(total: float, labels: list[tuple[str, Any]], masks: list[np.ndarray], e2: np.ndarray,
            top: int) -> list[dict[str, Any]]:
    out = []
    for (kind, rng), m in zip(labels, masks):
        if m.any():
            out.append({"kind": kind, "range": rng, "share": float(e2[m].sum() / total),
                        "fraction_of_rows": float(m.mean())})
    out.sort(key=lambda d: -d["share"])
    return out[:top]


def _quantile_bins(x: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    edges = np.unique(np.quantile(x, np.linspace(0, 1, n + 1)))
    if edges.size < 2:
        edges = np.array([x.min(), x.max() + 1e-12])
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    return edges, idx


def where(rows: _Rows, top: int = 5) -> list[dict[str, Any]]:
    """Shares of the summed squared validation error: top entries per kind, largest first.

    Kinds: ``run`` (range = run name), ``time`` (range = [run, t0 s, t1 s], 10 windows per run),
    ``input:<direction>`` (range = [lo, hi] input unit, quantile bins), ``rate`` (|input rate|
    bins, input unit/s), ``aux:<channel>`` (channel bins). ``fraction_of_rows`` is each bin's share
    of rows, so a share well above it marks where the model fails.
    """
    e2 = rows.e**2
    total = float(e2.sum()) or 1.0
    out: list[dict[str, Any]] = []
    runs = np.unique(rows.run)
    out += _shares(total, [("run", rows.keys[k]) for k in runs], [rows.run == k for k in runs], e2, top)
    labels, masks = [], []
    for k in runs:
        idx = np.flatnonzero(rows.run == k)
        for chunk in np.array_split(idx, min(10, idx.size)):
            labels.append(("time", [rows.keys[k], float(rows.t[chunk[0]]), float(rows.t[chunk[-1]])]))
            m = np.zeros(e2.size, bool)
            m[chunk] = True
            masks.append(m)
    out += _shares(total, labels, masks, e2, top)
    edges, idx = _quantile_bins(rows.u, 5)
    labels, masks = [], []
    for b in range(edges.size - 1):
        for d in ("rising", "falling", "turning", "hold"):
            labels.append((f"input:{d}", [float(edges[b]), float(edges[b + 1])]))
            masks.append((idx == b) & (rows.direction == d))
    out += _shares(total, labels, masks, e2, top)
    rate = np.abs(rows.du)
    edges, idx = _quantile_bins(rate, 5)
    out += _shares(total, [("rate", [float(edges[b]), float(edges[b + 1])]) for b in range(edges.size - 1)],
                   [idx == b for b in range(edges.size - 1)], e2, top)
    for c, a in rows.aux.items():
        ok = np.isfinite(a)
        if not ok.any():
            continue
        edges, idx = _quantile_bins(np.where(ok, a, np.nanmean(a)), 5)
        out += _shares(total, [(f"aux:{c}", [float(edges[b]), float(edges[b + 1])]) for b in range(edges.size - 1)],
                       [(idx == b) & ok for b in range(edges.size - 1)], e2, top)
    return out


# -- what the data can test ---------------------------------------------------------------------


def _excitation(result: FitResult, role: str = "all") -> dict[str, Any]:
    """:func:`excitation_summary` of the rows that train (``role="train"``) or train or validate."""
    active = [r for r in result.runs if len(r.data) and (r.train.any() or r.validation.any())]
    span = max(float(np.ptp(np.concatenate([r.data.input for r in active]))), 1e-12)
    us = [r.data.input[r.train if role == "train" else (r.train | r.validation)] for r in active]
    return excitation_summary(us, active[0].data.sample_rate_hz, span)


def _frequencies(ex: dict[str, Any]) -> str:
    return (f"{ex['frequencies_hz'][0]:.3g}-{ex['frequencies_hz'][1]:.3g} Hz, spread {ex['frequency_spread']:.2f}"
            if ex["frequencies_hz"] else "no input reversals")


def _aux_variation(runs: list[np.ndarray]) -> float:
    """How far an auxiliary channel moves beyond its noise: the range of its moving average (1 % of
    each run) over its sample-to-sample noise std. Pure noise gives well under 1 (the average
    removes it); a 1.5 degC drift under 0.15 degC of noise gives 10."""
    smooth, diffs, quantum = [], [], math.inf
    for a in runs:
        a = a[np.isfinite(a)]
        if a.size < 3:
            continue
        k = max(1, a.size // 100)
        smooth.append(np.convolve(a, np.ones(k) / k, mode="valid"))
        d = np.diff(a)
        diffs.append(d)
        nz = np.abs(d[d != 0])
        if nz.size:
            quantum = min(quantum, float(nz.min()))
    if not smooth:
        return 0.0
    d = np.concatenate(diffs)
    noise = 1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0)
    if math.isfinite(quantum):
        noise = max(noise, quantum / math.sqrt(12.0))  # a quantised, mostly constant channel
    s = np.concatenate(smooth)
    return float(np.ptp(s) / max(noise, 1e-12 * max(float(np.abs(s).max()), 1.0)))


@dataclass
class Testability:
    """What the diagnosis tries: effects refitted on the split as is, effects whose shape is
    calibrated across drive rates (:mod:`hilbench.rate_calibration`), and the untestable ones."""

    tries: list[str]
    untestable: list[dict[str, str]]
    plan: RatePlan | None = None  # for the effects in ``calibrated``
    calibrated: list[str] = field(default_factory=list)


def testable(spec: str, result: FitResult) -> Testability:
    """Effects to try (not in ``spec``) and the untestable ones with the reason.

    Rate effects are judged on the training rows, where their parameters are learned: several
    drive frequencies there for rate-dependence, several frequencies or steps for dynamics and
    delay. With one training rate, dynamics and delay are calibrated across the validation rates
    when those allow it; rate-dependence, whose rate-weighted operator weights are linear
    parameters a single rate cannot fix, is then untestable.
    """
    have = _names(spec)
    base = split_spec(spec)[0][0]
    ex = _excitation(result)
    ex_train = _excitation(result, "train")
    multi = ex["frequency_spread"] >= 1.5
    multi_train = ex_train["frequency_spread"] >= 1.5
    broadband = multi or ex["steps"] > 0
    broadband_train = multi_train or ex_train["steps"] > 0
    single = f"single drive frequency ({_frequencies(ex)})"
    single_train = (f"the training rows hold a single drive frequency ({_frequencies(ex_train)}) while the "
                    f"validation rows reach {_frequencies(ex)}")
    plan, no_plan = (None, "") if broadband_train or not broadband else rate_plan(result)
    out = Testability([], [], plan)
    for eff in CANDIDATES:
        if eff in have:
            continue
        reason = None
        if eff == "hysteresis" and base not in MEMORYLESS_BASES:
            reason = f"the base {base!r} already has memory"
        elif eff == "asymmetry" and base in ("mpi", "pmpi"):
            reason = f"the base {base!r} already has the polynomial (asymmetric) terms"
        elif eff == "saturation" and base == "fpmpi":
            reason = "the base 'fpmpi' already has the fractional (saturating) terms"
        elif eff == "rate-dependence" and not multi:
            reason = f"{single}: rate-dependence cannot be separated from hysteresis"
        elif eff == "rate-dependence" and not multi_train:
            reason = (f"{single_train}: rate-dependence cannot be separated from hysteresis in training "
                      "(train on two or more rates to test it)")
        elif eff in ("dynamics", "delay") and not broadband:
            reason = f"{single} and no steps: a {eff} phase lag at one frequency looks like loop width"
        elif eff in ("dynamics", "delay") and not broadband_train:
            if plan is None:
                reason = f"{single_train} and no steps, and {no_plan}"
            else:
                out.calibrated.append(eff)
        elif eff == "creep" and ex["longest_hold_s"] < 0.2:
            reason = (f"the input never holds still (longest hold {ex['longest_hold_s']:.3g} s): "
                      "slow drift cannot be told from hysteresis")
        if reason:
            out.untestable.append({"effect": eff, "reason": reason})
        else:
            out.tries.append(eff)
    channels = None
    for r in result.runs:
        if len(r.data):
            channels = list(r.data.aux) if channels is None else [c for c in channels if c in r.data.aux]
    for c in channels or []:
        if c in have:
            continue
        ratio = _aux_variation([r.data.aux[c] for r in result.runs if len(r.data)])
        if ratio < AUX_MIN_VARIATION:
            out.untestable.append({"effect": c, "reason": f"{c} barely varies (its smoothed range is {ratio:.3g}x "
                                                          f"its noise, below {AUX_MIN_VARIATION:g})"})
        else:
            out.tries.append(c)
    return out


# -- evidence and explanations ------------------------------------------------------------------


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.std(a[ok]) == 0 or np.std(b[ok]) == 0:
        return 0.0
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def _explained(e: np.ndarray, cols: list[np.ndarray]) -> float:
    """Fraction of the residual's variance a least-squares fit on ``cols`` (plus a constant) explains."""
    A = np.column_stack([np.ones_like(e), *cols])
    ok = np.all(np.isfinite(A), axis=1) & np.isfinite(e)
    if ok.sum() <= A.shape[1] or np.var(e[ok]) == 0:
        return 0.0
    w, *_ = np.linalg.lstsq(A[ok], e[ok], rcond=None)
    r = e[ok] - A[ok] @ w
    return float(max(0.0, 1.0 - np.var(r) / np.var(e[ok])))


def explain(effect: str, rows: _Rows) -> tuple[str, dict[str, Any]]:
    """One sentence from residual statistics, and the numbers behind it."""
    e, u, e2 = rows.e, rows.u, rows.e**2
    total = float(e2.sum()) or 1.0
    span = max(float(np.ptp(u)), 1e-12)
    if effect == "creep":
        hold = rows.direction == "hold"
        early = hold & (rows.since < 1.0)
        late = hold & (rows.since >= 1.0)
        # drift: residual changes along a hold; its size relative to the rms error
        drift = []
        for k in np.unique(rows.run):
            m = hold & (rows.run == k)
            idx = np.flatnonzero(m)
            for seg in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
                # skip the first CREEP_SETTLE_S of a hold: a delay or a resonance settles there, while
                # creep (time constants of tenths of seconds and more) keeps drifting after it
                seg = seg[rows.since[seg] >= CREEP_SETTLE_S]
                if seg.size > 50:
                    drift.append(abs(float(np.mean(e[seg[-20:]]) - np.mean(e[seg[:20]]))))
        rms = math.sqrt(total / e.size)
        ev = {"hold_share": float(e2[hold].sum() / total), "hold_rows": float(hold.mean()),
              "drift_over_hold_um": float(np.mean(drift)) if drift else 0.0,
              "drift_over_rms": float(np.mean(drift) / rms) if drift and rms > 0 else 0.0,
              "first_second_vs_later_mse": float(np.mean(e2[early]) / max(np.mean(e2[late]), 1e-30))
              if early.any() and late.any() else float("nan")}
        return (f"the error drifts by {ev['drift_over_hold_um']:.3g} (output unit) while the input holds still "
                f"({ev['drift_over_rms']:.2g}x the rms error) and decays after each step: creep"), ev
    if effect == "rate-dependence":
        rate = np.abs(rows.du)
        moving = rate > 0
        hi = moving & (rate >= np.percentile(rate[moving], 67)) if moving.any() else moving
        lo = moving & (rate <= np.percentile(rate[moving], 33)) if moving.any() else moving
        ratio = float(np.mean(e2[hi]) / max(np.mean(e2[lo]), 1e-30)) if hi.any() and lo.any() else float("nan")
        ev = {"mse_fast_over_slow": ratio, "corr_e2_rate": _corr(e2, rate)}
        return (f"the squared error is {ratio:.2g}x larger at the fastest third of input rates than at the slowest: "
                "rate-dependence"), ev
    if effect == "dynamics":
        c2 = _corr(e, rows.d2y)
        x = _explained(e, [rows.dy, rows.d2y])
        ev = {"corr_e_d2y": c2, "explained_by_dy_d2y": x, "signature": x}
        return (f"the error follows the output's derivatives ({100 * x:.2g} % of its variance, correlation "
                f"with acceleration {c2:.2f}): a lag and ringing of linear dynamics"), ev
    if effect == "delay":
        c1 = _corr(e, rows.dy)
        ev = {"corr_e_dy": c1, "explained_by_dy": _explained(e, [rows.dy])}
        ev["signature"] = ev["explained_by_dy"]
        # measured y(t) = model(t - lag) gives e = model - y ~ lag * dy/dt: a positive lag means the
        # measurement trails the model
        lag = float(np.dot(e, rows.dy) / max(np.dot(rows.dy, rows.dy), 1e-30))
        ev["equivalent_lag_s"] = lag
        return (f"the error is proportional to the output's rate of change (correlation {c1:.2f}, "
                f"as a lag of {1e3 * lag:.3g} ms): a time delay"), ev
    if effect == "asymmetry":
        v = (u - u.mean()) / (span / 2)
        even = _explained(e, [v**2, v**4])
        ev = {"explained_by_even_input": even, "corr_e_u2": _corr(e, v**2), "signature": even}
        return (f"{100 * even:.2g} % of the error's variance is an even function of the input: the loops are "
                "not centrally symmetric (asymmetry)"), ev
    if effect == "saturation":
        a = np.abs(u - np.median(u))
        outer = a >= np.percentile(a, 80)
        share = float(e2[outer].sum() / total)
        odd = _explained(e, [u, u**3])
        ev = {"outer_20pct_share": share, "explained_by_odd_input": odd, "signature": odd}
        return (f"{100 * share:.2g} % of the squared error lies in the outer fifth of the input range: the loops "
                "flatten at large drive (saturation)"), ev
    if effect == "hysteresis":
        s = np.where(rows.direction == "rising", 1.0, np.where(rows.direction == "falling", -1.0, 0.0))
        x = _explained(e, [s])
        ev = {"explained_by_direction": x, "corr_e_direction": _corr(e, s), "signature": x}
        return (f"the error's sign depends on the direction of motion ({100 * x:.2g} % of its variance): "
                "rate-independent memory (hysteresis)"), ev
    a = rows.aux.get(effect)
    c = _corr(e, a) if a is not None else 0.0
    ev = {"corr_e_channel": c, "explained_by_channel": _explained(e, [a, a * u]) if a is not None else 0.0}
    ev["signature"] = ev["explained_by_channel"]
    return (f"the error follows the {effect} channel (correlation {c:.2f}, {100 * ev['explained_by_channel']:.2g} % "
            f"of its variance with the input): dependence on {effect}"), ev


# -- comparing fits -----------------------------------------------------------------------------


def _validation_errors(result: FitResult, keys: Sequence[str] | None = None) -> np.ndarray:
    """Model minus measured on the validation rows (of the runs ``keys``, default all), output unit."""
    return np.concatenate([(r.simulated - r.data.output)[r.validation & np.isfinite(r.data.output)]
                           for r in result.runs if r.validation.any() and r.simulated is not None
                           and r.simulated.size and (keys is None or r.key in keys)])


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


def _gain(old: float, new: float) -> float:
    return 1.0 - new / old if old > 0 else 0.0


def block_test(e_old: np.ndarray, e_new: np.ndarray, n_blocks: int = N_BLOCKS) -> tuple[float, int, int]:
    """One-sided Wilcoxon signed-rank p-value that the new squared error is lower, over contiguous
    blocks; and how many blocks improved, of how many."""
    blocks = [b for b in np.array_split(np.arange(e_old.size), min(n_blocks, e_old.size)) if b.size]
    d = np.array([np.mean(e_old[b] ** 2) - np.mean(e_new[b] ** 2) for b in blocks])
    if d.size < 5 or not np.any(d != 0):
        return 1.0, int(np.sum(d > 0)), int(d.size)
    p = float(stats.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue)
    return p, int(np.sum(d > 0)), int(d.size)


def _variants(spec: str, effect: str) -> list[str]:
    """The specs a candidate effect is tried as. Rate-dependence in both forms of 003: fixed
    velocity damping (a rate normalised by one reference rate) and the frequency polynomials
    (normalised by each half cycle's 2 pi f A); which describes the plant is not known beforehand,
    and the frequency form cannot express damping whose strength depends on the amplitude."""
    if effect == "rate-dependence":
        return [spec_with(spec, "rate-dependence(form=damping)"), spec_with(spec, "rate-dependence(form=frequency)")]
    return [spec_with(spec, effect)]


def _inner_rmse(result: FitResult, inner: float, outer: float) -> float:
    """rmse on the rows between the ``inner`` and ``outer`` fractions of every run: training rows
    of the user's split that the inner fit did not see."""
    parts = []
    for r in result.runs:
        n = len(r.data)
        lo, hi = int(math.floor(n * inner)), int(math.floor(n * outer))
        if r.simulated is None or hi <= lo:
            continue
        e = (r.simulated - r.data.output)[lo:hi]
        parts.append(e[np.isfinite(e)])
    e = np.concatenate(parts) if parts else np.zeros(0)
    return float(np.sqrt(np.mean(e**2))) if e.size else float("inf")


def _creep_form(paths: Any, spec: str, train_fraction: float) -> str:
    """``spec`` plus creep in the form that predicts held-back training rows better.

    The output form (drift of every hysteresis column, the creep of a plant whose creep follows the
    hysteresis) has many more weights than the input form, so the training error always prefers
    it; an inner split of the training rows (its first CREEP_INNER part fits, the rest judges)
    tells whether the extra weights carry over. The user's validation rows stay untouched."""
    inner = CREEP_INNER * train_fraction
    if not 0.0 < inner < train_fraction:
        return spec_with(spec, "creep")
    scores = {form: _inner_rmse(fit(paths, spec_with(spec, f"creep(form={form})"), train_fraction=inner),
                                inner, train_fraction) for form in ("input", "output")}
    # the richer form must do clearly better on the held-back rows
    if scores["output"] < (1.0 - CREEP_OUTPUT_MARGIN) * scores["input"]:
        return spec_with(spec, "creep(form=output)")
    return spec_with(spec, "creep")


def _fit_effect(paths: Any, base: FitResult, effect: str, kw: dict[str, Any], plan: RatePlan | None) -> FitResult:
    """``base`` refitted with ``effect`` on the user's split; with a rate ``plan`` the effect's
    shape is calibrated across drive rates first and fixed."""
    if plan is not None:
        spec, _ = calibrated_spec(paths, base.spec, effect, plan)
        return fit(paths, spec, **kw)
    if effect == "creep" and not kw.get("train") and not kw.get("test"):
        return fit(paths, _creep_form(paths, base.spec, float(kw.get("train_fraction", 0.7))), **kw)
    new = None
    for spec in _variants(base.spec, effect):
        fitted = fit(paths, spec, **kw)
        # choose among the forms on training rows only, so the validation comparison stays fair
        if new is None or fitted.metrics["train"]["rmse"] < new.metrics["train"]["rmse"]:
            new = fitted
    assert new is not None
    return new


def _try(paths: Any, base: FitResult, effect: str, rows: _Rows, noise: float, kw: dict[str, Any],
         plan: RatePlan | None = None) -> Candidate:
    """Refit with ``effect`` and judge it (module docstring). With a rate ``plan`` the gain is
    measured on the confirming runs and must agree with the calibrating runs' instead of training's."""
    new = _fit_effect(paths, base, effect, kw, plan)
    old_v, new_v = base.metrics["validation"]["rmse"], new.metrics["validation"]["rmse"]
    old_t, new_t = base.metrics["train"]["rmse"], new.metrics["train"]["rmse"]
    gain_t = _gain(old_t, new_t)
    extra: dict[str, Any] = {}
    if plan is None:
        gain, learned = _gain(old_v, new_v), gain_t
        e_old, e_new = _validation_errors(base), _validation_errors(new)
        agree = "train_and_validation_agree"
    else:
        e_old, e_new = _validation_errors(base, plan.confirm), _validation_errors(new, plan.confirm)
        c_old, c_new = _rms(_validation_errors(base, plan.calibrate)), _rms(_validation_errors(new, plan.calibrate))
        gain, learned = _gain(_rms(e_old), _rms(e_new)), _gain(c_old, c_new)
        agree = "calibration_and_confirmation_agree"
        extra = {"rate_calibration": plan.to_json(), "confirmation_rmse": [_rms(e_old), _rms(e_new)],
                 "calibration_rmse": [c_old, c_new], "calibration_gain": learned}
    p, better, blocks = block_test(e_old, e_new)
    checks = {
        "gain_over_10pct": gain > MIN_GAIN,
        # a real effect is learned from one set of rows and holds on unseen rows: neither gain may
        # be a small fraction of the other (a gain on validation only is chance extrapolation)
        agree: learned > 0 and gain >= 0.5 * learned and learned >= 0.25 * gain,
        "blocks_p_below_0.01": p < P_MAX,
        "error_above_noise": _rms(e_old) > NOISE_FACTOR * noise,
    }
    if plan is not None:
        checks["training_not_worse"] = new_t <= old_t * (1.0 + 0.01)
    sentence, evidence = explain(effect, rows)
    if effect == "creep":
        checks["drift_on_holds"] = evidence["drift_over_rms"] >= CREEP_MIN_DRIFT
        if checks["drift_on_holds"] and not all(checks.values()):
            # the physical signature is there; say so, since the refit's verdict alone would hide it
            sentence += (f"; the drift is there, but adding creep alone changes the validation error by "
                         f"{-100 * gain:+.2g} %: another missing effect may mask it")
    if plan is not None:
        sentence += (f"; calibrated at {'/'.join(f'{f:.3g}' for f in plan.calibrate_hz)} Hz, it changes the error at "
                     f"{'/'.join(f'{f:.3g}' for f in plan.confirm_hz)} Hz by {-100 * gain:+.2g} %")
    evidence = {
        "validation_rmse": [old_v, new_v], "train_rmse": [old_t, new_t], "train_gain": gain_t,
        "p_value": p, "blocks_improved": [better, blocks], "noise_floor": noise, "checks": checks,
        "spec": new.spec, **extra, **evidence,
    }
    return Candidate(effect, new.spec, all(checks.values()), gain, sentence, evidence, fitted=new)


def rank(cands: list[Candidate]) -> None:
    """Order candidates in place: significant first, then by expected gain. When the best one's
    validation error cannot be told from another significant candidate's (block test both ways,
    p >= P_MAX) the two refits explain the data equally well, and the residual's own pattern
    decides: the candidate whose ``signature`` (fraction of the error's variance its physical
    pattern explains, e.g. even in the input for asymmetry, odd for saturation) is higher by at
    least SIGNATURE_MARGIN goes first. A cubic term mimics saturation on a bipolar drive, so
    without this asymmetry and saturation are a coin toss on saturating data."""
    cands.sort(key=lambda c: (not c.significant, -c.expected_gain))
    if not cands or not cands[0].significant or cands[0].fitted is None:
        return
    top = cands[0]
    if "signature" not in top.evidence:
        return  # no pattern to weigh against (rate-dependence, creep): gain order stands
    e_top = _validation_errors(top.fitted)
    best, best_p = top, 1.0
    for c in cands[1:]:
        if not c.significant or c.fitted is None or "rate_calibration" in c.evidence or "rate_calibration" in top.evidence:
            continue
        e_c = _validation_errors(c.fitted)
        if e_c.size != e_top.size:
            continue
        p_top_better, _, _ = block_test(e_c, e_top)
        if p_top_better < P_MAX:
            continue  # the data tell them apart: gain order stands
        if "signature" in c.evidence and c.evidence["signature"] >= best.evidence["signature"] + SIGNATURE_MARGIN:
            best, best_p = c, p_top_better
    if best is not top:
        cands.remove(best)
        cands.insert(0, best)
        best.evidence["ranked_by_signature"] = {
            "over": top.effect, "p_value_of_difference": best_p,
            "signatures": {top.effect: top.evidence.get("signature"), best.effect: best.evidence.get("signature")}}
        best.explanation += (f"; its validation error cannot be told from {top.effect}'s (p {best_p:.2g}) and the "
                             f"error's pattern fits {best.effect} better")


def _diagnose_once(paths: Any, base: FitResult, kw: dict[str, Any]) -> Diagnosis:
    rows = _rows(base)
    noise = noise_floor(rows.e, rows.run)
    plan = testable(base.spec, base)
    every = _rows(base, "all")  # evidence from all rows: holds and steps may all lie in training
    cands = [_try(paths, base, eff, every, noise, kw, plan.plan if eff in plan.calibrated else None)
             for eff in plan.tries]
    rank(cands)
    return Diagnosis(base.spec, base, where(rows), cands, plan.untestable, noise=noise)


def _add(paths: Any, base: FitResult, effect: str, kw: dict[str, Any]) -> FitResult:
    """``--add``: refit with ``effect``, calibrated across drive rates where the diagnosis would."""
    plan = testable(base.spec, base)
    # the same form the diagnosis would try (rate calibration, creep's and rate-dependence's forms)
    return _fit_effect(paths, base, effect, kw, plan.plan if effect in plan.calibrated else None)


def _step(result: FitResult, added: str | None) -> dict[str, Any]:
    return {"spec": result.spec, "added": added, "validation": dict(result.metrics["validation"]),
            "train": dict(result.metrics["train"])}


def diagnose(
    paths: PathLike | Sequence[PathLike],
    spec_or_model_file: str,
    *,
    train: Sequence[str] | None = None,
    test: Sequence[str] | None = None,
    add: str | None = None,
    auto: bool = False,
    max_steps: int = 4,
    train_fraction: float = 0.7,
) -> Diagnosis:
    """Fit (or load) the model, find where it fails and which effect is missing.

    With ``add`` the effect is added and the model refitted; with ``auto`` the best significant
    effect is added while one remains (at most ``max_steps`` additions). The returned diagnosis is
    of the final model; ``steps`` lists every model tried in order (the first is the start).
    A saved model is evaluated as is for ``metrics``; candidate effects are compared against its
    spec refitted on the same split, so both sides of every comparison saw the same training rows.
    """
    kw = {"train": train, "test": test, "train_fraction": train_fraction}
    start = fit_or_evaluate(paths, spec_or_model_file, **kw)
    base = start if start.refitted else fit(paths, start.spec, **kw)
    steps = [_step(start, None)]
    if add is not None:
        base = _add(paths, base, add, kw)
        steps.append(_step(base, add))
    result = _diagnose_once(paths, base, kw)
    rounds = [result]
    if auto:
        while len(steps) - 1 < max_steps and result.best is not None and result.best.significant:
            best = result.best
            base = best.fitted if best.fitted is not None else fit(paths, best.spec, **kw)
            steps.append(_step(base, best.effect))
            result = _diagnose_once(paths, base, kw)
            rounds.append(result)
    result.rounds = rounds
    if add is None and not auto and not start.refitted:
        result.result = start  # report the saved model's own metrics
    if add is not None or auto:
        result.steps = steps
    return result


__all__ = ["CANDIDATES", "Candidate", "Diagnosis", "Testability", "block_test", "rank", "diagnose", "explain", "noise_floor", "spec_with",
           "testable", "where"]
