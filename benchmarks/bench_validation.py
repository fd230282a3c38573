"""The refusal of an impossible model spec: how fast, and how much memory it takes.

``pi(n=100000)`` (and larger) would need hundreds of GB to fit; hilbench estimates the memory from
the spec and the data (:func:`hilbench.models.spec.fit_memory`) and refuses before allocating.
Measured, in one run:

1. ``in_process``: on an already read recording (``Dataset``), the time from ``fit(dataset, spec)``
   to the refusal and the peak of Python/numpy allocations meanwhile (``tracemalloc``), for
   ``pi(n=100000)``, ``pmpi(n=100000)`` and ``pi(n=10**9)``.
2. ``command_line``: ``hilbench fit REC --model 'pi(n=100000)'`` as a real process: wall time
   (imports included) and the process's peak RSS (``os.wait4`` rusage), next to the same command
   fitting ``pi(n=16)`` for scale (most of either is the interpreter with numpy, scipy and numba).
3. ``estimate_vs_measured``: the estimate for a spec that does fit (``pi(n=200)``) against the peak
   tracemalloc measures during that fit, to show the estimate is of the right size (ratio).

Peer: none (no other tool refuses specs); the figures stand on their own. Targets: refusal < 1 s,
refusal peak memory < 50 MB. Prints one JSON document on stdout; never fails on timing.

    python benchmarks/bench_validation.py
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path
from typing import Any


def _recording(folder: Path) -> Path:
    from hilbench.cli.app import run

    out = folder / "rec.h5"
    with contextlib.redirect_stdout(io.StringIO()):  # the sweep's JSON document is not this benchmark's
        status = run(["sweep", "gmm-issf-duhem", "-e", "sine:amplitude=1|2|3,frequency_hz=2,cycles=4", "-o",
                      str(out), "-q", "--json"])
    assert status == 0
    return out


def _refusal(dataset: Any, spec: str) -> dict[str, Any]:
    from hilbench.errors import UserError
    from hilbench.identify.fitting import fit

    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        fit(dataset, spec)
        message = None
    except UserError as exc:
        message = exc.line()
    seconds = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return {"spec": spec, "refused": message is not None, "seconds": round(seconds, 4),
            "peak_traced_mb": round(peak / 1e6, 3), "message": message}


def _process(rec: Path, spec: str) -> dict[str, Any]:
    """One ``hilbench fit`` process: wall time and its own peak RSS (os.wait4's rusage of that child)."""
    with tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "hilbench.cli", "fit", str(rec), "--model", spec, "-q",
                                 "--json"], stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
        seconds = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        stderr = err.read().decode().strip()
    return {"spec": spec, "exit": proc.returncode, "wall_s": round(seconds, 3),
            "peak_rss_mb": round(usage.ru_maxrss / 1024, 1),
            "stderr": stderr.splitlines()[-1] if stderr else ""}


def run() -> dict[str, Any]:
    from hilbench.identify.dataset import Dataset
    from hilbench.models.model import Model
    from hilbench.models.spec import fit_memory, memory_limit

    with tempfile.TemporaryDirectory() as tmp:
        rec = _recording(Path(tmp))
        dataset = Dataset.load(rec)
        in_process = [_refusal(dataset, spec) for spec in ("pi(n=100000)", "pmpi(n=100000)", "pi(n=1000000000)")]
        # a spec that fits: the estimate against what the fit really allocates
        model = Model("pi(n=200)")
        n = sum(len(r.data) for r in dataset.fit_runs())
        estimate = fit_memory(model.base, model.effects, n, int(0.7 * n))
        fitted = _refusal(dataset, "pi(n=200)")
        command_line = [_process(rec, "pi(n=100000)"), _process(rec, "pi(n=16)")]
    refusal = in_process[0]
    return {
        "benchmark": "validation",
        "memory_limit_mb": round(memory_limit() / 1e6, 1),
        "in_process": in_process,
        "command_line": command_line,
        "estimate_vs_measured": {"spec": "pi(n=200)", "samples": n, "estimate_mb": round(estimate / 1e6, 3),
                                 "measured_peak_mb": fitted["peak_traced_mb"],
                                 "ratio": round(estimate / 1e6 / max(fitted["peak_traced_mb"], 1e-9), 2)},
        "meets_target": {"refusal_under_1s": all(r["seconds"] < 1.0 for r in in_process),
                         "refusal_peak_under_50mb": all(r["peak_traced_mb"] < 50 for r in in_process),
                         "pi_n100000_refused": refusal["refused"]},
    }


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
