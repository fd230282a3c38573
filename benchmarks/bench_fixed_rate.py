"""The wall-clock fixed-rate loop (``hilbench.runners.fixed_rate``) on a simulated rig, per sample.

The benchmark rig (PI with 10 play operators + second-order dynamics, noisy quantised sensor) is
opened with ``Rig(config, lockstep=False)``: the simulated backend is then written and read one
sample at a time through the rig (``apply_value`` -> ``write`` -> ``read``), the path real devices
take, and ``run_plan(..., mode="fixed-rate")`` paces it by the wall clock. For each rate (1 kHz and
10 kHz by default, 10 s each) it reports the lateness of the samples (p50, p99, max; from the
recording's ``lateness`` channel) and the overruns (samples later than one period).

It also times what bounds the loop:

- ``per_sample_path_us``: the rig's per-sample path unpaced (``run_plan(..., pace=False)``: safety
  path, plant step, sensor read, interlock check, chunked recording), per sample;
- its parts: ``Rig.apply_value`` (the numba safety path, one value), the simulated ``write`` (plant
  step) and ``read``;
- ``sleep_overshoot_us``: how late ``time.sleep`` wakes up for short sleeps (the reason the loop
  sleeps only until ``spin_s`` before a deadline and spins the rest).

Prints one JSON document on stdout; progress on stderr. Never fails on timing.

    python benchmarks/bench_fixed_rate.py [--seconds 10] [--rates 1000,10000] [--quick]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C


def rig_file(folder: Path, fs: float) -> Path:
    text = C.rig_toml().replace(f"sample_rate_hz = {C.SAMPLE_RATE_HZ!r}", f"sample_rate_hz = {fs!r}")
    path = folder / f"bench-rig-{int(fs)}.toml"
    path.write_text(text, encoding="utf-8")
    return path


def percentiles_us(values: np.ndarray) -> dict[str, float]:
    v = np.asarray(values, dtype=np.float64) * 1e6
    return {"p50": round(float(np.percentile(v, 50)), 2), "p99": round(float(np.percentile(v, 99)), 2),
            "p99_9": round(float(np.percentile(v, 99.9)), 2), "max": round(float(v.max()), 2),
            "mean": round(float(v.mean()), 2)}


def sleep_overshoot(requests_s: tuple[float, ...] = (50e-6, 200e-6, 1e-3), n: int = 300) -> dict[str, Any]:
    out = {}
    for request in requests_s:
        late = np.empty(n)
        for k in range(n):
            t0 = time.perf_counter_ns()
            time.sleep(request)
            late[k] = (time.perf_counter_ns() - t0) * 1e-9 - request
        out[f"sleep_{request * 1e6:g}us"] = percentiles_us(late)
    return out


def time_parts(path: Path, n: int) -> dict[str, float]:
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig

    rig = Rig(load_rig(path), lockstep=False)
    u = np.sin(np.linspace(0, 20 * np.pi, n)) * 2.0
    apply_value, write, read = rig.apply_value, rig.actuator_device.write, rig.actuator_device.read
    t0 = time.perf_counter()
    for x in u:
        apply_value(float(x))
    t_apply = time.perf_counter() - t0
    t0 = time.perf_counter()
    for x in u:
        write(float(x))
    t_write = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(n):
        read()
    t_read = time.perf_counter() - t0
    rig.close()
    return {"apply_value_us": round(t_apply / n * 1e6, 3), "sim_write_plant_step_us": round(t_write / n * 1e6, 3),
            "sim_read_us": round(t_read / n * 1e6, 3)}


def run_loop(path: Path, out: Path, seconds: float, pace: bool) -> dict[str, Any]:
    from hilbench.excitation.plan import plan_from_compact
    from hilbench.recording.hdf5 import Recording
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig
    from hilbench.runners.sweep import run_plan

    config = load_rig(path)
    fs = config.sample_rate_hz
    runs = plan_from_compact([f"sine:amplitude=2,frequency_hz={1.0 / seconds * 5!r},cycles=5"])
    rig = Rig(config, lockstep=False)
    if out.exists():
        out.unlink()
    t0 = time.perf_counter()
    run_plan(rig, runs, out, mode="fixed-rate", pace=pace)
    elapsed = time.perf_counter() - t0
    rig.close()
    run = Recording(out).runs[0]
    n = run.n_samples
    result: dict[str, Any] = {"sample_rate_hz": fs, "samples": n, "elapsed_s": round(elapsed, 3)}
    if pace:
        lateness = run.data()["lateness"]
        result.update({
            "lateness_us": percentiles_us(lateness),
            "overruns": int(run.attrs["overruns"]),
            "overrun_fraction": round(int(run.attrs["overruns"]) / n, 6),
            "run_attrs": {k: float(run.attrs[k]) for k in ("lateness_p50_s", "lateness_p99_s", "lateness_max_s")},
            "period_us": round(1e6 / fs, 1),
        })
    else:
        result["per_sample_path_us"] = round(elapsed / n * 1e6, 3)
        result["max_rate_hz_unpaced"] = round(n / elapsed, 1)
    return result


def run(seconds: float, rates: list[float]) -> dict[str, Any]:
    result: dict[str, Any] = {"benchmark": "fixed_rate_loop", "environment": C.environment(), "seconds": seconds}
    with C.make_tempdir("hilbench-bench-fixed-rate-") as tmp:
        folder = Path(tmp)
        C.note("[fixed-rate] warming up (numba kernels) ...")
        warm = rig_file(folder, 1000.0)
        run_loop(warm, folder / "warm.h5", 0.2, pace=False)
        parts = time_parts(warm, 20_000)
        unpaced = run_loop(rig_file(folder, 10_000.0), folder / "unpaced.h5", 2.0, pace=False)
        loops = {}
        for fs in rates:
            C.note(f"[fixed-rate] {fs:g} Hz paced for {seconds:g} s ...")
            loops[f"{fs:g}_hz"] = run_loop(rig_file(folder, fs), folder / f"paced-{int(fs)}.h5", seconds, pace=True)
        C.note("[fixed-rate] sleep granularity ...")
        sleeps = sleep_overshoot()
    result["paced_loops"] = loops
    result["per_sample_rig_path"] = {**parts, "whole_loop_unpaced_us": unpaced["per_sample_path_us"],
                                     "max_rate_hz_unpaced": unpaced["max_rate_hz_unpaced"]}
    result["sleep_overshoot_us"] = sleeps
    result["limits"] = (
        "Per sample the loop pays Python: apply_value (a numba call), the device write and read (here the "
        "simulated plant's step and a dict), the interlock check and buffer stores; the whole unpaced path "
        f"costs {unpaced['per_sample_path_us']:.1f} us a sample, so ~{unpaced['max_rate_hz_unpaced'] / 1000:.0f} kHz "
        "is the ceiling on this machine before any real transport (a Modbus or serial round trip costs "
        "0.3-1 ms and sets the limit on hardware). Pacing sleeps until 200 us before a deadline and spins "
        "the rest, because time.sleep overshoots by tens of us (sleep_overshoot_us); the remaining lateness "
        "comes from appending a chunk to the HDF5 file and flushing it (every 0.2 s of samples, in the loop "
        "thread), other threads and processes taking the core (2 shared cores here), and the GIL."
    )
    return result


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="paced run length per rate, s (default 10)")
    ap.add_argument("--rates", default="1000,10000", help="sample rates, Hz, comma separated")
    ap.add_argument("--quick", action="store_true", help="1 s per rate")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    a = parse_args(argv)
    seconds = 1.0 if a.quick else a.seconds
    rates = [float(r) for r in a.rates.split(",") if r.strip()]
    with C.make_tempdir("hilbench-bench-fixed-rate-cache-") as cache:
        C.use_private_numba_cache(cache)
        result = run(seconds, rates)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
