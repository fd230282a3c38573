"""Speed of `hilbench batch` (hilbench.archive) against a plain loop over the same library call.

Measured in one run, on an archive of simulated recordings (``hilbench batch example``: the demo
stack over days, each recording ``--seconds`` long at 1 kHz, 10^5 samples at the default 100 s):

* **plain loop**: the task's library call (:func:`hilbench.archive.tasks.run_task`: read the
  recording, fit, build the row) for every recording, one after the other in this process, after
  one warm-up call (numba compiled, modules imported);
* **engine, 1 worker and 2 workers**: the same tasks through :class:`DaskEngine` on a local
  cluster, timed from the first submission to the last row (the cluster started and warmed
  before), and the cluster's start-up apart; the per-task overhead is the 1-worker wall against
  the plain loop's (goal < 5 %), the speed-up the 1-worker wall over the 2-worker wall (goal >= 1.8x);
* **peak memory per worker** (the workers' own ru_maxrss after the tasks);
* **the whole command** `hilbench batch fit` (cluster start, hashing, tables, report) end to end;
* **an estimate** for larger clusters from the measured per-task cost and overhead: said as an estimate.

Prints one JSON document on stdout; progress on stderr. Never fails on timing.

    python benchmarks/bench_batch.py [--recordings 12] [--diagnose-recordings 12] [--seconds 100] [--model pi]

Both the cheapest task (`fit -m pi`, where the engine's overhead weighs most) and a typical one
(`diagnose -m pi`) are measured.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

TARGET_SPEEDUP_2 = 1.8
TARGET_OVERHEAD = 0.05


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


def _engine_run(tasks: list[Any], workers: int) -> dict[str, Any]:
    from hilbench.archive.engine import DaskEngine
    from hilbench.archive.tasks import run_task

    t0 = time.perf_counter()
    with DaskEngine(None, workers) as engine:
        engine.client.run(run_task, tasks[0])  # every worker's warm-up, as the plain loop's: numba, imports
        started = time.perf_counter()
        rows = [o.result for o in engine.map_unordered(run_task, tasks, [t.key for t in tasks])]
        wall = time.perf_counter() - started
        peaks = engine.client.run(_peak_rss_mb)
    return {"workers": workers, "startup_and_warm_up_s": started - t0, "wall_s": wall,
            "task_s_median": statistics.median(r["task_s"] for r in rows),
            "failed": sum(r["status"] != "done" for r in rows),
            "peak_rss_mb_per_worker": sorted(round(v, 1) for v in peaks.values())}


def run(recordings: int, seconds: float, model: str, command: str = "fit") -> dict[str, Any]:
    from hilbench.archive.example import write_example_archive
    from hilbench.archive.sources import content_hash
    from hilbench.archive.tasks import ArchiveTask, run_task

    tmp = tempfile.TemporaryDirectory(prefix="hilbench-bench-batch-")
    C.use_private_numba_cache(tmp.name)
    folder = Path(tmp.name) / "archive"
    t0 = time.perf_counter()
    paths = write_example_archive(folder, recordings, seconds)
    _log(f"wrote {recordings} recordings of {seconds:g} s in {time.perf_counter() - t0:.1f} s")
    options: dict[str, Any] = {"model": model, "train": [], "test": [], "train_fraction": None}
    if command == "diagnose":
        options.update(add=None, auto=False, train_fraction=0.7, from_s=None, to_s=None, exclude=[])
    tasks = [ArchiveTask(command, str(p), content_hash(p), options) for p in paths]

    run_task(tasks[0])  # warm-up: imports, numba
    t0 = time.perf_counter()
    plain_rows = [run_task(t) for t in tasks]
    plain = time.perf_counter() - t0
    _log(f"plain loop: {plain:.2f} s")
    one = _engine_run(tasks, 1)
    _log(f"engine, 1 worker: {one['wall_s']:.2f} s (+{one['startup_and_warm_up_s']:.1f} s start-up)")
    two = _engine_run(tasks, 2)
    _log(f"engine, 2 workers: {two['wall_s']:.2f} s (+{two['startup_and_warm_up_s']:.1f} s start-up)")

    out_dir = Path(tmp.name) / "out"
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "hilbench.cli", "batch", command, str(folder), "-m", model, "-o",
                           str(out_dir), "--workers", "2", "--json"], capture_output=True, text=True)
    whole = time.perf_counter() - t0
    summary = json.loads(done.stdout) if done.returncode == 0 else {"error": done.stderr[-500:]}
    tmp.cleanup()

    samples = int(plain_rows[0]["samples"])
    per_task = plain / len(tasks)
    overhead = one["wall_s"] / plain - 1.0
    speedup = one["wall_s"] / two["wall_s"]
    per_task_overhead_s = max(one["wall_s"] - plain, 0.0) / len(tasks)
    return {
        "environment": C.environment(),
        "settings": {"recordings": recordings, "seconds": seconds, "samples_per_recording": samples,
                     "command": f"{command} -m {model}"},
        "plain_loop": {"wall_s": plain, "per_task_s": per_task},
        "engine_1_worker": one,
        "engine_2_workers": two,
        "overhead_1_worker_vs_plain": overhead,
        "speedup_2_vs_1": speedup,
        "meets_target": {"speedup_2_ge_1.8": speedup >= TARGET_SPEEDUP_2,
                         "overhead_lt_5pct": overhead < TARGET_OVERHEAD},
        "whole_command_2_workers": {"wall_s": whole, "rows": summary.get("rows"), "failed": summary.get("failed"),
                                    "error": summary.get("error")},
        "estimate_larger_clusters": {
            "note": "an estimate, not a measurement: wall = start-up + ceil(tasks / workers) x (per-task cost + "
                    "per-task overhead), from this run's figures; assumes the recordings are equally long, the "
                    "workers as fast as this machine's cores and the shared filesystem not the bottleneck",
            "per_task_s": per_task, "per_task_overhead_s": per_task_overhead_s,
            "wall_s_for_1000_recordings": {str(w): round(two["startup_and_warm_up_s"] + -(-1000 // w) * (per_task + per_task_overhead_s), 1)
                                           for w in (2, 16, 64, 256)},
        },
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=12)
    ap.add_argument("--seconds", type=float, default=100.0, help="length of each recording (1 kHz)")
    ap.add_argument("--model", default="pi")
    ap.add_argument("--diagnose-recordings", type=int, default=12,
                    help="recordings of the second part, `batch diagnose` (0: fit only)")
    ap.add_argument("--output", default=None, help="also write the JSON here")
    a = ap.parse_args(argv)
    doc = {"fit": run(a.recordings, a.seconds, a.model, "fit")}
    if a.diagnose_recordings:
        doc["diagnose"] = run(a.diagnose_recordings, a.seconds, a.model, "diagnose")
    C.print_document(doc, a.output)


if __name__ == "__main__":
    main()
