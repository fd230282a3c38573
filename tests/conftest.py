"""Shared fixtures: small rig configs written to tmp_path, the real-data folder."""

from __future__ import annotations

import os
import platform
import shutil
import tempfile

# What a diagnosis verdict's last bits depend on, pinned before anything imports numpy (pytest loads
# this file first; _check_pins below checks that it held). A few seeded verdicts rest on leaders a
# hair apart, and the hair followed the CPU:
# - numpy picks its SIMD kernels at import from the CPU: on AVX-512 machines (Intel Xeon, AMD EPYC
#   Zen 4) its X86_V4/ICL/SPR kernels round reductions and transcendentals differently from the AVX2
#   (X86_V3) ones that every x86-64 machine of the last decade has. Disabled here: X86_V3 everywhere.
# - OpenBLAS picks its kernels at load (SkylakeX on AVX-512, Haswell or Zen on AVX2 machines), and
#   they sum a product in different orders (seed 140's PMPI base lands in another optimum on each).
#   Haswell's kernels run on every x86-64 CPU with AVX2 and FMA; where the platform already sets
#   OPENBLAS_CORETYPE (some processors need it to compute right), its choice is kept.
# - BLAS and OpenMP run one thread, so no sum is split by the thread count (the suite's parallelism
#   is its worker processes).
# Set, not defaulted (but the core type): a CPU-dependent outcome must not come back through the
# environment. The tool itself is not pinned: users keep their machine's fastest kernels.
if platform.machine().lower() in ("x86_64", "amd64"):
    os.environ["NPY_DISABLE_CPU_FEATURES"] = "X86_V4 AVX512_ICL AVX512_SPR"
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as _cpuinfo:
            _flags = next((line for line in _cpuinfo if line.startswith("flags")), "").split()
    except OSError:
        _flags = []
    if {"avx2", "fma"} <= set(_flags):
        os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")
for _threads in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_threads] = "1"

# One numba cache for the run, made afresh: the test workers, the commands the tests start as
# subprocesses and the benchmark scripts (which otherwise compile into a private cache of their own)
# load the kernels whichever process compiled them first. Afresh, because a cached kernel that inlines
# one from another module is not recompiled when only that module changed (README, Layout).
_OWN_NUMBA_CACHE = "HILBENCH_TESTS_NUMBA_CACHE" not in os.environ and "NUMBA_CACHE_DIR" not in os.environ
if _OWN_NUMBA_CACHE:  # the first process of the run; its test workers inherit the variables
    os.environ["HILBENCH_TESTS_NUMBA_CACHE"] = os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(
        prefix="hilbench-tests-numba-")

import textwrap  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def real_data_dir() -> Path | None:
    """../shared/data/real next to the checkout, or $HILBENCH_REAL_DATA; None when absent."""
    candidates = [REPO.parent / "shared" / "data" / "real"]
    if os.environ.get("HILBENCH_REAL_DATA"):
        candidates.insert(0, Path(os.environ["HILBENCH_REAL_DATA"]))
    return next((c for c in candidates if c.is_dir()), None)


def require_real_data() -> Path:
    """The real-data folder, or skip the test when it is absent."""
    folder = real_data_dir()
    if folder is None:
        pytest.skip("real data folder ../shared/data/real not found (set HILBENCH_REAL_DATA)")
    return folder


MINIMAL_RIG = """
[rig]
name = "mini"
sample_rate_hz = 1000.0
seed = 7

[actuator]
driver = "sim"
unit = "V"
min = -10.0
max = 10.0
max_rate = 1000.0
rest = 0.0

[[sensors]]
channel = "output"
unit = "um"
driver = "sim"
noise_std = 0.01

[plant.hysteresis]
model = "play"
linear_gain = 1.0
thresholds = [0.5, 1.0, 2.0]
weights = [0.5, 0.3, 0.2]
"""


@pytest.fixture
def write_rig(tmp_path: Path):
    """Write a rig TOML (default: a minimal PI rig plus `extra` text) and return its path."""

    def _write(extra: str = "", base: str = MINIMAL_RIG, name: str = "rig.toml") -> Path:
        path = tmp_path / name
        path.write_text(textwrap.dedent(base) + "\n" + textwrap.dedent(extra), encoding="utf-8")
        return path

    return _write


# ----------------------------------------------------------------------------------------------------
# Parallel runs (pytest-xdist, `-n auto` in pyproject.toml)
# ----------------------------------------------------------------------------------------------------


def pytest_configure(config: pytest.Config) -> None:
    _check_pins()
    worker = os.environ.get("PYTEST_XDIST_WORKER")  # "gw0", "gw1", ... in a pytest-xdist worker
    if worker and hasattr(os, "sched_setaffinity"):
        # One core per test worker: a diagnosis sizes its own worker processes by the cores it may
        # run on (hilbench.diagnosis.workers.default_jobs), so two test workers that each forked a
        # process per core would run four CPU-bound processes on two cores. The verdicts do not
        # depend on the number of processes (results return in task order).
        cores = sorted(os.sched_getaffinity(0))
        count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
        if count <= len(cores):
            index = int(worker.lstrip("gw") or 0)
            share = cores[index::count]
            os.sched_setaffinity(0, share)


# Tests that share one worker, by module: the closed-loop modules compile the fused tracking loop
# (about 110 s on one core, cold), and on one worker they compile it once and load it from the run's
# numba cache afterwards, where two workers starting together would each compile it; the emulated
# 001 sweeps share their simulated reference's diagnosis (test_emulated_rigs' per-process cache).
# The batch tests share one generated archive and its fit (a module fixture).
# Grouped here, by the scheduler below, because pytest-xdist 3.8's own `xdist_group` mark renames
# the items' node ids, which pytest 9 computes afresh (a four-test group ran on both workers).
SHARED_WORKER_MODULES = {
    "tests/cli/test_track.py": "closed-loop",
    "tests/online/test_tracking.py": "closed-loop",
    "tests/online/test_feedback_design.py": "closed-loop",
    "tests/online/test_operating_range.py": "closed-loop",
    "tests/online/test_preview_tracking.py": "closed-loop",
    "tests/runners/test_emulated_track.py": "closed-loop",
    "tests/runners/test_emulated_rigs.py": "emulated-001-sweeps",
    "tests/archive/test_batch.py": "archive",  # one generated archive, fitted once
}


# Modules holding the suite's longest tests (20-120 s each in .ci/run's durations), handed out first:
# a long test started last keeps one worker busy while the other has nothing left to do. Every
# worker collects the same order (pytest-xdist requires it); only the order changes, never a verdict.
LONG_FIRST_MODULES = (
    "tests/diagnosis/test_pairs.py",
    "tests/diagnosis/test_random_cases.py",
    "tests/models/test_paper_reproductions.py",
    "tests/test_benchmarks.py",
    "tests/diagnosis/test_diagnosis.py",
    "tests/test_cli.py",
    "tests/diagnosis/test_creep_decades.py",
    "tests/test_cli_progress.py",
    "tests/test_real_data_diagnosis.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if os.environ.get("PYTEST_XDIST_WORKER"):
        rank = {m: i for i, m in enumerate(LONG_FIRST_MODULES)}
        items.sort(key=lambda item: rank.get(item.nodeid.split("::", 1)[0], len(rank)))  # stable


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """`--dist load` (the suite's default), but the modules of SHARED_WORKER_MODULES go to one worker
    per group; the biggest units are handed out first (pytest-xdist's loadscope reordering). Other
    `--dist` modes are pytest-xdist's own."""
    if config.getvalue("dist") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class SharedWorkerScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return SHARED_WORKER_MODULES.get(nodeid.split("::", 1)[0], nodeid)

    return SharedWorkerScheduling(config, log)


def pytest_unconfigure(config: pytest.Config) -> None:
    if _OWN_NUMBA_CACHE:
        shutil.rmtree(os.environ["HILBENCH_TESTS_NUMBA_CACHE"], ignore_errors=True)


def _check_pins() -> None:
    """The pins above held: numpy was not imported before this file set them."""
    import numpy as np  # noqa: F401  (after the pins: imported here first)

    try:
        from numpy._core._multiarray_umath import __cpu_features__ as features
    except ImportError:  # numpy < 2
        from numpy.core._multiarray_umath import __cpu_features__ as features
    active = [name for name in ("X86_V4", "AVX512_ICL", "AVX512_SPR") if features.get(name)]
    if os.environ.get("NPY_DISABLE_CPU_FEATURES") and active:
        raise pytest.UsageError(f"numpy was imported before tests/conftest.py pinned its kernels ({', '.join(active)} "
                                "still active): a plugin or sitecustomize imports numpy first; run without it")
    from threadpoolctl import threadpool_info

    wanted = os.environ.get("OPENBLAS_CORETYPE", "").lower()
    for pool in threadpool_info():
        if pool.get("internal_api") != "openblas":
            continue
        if pool.get("num_threads") != 1 or (wanted and str(pool.get("architecture", "")).lower() != wanted):
            raise pytest.UsageError(f"OpenBLAS runs {pool.get('num_threads')} threads with the "
                                    f"{pool.get('architecture')} kernels, not 1 with {wanted or 'any'}: it was "
                                    "loaded before tests/conftest.py pinned it")
