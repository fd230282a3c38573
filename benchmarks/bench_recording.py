"""Recording throughput and the memory of a long simulated run streamed to disk.

Two measurements, in one run:

1. ``writer``: 2*10^7 samples of 3 channels (time, input, output) streamed through
   ``RecordingWriter(path, flush_interval_s=1.0).begin_run(...)`` / ``RunWriter.append`` in chunks of
   65536, then ``finish("complete")``. Reports MB/s (MB = 10^6 bytes of float64 sample data), samples/s,
   the number of flushes and the longest time between two flushes (the format promises at least one
   flush a second; the writer checks the clock only inside ``append``).
   Peer, same run: the same arrays written with plain h5py into one preallocated contiguous dataset
   per channel (no resizing, no SWMR, no periodic flush): the ceiling for this disk and HDF5 build.
2. ``long_run``: a 10^8-sample run (sine at 10 Hz, 5000 s at 20 kHz) through the real runner,
   ``hilbench.runners.sweep.run_plan(Rig(load_rig(path)), runs, out_file)``, in a child process; reports the
   child's peak RSS (VmHWM, and the parent's ``getrusage(RUSAGE_CHILDREN).ru_maxrss``), its RSS after
   imports and rig setup, and end-to-end samples/s. Target: peak RSS < 300 MB.

Files go to a temporary directory that is deleted afterwards. Prints one JSON document on stdout;
progress on stderr. Never fails on timing or memory.

    python benchmarks/bench_recording.py [--samples 100000000] [--writer-samples 20000000]
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

CHUNK = 65536
TARGET_PEAK_RSS_MB = 300.0  # MB = 10^6 bytes (the stricter reading: 300 MB = 286.1 MiB)
MB = 1e6


def _status_kb(key: str) -> int:
    with open("/proc/self/status", encoding="utf-8") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    return -1


# -- 1. the writer ---------------------------------------------------------------------------------


def bench_writer(folder: Path, samples: int, repeats: int, fs: float) -> dict[str, Any]:
    import h5py

    from hilbench.recording.hdf5 import CANONICAL_CHANNELS, ChannelSpec, Recording, RecordingWriter

    channels = [
        ChannelSpec("time", "s", CANONICAL_CHANNELS["time"][1]),
        ChannelSpec("input", "A", CANONICAL_CHANNELS["input"][1]),
        ChannelSpec("output", "um", CANONICAL_CHANNELS["output"][1]),
    ]
    base = np.arange(CHUNK, dtype=np.float64)
    rng = np.random.default_rng(0)
    inputs = rng.standard_normal(CHUNK)
    outputs = rng.standard_normal(CHUNK)
    n_bytes = samples * len(channels) * 8

    def blocks() -> Any:
        for start in range(0, samples, CHUNK):
            m = min(CHUNK, samples - start)
            yield start, m, {"time": (start + base[:m]) / fs, "input": inputs[:m], "output": outputs[:m]}

    runs = []
    for rep in range(repeats):
        path = folder / f"writer-{rep}.h5"
        writer = RecordingWriter(path, flush_interval_s=1.0)
        run = writer.begin_run("bench", channels, experiment="benchmark", excitation={"kind": "synthetic"},
                               sample_rate_hz=fs)
        flush_times: list[float] = []
        original_flush = run.flush

        def counting_flush(original: Any = original_flush, times: list[float] = flush_times) -> None:
            original()
            times.append(time.perf_counter())

        run.flush = counting_flush  # type: ignore[method-assign]  # instance attribute, hilbench untouched
        t0 = time.perf_counter()
        for _, _, data in blocks():
            run.append(data)
        t_appended = time.perf_counter()
        run.finish("complete")
        t1 = time.perf_counter()
        marks = [t0, *flush_times]
        gaps = np.diff(marks) if len(marks) > 1 else np.array([t1 - t0])
        rec = Recording(path)
        r = rec.runs[0]
        with h5py.File(path, "r") as f:  # only the tail: Run.channel would read the whole channel
            last = f[f"runs/{r.name}/time"][-3:]
        ok = r.status == "complete" and r.n_samples == samples and np.allclose(last, (samples - 3 + np.arange(3)) / fs)
        runs.append({
            "seconds": t1 - t0,
            "append_seconds": t_appended - t0,
            "finish_seconds": t1 - t_appended,
            "flushes": len(flush_times),
            "flushes_during_appends": sum(1 for t in flush_times if t <= t_appended),
            "max_seconds_between_flushes": float(gaps.max()),
            "file_bytes": path.stat().st_size,
            "read_back_ok": bool(ok),
        })
        path.unlink()
        C.note(f"[recording] writer repeat {rep + 1}/{repeats}: {t1 - t0:.2f} s, {len(flush_times)} flushes")

    # Peer: plain h5py, one preallocated contiguous dataset per channel, no SWMR, no periodic flushes.
    peer_times = []
    for rep in range(repeats):
        path = folder / f"peer-{rep}.h5"
        t0 = time.perf_counter()
        with h5py.File(path, "w") as f:
            ds = {c.name: f.create_dataset(c.name, shape=(samples,), dtype="f8") for c in channels}
            for start, m, data in blocks():
                for name, values in data.items():
                    ds[name][start : start + m] = values
        peer_times.append(time.perf_counter() - t0)
        path.unlink()
    best = min(runs, key=lambda r: r["seconds"])
    peer_best = min(peer_times)
    return {
        "what": "RecordingWriter(flush_interval_s=1.0).begin_run + RunWriter.append (chunks of 65536) + finish",
        "samples": samples,
        "channels": [c.name for c in channels],
        "chunk_samples": CHUNK,
        "flush_interval_s": 1.0,
        "data_MB": n_bytes / MB,
        "repeats": repeats,
        "best_s": best["seconds"],
        "times_s": [r["seconds"] for r in runs],
        "MB_per_s": n_bytes / MB / best["seconds"],
        "samples_per_s": samples / best["seconds"],
        "flushes": best["flushes"],
        "flushes_during_appends": best["flushes_during_appends"],
        "max_seconds_between_flushes": best["max_seconds_between_flushes"],
        "finish_s": best["finish_seconds"],
        "file_MB": best["file_bytes"] / MB,
        "read_back_ok": all(r["read_back_ok"] for r in runs),
        "per_repeat": runs,
        "peer_plain_h5py": {
            "what": "h5py, preallocated contiguous datasets, slice assignment per chunk, no SWMR/resize/flush",
            "best_s": peer_best,
            "times_s": peer_times,
            "MB_per_s": n_bytes / MB / peer_best,
            "hilbench_ratio": peer_best / best["seconds"],
        },
        "note": "MB = 10^6 bytes of float64 sample data; writes land in the OS page cache (no fsync)",
    }


# -- 2. a long run through the runner, in a child process ------------------------------------------


def plan_table(kind: str, samples: int, fs: float) -> dict[str, Any]:
    duration = (samples - 1) / fs  # Excitation.n_samples = round(duration * fs) + 1
    if kind == "sine":
        return {"label": "long-sine", "kind": "sine", "amplitude": 1.0, "frequency_hz": 10.0, "duration_s": duration}
    if kind == "noise":
        return {"label": "long-noise", "kind": "noise", "rms": 0.3, "band_hz": [0.0, 200.0], "duration_s": duration,
                "seed": 1}
    raise ValueError(kind)


def child_main(rig_path: str, out_path: str, samples: int, kind: str) -> None:
    """Runs in the child: setup, then run_plan; prints one JSON line on stdout."""
    t_start = time.perf_counter()
    from hilbench.rig.config import load_rig
    from hilbench.excitation.plan import expand_runs
    from hilbench.rig.rig import Rig
    from hilbench.runners.sweep import run_plan

    rss_after_imports = _status_kb("VmRSS")
    cfg = load_rig(rig_path)
    rig = Rig(cfg)
    runs = expand_runs([plan_table(kind, samples, cfg.sample_rate_hz)], file="<bench_recording>")
    n_planned = runs[0].excitation.n_samples(cfg.sample_rate_hz)
    rss_after_setup = _status_kb("VmRSS")
    hwm_after_setup = _status_kb("VmHWM")
    setup_s = time.perf_counter() - t_start

    peak_sampled = [0]
    stop = threading.Event()

    def sampler() -> None:
        while not stop.is_set():
            peak_sampled[0] = max(peak_sampled[0], _status_kb("VmRSS"))
            stop.wait(0.05)

    thread = threading.Thread(target=sampler, daemon=True)
    thread.start()
    last_note = [0.0]
    first_chunk: list[float] = []

    def progress(_i: int, _label: str, done: int, total: int) -> None:
        now = time.perf_counter()
        if not first_chunk:
            first_chunk.append(now)  # the run's first chunk is recorded (plan check and ramp done)
        if now - last_note[0] > 5.0:
            last_note[0] = now
            C.note(f"[recording] long run: {done / total:6.1%} ({done:.3g}/{total:.3g}), RSS {_status_kb('VmRSS') / 1024:.0f} MiB")

    flush_marks: list[float] = []
    run_started: list[float] = []

    # The runner's flush hook has changed shape while the project evolves: use what is there.
    params = inspect.signature(run_plan).parameters
    hooks: dict[str, Any] = {}
    if "on_event" in params:

        def on_event(event: dict[str, Any]) -> None:
            if event.get("event") == "flushed":
                flush_marks.append(time.perf_counter())
            elif event.get("event") == "run-started":
                run_started.append(time.perf_counter())

        hooks["on_event"] = on_event
    elif "on_flush" in params:
        hooks["on_flush"] = lambda _group, _n: flush_marks.append(time.perf_counter())

    t0 = time.perf_counter()
    result = run_plan(rig, runs, out_path, progress=progress, **hooks)
    elapsed = time.perf_counter() - t0
    # Flush gaps from the start of the run on (before it, run_plan checks the whole plan and nothing
    # has been written yet): the run-started event if there is one, else the first recorded chunk.
    start = run_started[0] if run_started else (first_chunk[0] if first_chunk else t0)
    gaps = np.diff([start, *flush_marks])
    stop.set()
    thread.join()
    rss_end = _status_kb("VmRSS")
    hwm_end = _status_kb("VmHWM")
    ru_self = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({
        "samples_planned": n_planned,
        "status": result.status,
        "samples_recorded": result.runs[0].samples if result.runs else 0,
        "run_plan_s": elapsed,
        "setup_s": setup_s,
        "seconds_to_first_chunk": (first_chunk[0] if first_chunk else t0) - t0,
        "flush_hook": next(iter(hooks), None),
        "flushes_during_run": len(flush_marks) if hooks else None,
        "max_seconds_between_flushes": float(gaps.max()) if hooks and gaps.size else None,
        "rss_after_imports_kb": rss_after_imports,
        "rss_after_setup_kb": rss_after_setup,
        "hwm_after_setup_kb": hwm_after_setup,
        "peak_rss_sampled_during_run_kb": peak_sampled[0],
        "rss_end_kb": rss_end,
        "vmhwm_kb": hwm_end,
        "ru_maxrss_self_kb": ru_self,
        "file_bytes": os.path.getsize(out_path),
    }))


def bench_long_run(folder: Path, rig_path: Path, samples: int, kind: str) -> dict[str, Any]:
    out = folder / "long-run.h5"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(rig_path), str(out), str(samples), kind]
    C.note(f"[recording] long run: {samples:.3g} samples ({kind}) through hilbench.runners.sweep.run_plan in a child ...")
    parent_hwm_kb = _status_kb("VmHWM")
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, env=os.environ.copy())
    wall = time.perf_counter() - t0
    children_maxrss_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    if out.exists():
        out.unlink()
    if proc.returncode != 0:
        return {"error": f"child exited with {proc.returncode}", "stdout": proc.stdout[-2000:]}
    child = json.loads(proc.stdout.strip().splitlines()[-1])
    peak_mib = child["vmhwm_kb"] / 1024
    return {
        "what": "hilbench.runners.sweep.run_plan(Rig(load_rig(rig)), [one long run], out.h5) in a child process",
        "excitation": plan_table(kind, samples, C.SAMPLE_RATE_HZ),
        "samples": samples,
        "samples_recorded": child["samples_recorded"],
        "status": child["status"],
        "channels": ["time", "input", "output"],
        "file_MB": child["file_bytes"] / MB,
        "run_plan_s": child["run_plan_s"],
        "samples_per_s_end_to_end": child["samples_recorded"] / child["run_plan_s"] if child["run_plan_s"] > 0 else None,
        "child_wall_s": wall,
        "seconds_to_first_chunk": child["seconds_to_first_chunk"],
        "flushes_during_run": child["flushes_during_run"],
        "max_seconds_between_flushes": child["max_seconds_between_flushes"],
        "peak_rss_MB": peak_mib * 1.048576,
        "peak_rss_MiB": peak_mib,
        "rss_after_imports_MiB": child["rss_after_imports_kb"] / 1024,
        "rss_after_setup_MiB": child["rss_after_setup_kb"] / 1024,
        "growth_during_run_MiB": (child["vmhwm_kb"] - child["rss_after_setup_kb"]) / 1024,
        "peak_rss_sampled_during_run_MiB": child["peak_rss_sampled_during_run_kb"] / 1024,
        "rss_end_MiB": child["rss_end_kb"] / 1024,
        "ru_maxrss_children_MiB": children_maxrss_kb / 1024,
        "parent_peak_rss_at_spawn_MiB": parent_hwm_kb / 1024,
        "note": "peak_rss_MB/peak_rss_MiB: the child's VmHWM at the end (imports + rig setup + run_plan); "
                "MB = 10^6 bytes, the other *_MiB figures in MiB. ru_maxrss_children is max(child, parent at spawn): Linux folds the "
                "address space the child was (v)forked from into it, so it is only an upper bound here.",
    }


def run(samples: int = 100_000_000, writer_samples: int = 20_000_000, repeats: int = 3, excitation: str = "sine",
        workdir: str | Path | None = None) -> dict[str, Any]:
    tmp = C.make_tempdir("hilbench-bench-recording-")
    try:
        if workdir is None:
            workdir = tmp.name
        C.use_private_numba_cache(workdir)
        folder = Path(tmp.name)
        rig_path = C.write_rig(folder)
        from hilbench.rig.config import load_rig
        from hilbench.rig.rig import Rig

        # Compile (or load) the kernels here, so the child loads them from the cache rather than
        # compiling (LLVM would add its own memory to the child's peak).
        Rig(load_rig(rig_path)).measure(np.zeros(16))
        C.note(f"[recording] writer: {writer_samples:.3g} samples x 3 channels x {repeats} ...")
        writer = bench_writer(folder, writer_samples, repeats, C.SAMPLE_RATE_HZ)
        long_run = bench_long_run(folder, rig_path, samples, excitation)
    finally:
        tmp.cleanup()
    peak = long_run.get("peak_rss_MB")
    return {
        "benchmark": "recording",
        "environment": C.environment(),
        "writer": writer,
        "long_run": long_run,
        "targets": {"long_run_peak_rss_MB_max": TARGET_PEAK_RSS_MB, "flush_at_least_every_s": 1.0},
        "meets_target": {
            "long_run_peak_rss": bool(peak is not None and peak < TARGET_PEAK_RSS_MB and long_run.get("status") == "complete"),
            "long_run_complete": bool(long_run.get("status") == "complete" and long_run.get("samples_recorded") == samples),
        },
    }


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=100_000_000, help="samples of the long run (default 10^8)")
    ap.add_argument("--writer-samples", type=int, default=20_000_000, help="samples through the writer (default 2*10^7)")
    ap.add_argument("--repeats", type=int, default=3, help="writer: best of this many (default 3)")
    ap.add_argument("--excitation", choices=("sine", "noise"), default="sine", help="long run excitation")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--child":
        _, rig_path, out_path, samples, kind = argv
        child_main(rig_path, out_path, int(samples), kind)
        return
    a = parse_args(argv)
    print(json.dumps(run(a.samples, a.writer_samples, a.repeats, a.excitation), indent=2))


if __name__ == "__main__":
    main()
