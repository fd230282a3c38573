"""hilbench online: paper 000's online identifier (FPMPI + OIIR weights by RLS) against the offline
Hammerstein model, on a recording or a rig.

What is compared, per evaluated run (000 Table 4, metrics of eq. 18 in percent):

* ``online``: the OIIR output y_m(k) = sum p_i u_r(k-i) + sum q_j y(k-j), predicted *before* y(k)
  is used, with the weights of sample k-1 (000 eq. 11): a one-step-ahead prediction that uses the
  measured outputs up to k-1;
* ``offline``: the Hammerstein model of 000 sec. 4.1 (FPMPI + second-order dynamics + delay, spec
  ``fpmpi+dynamics+delay``), identified once on the training rows, then held, simulated free-run
  from the input alone;
* ``persistence``: the naive one-step-ahead predictor y(k-1), which uses the measured output and
  nothing else. The online error means something only against this: an identifier that merely
  copied its output lags would score it.

The offline free run is checked per run (:func:`offline_verdict`): unstable dynamics or a free run
that diverges is replaced by the static FPMPI's free run, or refused with the reasons. Where online
loses to y(k-1) the run says why, from numbers (:func:`persistence_verdict`). A capture's leading
rest is neither trained on nor scored, and the identifier's front end holds its input within the
training rows' range (decision 0083).

The identifier starts afresh on each evaluated run (zero weights, P = delta I, operators at rest)
and sees every sample of the run in recorded order; block mode runs the same numba kernel as the
step mode of the runner's loop, bit for bit (tests/online). Errors leave out the first ``--settle``
seconds of each run (the identifier's start-up transient; 000 compares at steady state) and every
training row.

On a rig (``hilbench online RIG``) the plan, or ``--excitation``, is swept through the runner into a
recording first (``--record``), which is then replayed through the identifier: the same samples in
the same order as stepping the identifier in the loop, without touching the runner.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable
from typing import Any, Optional

import numpy as np
import typer

from hilbench.cli.app import RunProgress, app, default_output, print_json, user_errors
from hilbench.errors import UserError
from hilbench.identify.health import ESCAPE_SPANS, escape_spans

#: what the three predictions are, in the JSON document and the report
COMPARISON = {
    "online": "one-step-ahead prediction of the OIIR (000 eq. 11): the weights of sample k-1 and the measured "
              "outputs y(k-1..k-N); identifier started afresh on each run",
    "offline": "free-run simulation of the offline Hammerstein model (FPMPI + dynamics + delay, 000 sec. 4.1), "
               "identified once on the training rows, then held",
    "persistence": "naive one-step-ahead baseline y(k-1): what the measured output lags give for free",
}
PLOT_RUNS = 4
PLOT_POINTS = 20_000


@dataclass
class RunComparison:
    """One evaluated run: the three predictions, the rows scored, the weights over time."""

    key: str
    name: str
    sample_rate_hz: float
    input: np.ndarray
    output: np.ndarray
    online: np.ndarray
    offline: np.ndarray
    persistence: np.ndarray
    u_r: np.ndarray
    weights: np.ndarray  # (n, K): theta after every sample
    weight_names: list[str]
    rows: np.ndarray  # bool: the rows scored
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)
    counters: dict[str, Any] = field(default_factory=dict)
    static_gain: float = float("nan")
    #: the offline free run's verdict (:func:`offline_verdict`): status, what was scored, why
    offline_check: dict[str, Any] = field(default_factory=dict)
    #: online against y(k-1) (:func:`persistence_verdict`): verdict, ratio, reasons with numbers
    against_persistence: dict[str, Any] = field(default_factory=dict)
    poles: np.ndarray = field(default_factory=lambda: np.zeros(0, complex))

    def to_json(self) -> dict[str, Any]:
        from hilbench.identify.fitting import finite_json

        idx = np.flatnonzero(self.rows)
        on, off, per = (self.metrics[k]["re_n2_pct"] for k in ("online", "offline", "persistence"))
        off = off if off is not None and math.isfinite(off) else math.nan
        return finite_json({
            "run": self.key,
            "samples": int(self.output.size),
            "evaluated_samples": int(idx.size),
            "evaluated_from_s": float(idx[0] / self.sample_rate_hz) if idx.size else None,
            "online": self.metrics["online"],
            "offline": self.metrics["offline"],
            "persistence": self.metrics["persistence"],
            "re_n2_ratio_offline_over_online": off / on if on > 0 else None,
            "re_n2_ratio_persistence_over_online": per / on if on > 0 else None,
            "offline_check": self.offline_check,
            "online_vs_persistence": self.against_persistence,
            "poles_final": {"max_radius": float(np.max(np.abs(self.poles))) if self.poles.size else 0.0,
                            "radius_bound": self.counters.get("pole_radius")},
            "weights_final": {n: float(w) for n, w in zip(self.weight_names, self.weights[-1])}
            if len(self.weights) else {},
            "static_gain_final": self.static_gain,
            "identifier": self.counters,
        })


# -- pieces -------------------------------------------------------------------------------------


def parse_orders(text: str) -> tuple[int, int]:
    """``"M,N"`` -> (M, N), the OIIR numerator and denominator orders (000: 3,5)."""
    parts = [p.strip() for p in text.split(",")]
    try:
        m, n = (int(p) for p in parts)
    except ValueError:
        raise UserError(f"expected two integers M,N (e.g. 3,5), got {text!r}", where="--orders") from None
    if not (0 <= m <= 50 and 0 <= n <= 50):
        raise UserError(f"orders {m},{n}: expected 0..50 each", where="--orders")
    return m, n


def _pick(m: dict[str, float]) -> dict[str, float]:
    keys = ("re_n2_pct", "re_ninf_pct", "rmse", "max_abs_error", "n")
    return {k: m[k] for k in keys}


def record_on_rig(config: str, excitation: list[str], record: Path | None, realtime: bool | None,
                  quiet: bool) -> tuple[Path, str]:
    """Sweep the rig's plan (or ``excitation``) through the runner into a recording; returns it."""
    from hilbench.excitation.plan import expand_runs, plan_from_compact
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig
    from hilbench.runners.sweep import run_plan

    cfg = load_rig(config)
    if excitation:
        planned = plan_from_compact(excitation)
    elif cfg.plan:
        planned = expand_runs(cfg.plan, file=cfg.path)
    else:
        raise UserError("the rig config has no [[plan.runs]]", where=cfg.path,
                        hint="give --excitation runs, e.g. a training run and the drives to identify online")
    out = record or default_output(cfg.name)
    with RunProgress(not quiet) as progress:
        result = run_plan(Rig(cfg), planned, out, experiment="online", realtime=realtime, progress=progress)
    if result.status != "complete":
        raise UserError(f"the sweep ended {result.status}; nothing identified", where=str(out))
    return out, cfg.name


def fit_front_end(active: list[Any], masks: list[np.ndarray], loaded: Any, model: Path | None, split: str,
                  global_starts: int, note: Any) -> tuple[Any, Any, str, tuple[float, float] | None, Any]:
    """The offline model and the identifier's front end from the training rows (or a loaded fpmpi
    model): (front model, Hammerstein model, where it came from, the front end's input range, front end)."""
    from hilbench.online.oiir import OFFLINE_SPEC, FPMPIFrontEnd, offline_hammerstein

    if loaded is not None and loaded.base.name != "fpmpi":
        raise UserError(f"the model's base is {loaded.base.name!r}; the front end needs an fpmpi model",
                        where=str(model), hint="fit one with `hilbench fit DATA --model fpmpi -o fpmpi.json`")
    if loaded is not None and loaded.effect("dynamics") is not None:
        hammerstein, source = loaded, f"loaded from {model}, held"
        front_model = loaded
    else:
        if note is not None:
            note(f"fitting the offline model {OFFLINE_SPEC} on the training rows ({split}) ...")
        front_model, hammerstein = offline_hammerstein(
            [r.data for r in active], masks, hysteresis=loaded, global_starts=global_starts, progress=note)
        source = ("fitted on the training rows, then held; FPMPI " +
                  (f"from {model}" if loaded is not None else "fitted first (spec fpmpi), as 000 sec. 4.1"))
    # A front end fitted here on the training rows holds its input within their range: beyond it its
    # polynomial is an extrapolation the identifier would have to unlearn (decision 0083). A loaded
    # one was fitted on data this command has not seen: its range is unknown, none is imposed.
    train_u = np.concatenate([np.asarray(r.data.input, float)[m] for r, m in zip(active, masks)])
    train_u = train_u[np.isfinite(train_u)]
    fitted_range = (float(train_u.min()), float(train_u.max())) if loaded is None and train_u.size else None
    try:
        front_end = FPMPIFrontEnd.from_model(front_model, input_range=fitted_range)
    except ValueError as exc:
        raise UserError(str(exc), where=str(model) if model is not None else "--model") from None
    return front_model, hammerstein, source, fitted_range, front_end


def identify_live_on_rig(config: str, excitation: list[str], record: Path | None, train: list[str], model: Path | None,
                         *, M: int, N: int, lam: float, delta: float, forgetting: str, global_starts: int,
                         allow_late: bool, quiet: bool, note: Any) -> tuple[Path, str, list[str], tuple]:
    """A rig of real devices: its training runs (``--train`` labels or numbers; default the plan's
    first run) are swept, the offline model and the identifier's front end fitted on them; then
    the other runs are swept with the identifier live in the fixed-rate loop
    (:class:`hilbench.online.live.IdentifierLaw`), into the same recording. Returns the recording,
    the rig's name, the training runs' names in it and the fit (:func:`fit_front_end`)."""
    from hilbench.excitation.plan import expand_runs, plan_from_compact
    from hilbench.identify.dataset import as_dataset
    from hilbench.models import Model
    from hilbench.online.live import IdentifierLaw
    from hilbench.online.oiir import OIIR
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig
    from hilbench.runners.sweep import run_plan

    cfg = load_rig(config)
    planned = plan_from_compact(excitation) if excitation else expand_runs(cfg.plan, file=cfg.path) if cfg.plan else []
    if len(planned) < 2:
        raise UserError("identifying live needs a training run and at least one run to identify "
                        f"({len(planned)} planned)", where=cfg.path if not excitation else "--excitation",
                        hint="give two or more runs; the first trains unless --train names others")
    wanted = set(train or ["1"])
    chosen = [i for i, p in enumerate(planned, start=1) if str(i) in wanted or p.label in wanted]
    unknown = wanted - {str(i) for i in chosen} - {planned[i - 1].label for i in chosen}
    if unknown or not chosen or len(chosen) == len(planned):
        raise UserError(f"--train {', '.join(sorted(wanted))}: expected run numbers (1-{len(planned)}) or labels of "
                        "the plan, leaving at least one run to identify", where="--train",
                        hint="labels: " + ", ".join(p.label for p in planned))
    out = record or default_output(cfg.name)
    with Rig(cfg) as rig, RunProgress(not quiet) as progress:
        first = run_plan(rig, [planned[i - 1] for i in chosen], out, experiment="online training",
                         progress=progress, check_rate=not allow_late)
        _stopped(first, out)
        dataset = as_dataset([out])
        runs = dataset.fit_runs()
        keeps, _ = leading_rests(runs)
        active = [r for r in runs if len(r.data)]
        masks = [k for r, k in zip(runs, keeps) if len(r.data)]
        prefit = fit_front_end(active, masks, Model.load(model) if model is not None else None, model,
                               "the training runs", global_starts, note)
        front_end = prefit[4]
        law = IdentifierLaw(lambda: OIIR(front_end, M, N, lam=lam, delta=delta, forgetting=forgetting),
                            dataset.output_unit)
        rest = [p for i, p in enumerate(planned, start=1) if i not in chosen]
        second = run_plan(rig, rest, out, experiment="online", progress=progress, law=law, check_rate=False)
        _stopped(second, out)
    return out, cfg.name, [r.group for r in first.runs], prefit


def _stopped(result: Any, out: Path) -> None:
    """A sweep that did not complete ends the command: a Ctrl-C/SIGTERM as a stopped run (exit 130)."""
    from hilbench.errors import RunStopped

    if result.status == "complete":
        return
    last = result.runs[-1] if result.runs else None
    if result.status == "aborted" and last is not None:
        raise RunStopped.of_run(last.reason, str(out), last.group, "; nothing identified")
    raise UserError(f"the sweep ended {result.status}; nothing identified", where=str(out))


#: A free run farther than this many measured output spans beyond the measured range has diverged (no
#: model error is that large): the bound the fit's health check uses, :data:`hilbench.identify.health.ESCAPE_SPANS`.
DIVERGED_SPANS = ESCAPE_SPANS
#: The front end is said to run outside its fitted inputs when the scored inputs leave the training
#: inputs' range by more than this fraction of the scored inputs' span.
EXTRAPOLATION_FRACTION = 0.1
#: Online within this factor of y(k-1) over the last quarter of the scored rows is "at y(k-1)" there.
STEADY_TOLERANCE = 1.05


def _re_n2(y: np.ndarray, pred: np.ndarray) -> float:
    n = float(np.linalg.norm(y))
    return 100.0 * float(np.linalg.norm(y - pred)) / n if n > 0 else math.nan


def dynamics_poles(model: Any, sample_rate_hz: float) -> np.ndarray:
    """Discrete poles of a model's ``dynamics`` effect at the run's rate (none without dynamics)."""
    dyn = model.effect("dynamics")
    if dyn is None:
        return np.zeros(0, complex)
    _, a = dyn.coefficients(sample_rate_hz)
    a = np.trim_zeros(np.asarray(a, float), "b")
    return np.roots(a) if a.size > 1 else np.zeros(0, complex)


def input_extrapolation(train_u: np.ndarray, scored_u: np.ndarray, unit: str) -> str | None:
    """A sentence when the scored inputs leave the range the front end was fitted on, else None."""
    tu, su = train_u[np.isfinite(train_u)], scored_u[np.isfinite(scored_u)]
    if tu.size == 0 or su.size == 0:
        return None
    t_lo, t_hi, s_lo, s_hi = float(tu.min()), float(tu.max()), float(su.min()), float(su.max())
    beyond = max(t_lo - s_lo, s_hi - t_hi, 0.0)
    if beyond <= EXTRAPOLATION_FRACTION * max(s_hi - s_lo, 1e-300):
        return None
    held = " (held still: nothing to fit the FPMPI on)" if t_hi - t_lo <= 1e-9 * max(abs(t_lo), abs(t_hi), 1.0) else ""
    return (f"the FPMPI front end was fitted on inputs {t_lo:.4g}..{t_hi:.4g} {unit}{held} and runs here at "
            f"{s_lo:.4g}..{s_hi:.4g} {unit}: its polynomial is evaluated outside the inputs it was fitted on")


def offline_verdict(y: np.ndarray, hammerstein: np.ndarray, static: np.ndarray | None, rows: np.ndarray,
                    poles: np.ndarray, extrapolation: str | None, output_unit: str) -> tuple[dict[str, Any], np.ndarray | None]:
    """Whether the offline free run may be scored, and what to score.

    ``status``: ``ok`` (the Hammerstein free run), ``static-fallback`` (its dynamics are unstable or
    its free run diverges, the static FPMPI's free run does not: that is scored instead) or
    ``refused`` (both diverge: nothing is scored, the figures are null). Divergence: a free run more
    than :data:`DIVERGED_SPANS` measured output spans beyond the measured range on the scored rows,
    or not finite. The reasons carry the numbers.
    """
    yr = y[rows]
    radius = float(np.max(np.abs(poles))) if poles.size else 0.0
    check: dict[str, Any] = {"dynamics_pole_radius": radius if poles.size else None,
                             "diverged_beyond_spans": DIVERGED_SPANS}
    reasons: list[str] = []
    unstable = poles.size > 0 and radius >= 1.0
    if unstable:
        reasons.append(f"the dynamics have a pole at |z| = {radius:.6g} (>= 1): the filter is unstable")
    esc = escape_spans(yr, hammerstein[rows])
    check["free_run_escape_spans"] = esc
    diverged = esc > DIVERGED_SPANS
    if diverged:
        peak = float(np.max(np.abs(hammerstein[rows][np.isfinite(hammerstein[rows])]), initial=0.0))
        reasons.append(f"its free run diverges: {'not finite' if not math.isfinite(esc) else f'{esc:.3g} spans'} "
                       f"beyond the measured output range {float(yr.min()):.4g}..{float(yr.max()):.4g} {output_unit}"
                       f" (|y| up to {peak:.3g} {output_unit}; bound {DIVERGED_SPANS:g} spans)")
    if extrapolation:
        check["warnings"] = [extrapolation]
    if not (unstable or diverged):
        check.update(status="ok", scored="hammerstein free run", reasons=[])
        return check, hammerstein
    static_esc = escape_spans(yr, static[rows]) if static is not None else math.inf
    check["static_escape_spans"] = static_esc if static is not None else None
    if static is not None and static_esc <= DIVERGED_SPANS:
        if diverged and not unstable and poles.size:
            reasons.append(f"the dynamics are stable (|z| <= {radius:.6g}) and the static FPMPI stays within "
                           f"{static_esc:.3g} spans: the dynamics with this front end diverge")
        check.update(status="static-fallback", scored="static FPMPI free run (dynamics and delay left out)",
                     reasons=reasons)
        return check, static
    if static is not None:
        reasons.append(f"the static FPMPI alone diverges too ({'not finite' if not math.isfinite(static_esc) else f'{static_esc:.3g} spans'}): "
                       "the front end, not the dynamics" + ("" if extrapolation else ""))
    if extrapolation:
        reasons.append(extrapolation)
    check.update(status="refused", scored=None, reasons=reasons)
    return check, None


def _drive_frequency_hz(u: np.ndarray, fs: float) -> float:
    """The scored input's strongest frequency (NaN when it does not move)."""
    u = u[np.isfinite(u)]
    if u.size < 8 or np.ptp(u) == 0:
        return math.nan
    spec = np.abs(np.fft.rfft(u - u.mean()))
    k = int(np.argmax(spec[1:])) + 1
    return k * fs / u.size


def persistence_verdict(y: np.ndarray, online: np.ndarray, per: np.ndarray, rows: np.ndarray, fs: float,
                        u: np.ndarray, counters: dict[str, Any], weights_final: np.ndarray, M: int, N: int,
                        extrapolation: str | None, output_unit: str) -> dict[str, Any]:
    """Online against y(k-1) on the scored rows, and when online is worse, why, from numbers.

    What is looked at: the errors over the four quarters of the scored rows and over their last
    half (a start-up or an episode, or the steady state too); the identifier's guard counters; the
    final weights (sum q near 1 is y(k-1) itself); samples per drive cycle and the output's noise
    (y(k-1) is hard to beat when the output moves less per sample than the model's own mismatch);
    whether the front end runs outside its fitted inputs.
    """
    from hilbench.identify.statistics import difference_noise_std

    idx = np.flatnonzero(rows)
    on, pp = _re_n2(y[idx], online[idx]), _re_n2(y[idx], per[idx])
    quarters = [q for q in np.array_split(idx, 4) if q.size]
    q_on = [_re_n2(y[q], online[q]) for q in quarters]
    q_per = [_re_n2(y[q], per[q]) for q in quarters]
    last = quarters[-1]
    on_last, per_last = q_on[-1], q_per[-1]
    sq = [float(np.sum((y[q] - online[q]) ** 2)) for q in quarters]
    worst = int(np.argmax(sq))
    share = sq[worst] / sum(sq) if sum(sq) > 0 else 0.0
    f_drive = _drive_frequency_hz(u[idx], fs)
    per_cycle = fs / f_drive if math.isfinite(f_drive) and f_drive > 0 else math.nan
    d = np.diff(y[idx], 4)
    noise = difference_noise_std(d[np.isfinite(d)], order=4) if d.size > 8 else math.nan
    per_rmse = float(np.sqrt(np.mean((y[last] - per[last]) ** 2)))
    on_rmse = float(np.sqrt(np.mean((y[last] - online[last]) ** 2)))
    sum_q = float(np.sum(weights_final[M + 1:M + 1 + N])) if weights_final.size else math.nan
    doc: dict[str, Any] = {
        "verdict": "better" if on <= pp else "worse",
        "ratio_online_over_persistence": on / pp if pp > 0 else None,
        "quarters_re_n2_pct": {"online": q_on, "persistence": q_per},
        "worst_quarter": worst + 1, "worst_quarter_share": share,
        "samples_per_drive_cycle": per_cycle, "output_noise_std": noise,
        "last_quarter_rmse": {"online": on_rmse, "persistence": per_rmse}, "sum_q_final": sum_q, "reasons": [],
    }
    if on <= pp:
        return doc
    reasons: list[str] = []
    span_s = (quarters[worst][0] / fs, (quarters[worst][-1] + 1) / fs)
    where = f" ({span_s[0]:.4g}-{span_s[1]:.4g} s into the run)"
    episode = (f"quarter {worst + 1} of the scored rows{where} holds {100 * share:.0f} % of the online squared "
               f"error ({q_on[worst]:.3g} % there, y(k-1) {q_per[worst]:.3g} %)")
    if on_last <= STEADY_TOLERANCE * per_last:
        reasons.append(f"an episode, not the steady state: over the last quarter of the scored rows online "
                       f"{on_last:.3g} %, y(k-1) {per_last:.3g} %; {episode}")
    else:
        reasons.append(f"the steady state too: over the last quarter of the scored rows online {on_last:.3g} % > "
                       f"y(k-1) {per_last:.3g} % (rms miss {on_rmse:.3g} vs {per_rmse:.3g} {output_unit})")
        if share > 0.5:
            reasons.append(episode)
        if math.isfinite(noise) and noise > 0 and per_rmse <= 3.0 * math.sqrt(2.0) * noise:
            reasons.append(f"y(k-1) is already at the sensor's noise (rms miss {per_rmse:.3g} {output_unit}, "
                           f"{per_rmse / noise:.3g} x the noise {noise:.2g} {output_unit}): nothing is left for a "
                           "one-step prediction to gain")
        elif math.isfinite(per_cycle) and per_cycle >= 100.0:
            reasons.append(f"sampled far faster than the drive ({per_cycle:.3g} samples per cycle, {f_drive:.3g} Hz "
                           f"at {fs:.4g} Hz): the output moves only {per_rmse:.3g} {output_unit} rms per sample, "
                           f"less than the identifier's own rms miss {on_rmse:.3g} {output_unit}")
        if math.isfinite(sum_q) and abs(sum_q - 1.0) < 0.05:
            reasons.append(f"the denominator settled at an integrator (sum q = {sum_q:.4g}): the weights model the "
                           "change from the last outputs, so what the numerator adds is the front end's error")
    guard = {k: int(counters.get(k, 0)) for k in ("divergence_resets", "predictions_bounded", "poles_projected")}
    if guard["divergence_resets"] or guard["predictions_bounded"]:
        reasons.append(f"the identifier's guard acted: {guard['divergence_resets']} divergence resets, "
                       f"{guard['predictions_bounded']} predictions held at the bound of the outputs seen, "
                       f"{guard['poles_projected']} pole projections")
    if extrapolation:
        reasons.append(extrapolation)
    doc["reasons"] = reasons
    return doc


def leading_rests(runs: list[Any]) -> tuple[list[np.ndarray], list[str]]:
    """Rows each run keeps for training and scoring: all but the leading rest of a run whose history
    is unknown (an imported capture; :func:`hilbench.identify.trimming.leading_rest`), and a note
    per run left short.

    ``fit`` and ``diagnose`` leave such a rest out only where the output moves on its own in it
    (a power-on transient). Here it goes whether settled or not: a held input identifies no
    hysteresis, and the default split trains on the first part of each run, which on a capture that
    rests first is the rest alone (the piezo stack rests 3.26 s of 10 s: its training rows held 0 V
    and the FPMPI fitted on them reached 3.6e9 um at 150 V; decision 0083). The identifier still
    runs through the rest: it is only neither trained on nor scored."""
    from hilbench.identify.trimming import leading_rest

    keeps, notes = [], []
    for r in runs:
        d = r.data
        keep = np.ones(len(d), bool)
        history_known = bool(getattr(d, "chain", False)) or getattr(d, "approach_from", None) is not None
        k = 0 if history_known or not len(d) else leading_rest(np.asarray(d.input, float), float(d.sample_rate_hz))
        if k:
            keep[:k] = False
            notes.append(f"run {r.key}: 0-{k / d.sample_rate_hz:.4g} s neither trained on nor scored: the input rests at "
                         f"{float(d.input[0]):.4g} before the excitation starts (a held input identifies no hysteresis)")
        keeps.append(keep)
    return keeps, notes


def compare(
    runs: list[Any], offline_model: Any, front_end: Any, *, M: int = 3, N: int = 5, lam: float = 1.0,
    delta: float = 1.0e5, forgetting: str = "directional", settle_s: float = 0.5,
    units: tuple[str, str] = ("V", "um"),
) -> list[RunComparison]:
    """Online vs offline vs persistence on every run with validation rows (``runs``: FitRun with
    masks set). The offline model is simulated free-run over all runs, memory chained as recorded;
    where that free run is unstable or diverges, the front end's static FPMPI (operators at rest at
    the run's start) is its fallback (:func:`offline_verdict`). ``units``: (input, output)."""
    from hilbench.identify.metrics import metrics
    from hilbench.online.oiir import OIIR, persistence

    active = [r for r in runs if len(r.data)]
    datas = [r.data for r in active]
    offline_all = offline_model.simulate_runs(datas)
    static_fe = front_end.unbounded()  # the offline model's static part as fitted, extrapolation and all
    static_all = [static_fe.simulate(np.asarray(d.input, dtype=np.float64)) for d in datas]
    train_u = np.concatenate([np.asarray(r.data.input, float)[r.train] for r in active]) if active else np.zeros(0)
    out = []
    for r, y_off, y_static in zip(active, offline_all, static_all):
        if not r.validation.any():
            continue
        u = np.asarray(r.data.input, dtype=np.float64)
        y = np.asarray(r.data.output, dtype=np.float64)
        fs = float(r.data.sample_rate_hz)
        oiir = OIIR(front_end, M, N, lam=lam, delta=delta, forgetting=forgetting)
        res = oiir.run(u, y, decimate=1)
        y_per = persistence(y)
        rows = r.validation & (np.arange(y.size) >= round(settle_s * fs))
        rows &= np.isfinite(y) & np.isfinite(res["y_m"]) & np.isfinite(y_per)
        if not rows.any():
            raise UserError(f"run {r.key}: no row left to score after the first {settle_s:g} s and the training rows",
                            hint="lower --settle or give the run fewer training rows")
        y_off = np.asarray(y_off, float)
        extrapolation = input_extrapolation(train_u, u[rows], units[0])
        check, scored_off = offline_verdict(y, y_off, None if y_static is None else np.asarray(y_static, float),
                                            rows, dynamics_poles(offline_model, fs), extrapolation, units[1])
        shown_off = scored_off if scored_off is not None else np.full(y.size, np.nan)
        c = RunComparison(r.key, r.data.name, fs, u, y, res["y_m"], shown_off, y_per, res["u_r"],
                          res["weights"], oiir.weight_names, rows)
        c.offline_check = check
        c.metrics = {name: _pick(metrics(y[rows], pred[rows]))
                     for name, pred in (("online", c.online), ("offline", shown_off), ("persistence", y_per))}
        c.counters = {**oiir.counters(), "pole_radius": oiir.pole_radius}
        c.static_gain = oiir.static_gain()
        c.poles = oiir.poles()
        c.against_persistence = persistence_verdict(
            y, c.online, y_per, rows, fs, u, c.counters, res["weights"][-1] if len(res["weights"]) else np.zeros(0),
            M, N, extrapolation, units[1])
        out.append(c)
    return out


def write_online(path: Path, comparisons: list[RunComparison], settings: dict[str, Any], output_unit: str,
                 input_unit: str) -> list[str]:
    """One new run per evaluated run: measured input and output, online and offline outputs, the
    FPMPI output u_r and the weights after every sample (``weight_p0``.., ``weight_q1``..)."""
    from hilbench.identify.fitting import finite_json
    from hilbench.recording.hdf5 import RecordingWriter

    writer = RecordingWriter(path)
    names = []
    for c in comparisons:
        n = c.output.size
        data: dict[str, np.ndarray] = {
            "time": np.arange(n) / c.sample_rate_hz, "input": c.input, "output": c.output,
            "online_output": c.online, "offline_output": c.offline, "u_r": c.u_r,
        }
        units = {"time": "s", "input": input_unit, "output": output_unit, "online_output": output_unit,
                 "offline_output": output_unit, "u_r": output_unit}
        desc = {"online_output": "OIIR one-step-ahead prediction y_m(k) (000 eq. 11), a priori",
                "offline_output": "offline Hammerstein model, free-run simulation",
                "u_r": "FPMPI front-end output (000 eq. 4)"}
        for j, name in enumerate(c.weight_names):
            data[f"weight_{name}"] = c.weights[:, j]
            units[f"weight_{name}"] = ""
            desc[f"weight_{name}"] = f"OIIR weight {name} after sample k (000 eq. 9)"
        scored = {k: c.metrics[k]["re_n2_pct"] for k in c.metrics}
        names.append(writer.write_run(
            f"online-{c.name.split('-', 1)[1] if c.name[:4].isdigit() and '-' in c.name else c.name}", data, units, descriptions=desc, experiment="online",
            excitation={"online_identification_of": c.key, **settings}, sample_rate_hz=c.sample_rate_hz,
            extra_attrs={"source_run": c.key, "re_n2_pct": json.dumps(finite_json(scored)),
                         "scored_rows": json.dumps([int(i) for i in _spans(c.rows)])},
        ))
    return names


def _spans(mask: np.ndarray) -> list[int]:
    """Start/stop pairs of the True stretches of ``mask`` (flattened)."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return [v for pair in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)) for v in pair]


def plot_online(comparisons: list[RunComparison], png: Path, output_unit: str, input_unit: str) -> Path:
    """Per run (up to 4): measured, offline and online outputs over time; loops over the scored
    rows; the weights over time (000 Fig. 10c-d)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = comparisons[:PLOT_RUNS]
    fig, axes = plt.subplots(len(shown), 3, figsize=(15, 3.4 * len(shown)), squeeze=False)
    for row, c in zip(axes, shown):
        t = np.arange(c.output.size) / c.sample_rate_hz
        step = max(1, c.output.size // PLOT_POINTS)
        ax = row[0]
        ax.plot(t[::step], c.output[::step], "k-", lw=1.2, label="measured")
        ax.plot(t[::step], c.offline[::step], "b--", lw=1, label=f"offline ({c.metrics['offline']['re_n2_pct']:.3g} %)")
        ax.plot(t[::step], c.online[::step], "r:", lw=1, label=f"online ({c.metrics['online']['re_n2_pct']:.3g} %)")
        ax.set(xlabel="time (s)", ylabel=f"output ({output_unit})", title=c.key)
        ax.legend(fontsize=7, loc="best")
        ax = row[1]
        idx = np.flatnonzero(c.rows)
        idx = idx[:: max(1, idx.size // PLOT_POINTS)]
        ax.plot(c.input[idx], c.output[idx], "k-", lw=0.8, label="measured")
        ax.plot(c.input[idx], c.offline[idx], "b--", lw=0.8, label="offline")
        ax.plot(c.input[idx], c.online[idx], "r:", lw=0.8, label="online")
        ax.set(xlabel=f"input ({input_unit})", ylabel=f"output ({output_unit})", title="loops (scored rows)")
        ax.legend(fontsize=7, loc="best")
        ax = row[2]
        for j, name in enumerate(c.weight_names):
            ax.plot(t[::step], c.weights[::step, j], lw=1, label=name)
        lim = np.nanpercentile(np.abs(c.weights[c.rows]), 99.5) if c.rows.any() else 1.0
        if np.isfinite(lim) and lim > 0:
            ax.set_ylim(-1.2 * lim, 1.2 * lim)
        ax.set(xlabel="time (s)", ylabel="weight", title="OIIR weights (000 Fig. 10c-d)")
        ax.legend(fontsize=7, ncol=2, loc="best")
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=90)
    plt.close(fig)
    return png


def report_lines(doc: dict[str, Any]) -> list[str]:
    lines = [f"offline model: {doc['offline']['spec']} ({doc['offline']['source']}); {doc['split']}",
             (f"online: OIIR M={doc['online']['M']}, N={doc['online']['N']}, lambda {doc['online']['lambda']:g}, "
              f"delta {doc['online']['delta']:g}; errors from {doc['settle_s']:g} s into each run, "
              "training rows left out"),
             f"{'run':36s} {'re_N2 %':>30s}   {'re_Ninf %':>30s}",
             f"{'':36s} {'online':>9s} {'offline':>9s} {'y(k-1)':>9s}   {'online':>9s} {'offline':>9s} {'y(k-1)':>9s}"]
    def cell(value: Any, status: str = "ok") -> str:
        if status == "refused" or value is None:
            return f"{'refused':>9s}"
        return f"{value:9.3g}" + ("*" if status == "static-fallback" else "")

    notes: list[str] = []
    for r in doc["runs"]:
        a, b, c = r["online"], r["offline"], r["persistence"]
        st = r.get("offline_check", {}).get("status", "ok")
        lines.append(f"{r['run'][:36]:36s} {cell(a['re_n2_pct'])} {cell(b['re_n2_pct'], st)} {cell(c['re_n2_pct'])}   "
                     f"{cell(a['re_ninf_pct'])} {cell(b['re_ninf_pct'], st)} {cell(c['re_ninf_pct'])}")
        check = r.get("offline_check", {})
        if st == "static-fallback":
            notes.append(f"{r['run']}: offline* is the static FPMPI's free run, the Hammerstein model set aside: "
                         + "; ".join(check.get("reasons", [])))
        elif st == "refused":
            notes.append(f"{r['run']}: offline refused, nothing scored: " + "; ".join(check.get("reasons", [])))
        else:
            notes.extend(f"{r['run']}: offline: {w}" for w in check.get("warnings", []))
        vs = r.get("online_vs_persistence", {})
        if vs.get("verdict") == "worse":
            notes.append(f"{r['run']}: online {r['online']['re_n2_pct']:.4g} % is worse than y(k-1) "
                         f"{r['persistence']['re_n2_pct']:.4g} %: " + "; ".join(vs.get("reasons", [])))
    lines.append("online and y(k-1) are one-step-ahead predictions from measured outputs; offline is a free-run "
                 "simulation from the input alone: read online against y(k-1), not only against offline.")
    lines.extend(notes)
    return lines


def _overall_status(statuses: list[str]) -> str:
    """One word for the offline model over the evaluated runs: ok, static-fallback, refused, or mixed."""
    kinds = sorted(set(statuses))
    return kinds[0] if len(kinds) == 1 else "mixed: " + ", ".join(f"{k} {statuses.count(k)}" for k in kinds) if kinds else "ok"


# -- the command --------------------------------------------------------------------------------


def check_online_settings(forgetting: float, forgetting_kind: str, delta: float, settle: float,
                          global_starts: int) -> None:
    """Refuse identifier settings that cannot work, naming the option."""
    from hilbench.online.rls import FORGETTING

    if not 0.0 < forgetting <= 1.0:
        raise UserError(f"lambda = {forgetting:g}: expected 0 < lambda <= 1", where="--forgetting")
    if forgetting_kind not in FORGETTING:
        raise UserError(f"{forgetting_kind!r}: expected one of {', '.join(FORGETTING)}", where="--forgetting-kind")
    if not delta > 0.0:
        raise UserError(f"delta = {delta:g}: expected > 0", where="--delta")
    if settle < 0.0:
        raise UserError(f"{settle:g} s: expected >= 0", where="--settle")
    if global_starts < 0:
        raise UserError(f"{global_starts}: expected >= 0", where="--global-starts")


def online_on_recordings(paths: Any, *, train: list[str], train_fraction: float, M: int, N: int, forgetting: float,
                         forgetting_kind: str, delta: float, model: Path | None, settle: float, global_starts: int,
                         note: Callable[[str], None], quiet: bool = True, prefit: Any = None,
                         mode: str = "recording") -> tuple[dict[str, Any], list[RunComparison], Any]:
    """What `hilbench online DATA.h5...` computes: the offline model fitted on the training rows (or
    ``prefit``), every other run identified online from a fresh identifier, and the comparison
    document (``--json``). ``paths``: recordings or a loaded Dataset. Also used by `hilbench batch online`."""
    from hilbench.identify.dataset import as_dataset
    from hilbench.identify.fitting import assign_roles
    from hilbench.identify.metrics import metrics
    from hilbench.models import Model

    dataset = as_dataset(paths)
    runs = dataset.fit_runs()
    keeps, left_out = leading_rests(runs)
    split = assign_roles(runs, train or None, None, train_fraction, keep=keeps)
    for line in left_out:
        note(line)
    if not any(r.validation.any() for r in runs):
        raise UserError(f"no run is left to identify online ({split})", where="--train")
    active = [r for r in runs if len(r.data)]
    masks = [r.train for r in active]
    if not any(m.any() for m in masks):
        raise UserError(f"the training set is empty ({split})", where="--train")

    loaded = Model.load(model) if model is not None else None
    if prefit is None:
        prefit = fit_front_end(active, masks, loaded, model, split, global_starts, None if quiet else note)
    front_model, hammerstein, source, fitted_range, front_end = prefit
    train_y = [(r.data.output[m], y[m]) for r, m, y in zip(active, masks, hammerstein.simulate_runs([r.data for r in active]))]
    train_metrics = _pick(metrics(np.concatenate([a for a, _ in train_y]), np.concatenate([b for _, b in train_y])))

    comparisons = compare(runs, hammerstein, front_end, M=M, N=N, lam=forgetting, delta=delta,
                          forgetting=forgetting_kind, settle_s=settle,
                          units=(dataset.input_unit, dataset.output_unit))
    settings = {"M": M, "N": N, "lambda": forgetting, "delta": delta, "forgetting": forgetting_kind,
                "outlier": "huber", "settle_s": settle}
    doc: dict[str, Any] = {
        "mode": mode,
        "files": [str(p) for p in dataset.paths],
        "replay": "each evaluated run is fed to a fresh identifier sample by sample in recorded order "
                  "(block mode: the same kernel as step mode)",
        "split": split,
        "left_out": left_out,
        "settle_s": settle,
        "offline": {"spec": hammerstein.spec, "source": source, "train": train_metrics,
                    "dynamics": {p.name: p.value for p in hammerstein.effect("dynamics").shape()},
                    "status": _overall_status([c.offline_check.get("status", "ok") for c in comparisons])},
        "front_end": {"operators": int(front_end.r.size), "exponents": front_end.exps.tolist(),
                      "w_p": front_end.w_p.tolist(), "u_scale": float(front_end.fe[0]),
                      "input_range": list(fitted_range) if fitted_range is not None else None,
                      "input_range_note": "the identifier's front end holds its input within the training rows' "
                                          "range (the offline model is simulated without)" if fitted_range else
                                          "none: the front end was loaded"},
        "online": {**settings, "weights": comparisons[0].weight_names if comparisons else []},
        "comparison": COMPARISON,
        "runs": [c.to_json() for c in comparisons],
    }
    return doc, comparisons, dataset


@app.command("online")
@user_errors
def online(
    data: list[str] = typer.Argument(..., metavar="DATA.h5...|RIG",
                                     help="Recording(s) to replay, or a rig config (TOML path or built-in name) to sweep."),
    train: list[str] = typer.Option(
        [], "--train", metavar="RUN", help="Run that trains the offline model entirely (name, label or number; "
        "FILE-STEM:RUN with several files). Repeatable. The other runs are identified online and compared.",
    ),
    train_fraction: float = typer.Option(
        0.3, "--train-fraction", help="Without --train: the first part of every run that trains the offline model; "
        "errors are scored on the rest.",
    ),
    orders: str = typer.Option("3,5", "--orders", metavar="M,N", help="OIIR numerator and denominator orders (000: 3,5)."),
    forgetting: float = typer.Option(1.0, "--forgetting", help="Forgetting factor lambda, 0 < lambda <= 1 (000: 1)."),
    forgetting_kind: str = typer.Option("directional", "--forgetting-kind",
                                        help="directional (no wind-up) or exponential; moot at lambda = 1."),
    delta: float = typer.Option(1.0e5, "--delta", help="Initial covariance P0 = delta I (000: 1e5)."),
    model: Optional[Path] = typer.Option(
        None, "--model", metavar="FIT.json", help="A fitted fpmpi model for the front end (e.g. from `hilbench fit "
        "--model fpmpi`); default: fit fpmpi on the training rows. A model with dynamics is also held as the offline model.",
    ),
    settle: float = typer.Option(0.5, "--settle", help="Seconds at the start of each run left out of all errors "
                                 "(the identifier's start-up transient)."),
    global_starts: int = typer.Option(16, "--global-starts", help="Global starts of the fpmpi shape search."),
    excitation: list[str] = typer.Option(
        [], "--excitation", "-e", metavar="KIND:KEY=VALUE,...", help="Rig mode: runs to sweep instead of the config's plan. Repeatable.",
    ),
    record: Optional[Path] = typer.Option(None, "--record", help="Rig mode: the recording of the sweep "
                                          "(default recordings/RIG-STAMP.h5)."),
    realtime: Optional[bool] = typer.Option(None, "--realtime/--no-realtime",
                                            help="Rig mode: pace a simulated rig at its sample rate (default: the config's)."),
    allow_late: bool = typer.Option(False, "--allow-late", help="Rig mode, real devices: run even when their measured "
                                    "round trip cannot hold the rig's rate (the overruns are recorded)."),
    output: Optional[Path] = typer.Option(None, "--output", "-o", metavar="FILE.h5",
                                          help="Write the online output and the weights as channels of a new run per run."),
    plot_png: Optional[Path] = typer.Option(None, "--plot", metavar="PNG", help="Measured, offline and online outputs and "
                                            "the weights over time, per run (up to 4)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress on stderr."),
) -> None:
    """Identify online (paper 000: FPMPI front end + OIIR weights by RLS) and compare with the offline model.

    Every run not used for training is fed sample by sample to a fresh identifier; its one-step-ahead
    prediction, the held offline Hammerstein model's free-run output and the naive y(k-1) are scored
    with re_n2_pct and re_ninf_pct (000 eq. 18, Table 4).
    """
    def note(message: str) -> None:
        if not quiet:
            typer.echo(message, err=True)

    M, N = parse_orders(orders)
    check_online_settings(forgetting, forgetting_kind, delta, settle, global_starts)

    rig_name = None
    prefit = None
    live = False
    is_rig = len(data) == 1 and not data[0].lower().endswith((".h5", ".hdf5")) and not Path(data[0]).is_file()
    is_rig = is_rig or (len(data) == 1 and data[0].lower().endswith(".toml"))
    if is_rig:
        from hilbench.rig.config import load_rig

        if load_rig(data[0]).simulated:
            recorded, rig_name = record_on_rig(data[0], excitation, record, realtime, quiet or as_json)
        else:  # real devices: the identifier runs in the loop
            live = True
            recorded, rig_name, train, prefit = identify_live_on_rig(
                data[0], excitation, record, train, model, M=M, N=N, lam=forgetting, delta=delta,
                forgetting=forgetting_kind, global_starts=global_starts, allow_late=allow_late, quiet=quiet or as_json,
                note=note)
        note(f"recorded {recorded}")
        paths = [recorded]
    else:
        if excitation or record is not None:
            raise UserError("--excitation and --record sweep a rig; DATA names recordings here",
                            hint="give a rig config or built-in rig name instead of a recording")
        paths = [Path(p) for p in data]
    doc, comparisons, dataset = online_on_recordings(
        paths, train=train, train_fraction=train_fraction, M=M, N=N, forgetting=forgetting,
        forgetting_kind=forgetting_kind, delta=delta, model=model, settle=settle, global_starts=global_starts,
        note=note, quiet=quiet, prefit=prefit, mode="rig" if is_rig else "recording")
    if rig_name is not None:
        doc["rig"] = rig_name
        doc["mode_note"] = ("rig: the plan was swept through the runner into the recording, then replayed through "
                            "the identifier (the samples and their order are those of a step-mode loop)")
    if live:
        doc["mode"] = "rig-live"
        doc["mode_note"] = ("real devices: the training runs were swept and the offline model fitted on them; the "
                            "other runs were identified live, in the fixed-rate loop, their predictions and weights "
                            "recorded as channels; the replay of the recording gives the same predictions")
        from hilbench.recording.hdf5 import Recording

        live_runs = {run.name: run for run in Recording(paths[0])}
        for c, entry in zip(comparisons, doc["runs"]):
            recorded_online = live_runs[c.name].channel("online")
            entry["live_vs_replay_max_abs"] = float(np.max(np.abs(recorded_online - c.online)))
    if output is not None:
        doc["output"] = str(output)
        settings = {k: v for k, v in doc["online"].items() if k != "weights"}
        doc["output_runs"] = write_online(output, comparisons, settings, dataset.output_unit, dataset.input_unit)
        note(f"wrote {output}: runs {', '.join(doc['output_runs'])}")
    if plot_png is not None:
        doc["png"] = str(plot_online(comparisons, plot_png, dataset.output_unit, dataset.input_unit))
        note(f"wrote {plot_png}")
    if as_json:
        print_json(doc)
        return
    for line in report_lines(doc):
        typer.echo(line)
