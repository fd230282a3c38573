"""Randomized cases of a sharp resonance well above the drive (issue 62, part 3).

    from resonance_cases import draw_resonance_case, write_resonance_case
    case = draw_resonance_case(4)                     # deterministic per seed
    paths, kwargs = write_resonance_case(case, folder)
    diagnose(paths, case.spec, **kwargs)              # case.strength["dynamics"]: the true f_n, zeta

A bench records an actuator whose mechanics ring: a lightly damped second-order resonance after the
hysteresis, rung by every corner of a triangle drive and every step of a staircase. Each case
draws, from its seed alone:

* the **base hysteresis** and the start spec that matches it: ``play`` -> ``pi``, ``m-play`` ->
  ``pmpi`` (unipolar drive), ``duhem`` (a shape function drawn) -> ``duhem-g/-m/-d``, ``bouc-wen``
  -> ``bouc-wen`` (made here with hilbench's exact per-sample Bouc-Wen solution, n = 1: the plant
  has no Bouc-Wen model);
* the **resonance**: zeta log-uniform in [0.005, 0.1] and f_n log-uniform from a few hundred Hz to
  a few kHz, at least 30x the drive's highest frequency and at most fs / 8;
* the **sample rate**, 10-50 kHz; the **program** of each run: a rest, triangles at 1-4 drive
  frequencies (1-20 Hz), sometimes a triangle staircase, two staircases of steps (after the first
  triangles and at the end; the rig's slew limit makes each step a ramp of 0.05-0.5 ms); the command
  clamped and slew-limited as the rig does;
* the **sensor noise**, white, 0.05-0.5 % of the output span, lowered (not below 0.02 %) until the
  resonance's own contribution (output with it minus without it, less an offset and a gain of the
  latter) is at least :data:`diagnosis_cases.MIN_SNR` times the noise rms; its ratio is ``snr``;
* the **split**: one run with a training fraction, or a training and a test run.

The plant (hysteresis only) comes from ``diagnosis_cases``; the resonance is applied after it with
the same discretisation (``hilbench.sim.dynamics.discretize_dynamics``) as that generator's
output-side dynamics stage.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import diagnosis_cases as DC

FAMILIES = ("play", "m-play", "duhem", "bouc-wen")
#: the damping ratios drawn (log-uniform): the issue's "lightly damped"
ZETA_RANGE = (0.005, 0.1)
#: natural frequencies drawn (log-uniform), Hz, within [FN_OVER_DRIVE f_hi, fs / 8]
FN_RANGE = (300.0, 4000.0)
FN_OVER_DRIVE = 30.0


def _bouc_wen(u: np.ndarray, u_max: float, beta: float, gamma_over_beta: float, k: float) -> np.ndarray:
    """y = k v + z, v = u / u_max, dz = dv - beta |dv| z - gamma dv |z| (n = 1), from rest."""
    from hilbench.models import kernels as MK

    v = np.ascontiguousarray(u / u_max, dtype=float)
    z = np.empty_like(v)
    MK.bouc_wen_block(v, beta, beta * gamma_over_beta, 1.0, np.array([0.0, v[0]]), z)
    return k * v + z


def _program(rng: np.random.Generator, fs: float, samples: int, lo: float, hi: float, unipolar: bool,
             freqs: list[float]) -> list[dict[str, Any]]:
    """Rest, triangles at ``freqs`` (sometimes a triangle staircase), two step staircases; about ``samples`` long."""
    center = 0.5 * (lo + hi) if unipolar else 0.0
    half = 0.5 * (hi - lo) if unipolar else hi
    pieces: list[dict[str, Any]] = [{"kind": "hold", "level": float(lo if unipolar else 0.0),
                                     "duration_s": float(rng.uniform(0.02, 0.08))}]
    budget = samples / fs - pieces[0]["duration_s"]
    step_s = 0.25 * budget
    tri_s = budget - step_s
    kinds = ["triangle"] * len(freqs)
    if rng.random() < 0.4:
        kinds[-1] = "triangle-staircase"
    per = tri_s / len(freqs)
    order = rng.permutation(len(freqs))
    for i in order:
        f = freqs[i]
        cycles = max(1, int(per * f))
        amp = half * rng.uniform(0.6, 0.95)
        if kinds[i] == "triangle":
            pieces.append({"kind": "triangle", "frequency_hz": f, "offset": center, "amplitude": amp, "cycles": cycles})
        else:
            amps = np.linspace(amp, amp * rng.uniform(0.2, 0.5), max(cycles, 2))
            pieces.append({"kind": "triangle", "frequency_hz": f, "offset": center,
                           "amplitudes": [float(a) for a in amps]})
    # two staircases, after the first triangles and at the end: a split by time keeps steps on
    # both sides (a training part of triangles alone would hold only their weaker ringing)
    for at in (2, len(pieces) + 1):
        n = int(rng.integers(3, 6))
        levels = rng.uniform(lo + 0.05 * (hi - lo), hi - 0.05 * (hi - lo), n)
        pieces.insert(at, {"kind": "step", "levels": [float(x) for x in levels], "hold_s": 0.5 * step_s / n})
    return pieces


def _simulate(case: DC.Case, k: int, *, with_resonance: bool = True) -> np.ndarray:
    """The true output (um) of run k: the base, then the resonance when asked."""
    u = DC.command(case, k)
    if case.family == "bouc-wen":
        b = case.strength["bouc-wen"]
        y = b["output_scale"] * _bouc_wen(u, b["u_max"], b["beta"], b["gamma_over_beta"], b["k"])
    else:
        _, y, _ = DC.simulate(case, k, post=[])
    return DC._apply_post(y, case.post, case.sample_rate_hz) if with_resonance else y


def draw_resonance_case(seed: int, samples: int = 60_000) -> DC.Case:
    """A case from its seed alone (module docstring); ``samples`` over all runs, about."""
    rng = np.random.default_rng([62003, seed])
    family = str(rng.choice(FAMILIES))
    unipolar = family == "m-play"
    unit = "V" if rng.random() < 0.6 else "A"
    u_max = DC._logu(rng, 0.5, 6.0) if unit == "A" else DC._logu(rng, 5.0, 150.0)
    lo, hi = (0.0, u_max) if unipolar else (-u_max, u_max)
    fs = float(round(DC._logu(rng, 10_000.0, 50_000.0), -2))
    two_runs = rng.random() < 0.5
    n_runs = 2 if two_runs else 1
    run_samples = samples // n_runs
    f_lo = DC._logu(rng, 1.0, 5.0)
    f_hi = min(f_lo * DC._logu(rng, 2.0, 5.0), 20.0)
    freqs = sorted({f_lo, f_hi, *[DC._logu(rng, f_lo, f_hi) for _ in range(int(rng.integers(0, 3)))]})
    runs = []
    for k in range(n_runs):
        label = ["run"] if n_runs == 1 else ["train", "test"]
        runs.append({"label": label[k], "pieces": _program(rng, fs, run_samples, lo, hi, unipolar, freqs)})
    split: dict[str, Any] = ({"train": ["train"], "test": ["test"]} if two_runs else
                             {"train_fraction": float(round(rng.uniform(0.6, 0.75), 3))})
    strength: dict[str, dict[str, Any]] = {}
    if family == "bouc-wen":
        hyst: dict[str, Any] = {"model": "linear"}
        strength["bouc-wen"] = {"u_max": u_max, "beta": DC._logu(rng, 1.0, 8.0),
                                "gamma_over_beta": float(rng.uniform(-0.5, 0.8)), "k": float(rng.uniform(0.2, 1.0)),
                                "output_scale": 1.0}
        spec, note = "bouc-wen", "bouc-wen n = 1"
    else:
        hyst, spec, note = DC._base_table(rng, family, u_max)
    rise = DC._logu(rng, 5e-5, 5e-4)  # a full-range step takes 0.05-0.5 ms
    case = DC.Case(seed=seed, hidden=["dynamics"], forms={"dynamics": "sharp-resonance"}, family=family, spec=spec,
                   sample_rate_hz=fs, input_unit=unit, actuator_range=(lo, hi), max_rate=(hi - lo) / rise,
                   tables={"hysteresis": hyst}, run_tables=[{} for _ in range(n_runs)], pre=[], post=[], runs=runs,
                   split=split, noise_std_um=0.0, quantization_um=0.0, output_span_um=0.0, aux_sensors={},
                   frequencies_hz=(f_lo, f_hi), strength=strength, notes=[note])
    # the output span: 5-150 um
    y1 = _simulate(case, 0, with_resonance=False)
    span = DC._logu(rng, 5.0, 150.0)
    scale = span / (float(np.ptp(y1)) or 1.0)
    if family == "bouc-wen":
        strength["bouc-wen"]["output_scale"] = scale
    else:
        hyst["output_scale"] = hyst.get("output_scale", 1.0) * scale
    case.output_span_um = span
    fn_lo = max(FN_RANGE[0], FN_OVER_DRIVE * f_hi)
    fn_hi = max(min(FN_RANGE[1], fs / 8.0), 1.5 * fn_lo)
    fn, zeta = DC._logu(rng, fn_lo, fn_hi), DC._logu(rng, *ZETA_RANGE)
    case.post = [{"stage": "dynamics", "table": {"kind": "second-order", "natural_frequency_hz": fn, "zeta": zeta}}]
    strength["dynamics"] = {"natural_frequency_hz": fn, "zeta": zeta}
    # the sensor: noise drawn, lowered until the resonance stands MIN_SNR times above it
    y_base = np.concatenate([_simulate(case, k, with_resonance=False) for k in range(n_runs)])
    y_res = np.concatenate([_simulate(case, k) for k in range(n_runs)])
    contribution = float(np.sqrt(np.mean(DC._projection_residual(y_res - y_base, y_base) ** 2)))
    noise = DC._logu(rng, 0.0005, 0.005) * span
    noise = max(min(noise, contribution / DC.MIN_SNR), 0.0002 * span)
    case.noise_std_um = noise
    case.snr = {"dynamics": round(contribution / noise, 3)}
    return case


def write_resonance_case(case: DC.Case, folder: str | Path) -> tuple[list[Path], dict[str, Any]]:
    """Simulate every run and write one HDF5 recording; (paths, diagnose keyword arguments)."""
    return DC.write_case(case, folder, simulate_run=lambda c, k: (DC.command(c, k), _simulate(c, k), {}),
                         prefix="resonance", experiment="resonance-case")


if __name__ == "__main__":  # a quick look at some draws
    for s in range(int(sys.argv[1]) if len(sys.argv) > 1 else 10):
        c = draw_resonance_case(s)
        d = c.strength["dynamics"]
        print(s, c.family, c.spec, c.sample_rate_hz, c.frequencies_hz, len(c.runs), c.samples(),
              f"fn {d['natural_frequency_hz']:.0f} zeta {d['zeta']:.4f} snr {c.snr['dynamics']:.1f}",
              f"noise {c.noise_std_um / c.output_span_um:.5f}")
