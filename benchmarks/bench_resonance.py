"""Does the diagnosis find a sharp resonance, and where does it put it? (issue 62, part 3)

    python benchmarks/bench_resonance.py --only 0 1 2          # these seeds of resonance_cases.py
    python benchmarks/bench_resonance.py --cases 10 --auto     # seeds 0..9, also diagnose --auto
    python benchmarks/bench_resonance.py --cases 10 --refit-only   # only the dynamics refit (fast)

Per case (``resonance_cases.draw_resonance_case``: a lightly damped resonance, zeta 0.005-0.1, well
above a triangle and step drive, fs 10-50 kHz): the true f_n and zeta, those of the ``dynamics``
refit of the start model (the diagnosis' own refit, or with ``--refit-only`` the same refit outside
it: warm-started from the base fit), their errors (f_n in %, zeta as a factor), whether ``dynamics``
is ranked first and significant, and with ``--auto`` the validation rmse before / after.
Prints one JSON document (progress on stderr); ``summary`` has the detection rate, the share with
f_n within 2 % and zeta within 1.5x, the median errors and the runtimes.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C
import resonance_cases as RC

#: a resonance counts as placed when f_n is within this fraction and zeta within this factor
FN_TOLERANCE = 0.02
ZETA_FACTOR = 1.5


def _dynamics_of(model: Any) -> dict[str, float]:
    d = model.effect("dynamics")
    return {p.name: float(p.value) for p in d.shape()} if d is not None else {}


def run_case(seed: int, auto: bool, refit_only: bool, folder: str, samples: int) -> dict[str, Any]:
    case = RC.draw_resonance_case(seed, samples)
    true = case.strength["dynamics"]
    out: dict[str, Any] = {"seed": seed, "family": case.family, "spec": case.spec, "fs": case.sample_rate_hz,
                           "samples": case.samples(), "snr": case.snr["dynamics"],
                           "fn_true": true["natural_frequency_hz"], "zeta_true": true["zeta"]}
    paths, kw = RC.write_resonance_case(case, Path(folder) / f"r{seed}")
    t0 = time.perf_counter()
    if refit_only:
        from hilbench.identify.fitting import fit

        base = fit(paths, case.spec, **kw)
        refit = fit(paths, f"{case.spec}+dynamics", start_from=base.model, **kw)
        out.update(rmse_base=base.metrics["validation"]["rmse"], rmse_refit=refit.metrics["validation"]["rmse"])
        fitted = _dynamics_of(refit.model)
    else:
        from hilbench.diagnosis.diagnose import diagnose

        da = diagnose(paths, case.spec, auto=auto, jobs=1, **kw)
        d = da.rounds[0] if auto and da.rounds else da
        first = d.effects[0] if d.effects else None
        cand = next((c for c in d.effects if c.effect == "dynamics"), None)
        fitted = _dynamics_of(cand.fitted.model) if cand is not None and cand.fitted is not None else {}
        out.update(ranked_first=first.effect if first else None, first_significant=bool(first and first.significant),
                   significant=[c.effect for c in d.effects if c.significant],
                   gains={c.effect: round(float(c.expected_gain), 4) for c in d.effects})
        if auto:
            steps = da.steps or []
            before = float(steps[0]["validation"]["rmse"])
            after = float(steps[-1]["validation"]["rmse"])
            out.update(auto_added=[s["added"] for s in steps[1:]], reduction=before / after if after > 0 else None)
    out["seconds"] = time.perf_counter() - t0
    if fitted:
        out.update(fn_fit=fitted.get("natural_frequency_hz"), zeta_fit=fitted.get("zeta"))
        out["fn_error"] = abs(out["fn_fit"] / out["fn_true"] - 1.0)
        out["zeta_factor"] = max(out["zeta_fit"] / out["zeta_true"], out["zeta_true"] / out["zeta_fit"])
        out["placed"] = out["fn_error"] <= FN_TOLERANCE and out["zeta_factor"] <= ZETA_FACTOR
    C.note(f"seed {seed}: {case.family} fn {out['fn_true']:.0f} zeta {out['zeta_true']:.4f} -> "
           f"fn {out.get('fn_fit', float('nan')):.1f} zeta {out.get('zeta_fit', float('nan')):.4f} "
           f"first {out.get('ranked_first')} sig {out.get('significant')} red {out.get('reduction')} "
           f"({out['seconds']:.1f} s)")
    return out


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    def rate(xs: list[bool]) -> float | None:
        return sum(xs) / len(xs) if xs else None

    fitted = [r for r in rows if "fn_error" in r]
    red = [r["reduction"] for r in rows if r.get("reduction") is not None]
    return {
        "n": len(rows),
        "dynamics_first_and_significant": rate([r.get("ranked_first") == "dynamics" and r.get("first_significant", False)
                                                for r in rows if "ranked_first" in r]),
        "placed": rate([bool(r.get("placed")) for r in fitted]),
        "median_fn_error_pct": 100 * statistics.median([r["fn_error"] for r in fitted]) if fitted else None,
        "median_zeta_factor": statistics.median([r["zeta_factor"] for r in fitted]) if fitted else None,
        "median_auto_reduction": statistics.median(red) if red else None,
        "share_auto_3x": rate([x >= 3.0 for x in red]),
        "median_seconds": statistics.median([r["seconds"] for r in rows]),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="sharp resonances: found, and where (issue 62 part 3)")
    ap.add_argument("--cases", type=int, default=10)
    ap.add_argument("--only", type=int, nargs="*")
    ap.add_argument("--auto", action="store_true", help="diagnose --auto (the first round is the diagnosis)")
    ap.add_argument("--refit-only", action="store_true", help="only the base fit and its refit with dynamics")
    ap.add_argument("--samples", type=int, default=60_000, help="samples per case, about")
    ap.add_argument("--output", type=str, default=None)
    a = ap.parse_args(argv)
    seeds = a.only if a.only else list(range(a.cases))
    with tempfile.TemporaryDirectory(prefix="hilbench-bench-resonance-") as tmp:
        rows = [run_case(s, a.auto, a.refit_only, tmp, a.samples) for s in seeds]
    doc = {"environment": C.environment(), "summary": summarize(rows), "cases": rows}
    C.print_document(doc, a.output)


if __name__ == "__main__":
    main()
