"""Shared helpers of the benchmarks: the benchmark rig, environment facts, timing.

Nothing here asserts on timing; the benchmarks report figures, ratios and ``meets_target`` flags.
"""

from __future__ import annotations

import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

SAMPLE_RATE_HZ = 20_000.0
THRESHOLDS = [round(0.1 * k, 1) for k in range(1, 11)]  # 0.1 .. 1.0, normalised input units
WEIGHTS = [round(1.0 / k, 4) for k in range(1, 11)]  # positive, decreasing
LINEAR_GAIN = 0.2  # p0
OUTPUT_SCALE = 1.0  # um per model unit (the dynamics gain carries the um)
NOISE_STD_UM = 0.01
QUANTIZATION_UM = 0.001
SEED = 7
PRIVATE_NUMBA_CACHE = False  # set when the benchmark redirected numba's cache to its temp dir


def numbers(values: list[float]) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def rig_toml(*, noise_std: float = NOISE_STD_UM, quantization: float = QUANTIZATION_UM,
             max_rate: float = 1.0e5) -> str:
    """A simulated rig: PI (10 play operators) + second-order dynamics + noisy quantised sensor."""
    return f"""\
# Benchmark rig written by hilbench/benchmarks: PI with 10 play operators, second-order dynamics,
# output sensor with white noise and quantisation.
[rig]
name = "bench-pi10-2nd-order"
description = "benchmark rig: PI (10 play operators) + second-order dynamics + noisy quantised sensor"
sample_rate_hz = {SAMPLE_RATE_HZ!r}
seed = {SEED}

[actuator]
driver = "sim"
kind = "benchmark actuator"
unit = "A"
min = -5.0
max = 5.0
max_rate = {max_rate!r}
rest = 0.0

[[sensors]]
channel = "output"
unit = "um"
driver = "sim"
description = "simulated displacement sensor"
noise_std = {noise_std!r}
quantization = {quantization!r}

[plant.hysteresis]
model = "play"
linear_gain = {LINEAR_GAIN!r}
output_scale = {OUTPUT_SCALE!r}
thresholds = {numbers(THRESHOLDS)}
weights = {numbers(WEIGHTS)}

[plant.dynamics]
kind = "second-order"
gain = 10.0                      # um per model unit
zeta = 0.3
natural_frequency_hz = 500.0
"""


def write_rig(folder: str | Path, name: str = "bench-rig.toml", **kwargs: Any) -> Path:
    path = Path(folder) / name
    path.write_text(rig_toml(**kwargs), encoding="utf-8")
    return path


def use_private_numba_cache(folder: str | Path) -> None:
    """Keep numba's on-disk cache out of the source tree unless the user chose a cache dir.

    Must run before numba is imported. Child processes inherit the variable, so they load the
    kernels the parent compiled instead of compiling again (which would inflate their peak RSS).
    """
    global PRIVATE_NUMBA_CACHE
    if "NUMBA_CACHE_DIR" not in os.environ and "numba" not in sys.modules:
        os.environ["NUMBA_CACHE_DIR"] = str(Path(folder) / "numba-cache")
        PRIVATE_NUMBA_CACHE = True


def make_tempdir(prefix: str) -> tempfile.TemporaryDirectory[str]:
    return tempfile.TemporaryDirectory(prefix=prefix)


def best_of(repeats: int, fn: Callable[[], Any], setup: Callable[[], Any] | None = None) -> tuple[float, list[float]]:
    """Smallest wall time of ``repeats`` calls of ``fn`` (``setup`` runs untimed before each)."""
    times = []
    for _ in range(repeats):
        if setup is not None:
            setup()
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times), times


def environment() -> dict[str, Any]:
    import h5py
    import numba
    import numpy
    import scipy

    try:
        import hilbench

        hilbench_version = hilbench.__version__
    except Exception:  # pragma: no cover - benchmarks still report
        hilbench_version = "?"
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "hilbench": hilbench_version,
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "numba": numba.__version__,
        "h5py": h5py.__version__,
        "hdf5": h5py.version.hdf5_version,
        "OPENBLAS_CORETYPE": os.environ.get("OPENBLAS_CORETYPE"),
        "numba_cache": "benchmark temp dir" if PRIVATE_NUMBA_CACHE else os.environ.get("NUMBA_CACHE_DIR", "default (__pycache__)"),
    }


def note(*parts: Any) -> None:
    """Progress and notes go to stderr; stdout carries only the JSON document."""
    print(*parts, file=sys.stderr, flush=True)


def map_cases(func: Any, jobs: list[Any], workers: int = 1, scheduler: str | None = None,
              jsonl: str | None = None) -> list[Any]:
    """``func`` over ``jobs`` through hilbench's batch engine (hilbench.archive.engine): in this process
    when ``workers`` is 1 and no scheduler is given (for a debugger), else on a local Dask cluster of
    ``workers`` processes or the cluster at ``scheduler``, whose workers need this folder at the same
    path. Results in the order of ``jobs``; each is appended to ``jsonl`` as it arrives."""
    import json

    def keep(result: Any) -> None:
        if jsonl:  # one line per finished case: a long run can be read (and summarised) while it runs
            with open(jsonl, "a", encoding="utf-8") as f:
                f.write(json.dumps(result, default=float) + "\n")

    if workers == 1 and not scheduler:
        results = []
        for job in jobs:
            results.append(func(job))
            keep(results[-1])
        return results
    from hilbench.archive.engine import DaskEngine

    results_by_index: dict[int, Any] = {}
    with DaskEngine(scheduler, None if scheduler else workers, sys_path=[str(Path(__file__).resolve().parent)]) as engine:
        for outcome in engine.map_unordered(func, jobs):
            job = jobs[outcome.index]
            result = outcome.result if outcome.ok else {"seed": job[0] if isinstance(job, tuple) else job,
                                                        "error": outcome.error}
            results_by_index[outcome.index] = result
            keep(result)
    return [results_by_index[i] for i in range(len(jobs))]


def print_document(doc: Any, output: str | None = None) -> None:
    """The benchmark's JSON on stdout, and in ``output`` when given."""
    import json

    text = json.dumps(doc, indent=2, default=float)
    if output:
        Path(output).write_text(text, encoding="utf-8")
    print(text)
