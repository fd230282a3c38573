"""The wall-clock fixed-rate loop (``hilbench.runners.fixed_rate``) against this machine's own limit.

The benchmark rig (PI with 10 play operators + second-order dynamics, noisy quantised sensor) is
opened with ``Rig(config, lockstep=False)``: the simulated backend is then written and read one
sample at a time through the rig (``apply_value`` -> ``write`` -> ``read``), the path real devices
take, and ``run_plan(..., mode="fixed-rate")`` paces it by the wall clock. For each rate (1 kHz and
10 kHz by default, 10 s each) it reports the lateness of the samples (p50, p99, max; from the
recording's ``lateness`` channel) and the overruns (samples later than one period).

The reference, in the same run right after each hilbench loop: a **bare loop**, plain Python with the
same sleep-then-spin pacing (sleep until 200 us before the deadline, spin the rest) and nothing else
per sample but storing its lateness. Its p99 is what this machine allows for the pacing itself;
``p99_ratio`` is hilbench's p99 lateness over the bare loop's (the issue's goal: <= 1.5 on a quiet
machine). The same pair runs **with a device round trip**: the Modbus AIO + Keyence template against
``hilbench emulate`` in another process (the way a user dry-runs a real rig), the hilbench loop
sweeping a sine through the rig's drivers, the bare loop writing the held command and reading the
sensor through the same drivers, at the rate the rate check (``--check``) says the devices can hold.

It also times what bounds the loop:

- ``per_sample_path_us``: the rig's per-sample path unpaced (``run_plan(..., pace=False)``: safety
  path, plant step, sensor read, interlock check, chunked recording), per sample;
- its parts: ``Rig.apply_value`` (the numba safety path, one value), the simulated ``write`` (plant
  step) and ``read``;
- ``sleep_overshoot_us``: how late ``time.sleep`` wakes up for short sleeps (the reason the loop
  sleeps only until ``spin_s`` before a deadline and spins the rest).

Prints one JSON document on stdout; progress on stderr. Never fails on timing.

    python benchmarks/bench_fixed_rate.py [--seconds 10] [--rates 1000,10000] [--quick] [--no-device]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C


TEMPLATE = Path(__file__).resolve().parents[1] / "configs" / "templates" / "gmm-modbus-keyence.toml"


def rig_file(folder: Path, fs: float, priority: int = 0) -> Path:
    text = C.rig_toml().replace(f"sample_rate_hz = {C.SAMPLE_RATE_HZ!r}",
                                f"sample_rate_hz = {fs!r}\nloop_priority = {priority}")
    path = folder / f"bench-rig-{int(fs)}-{priority}.toml"
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


def bare_loop(fs: float, seconds: float, io: Callable[[], None] | None = None,
              spin_s: float = 200e-6, priority: int = 0) -> np.ndarray:
    """The machine's limit: the fixed-rate loop's pacing and nothing else (``io``: one device round trip),
    under the same scheduling, timer slack and spin as the hilbench loop it is compared with
    (``priority``: SCHED_FIFO)."""
    from hilbench.runners.loop_tuning import LoopTuning, apply_tuning, spin_for

    tuning = LoopTuning(lock_memory=True, priority=priority)
    restore = apply_tuning(tuning)
    try:
        return _bare(fs, seconds, io, spin_for(1.0 / fs, spin_s, tuning.realtime))
    finally:
        restore()


def _bare(fs: float, seconds: float, io: Callable[[], None] | None, spin_s: float) -> np.ndarray:
    n = int(round(fs * seconds))
    late = np.empty(n)
    period_ns = 1e9 / fs
    spin_ns = int(spin_s * 1e9)
    perf, sleep = time.perf_counter_ns, time.sleep
    t0 = perf() + int(2 * period_ns)
    for k in range(n):
        deadline = t0 + int(k * period_ns)
        wait = deadline - perf() - spin_ns
        if wait > 0:
            sleep(wait * 1e-9)
        now = perf()
        while now < deadline:
            now = perf()
        late[k] = (now - deadline) * 1e-9
        if io is not None:
            io()
    return late


def pacing_figures(lateness: np.ndarray, fs: float) -> dict[str, Any]:
    over = int(np.count_nonzero(lateness > 1.0 / fs))
    return {"lateness_us": percentiles_us(lateness), "overruns": over,
            "overrun_fraction": round(over / lateness.size, 6),
            "later_than_10us_pct": round(100.0 * float(np.mean(lateness > 10e-6)), 4)}


def compare(ours: list[dict[str, Any]], bare: list[np.ndarray], fs: float) -> dict[str, Any]:
    """hilbench against the bare loop over the repeats (run alternately): medians of each one's p99."""
    refs = [pacing_figures(b, fs) for b in bare]
    p99_ours = float(np.median([o["lateness_us"]["p99"] for o in ours]))
    p99_bare = float(np.median([r["lateness_us"]["p99"] for r in refs]))
    return {"hilbench": ours, "bare_loop": refs, "p99_us_median": {"hilbench": p99_ours, "bare_loop": p99_bare},
            "p99_ratio": round(p99_ours / max(p99_bare, 1e-3), 3),
            "overruns_hilbench_vs_bare": [[o["overruns"] for o in ours], [r["overruns"] for r in refs]]}


@dataclasses.dataclass
class Emulated:
    """``hilbench emulate TEMPLATE --json`` in another process, and the rig config pointing at it."""

    process: subprocess.Popen
    config: Any

    def close(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()


def start_emulate(template: Path, seconds: float, write_config: Path | None = None) -> Emulated:
    """``hilbench emulate`` for ``seconds``; with ``write_config``, the config pointed at it written
    there too (as a user does before a dry run from another shell)."""
    from hilbench.rig.config import load_rig

    extra = ["--write-config", str(write_config)] if write_config is not None else []
    proc = subprocess.Popen([sys.executable, "-m", "hilbench.cli", "emulate", str(template), "--json",
                             "--seconds", f"{seconds:g}", *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    text = ""
    assert proc.stdout is not None
    while True:
        line = proc.stdout.readline()
        if not line:
            raise RuntimeError(f"hilbench emulate ended: {proc.stderr.read() if proc.stderr else ''}")
        text += line
        try:
            document = json.loads(text)
            break
        except json.JSONDecodeError:
            continue
    config = load_rig(template)
    devices = {name: {**table, **{k: v for k, v in document["devices"].get(name, {}).items() if k != "driver"}}
               for name, table in config.devices.items()}
    return Emulated(proc, dataclasses.replace(config, devices=devices))


def device_pair(config: Any, folder: Path, seconds: float, repeats: int, priority: int = 0) -> dict[str, Any]:
    """The hilbench loop and the bare loop with the same device round trip, at half the rate the rate
    check would let the devices run (so that the comparison is of the loops, not of the devices' p99)."""
    from hilbench.excitation.plan import plan_from_compact
    from hilbench.recording.hdf5 import Recording
    from hilbench.rig.rig import Rig
    from hilbench.runners.rate_check import _round_down, time_round_trips
    from hilbench.runners.sweep import run_plan

    rig = Rig(config)
    try:
        rig.start_run(0.0)
        trips = time_round_trips(rig, 500)
        fs = min(_round_down(trips.max_rate_hz / 2), 1000.0)
        rig.close()
        rig = Rig(dataclasses.replace(config, sample_rate_hz=fs, loop_priority=priority))
        C.note(f"[fixed-rate] emulated Modbus AIO + Keyence at {fs:g} Hz (round trip p99 "
               f"{trips.p(0.99) * 1e3:.3g} ms) for {seconds:g} s ...")
        runs = plan_from_compact([f"sine:amplitude=1,frequency_hz={5.0 / seconds!r},cycles=5"])
        write = rig.actuator_device.write
        reads = [device.read for _, device, _ in rig.sensor_reads]
        ours, bare = [], []
        for k in range(repeats):
            out = folder / f"device-{k}.h5"
            run_plan(rig, runs, out, mode="fixed-rate")
            run = Recording(out).runs[0]
            ours.append({"sample_rate_hz": fs, "samples": run.n_samples,
                         **pacing_figures(run.channel("lateness"), fs)})
            rig.start_run(0.0)
            held = rig.last_applied

            def io() -> None:
                write(held)
                for read in reads:
                    read()

            bare.append(bare_loop(fs, seconds, io, priority=priority))
        return {"round_trip": trips.describe(), "loop_priority": priority, **compare(ours, bare, fs)}
    finally:
        rig.close()


def viewer_pair(path: Path, folder: Path, seconds: float, repeats: int) -> dict[str, Any]:
    """The same paced run without and with ``hilbench watch`` following its recording (the page's
    refresher reading the file four times a second, in its own process), alternately."""
    without, with_viewer = [], []
    for k in range(repeats):
        without.append(run_loop(path, folder / f"no-viewer-{k}.h5", seconds, pace=True))
        out = folder / f"viewer-{k}.h5"
        viewer = subprocess.Popen([sys.executable, "-m", "hilbench.cli", "watch", str(out), "--linger", "0",
                                   "--wait", "120"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            with_viewer.append(run_loop(path, out, seconds, pace=True))
        finally:
            try:
                viewer.wait(30)
            except subprocess.TimeoutExpired:
                viewer.kill()
    p99 = [float(np.median([r["lateness_us"]["p99"] for r in runs])) for runs in (without, with_viewer)]
    p999 = [float(np.median([r["lateness_us"]["p99_9"] for r in runs])) for runs in (without, with_viewer)]
    return {"without_viewer": without, "with_viewer": with_viewer,
            "p99_us_median": {"without": p99[0], "with": p99[1]},
            "p99_9_us_median": {"without": p999[0], "with": p999[1]},
            "p99_change_pct": round(100.0 * (p99[1] - p99[0]) / max(p99[0], 1e-3), 1),
            "overruns": {"without": [r["overruns"] for r in without], "with": [r["overruns"] for r in with_viewer]}}


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
        result.update({
            **pacing_figures(run.channel("lateness"), fs),
            "run_attrs": {k: float(run.attrs[k]) for k in ("lateness_p50_s", "lateness_p99_s", "lateness_max_s")},
            "loop_tuning": str(run.attrs.get("loop_tuning", "")),
            "period_us": round(1e6 / fs, 1),
        })
    else:
        result["per_sample_path_us"] = round(elapsed / n * 1e6, 3)
        result["max_rate_hz_unpaced"] = round(n / elapsed, 1)
    return result


def run(seconds: float, rates: list[float], device: bool = True, repeats: int = 3,
        priorities: tuple[int, ...] = (0, 50)) -> dict[str, Any]:
    result: dict[str, Any] = {"benchmark": "fixed_rate_loop", "environment": C.environment(), "seconds": seconds,
                              "repeats": repeats}
    with C.make_tempdir("hilbench-bench-fixed-rate-") as tmp:
        folder = Path(tmp)
        C.note("[fixed-rate] warming up (numba kernels) ...")
        warm = rig_file(folder, 1000.0)
        run_loop(warm, folder / "warm.h5", 0.2, pace=False)
        parts = time_parts(warm, 20_000)
        unpaced = run_loop(rig_file(folder, 10_000.0), folder / "unpaced.h5", 2.0, pace=False)
        loops = {}
        for priority in priorities:
            sched = f"SCHED_FIFO {priority}" if priority else "the normal scheduler"
            for fs in rates:
                C.note(f"[fixed-rate] {fs:g} Hz under {sched}: hilbench then the bare loop, {seconds:g} s each, "
                       f"{repeats} times ...")
                ours, bare = [], []
                for k in range(repeats):
                    ours.append(run_loop(rig_file(folder, fs, priority), folder / f"paced-{int(fs)}-{priority}-{k}.h5",
                                         seconds, pace=True))
                    bare.append(bare_loop(fs, seconds, priority=priority))
                loops[f"{fs:g}_hz" + (f"_fifo{priority}" if priority else "")] = {
                    "scheduling": sched, "loop_tuning": ours[-1]["loop_tuning"], **compare(ours, bare, fs)}
        viewer = {}
        for priority in priorities:
            C.note(f"[fixed-rate] 1000 Hz with and without hilbench watch following the file, priority {priority}, "
                   f"{repeats} times ...")
            viewer["fifo" + str(priority) if priority else "normal"] = viewer_pair(
                rig_file(folder, 1000.0, priority), folder, seconds, repeats)
        if device:
            emu = start_emulate(TEMPLATE, 120.0 + 4 * seconds * repeats)
            try:
                loops["emulated_device"] = device_pair(emu.config, folder, seconds, repeats, max(priorities))
            finally:
                emu.close()
        C.note("[fixed-rate] sleep granularity ...")
        sleeps = sleep_overshoot()
    result["paced_loops"] = loops
    result["viewer"] = viewer
    result["p99_ratio"] = {name: pair["p99_ratio"] for name, pair in loops.items()}
    result["per_sample_rig_path"] = {**parts, "whole_loop_unpaced_us": unpaced["per_sample_path_us"],
                                     "max_rate_hz_unpaced": unpaced["max_rate_hz_unpaced"]}
    result["sleep_overshoot_us"] = sleeps
    result["limits"] = (
        "Per sample the loop pays Python: apply_value (a numba call), the device write and read (here the "
        "simulated plant's step and a dict), the interlock check and buffer stores; the whole unpaced path "
        f"costs {unpaced['per_sample_path_us']:.1f} us a sample, so ~{unpaced['max_rate_hz_unpaced'] / 1000:.0f} kHz "
        "is the ceiling on this machine before any real transport (a Modbus or serial round trip costs "
        "0.3-1 ms and sets the limit on hardware). Pacing sleeps until 200 us before a deadline and spins "
        "the rest, because time.sleep overshoots by tens of us (sleep_overshoot_us). The recording is written "
        "by a process of its own (the loop hands over 0.2 s chunks through shared memory), the garbage "
        "collector is held off. Under the normal scheduler any other busy process (a viewer, the writer, "
        "an editor) can delay the loop's wake-up by milliseconds; with [rig] loop_priority (SCHED_FIFO) the "
        "loop preempts them at once. "
        "What remains above the bare loop is the loop's per-sample Python (the "
        "safety path, device calls, interlocks) delaying the next wake-up, and other processes taking "
        "the core (2 shared cores here)."
    )
    return result


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="paced run length per rate, s (default 10)")
    ap.add_argument("--rates", default="1000,10000", help="sample rates, Hz, comma separated")
    ap.add_argument("--quick", action="store_true", help="1 s per rate, one repeat")
    ap.add_argument("--repeats", type=int, default=3, help="hilbench / bare loop pairs per case (default 3)")
    ap.add_argument("--no-device", action="store_true", help="skip the emulated device round trip")
    ap.add_argument("--priority", type=int, default=50, help="also run every case with the loop at this SCHED_FIFO "
                    "priority ([rig] loop_priority; refused without the permission, which the JSON says); 0: skip")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    a = parse_args(argv)
    seconds = 1.0 if a.quick else a.seconds
    rates = [float(r) for r in a.rates.split(",") if r.strip()]
    with C.make_tempdir("hilbench-bench-fixed-rate-cache-") as cache:
        C.use_private_numba_cache(cache)
        result = run(seconds, rates, device=not a.no_device, repeats=1 if a.quick else max(1, a.repeats),
                     priorities=(0, a.priority) if a.priority > 0 else (0,))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
