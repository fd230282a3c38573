"""Randomized tracking benchmark: characterise, diagnose, fit and track on rigs the compensator was never tuned to.

    python benchmarks/bench_tracking_random.py                        # 30 rigs, seeds 0-29
    python benchmarks/bench_tracking_random.py --cases 60 --workers 2
    python benchmarks/bench_tracking_random.py --only 3 17 42         # these rig seeds
    python benchmarks/bench_tracking_random.py --cases 2 --output smoke.json

Rigs come from ``benchmarks/tracking_cases.py`` (``draw(seed)``, ``draw_rig(seed)`` the TOML): a
simulated actuator drawn from physics and measurement practice (hysteresis base, dynamics, creep,
saturation, temperature or load, units, ranges, sample rate, sensor) with its characterisation plan.
Per rig, in a temp folder, the bench engineer's chain:

1. the rig config TOML is written and loaded (``load_rig``); its plan is played by
   ``hilbench.runners.sweep.run_plan`` (what ``hilbench sweep RIG`` does) into one recording;
2. ``diagnose(recording, base, auto=True)`` from the base matching the plant's hysteresis (what
   ``hilbench diagnose --auto`` does); the last step's spec is the model spec;
3. that spec is fitted (``hilbench.identify.fitting.fit``, what ``hilbench fit`` does; default split:
   the last 30 % of every run validates); the model's validation ``erms_pct`` is the yardstick;
4. the references of :func:`tracking_cases.references` (sine, triangle, multi-tone, steps,
   attenuated triangle, each spanning 40-90 % of the output range the plant holds quasi-statically
   over its command range, ``tracking_cases.quasi_static_range``, and a triangle spanning twice that
   range; the range the sweep recorded is kept too, but it holds the overshoot where fast runs start) are tracked with ``hilbench.online.tracking.track(rig, model, reference)``,
   feed-forward alone (``feedback=None``) and with feedback (``feedback=True``), each on a freshly
   opened rig.

Prints one JSON document on stdout (progress on stderr):

* ``cases``: per rig: the draw (family, spec, unit, range, sample rate, dynamics, effects), sweep
  samples and output range, ``auto_added`` and ``final_spec``, the model's ``validation_erms_pct``,
  seconds per stage, and ``tracks``: per reference and mode, ``erms_pct``, its ratio to the
  validation erms, ``bound_met`` (feed-forward: erms <= max(2 m, m + 0.3 points), m the model's
  validation rmse over the reference's span, ``validation_on_reference_pct``: the tracking erms_pct's
  own denominator, decision 0116; ``bound_met_validation_span`` with m the model's erms_pct as it
  stands, over the span of its validation rows),
  ``feedback_not_worse``, ``model_erms_pct`` (the fitted model's own free-run error on the run's
  applied commands, normalised like the tracking error: where it is close to ``erms_pct`` the model
  does not carry over to the reference), ``refused`` (the message of a UserError/InstabilityError raised before the
  run), ``unstable`` (a loop that ran with erms_pct > 100 or a non-finite output); for the
  beyond-reach reference ``refused_as_unreachable`` (refused, and not with the message that refused
  the rig's reachable references in the same mode); ``error`` when a stage raised (the case is a
  row, the run goes on);
* ``summary``: the rates the issue names, over reachable references: feed-forward bound met
  (target >= 95 %; a refused or failed reachable reference does not meet it), feedback not worse
  than feed-forward (>= 98 %, over references where both ran); every beyond-reach reference refused
  as unreachable (100 %, per call: feed-forward and feedback); no unstable loop started (0);
  ``meets_target`` flags;
* runtime.

Nothing is tuned per rig: the generator draws from physics, every stage runs with its defaults.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C

TARGET_FF_BOUND = 0.95
TARGET_FB_NOT_WORSE = 0.98
TARGET_UNREACHABLE_REFUSED = 1.0
TARGET_UNSTABLE = 0
MAX_WORKERS = 2
#: a loop whose error rms exceeds this share of the reference span (or whose output is not finite)
#: ran unstable
UNSTABLE_ERMS_PCT = 100.0
#: feedback counts as not worse when its erms is within this relative margin of feed-forward's
#: (float noise only; the margin is not a tolerance of the criterion)
FB_TIE = 1e-9


def ff_bound(val_erms_pct: float) -> float:
    """The feed-forward bound of the issue: max(2 val, val + 0.3 points)."""
    return max(2.0 * val_erms_pct, val_erms_pct + 0.3)


def _track_one(rig_path: Path, model: Any, reference: str, feedback: bool | None) -> dict[str, Any]:
    from hilbench.errors import UserError
    from hilbench.online.tracking import track

    t0 = time.perf_counter()
    row: dict[str, Any] = {}
    try:
        res = track(str(rig_path), model, reference, feedback=feedback)
    except UserError as exc:  # InstabilityError is one: refused before anything moved
        row.update(refused=True, refusal=f"{type(exc).__name__}: {exc.line()}")
        row["seconds"] = time.perf_counter() - t0
        return row
    except Exception as exc:  # noqa: BLE001 - a bug is the row's result, not the end of the run
        row.update(refused=False, error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc(limit=6))
        row["seconds"] = time.perf_counter() - t0
        return row
    import numpy as np

    m = res.metrics
    erms = float(m.get("erms_pct", math.nan))
    finite = bool(np.all(np.isfinite(res.output)))
    comp = res.compensator
    row.update(refused=False, erms_pct=erms, rmse_um=float(m.get("rmse", math.nan)),
               max_abs_error_um=float(m.get("max_abs_error", math.nan)), samples=int(res.time.size),
               finite_output=finite, unstable=(not finite) or not (erms <= UNSTABLE_ERMS_PCT),
               commands_limited=int(res.limited), compensator=comp.get("kind", comp.get("method")),
               feedback_gains=comp.get("feedback"), compensator_notes=list(comp.get("notes", [])),
               compensator_checks=comp.get("checks"),
               loop_seconds=float(res.seconds),
               # the model's validation rmse over the reference's span, as the run's health compares it
               validation_on_reference_pct=res.health.get("model_erms_on_reference_pct"))
    try:
        model_erms = _model_erms_pct(model, res, rig_path)
    except Exception as exc:  # noqa: BLE001 - a diagnostic column; its failure is noted, the row stays
        row["model_error"] = f"{type(exc).__name__}: {exc}"
    else:
        row["model_erms_pct"] = model_erms
    row["seconds"] = time.perf_counter() - t0
    return row


def _model_erms_pct(model: Any, res: Any, rig_path: Path) -> float:
    """The fitted model's own error on the tracking run: its free run on the commands the rig
    applied, from rest through the approach ``track`` drove before the run (``TrackResult.approach``:
    the precondition, the approach, the hold at the first command) and the pre-actuation, against the
    measured output, normalised like the tracking metric (by the reference's span). Near the
    tracking error, the model does not carry over to this reference; well below it, the inverse or
    the loop loses the rest."""
    import numpy as np

    from hilbench.models.model import RunData
    from hilbench.rig.config import load_rig

    cfg = load_rig(rig_path)
    rest, fs = cfg.actuator.rest, cfg.sample_rate_hz
    lead = res.preactuation.get("input", np.zeros(0))  # the run's pre-actuation, before its first sample
    pre = np.concatenate([[rest], res.approach, lead])
    u = np.concatenate([pre, res.input])
    aux = {ch: np.concatenate([np.full(pre.size - lead.size, v[0]), res.preactuation.get(f"aux:{ch}", v[:0]), v])
           for ch, v in res.aux.items()}
    y = model.simulate(RunData(u, None, aux, fs, name="track", approach_from=rest))[pre.size:]
    e = y - res.output
    span = float(np.ptp(res.reference))
    return float(100.0 * np.sqrt(np.mean(e[np.isfinite(e)] ** 2)) / span) if span > 0 else math.nan


def run_case(seed: int, folder: str) -> dict[str, Any]:
    """Draw, sweep, diagnose, fit and track one rig; never raises (an exception is the row's result)."""
    import tracking_cases as TC

    t0 = time.perf_counter()
    out: dict[str, Any] = {"seed": seed}
    stage = "draw"
    try:
        d = TC.draw(seed)
        out.update(d.summary())
        case_dir = Path(folder) / f"rig-{seed}"
        case_dir.mkdir(parents=True, exist_ok=True)
        rig_path = case_dir / f"tracking-rig-{seed}.toml"
        rig_path.write_text(d.toml, encoding="utf-8")

        stage = "sweep"
        import numpy as np

        from hilbench.excitation.plan import expand_runs
        from hilbench.recording.hdf5 import Recording
        from hilbench.rig.config import load_rig
        from hilbench.rig.rig import Rig
        from hilbench.runners.sweep import run_plan

        t1 = time.perf_counter()
        cfg = load_rig(rig_path)
        rec = case_dir / "sweep.h5"
        sweep = run_plan(Rig(cfg), expand_runs(cfg.plan, file=str(rig_path)), rec)
        if sweep.status != "complete":
            raise RuntimeError(f"sweep ended {sweep.status}: " + "; ".join(r.reason.splitlines()[0] for r in sweep.runs if r.reason))
        ys = [run.channel("output") for run in Recording(rec)]
        y = np.concatenate(ys)
        y = y[np.isfinite(y)]
        y_lo, y_hi = float(y.min()), float(y.max())
        out.update(sweep_runs=len(ys), sweep_samples=int(sum(v.size for v in ys)), output_range_um=[y_lo, y_hi],
                   sweep_s=time.perf_counter() - t1)

        # what a reference may ask for: the plant's quasi-static range (the recorded one also holds
        # the overshoot of fast runs' starts)
        reach_lo, reach_hi = TC.quasi_static_range(str(rig_path), d)
        out["quasi_static_range_um"] = [reach_lo, reach_hi]

        stage = "diagnose"
        from hilbench.diagnosis.diagnose import diagnose

        t1 = time.perf_counter()
        da = diagnose([rec], d.spec, auto=True, jobs=1)
        steps = da.steps or []
        final_spec = steps[-1]["spec"] if steps else da.spec
        out.update(auto_added=[s["added"] for s in steps[1:]], final_spec=final_spec,
                   diagnose_validation_erms_pct=[float(s["validation"].get("erms_pct", math.nan)) for s in steps],
                   diagnose_s=time.perf_counter() - t1)

        stage = "fit"
        from hilbench.identify.fitting import fit

        t1 = time.perf_counter()
        fr = fit([rec], final_spec)
        fr.save(case_dir / "model.json")
        val = float(fr.metrics["validation"]["erms_pct"])
        val_rmse = float(fr.metrics["validation"]["rmse"])
        out.update(validation_erms_pct=val, validation_rmse_um=val_rmse, train_erms_pct=float(fr.metrics["train"]["erms_pct"]),
                   ff_bound_pct=ff_bound(val), fit_s=time.perf_counter() - t1)

        stage = "track"
        t1 = time.perf_counter()
        tracks = []
        for ref in TC.references(d, reach_lo, reach_hi):
            row: dict[str, Any] = {"kind": ref["kind"], "reachable": ref["reachable"], "share": ref["share"],
                                   "range_um": [ref["low"], ref["high"]], "reference": ref["compact"]}
            ff = _track_one(rig_path, fr.model, ref["compact"], None)
            fb = _track_one(rig_path, fr.model, ref["compact"], True)
            row["feedforward"], row["feedback"] = ff, fb
            for r in (ff, fb):
                if "erms_pct" in r:  # erms against the reference's span, rmse in um against the model's
                    r["over_validation"] = r["erms_pct"] / val if val > 0 else None
                    r["rmse_over_validation_rmse"] = r["rmse_um"] / val_rmse if val_rmse > 0 else None
            if ref["reachable"] and "erms_pct" in ff:
                # the bound on one span: the model's validation rmse over the reference's span; the
                # issue's formula with the model's erms_pct as it stands (over the validation rows'
                # span, a different denominator) is kept beside it
                m = ff["validation_on_reference_pct"]
                row["bound_met"] = bool(m is not None and ff["erms_pct"] <= ff_bound(m))
                row["bound_met_validation_span"] = bool(ff["erms_pct"] <= ff_bound(val))
            if "erms_pct" in ff and "erms_pct" in fb:
                row["feedback_not_worse"] = bool(fb["erms_pct"] <= ff["erms_pct"] * (1.0 + FB_TIE))
            tracks.append(row)
            C.note(f"  rig {seed} {ref['kind']}: ff {_fmt(ff)} fb {_fmt(fb)} (val {val:.3g} %)")
        # a beyond-reach reference counts as refused for being out of reach only when the reachable
        # ones of the same rig and mode were not refused with the same message (a model the
        # compensator cannot invert refuses every reference alike)
        for row in tracks:
            if row["reachable"]:
                continue
            for mode in ("feedforward", "feedback"):
                r = row[mode]
                same = [t[mode].get("refusal") == r.get("refusal") for t in tracks if t["reachable"] and t[mode].get("refused")]
                r["refused_as_unreachable"] = bool(r.get("refused")) and not any(same)
        out["tracks"] = tracks
        out["track_s"] = time.perf_counter() - t1
    except Exception as exc:  # noqa: BLE001 - the exception is the case's result
        out.update(error=f"{stage}: {type(exc).__name__}: {exc}", traceback=traceback.format_exc(limit=6))
    out["seconds"] = time.perf_counter() - t0
    C.note(f"rig {seed}: {out.get('family')} {out.get('spec')} -> {out.get('final_spec')} val "
           f"{out.get('validation_erms_pct', math.nan):.3g} % ({out['seconds']:.1f} s)"
           + (f" ERROR {out['error']}" if "error" in out else ""))
    return out


def _fmt(r: dict[str, Any]) -> str:
    if r.get("refused"):
        return "refused"
    if "error" in r:
        return "error"
    return f"{r['erms_pct']:.3g} %" + (" UNSTABLE" if r.get("unstable") else "")


_JSONL: str | None = None


def run_case_of(args: tuple[int, str]) -> dict[str, Any]:
    """One job of :func:`run` (a tuple: what a Dask task carries)."""
    return run_case(*args)


def summarize(results: list[dict[str, Any]]) -> dict[str, Any]:
    rows = [(r["seed"], t) for r in results for t in r.get("tracks", [])]
    reach = [(s, t) for s, t in rows if t["reachable"]]
    beyond = [(s, t) for s, t in rows if not t["reachable"]]

    def rate(xs: list[bool]) -> float | None:
        return sum(xs) / len(xs) if xs else None

    # feed-forward bound: over reachable references; a refused or failed reachable reference does not meet it
    ff_met = [bool(t.get("bound_met")) for _, t in reach]
    ff_met_literal = [bool(t.get("bound_met_validation_span")) for _, t in reach]
    pairs = [t for _, t in reach if "feedback_not_worse" in t]
    fb_ok = [t["feedback_not_worse"] for t in pairs]
    calls = [(s, t["kind"], mode, t[mode]) for s, t in rows for mode in ("feedforward", "feedback")]
    beyond_calls = [(s, mode, t[mode]) for s, t in beyond for mode in ("feedforward", "feedback")]
    unstable = [{"seed": s, "reference": k, "mode": m, "erms_pct": r.get("erms_pct")} for s, k, m, r in calls
                if r.get("unstable")]
    refused_reachable = [{"seed": s, "reference": t["kind"], "mode": m, "refusal": t[m]["refusal"]}
                         for s, t in reach for m in ("feedforward", "feedback") if t[m].get("refused")]
    ratios = [t["feedforward"]["over_validation"] for _, t in reach if t["feedforward"].get("over_validation") is not None]
    fb_ratios = [t["feedback"]["over_validation"] for _, t in reach if t["feedback"].get("over_validation") is not None]
    by_kind: dict[str, Any] = {}
    for kind in sorted({t["kind"] for _, t in reach}):
        ts = [t for _, t in reach if t["kind"] == kind]
        by_kind[kind] = {
            "n": len(ts),
            "ff_bound_met": rate([bool(t.get("bound_met")) for t in ts]),
            "feedback_not_worse": rate([t["feedback_not_worse"] for t in ts if "feedback_not_worse" in t]),
            "median_ff_over_validation": statistics.median([t["feedforward"]["over_validation"] for t in ts
                                                            if t["feedforward"].get("over_validation") is not None] or [math.nan]),
            "median_fb_over_validation": statistics.median([t["feedback"]["over_validation"] for t in ts
                                                            if t["feedback"].get("over_validation") is not None] or [math.nan]),
        }
    rates = {
        "ff_bound_met": rate(ff_met),
        "ff_bound_met_validation_span": rate(ff_met_literal),
        "ff_bound_met_of_those_run": rate([bool(t.get("bound_met")) for _, t in reach if "bound_met" in t]),
        "feedback_not_worse": rate(fb_ok),
        "unreachable_refused": rate([bool(r.get("refused_as_unreachable")) for _, _, r in beyond_calls]),
        "unreachable_refused_any_reason": rate([bool(r.get("refused")) for _, _, r in beyond_calls]),
        "unstable_loops": len(unstable),
        "n_rigs": len(results), "n_rigs_with_errors": sum("error" in r for r in results),
        "n_reachable": len(reach), "n_feedback_pairs": len(pairs), "n_beyond_reach_calls": len(beyond_calls),
        "n_track_errors": sum("error" in r for _, _, _, r in calls),
        "n_refused_reachable_calls": len(refused_reachable),
        "median_ff_over_validation": statistics.median(ratios) if ratios else None,
        "median_fb_over_validation": statistics.median(fb_ratios) if fb_ratios else None,
    }
    return {
        "rates": rates,
        "by_reference": by_kind,
        "targets": {"ff_bound_met": TARGET_FF_BOUND, "feedback_not_worse": TARGET_FB_NOT_WORSE,
                    "unreachable_refused": TARGET_UNREACHABLE_REFUSED, "unstable_loops": TARGET_UNSTABLE},
        "meets_target": {
            "ff_bound_met": (rates["ff_bound_met"] or 0.0) >= TARGET_FF_BOUND,
            "feedback_not_worse": (rates["feedback_not_worse"] or 0.0) >= TARGET_FB_NOT_WORSE,
            "unreachable_refused": (rates["unreachable_refused"] or 0.0) >= TARGET_UNREACHABLE_REFUSED,
            "no_unstable_loop": rates["unstable_loops"] <= TARGET_UNSTABLE,
        },
        "unstable": unstable,
        "refused_reachable": refused_reachable,
        "beyond_reach": [{"seed": s, "mode": m, "refused": bool(r.get("refused")),
                          "refused_as_unreachable": bool(r.get("refused_as_unreachable")), "refusal": r.get("refusal"),
                          "erms_pct": r.get("erms_pct")} for s, m, r in beyond_calls],
        "errors": [{"seed": r["seed"], "error": r["error"]} for r in results if "error" in r]
        + [{"seed": s, "reference": k, "mode": m, "error": r["error"]} for s, k, m, r in calls if "error" in r],
    }


def run(cases: int = 30, seed: int = 0, workers: int = 1, only: list[int] | None = None,
        scheduler: str | None = None, keep: str | None = None) -> dict[str, Any]:
    tmp = tempfile.TemporaryDirectory(prefix="hilbench-bench-track-random-")
    C.use_private_numba_cache(tmp.name)
    folder = tmp.name
    if keep is not None:  # each rig's config, sweep and fitted model kept (rig-SEED/) to track again
        Path(keep).mkdir(parents=True, exist_ok=True)
        folder = str(Path(keep).resolve())
    seeds = list(only) if only else list(range(seed, seed + cases))
    jobs = [(s, folder) for s in seeds]
    workers = max(1, min(workers, MAX_WORKERS))
    t0 = time.perf_counter()
    try:
        results = C.map_cases(run_case_of, jobs, workers, scheduler, _JSONL)
    finally:
        tmp.cleanup()
    wall = time.perf_counter() - t0
    for r in results:  # tracebacks only where something raised
        if "error" not in r:
            r.pop("traceback", None)

    def med(key: str) -> float | None:
        xs = [r[key] for r in results if key in r]
        return statistics.median(xs) if xs else None

    return {
        "environment": C.environment(),
        "settings": {"cases": len(seeds), "seeds": seeds, "workers": workers},
        **summarize(results),
        "runtime": {"wall_s": wall, "per_rig_median_s": med("seconds"), "sweep_median_s": med("sweep_s"),
                    "diagnose_median_s": med("diagnose_s"), "fit_median_s": med("fit_s"),
                    "track_median_s": med("track_s")},
        "cases": results,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="randomized tracking benchmark (feed-forward bound, feedback, refusals)")
    ap.add_argument("--cases", type=int, default=30, help="number of rigs (seeds --seed ..)")
    ap.add_argument("--seed", type=int, default=0, help="first rig seed")
    ap.add_argument("--workers", type=int, default=1, help=f"worker processes of a local Dask cluster (at most "
                    f"{MAX_WORKERS}; 1: in this process)")
    ap.add_argument("--scheduler", type=str, default=None, help="an existing Dask scheduler (tcp://HOST:PORT) whose "
                    "workers have this folder and hilbench at the same paths")
    ap.add_argument("--only", type=int, nargs="*", help="these rig seeds instead of a range")
    ap.add_argument("--output", type=str, default=None, help="also write the JSON to this file")
    ap.add_argument("--jsonl", type=str, default=None, help="append each rig's row to this file as it finishes")
    ap.add_argument("--keep", type=str, default=None, help="keep each rig's config, sweep and fitted model "
                    "(model.json) in this folder (rig-SEED/), to track them again")
    a = ap.parse_args(argv)
    global _JSONL
    _JSONL = a.jsonl
    doc = run(a.cases, a.seed, a.workers, a.only, a.scheduler, a.keep)
    C.print_document(doc, a.output)


if __name__ == "__main__":
    main()
