"""Step mode per sample: compiled model step (``hilbench.models.stepping``) and plant step.

Models ``pi`` and ``pmpi+dynamics``, fitted briefly on a recording of the benchmark rig (PI with 10
play operators + second-order dynamics, 20 kHz, chirp drive): per-sample cost of

- ``compiled_step_python``: ``ModelStepper.step(u)`` from Python (the compiled step, one numba call);
- ``model_step_python``: ``stepping.model_step(I, P, X, u, aux)`` called directly from Python;
- ``compiled_step_njit``: ``model_step`` in a numba loop (what a compiled closed loop pays);
- ``block_kernel``: ``stepping.model_block`` on the whole input, per sample (the same loop body);
- ``simulate_block``: ``Model.simulate`` (the regressor-matrix block path), per sample;
- ``python_stepper``: the previous step mode (``ModelStepper.step_python``: component code on
  blocks of one sample, ``lfilter`` per sample);
- ``plain_python_loop`` (pi only, the peer): the same fitted PI model as a plain Python loop over floats.

Plant (the benchmark rig with its noisy, quantised sensor): ``Plant.step_value`` (fast path),
``Plant.step`` (with the ``PlantOutput``), ``plant_step_flat`` in a numba loop, ``Plant.simulate``
per sample, and the previous step mode (``Plant.simulate`` of one-sample arrays).

Closed loop: model step + plant step per sample, from Python and fused in one numba loop.

Target (issue): at most 2 us per sample for a model plus plant step from Python. Prints one JSON
document on stdout; progress on stderr. Never fails on timing.

    python benchmarks/bench_step.py [--samples 100000] [--old-samples 3000] [--repeats 3]
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
import _common as C  # noqa: E402

TARGET_US = 2.0  # model step + plant step, per sample, from Python
SPECS = ("pi", "pmpi+dynamics")


def per_sample_us(n: int, repeats: int, fn: Any, setup: Any = None) -> float:
    best, _ = C.best_of(repeats, fn, setup)
    return best / n * 1e6


def make_plant(folder: Path) -> Any:
    from hilbench.rig.config import load_rig
    from hilbench.sim.plant import Plant

    return Plant.from_rig(load_rig(C.write_rig(folder)))


def drive(n: int, fs: float) -> np.ndarray:
    t = np.arange(n) / fs
    f = 5.0 + 195.0 * t / max(t[-1], 1e-9)  # chirp 5 -> 200 Hz
    return 3.0 * np.sin(2 * np.pi * np.cumsum(f) / fs) * (0.6 + 0.4 * np.cos(2 * np.pi * 3 * t))


def fit(spec: str, u: np.ndarray, y: np.ndarray, fs: float) -> Any:
    from hilbench.identify import fit_model
    from hilbench.models import Model, RunData

    model = Model(spec)
    run = RunData(u, y, {}, fs, "bench")
    fit_model(model, [run], [np.ones(u.size, bool)], max_evaluations=40, global_starts=0, local_starts=1)
    return model


def plain_python_pi(model: Any) -> Any:
    """The fitted pi model as a plain Python loop over floats (the peer)."""
    base = model.base
    r = [float(x) for x in base.constants["thresholds"]]
    w = [float(x) for x in model.weights]
    scale = float(model.norm["u_scale"])
    offset, weights = w[0], w[1:]

    def run(u: np.ndarray) -> list[float]:
        state = [0.0] * len(r)
        out = []
        for x in u.tolist():
            v = x / scale
            acc = offset
            for i, ri in enumerate(r):
                s = max(v - ri, min(v + ri, state[i]))
                state[i] = s
                acc += weights[i] * s
            out.append(acc)
        return out

    return run


def run(samples: int, old_samples: int, repeats: int) -> dict[str, Any]:
    from numba import njit

    from hilbench.models.stepping import compile_model, model_block, model_step
    from hilbench.sim import kernels as K

    @njit(_nrt=False)
    def model_loop(I, P, X, u, aux, out):  # noqa: N803
        for n in range(u.shape[0]):
            out[n] = model_step(I, P, X, u[n], aux)

    @njit(_nrt=False)
    def plant_loop(F, L, B, u, out):  # noqa: N803
        nb = B.shape[1]
        for n in range(u.shape[0]):
            out[n] = K.plant_step_flat(F, L, B, n % nb, u[n])

    @njit(_nrt=False)
    def closed_loop(I, P, X, aux, F, L, B, u, out):  # noqa: N803
        nb = B.shape[1]
        for n in range(u.shape[0]):
            y = K.plant_step_flat(F, L, B, n % nb, u[n])
            out[n] = y - model_step(I, P, X, u[n], aux)  # model error per sample

    result: dict[str, Any] = {"benchmark": "step", "environment": C.environment(), "samples": samples,
                              "old_samples": old_samples, "repeats": repeats}
    with C.make_tempdir("hilbench-bench-step-") as work:
        folder = Path(work)
        plant = make_plant(folder)
        fs = plant.sample_rate_hz
        u = drive(samples, fs)
        u_fit = drive(8000, fs)
        y_fit = make_plant(folder).simulate(u_fit).output
        aux = np.zeros(1)
        models: dict[str, Any] = {}
        for spec in SPECS:
            C.note(f"[step] fitting {spec}")
            model = fit(spec, u_fit, y_fit, fs)
            compiled = compile_model(model, fs)
            I, P, X = compiled.arrays()
            stepper = model.stepper(fs)
            assert stepper.compiled is not None, stepper.fallback_reason
            out = np.empty(samples)
            # warm up (compile or load from cache), then check agreement with the block path
            from hilbench.models import RunData

            ref = model.simulate(RunData(u[:2000], None, {}, fs))
            check = np.array([stepper.step(x) for x in u[:2000]])
            max_diff = float(np.max(np.abs(check - ref)))
            model_step(I, P, X, 0.0, aux)
            model_loop(I, P, X, u[:10], aux, out[:10])
            model_block(I, P, X, u[:10], np.zeros((10, 1)), out[:10])
            old = model.stepper(fs)
            old.step_python(0.0)
            u_list = u.tolist()

            def step_python() -> None:
                s = stepper.step
                for x in u_list:
                    s(x)

            def step_direct() -> None:
                for x in u_list:
                    model_step(I, P, X, x, aux)

            aux_block = np.zeros((samples, 1))
            timings = {
                "compiled_step_python": per_sample_us(samples, repeats, step_python, stepper.reset),
                "model_step_python": per_sample_us(samples, repeats, step_direct, compiled.reset),
                "compiled_step_njit": per_sample_us(samples, repeats, lambda: model_loop(I, P, X, u, aux, out),
                                                    compiled.reset),
                "block_kernel": per_sample_us(samples, repeats, lambda: model_block(I, P, X, u, aux_block, out),
                                              compiled.reset),
                "simulate_block": per_sample_us(samples, repeats, lambda: model.simulate(RunData(u, None, {}, fs))),
            }
            u_old = u_list[:old_samples]

            def old_steps() -> None:
                for x in u_old:
                    old.step_python(x)

            timings["python_stepper"] = per_sample_us(old_samples, repeats, old_steps, old.reset)
            if spec == "pi":
                peer = plain_python_pi(model)
                peer_out = np.array(peer(u[:2000]))
                timings["plain_python_loop"] = per_sample_us(old_samples, repeats, lambda: peer(u[:old_samples]))
                peer_diff = float(np.max(np.abs(peer_out - ref)))
            c = timings["compiled_step_python"]
            entry = {
                "us_per_sample": {k: round(v, 4) for k, v in timings.items()},
                "max_abs_diff_step_vs_simulate_um": max_diff,
                "ratios": {
                    "python_stepper_over_compiled_step": round(timings["python_stepper"] / c, 1),
                    "compiled_step_python_over_njit": round(c / timings["compiled_step_njit"], 1),
                    "compiled_step_python_over_block_kernel": round(c / timings["block_kernel"], 1),
                    "njit_step_over_block_kernel": round(timings["compiled_step_njit"] / timings["block_kernel"], 2),
                    "simulate_block_over_block_kernel": round(timings["simulate_block"] / timings["block_kernel"], 2),
                },
                "n_weights": int(model.weights.size),
            }
            if spec == "pi":
                entry["ratios"]["plain_python_loop_over_compiled_step"] = round(timings["plain_python_loop"] / c, 1)
                entry["max_abs_diff_plain_python_vs_simulate_um"] = peer_diff
            result[spec] = entry
            models[spec] = (compiled, stepper)
            C.note(f"[step] {spec}: {entry['us_per_sample']}")

        # -- plant -------------------------------------------------------------------------------------
        C.note("[step] plant")
        plant.simulate(u[:10])
        plant.step_value(0.0)
        plant.step(0.0)
        F, L = plant.step_arrays()
        B = np.zeros((3, plant.STEP_BATCH))
        B[K.B_NOISE] = np.random.default_rng(0).standard_normal(plant.STEP_BATCH)
        out = np.empty(samples)
        plant_loop(F, L, B, u[:10], out[:10])
        u_list = u.tolist()

        def plant_step_value() -> None:
            s = plant.step_value
            for x in u_list:
                s(x)

        def plant_step_full() -> None:
            s = plant.step
            for x in u_list[:old_samples]:
                s(x)

        def plant_old_step() -> None:  # what Plant.step did before: the block path on one-sample arrays
            sim = plant.simulate
            for x in u_list[:old_samples]:
                sim(np.array([x], dtype=np.float64))

        plant_t = {
            "step_value_python": per_sample_us(samples, repeats, plant_step_value, plant.reset),
            "step_python": per_sample_us(old_samples, repeats, plant_step_full, plant.reset),
            "plant_step_njit": per_sample_us(samples, repeats, lambda: plant_loop(F, L, B, u, out), plant.reset),
            "simulate_block": per_sample_us(samples, repeats, lambda: plant.simulate(u), plant.reset),
            "old_step_one_sample_block": per_sample_us(old_samples, repeats, plant_old_step, plant.reset),
        }
        result["plant"] = {
            "us_per_sample": {k: round(v, 4) for k, v in plant_t.items()},
            "ratios": {
                "old_step_over_step_value": round(plant_t["old_step_one_sample_block"] / plant_t["step_value_python"], 1),
                "step_value_over_njit": round(plant_t["step_value_python"] / plant_t["plant_step_njit"], 1),
                "step_value_over_block": round(plant_t["step_value_python"] / plant_t["simulate_block"], 1),
            },
        }
        C.note(f"[step] plant: {result['plant']['us_per_sample']}")

        # -- closed loop: model step + plant step per sample ---------------------------------------------
        closed: dict[str, Any] = {}
        for spec, (compiled, stepper) in models.items():
            I, P, X = compiled.arrays()
            closed_loop(I, P, X, aux, F, L, B, u[:10], out[:10])

            def python_loop(stepper: Any = stepper) -> None:
                ps = plant.step_value
                ms = stepper.step
                for x in u_list:
                    ps(x)
                    ms(x)

            def resets(stepper: Any = stepper) -> None:
                plant.reset()
                stepper.reset()

            py = per_sample_us(samples, repeats, python_loop, resets)
            fused = per_sample_us(samples, repeats, lambda: closed_loop(I, P, X, aux, F, L, B, u, out), resets)
            closed[spec] = {"python_us_per_sample": round(py, 4), "fused_njit_us_per_sample": round(fused, 4),
                            "python_over_fused": round(py / fused, 1), "meets_target": py <= TARGET_US}
        result["closed_loop_model_plus_plant"] = closed
        result["targets"] = {"model_plus_plant_step_python_us_max": TARGET_US}
        result["meets_target"] = {f"model_plus_plant.{s}": closed[s]["meets_target"] for s in closed}
    return result


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=100_000, help="samples of the compiled paths (default 10^5)")
    ap.add_argument("--old-samples", type=int, default=3000, help="samples of the Python paths (default 3000)")
    ap.add_argument("--repeats", type=int, default=3, help="best of this many (default 3)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    a = parse_args(argv)
    with C.make_tempdir("hilbench-bench-step-cache-") as cache:
        C.use_private_numba_cache(cache)
        result = run(a.samples, a.old_samples, a.repeats)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
