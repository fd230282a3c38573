"""Throughput of the simulated plant (hilbench.sim.plant.Plant) against plain Python loops.

The plant: PI hysteresis with 10 play operators (thresholds 0.1..1.0, positive weights, linear
term p0), second-order dynamics (500 Hz, zeta 0.3, zero-order hold at 20 kHz) and an output
sensor with white noise and quantisation. It is built the way every rig builds it: a rig TOML
through ``hilbench.rig.config.load_rig`` and ``Plant.from_rig``.

Measured in one run:

* block mode: ``Plant.simulate`` on 10^7 samples, best of 3 after a warm-up call (numba compile
  time excluded);
* the peers, the same physics written as a plain per-sample loop: ``numpy_loop`` (numpy over the
  10 operators and the filter state) and ``python_loop`` (Python floats), on 2*10^5 samples;
* step mode: ``Plant.step`` one sample at a time, 2*10^4 samples;
* equivalence: the peers and the plant fed the same input and the same standard normals
  (the plant's own seeded stream) must agree to ~1e-9 um or better; step mode must equal block mode.

Prints one JSON document on stdout; progress on stderr. Never fails on timing.

    python benchmarks/bench_plant.py [--samples 10000000] [--peer-samples 200000] [--step-samples 20000]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

TARGET_BLOCK_SAMPLES_PER_S = 10e6
TARGET_RATIO_VS_LOOP = 50.0


def excitation(n: int, fs: float) -> np.ndarray:
    """A command that exercises every operator and the resonance: two tones, peak ~1.5 A."""
    t = np.arange(n, dtype=np.float64) / fs
    return 1.2 * np.sin(2 * np.pi * 50.0 * t) + 0.3 * np.sin(2 * np.pi * 733.0 * t + 0.5)


# -- the peers: the same physics as a plain per-sample loop ----------------------------------------


def peer_parameters(rig: Any, plant: Any) -> dict[str, Any]:
    """Parameters of the peers: the rig tables, and the discrete filter of the plant object."""
    h = rig.plant["hysteresis"]
    out = rig.sensor("output")
    return {
        "r": np.asarray(h["thresholds"], float),
        "w": np.asarray(h["weights"], float),
        "p0": float(h["linear_gain"]),
        "input_scale": float(h["input_scale"]),
        "output_scale": float(h["output_scale"]),
        "b": np.asarray(plant.dyn_b, float),
        "a": np.asarray(plant.dyn_a, float),
        "noise_std": float(out.noise_std),
        "q": float(out.quantization),
        "seed": int(rig.seed),
    }


def sensor_noise(seed: int, n: int) -> np.ndarray:
    """The plant's sensor-noise stream (Plant.reset: default_rng([seed, 1]), standard normals)."""
    return np.random.default_rng([seed, 1]).standard_normal(n)


def numpy_loop(u: np.ndarray, P: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample loop, numpy over the operators and the filter state. Returns (measured, true)."""
    n = u.shape[0]
    noise = sensor_noise(P["seed"], n)
    r, w, b, a = P["r"], P["w"], P["b"], P["a"]
    nd = a.shape[0] - 1
    p0, in_scale, out_scale, std, q = P["p0"], P["input_scale"], P["output_scale"], P["noise_std"], P["q"]
    ops = np.zeros_like(r)  # play operators start at zero
    z = np.zeros(nd)  # direct form II transposed state (scipy.signal.lfilter convention)
    measured = np.empty(n)
    true = np.empty(n)
    for k in range(n):
        x = u[k] / in_scale
        ops = np.maximum(x - r, np.minimum(x + r, ops))
        hyst = (p0 * x + np.dot(w, ops)) * out_scale
        y = b[0] * hyst + z[0]
        z[:-1] = b[1:-1] * hyst + z[1:] - a[1:-1] * y
        z[-1] = b[nd] * hyst - a[nd] * y
        true[k] = y
        m = y + std * noise[k]
        measured[k] = q * np.floor(m / q + 0.5) if q > 0 else m
    return measured, true


def python_loop(u: np.ndarray, P: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample loop over Python floats (faster than numpy for 10 operators)."""
    n = u.shape[0]
    noise = sensor_noise(P["seed"], n).tolist()
    r = P["r"].tolist()
    w = P["w"].tolist()
    b = P["b"].tolist()
    a = P["a"].tolist()
    nd = len(a) - 1
    p0, in_scale, out_scale, std, q = P["p0"], P["input_scale"], P["output_scale"], P["noise_std"], P["q"]
    n_ops = len(r)
    ops = [0.0] * n_ops
    z = [0.0] * nd
    measured = [0.0] * n
    true = [0.0] * n
    floor = math.floor
    for k, x in enumerate(u.tolist()):
        x = x / in_scale
        hyst = p0 * x
        for i in range(n_ops):
            o = min(x + r[i], ops[i])
            o = max(x - r[i], o)
            ops[i] = o
            hyst += w[i] * o
        hyst *= out_scale
        y = b[0] * hyst + z[0]
        for j in range(nd - 1):
            z[j] = b[j + 1] * hyst + z[j + 1] - a[j + 1] * y
        z[nd - 1] = b[nd] * hyst - a[nd] * y
        true[k] = y
        m = y + std * noise[k]
        measured[k] = q * floor(m / q + 0.5) if q > 0 else m
    return np.asarray(measured), np.asarray(true)


# -- the benchmark -------------------------------------------------------------------------------


def rate(n: int, seconds: float) -> float:
    return n / seconds if seconds > 0 else float("inf")


def run(samples: int = 10_000_000, peer_samples: int = 200_000, step_samples: int = 20_000,
        repeats: int = 3, workdir: str | Path | None = None) -> dict[str, Any]:
    tmp = None
    if workdir is None:
        tmp = C.make_tempdir("hilbench-bench-plant-")
        workdir = tmp.name
    C.use_private_numba_cache(workdir)
    try:
        return _run(samples, peer_samples, step_samples, repeats, Path(workdir))
    finally:
        if tmp is not None:
            tmp.cleanup()


def _run(samples: int, peer_samples: int, step_samples: int, repeats: int, workdir: Path) -> dict[str, Any]:
    from hilbench.rig.config import load_rig
    from hilbench.sim import kernels as K
    from hilbench.sim.plant import Plant

    rig_path = C.write_rig(workdir)
    rig = load_rig(rig_path)
    plant = Plant.from_rig(rig)
    fs = rig.sample_rate_hz
    P = peer_parameters(rig, plant)

    # The peers implement exactly this chain; refuse to compare against a plant with more switched on.
    S = plant.S
    assert plant.effects == ["hysteresis", "dynamics"], plant.effects
    assert S[K.S_AMP_ON] == 0 and S[K.S_DELAY] == 0 and S[K.S_MODEL] == 1 and S[K.S_DYN_ON] == 1
    assert np.all(plant.op_eta == 1.0) and plant.in_exp.size == 0 and plant.asym.size == 0
    assert S[K.S_NOISE_STD] == P["noise_std"] > 0 and S[K.S_QUANT] == P["q"] > 0

    u = excitation(max(samples, peer_samples, step_samples), fs)
    u_block = u[:samples]

    # -- block mode ----------------------------------------------------------------------------
    C.note("[plant] warm-up (numba compile or cache load) ...")
    t0 = time.perf_counter()
    plant.simulate(u[:1000])
    warmup_s = time.perf_counter() - t0
    C.note(f"[plant] warm-up took {warmup_s:.2f} s; block mode, {samples:.3g} samples x {repeats} ...")
    block_best, block_times = C.best_of(repeats, lambda: plant.simulate(u_block), setup=plant.reset)

    # The kernel alone, with the noise and output buffers preallocated: what simulate() adds around it.
    n = samples
    noise = np.random.default_rng([rig.seed, 1]).standard_normal(n)
    bufs = [np.empty(n), np.empty(n), np.empty(n)]

    def kernel_block() -> None:
        K.plant_block(
            u_block, np.zeros(0), np.zeros(0), noise, plant.S, plant.in_exp, plant.in_w, plant.op_r, plant.op_w,
            plant.op_eta, plant.relay_a, plant.relay_b, plant.asym, plant.dz_r, plant.dz_g, plant.rate_kp,
            plant.rate_cp, plant.rate_mp, plant.creep_g, plant.creep_a, plant.dyn_b, plant.dyn_a, plant.X, plant.op_state, plant.creep_state,
            plant.dyn_state, plant.delay_buf, plant.tp_state, *bufs,
        )

    C.note("[plant] kernel alone (preallocated buffers) ...")
    try:  # a diagnostic only: it calls the kernel with its current signature
        kernel_best: float | None = C.best_of(repeats, kernel_block, setup=plant.reset)[0]
    except Exception as exc:  # noqa: BLE001
        C.note(f"[plant] kernel-only diagnostic unavailable: {exc!r}")
        kernel_best = None
    del noise, bufs

    # -- peers -----------------------------------------------------------------------------------
    u_peer = np.ascontiguousarray(u[:peer_samples])
    peers: dict[str, Any] = {}
    peer_out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, fn in (("numpy_loop", numpy_loop), ("python_loop", python_loop)):
        C.note(f"[plant] peer {name}, {peer_samples:.3g} samples x {repeats} ...")
        holder: dict[str, Any] = {}

        def call(fn: Any = fn, holder: dict[str, Any] = holder) -> None:
            holder["out"] = fn(u_peer, P)

        best, times = C.best_of(repeats, call)
        peer_out[name] = holder["out"]
        peers[name] = {
            "samples": peer_samples,
            "best_s": best,
            "times_s": times,
            "samples_per_s": rate(peer_samples, best),
            "hilbench_block_ratio": rate(samples, block_best) / rate(peer_samples, best),
        }

    # -- equivalence: same input, same standard normals ---------------------------------------
    C.note("[plant] equivalence checks ...")
    fresh = Plant.from_rig(rig)
    ref = fresh.simulate(u_peer)
    equivalence: dict[str, Any] = {"samples": peer_samples, "noise": "the plant's own stream default_rng([seed, 1])"}
    for name, (meas, true) in peer_out.items():
        d_true = np.abs(true - ref.true_output)
        d_meas = np.abs(meas - ref.output)
        equivalence[name] = {
            "max_abs_diff_true_output_um": float(d_true.max()),
            "max_abs_diff_measured_um": float(d_meas.max()),
            "samples_differing_measured": int(np.count_nonzero(d_meas)),
        }
    # Independent check of the dynamics: scipy.signal.lfilter on the peer's hysteresis output.
    from scipy import signal as sps

    xs = u_peer / P["input_scale"]
    ops = np.zeros_like(P["r"])
    hyst = np.empty(peer_samples)
    for k in range(min(peer_samples, 20_000)):
        ops = np.maximum(xs[k] - P["r"], np.minimum(xs[k] + P["r"], ops))
        hyst[k] = (P["p0"] * xs[k] + np.dot(P["w"], ops)) * P["output_scale"]
    m = min(peer_samples, 20_000)
    y_lfilter = sps.lfilter(P["b"], P["a"], hyst[:m])
    equivalence["scipy_lfilter_dynamics"] = {
        "samples": m,
        "max_abs_diff_true_output_um": float(np.max(np.abs(y_lfilter - ref.true_output[:m]))),
    }
    max_diff = max(
        max(v["max_abs_diff_true_output_um"], v["max_abs_diff_measured_um"])
        for k, v in equivalence.items()
        if k in peer_out
    )
    equivalence["max_abs_diff_um"] = max_diff
    equivalence["equivalent"] = bool(max_diff <= 1e-9)

    # -- step mode -------------------------------------------------------------------------------
    u_step = u[:step_samples].tolist()

    def step_all() -> None:
        step = plant.step
        for x in u_step:
            step(x)

    C.note(f"[plant] step mode, {step_samples:.3g} samples x {repeats} ...")
    step_best, step_times = C.best_of(repeats, step_all, setup=plant.reset)

    # Step mode must give the block-mode samples (same kernel, same noise stream order).
    plant.reset()
    n_cmp = min(step_samples, 5000)
    stepped = np.array([plant.step(x).output[0] for x in u_step[:n_cmp]])
    plant.reset()
    blocked = plant.simulate(np.asarray(u_step[:n_cmp])).output
    step_vs_block = float(np.max(np.abs(stepped - blocked)))

    # The kernel called per sample with preallocated length-1 arrays: the floor of step mode.
    one = [np.empty(1), np.empty(1), np.empty(1)]
    zero1 = np.zeros(1)
    e0 = np.zeros(0)
    u1 = np.empty(1)

    def kernel_steps() -> None:
        for x in u_step:
            u1[0] = x
            K.plant_block(
                u1, e0, e0, zero1, plant.S, plant.in_exp, plant.in_w, plant.op_r, plant.op_w,
                plant.op_eta, plant.relay_a, plant.relay_b, plant.asym, plant.dz_r, plant.dz_g, plant.rate_kp,
                plant.rate_cp, plant.rate_mp, plant.creep_g, plant.creep_a, plant.dyn_b, plant.dyn_a, plant.X, plant.op_state,
                plant.creep_state, plant.dyn_state, plant.delay_buf, plant.tp_state, *one,
            )

    try:
        kernel_step_best: float | None = C.best_of(repeats, kernel_steps, setup=plant.reset)[0]
    except Exception as exc:  # noqa: BLE001
        C.note(f"[plant] kernel-only step diagnostic unavailable: {exc!r}")
        kernel_step_best = None

    block_rate = rate(samples, block_best)
    fastest_peer = max(peers, key=lambda k: peers[k]["samples_per_s"])
    ratio = block_rate / peers[fastest_peer]["samples_per_s"]
    return {
        "benchmark": "plant",
        "environment": C.environment(),
        "plant": {
            "built_with": "hilbench.rig.config.load_rig(rig TOML) -> hilbench.sim.plant.Plant.from_rig",
            "effects": plant.effects,
            "model": "play (PI)",
            "n_operators": int(plant.op_r.shape[0]),
            "thresholds": P["r"].tolist(),
            "weights": P["w"].tolist(),
            "linear_gain_p0": P["p0"],
            "dynamics": {"kind": "second-order", "natural_frequency_hz": 500.0, "zeta": 0.3, "gain": 10.0,
                         "discretization": "zoh", "dyn_b": P["b"].tolist(), "dyn_a": P["a"].tolist()},
            "sample_rate_hz": fs,
            "sensor": {"noise_std_um": P["noise_std"], "quantization_um": P["q"]},
            "command": "1.2 sin(2 pi 50 t) + 0.3 sin(2 pi 733 t + 0.5) A",
        },
        "block_mode": {
            "what": "Plant.simulate(command) on one array, state reset before each repeat",
            "samples": samples,
            "repeats": repeats,
            "warmup_s": warmup_s,
            "best_s": block_best,
            "times_s": block_times,
            "samples_per_s": block_rate,
            "ns_per_sample": 1e9 / block_rate,
        },
        "peers": peers,
        "ratio_vs_loop": {
            "peer": fastest_peer,
            "ratio": ratio,
            "note": "hilbench block-mode samples/s over the faster peer loop's samples/s",
        },
        "step_mode": {
            "what": "Plant.step(x) called once per sample from Python",
            "samples": step_samples,
            "best_s": step_best,
            "times_s": step_times,
            "samples_per_s": rate(step_samples, step_best),
            "us_per_sample": 1e6 * step_best / step_samples,
            "ratio_vs_python_loop": rate(step_samples, step_best) / peers["python_loop"]["samples_per_s"],
            "max_abs_diff_vs_block_mode_um": step_vs_block,
            "compared_samples": n_cmp,
        },
        "equivalence": equivalence,
        "diagnostics": {
            "kernel_only_block_samples_per_s": rate(samples, kernel_best) if kernel_best else None,
            "simulate_overhead_pct_of_block_time":
                100.0 * (block_best - kernel_best) / block_best if kernel_best else None,
            "kernel_only_step_samples_per_s": rate(step_samples, kernel_step_best) if kernel_step_best else None,
            "kernel_only_step_us_per_sample": 1e6 * kernel_step_best / step_samples if kernel_step_best else None,
            "note": "kernel_only_*: hilbench.sim.kernels.plant_block called directly with preallocated "
                    "noise/output arrays, i.e. without Plant.simulate's per-call allocations",
        },
        "targets": {"block_samples_per_s_min": TARGET_BLOCK_SAMPLES_PER_S, "ratio_vs_loop_min": TARGET_RATIO_VS_LOOP},
        "meets_target": {
            "block_mode": bool(block_rate >= TARGET_BLOCK_SAMPLES_PER_S),
            "ratio_vs_loop": bool(ratio >= TARGET_RATIO_VS_LOOP),
            "equivalent": equivalence["equivalent"],
        },
    }


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=10_000_000, help="block-mode samples (default 10^7)")
    ap.add_argument("--peer-samples", type=int, default=200_000, help="samples of each peer loop (default 2*10^5)")
    ap.add_argument("--step-samples", type=int, default=20_000, help="step-mode samples (default 2*10^4)")
    ap.add_argument("--repeats", type=int, default=3, help="best of this many (default 3)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    a = parse_args(argv)
    result = run(a.samples, a.peer_samples, a.step_samples, a.repeats)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
