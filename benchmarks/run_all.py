"""Run every benchmark and print one combined JSON document on stdout (progress on stderr).

    python benchmarks/run_all.py                 # full size: about 10 minutes on 2 cores (the DE peers
                                                 # of bench_identification take most of it)
    python benchmarks/run_all.py --quick         # small sizes, under a minute: checks the scripts work
    python benchmarks/run_all.py --only plant models   # a subset (plant, recording, models, identification, diagnosis)

Never fails on timing; see the ``meets_target`` entries of each benchmark.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

BENCHMARKS = ("plant", "recording", "models", "identification", "diagnosis")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="run all hilbench benchmarks")
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test of the benchmarks)")
    ap.add_argument("--only", nargs="+", choices=BENCHMARKS, default=list(BENCHMARKS), metavar="NAME",
                    help=f"run only these ({', '.join(BENCHMARKS)}; default all)")
    a = ap.parse_args(argv)
    results: dict[str, dict] = {}
    with C.make_tempdir("hilbench-bench-") as work:
        C.use_private_numba_cache(work)  # before numba is imported by the benchmarks
        import bench_diagnosis
        import bench_identification
        import bench_models
        import bench_plant
        import bench_recording

        t0 = time.perf_counter()
        if a.quick:
            runs = {
                "plant": lambda: bench_plant.run(samples=1_000_000, peer_samples=20_000, step_samples=5_000,
                                                 repeats=1, workdir=work),
                "recording": lambda: bench_recording.run(samples=2_000_000, writer_samples=2_000_000, repeats=1,
                                                         workdir=work),
                "models": lambda: bench_models.run(samples=100_000, fit_samples=2000, step_samples=500, repeats=1,
                                                   max_evaluations=10, workdir=work),
                "identification": lambda: bench_identification.run(pi_samples=20_000, pmpi_samples=10_000,
                                                                   duhem_cycles=1, de_budget_ratio=2.0, repeats=1,
                                                                   workdir=work),
                "diagnosis": lambda: bench_diagnosis.run(samples=20_000, workdir=work),
            }
        else:
            runs = {
                "plant": lambda: bench_plant.run(workdir=work),
                "recording": lambda: bench_recording.run(workdir=work),
                "models": lambda: bench_models.run(workdir=work),
                "identification": lambda: bench_identification.run(workdir=work),
                "diagnosis": lambda: bench_diagnosis.run(workdir=work),
            }
        for name in BENCHMARKS:
            if name in a.only:
                results[name] = runs[name]()
        elapsed = time.perf_counter() - t0
    env = None
    for result in results.values():
        env = result.pop("environment")  # the same machine and versions for all
    meets = {f"{name}.{k}": v for name, result in results.items() for k, v in result["meets_target"].items()}
    summary: dict[str, object] = {}
    if "plant" in results:
        plant = results["plant"]
        summary.update({
            "plant_block_samples_per_s": plant["block_mode"]["samples_per_s"],
            "plant_ratio_vs_loop": plant["ratio_vs_loop"]["ratio"],
            "plant_step_samples_per_s": plant["step_mode"]["samples_per_s"],
            "plant_peer_max_abs_diff_um": plant["equivalence"]["max_abs_diff_um"],
        })
    if "recording" in results:
        recording = results["recording"]
        summary.update({
            "writer_MB_per_s": recording["writer"]["MB_per_s"],
            "writer_samples_per_s": recording["writer"]["samples_per_s"],
            "long_run_samples": recording["long_run"].get("samples"),
            "long_run_peak_rss_MB": recording["long_run"].get("peak_rss_MB"),
            "long_run_samples_per_s": recording["long_run"].get("samples_per_s_end_to_end"),
        })
    if "models" in results:
        models = results["models"]
        summary.update({
            "models_block_samples_per_s": models["summary"]["samples_per_s"],
            "models_shortfalls": models["summary"]["shortfalls"],
        })
    if "identification" in results:
        ident = results["identification"]
        summary.update({
            "pi_weight_fit_s": ident["summary"]["pi_fit_s"],
            "pmpi_fit_vs_de": ident["summary"]["pmpi"],
            "duhem_d_fit_vs_de": ident["summary"]["duhem_d"],
        })
    if "diagnosis" in results:
        diag = results["diagnosis"]
        summary.update({
            "diagnose_all_candidates_s": diag["summary"]["diagnose_s"],
            "diagnose_candidates": diag["summary"]["candidates"],
            "diagnose_auto_s": diag["summary"]["auto_s"],
        })
    print(json.dumps({
        "environment": env,
        "quick": a.quick,
        "elapsed_s": elapsed,
        "summary": summary,
        "meets_target": meets,
        **results,
    }, indent=2))


if __name__ == "__main__":
    main()
