"""Run every benchmark and print one combined JSON document on stdout (progress on stderr).

    python benchmarks/run_all.py                 # full size: about 2-3 minutes on 2 cores
    python benchmarks/run_all.py --quick         # small sizes, a few seconds: checks the scripts work

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


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="run all hilbench benchmarks")
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test of the benchmarks)")
    a = ap.parse_args(argv)
    with C.make_tempdir("hilbench-bench-") as work:
        C.use_private_numba_cache(work)  # before numba is imported by the benchmarks
        import bench_plant
        import bench_recording

        t0 = time.perf_counter()
        if a.quick:
            plant = bench_plant.run(samples=1_000_000, peer_samples=20_000, step_samples=5_000, repeats=1, workdir=work)
            recording = bench_recording.run(samples=2_000_000, writer_samples=2_000_000, repeats=1, workdir=work)
        else:
            plant = bench_plant.run(workdir=work)
            recording = bench_recording.run(workdir=work)
        elapsed = time.perf_counter() - t0
    env = plant.pop("environment")
    recording.pop("environment")
    meets = {f"plant.{k}": v for k, v in plant["meets_target"].items()}
    meets.update({f"recording.{k}": v for k, v in recording["meets_target"].items()})
    summary = {
        "plant_block_samples_per_s": plant["block_mode"]["samples_per_s"],
        "plant_ratio_vs_loop": plant["ratio_vs_loop"]["ratio"],
        "plant_step_samples_per_s": plant["step_mode"]["samples_per_s"],
        "plant_peer_max_abs_diff_um": plant["equivalence"]["max_abs_diff_um"],
        "writer_MB_per_s": recording["writer"]["MB_per_s"],
        "writer_samples_per_s": recording["writer"]["samples_per_s"],
        "long_run_samples": recording["long_run"].get("samples"),
        "long_run_peak_rss_MB": recording["long_run"].get("peak_rss_MB"),
        "long_run_samples_per_s": recording["long_run"].get("samples_per_s_end_to_end"),
    }
    print(json.dumps({
        "environment": env,
        "quick": a.quick,
        "elapsed_s": elapsed,
        "summary": summary,
        "meets_target": meets,
        "plant": plant,
        "recording": recording,
    }, indent=2))


if __name__ == "__main__":
    main()
