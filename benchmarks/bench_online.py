"""Speed of the online identifier (hilbench.online) against padasip's RLS.

Measured in one run:

* **RLS alone** (8 parameters, a random stable ARX(4, 4) with white input and 0.01 output noise,
  2*10^5 samples, lambda = 0.999, P0 = 1e3 I): ``hilbench.online.rls.RLS.run`` (block mode, numba)
  against ``padasip.filters.FilterRLS.run`` (the same recursion in numpy, one sample per Python
  iteration). hilbench is timed twice: configured as padasip's textbook RLS (exponential
  forgetting, no guards, no covariance cap) and with its defaults (directional forgetting, Huber
  outlier weighting, trace cap). Both estimators' final parameter errors are reported, and the
  a-priori predictions of the textbook configuration are compared with padasip's over the first
  10^4 samples (same recursion: they agree to rounding before the naive update drifts).
* **OIIR chain** of paper 000 (FPMPI with 10 one-sided play operators and the 8-term fractional
  polynomial of the gmm-fpmpi rig, M = 3, N = 5, so 9 weights, RLS every sample): block mode
  (``OIIR.run``, 10^6 samples) and step mode called from Python (``OIIR.step``, 2*10^4 samples),
  per-sample cost in ns / us.

Prints one JSON document on stdout; progress on stderr. Never fails on timing.

    python benchmarks/bench_online.py [--samples 200000] [--oiir-samples 1000000] [--step-samples 20000]

padasip is an optional dependency: ``pip install hilbench[bench]``; without it the peer is reported
as unavailable.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

TARGET_RATIO_VS_PADASIP = 100.0
N_A, N_B = 4, 4
LAMBDA = 0.999
DELTA = 1.0e3
FS_OIIR = 1000.0

# gmm-fpmpi rig (paper 000 Table 3): fractional polynomial and one-sided play operators
IN_EXP = [0.0, 1.0, 2.0, 0.5, 3.0, 1.0 / 3.0, 4.0, 0.25]
IN_W = [0.0057, 0.4640, 0.2343, -1.0113, 0.5568, 0.7493, -0.9740, 0.4889]
OP_R = [0.0000, 0.0669, 0.1338, 0.2007, 0.2676, 0.3345, 0.4014, 0.4683, 0.5352, 0.6021]
OP_W = [0.3955, 0.2042, 0.4940, 0.3927, 0.7198, 0.1228, 0.1889, 0.1550, 0.2058, -0.0060]


def arx_problem(n: int, seed: int = C.SEED) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """theta_true (8,), regressors (n, 8) = [y(k-1..k-4), u(k..k-3)], outputs (n,)."""
    from scipy import signal as sps

    rng = np.random.default_rng(seed)
    mags = rng.uniform(0.3, 0.9, N_A // 2)
    angles = rng.uniform(0.1, math.pi - 0.1, N_A // 2)
    poles = np.concatenate([mags * np.exp(1j * angles), mags * np.exp(-1j * angles)])
    den = np.real(np.poly(poles))
    b = rng.uniform(-1.0, 1.0, N_B)
    u = rng.standard_normal(n)
    y = sps.lfilter(b, den, u) + sps.lfilter([1.0], den, 0.01 * rng.standard_normal(n))
    phi = np.zeros((n, N_A + N_B))
    for j in range(N_A):
        phi[j + 1 :, j] = y[: n - j - 1]
    for i in range(N_B):
        phi[i:, N_A + i] = u[: n - i]
    return np.concatenate([-den[1:], b]), phi, y


def bench_rls(samples: int, repeats: int) -> dict[str, Any]:
    from hilbench.online.rls import RLS

    theta_true, phi, y = arx_problem(samples)
    n_par = theta_true.size
    textbook = dict(lam=LAMBDA, delta=DELTA, forgetting="exponential", outlier="off", trace_max=math.inf,
                    forget_threshold=0.0)
    out: dict[str, Any] = {"parameters": n_par, "samples": samples, "lambda": LAMBDA, "P0": f"{DELTA:g} I",
                           "data": "random stable ARX(4, 4), white unit input, output noise std 0.01"}
    for label, options in (("hilbench_textbook", textbook), ("hilbench_default", dict(lam=LAMBDA, delta=DELTA))):
        rls = RLS(n_par, **options)
        C.note(f"[online] {label}: warm-up (numba compile) ...")
        rls.run(phi[:1000], y[:1000])
        best, times = C.best_of(repeats, lambda: rls.run(phi, y, decimate=1), setup=rls.reset)
        rls.reset()
        y_hat, hist = rls.run(phi, y)
        out[label] = {
            "what": f"RLS({n_par}, {', '.join(f'{k}={v!r}' for k, v in options.items())}).run(Phi, Y), "
                    "theta history of every sample recorded",
            "best_s": best,
            "times_s": times,
            "samples_per_s": samples / best,
            "ns_per_sample": 1e9 * best / samples,
            "final_parameter_error_max_abs": float(np.max(np.abs(rls.theta - theta_true))),
            "all_finite": bool(np.all(np.isfinite(hist)) and np.all(np.isfinite(rls.P))),
            "counters": rls.counters(),
        }
        if label == "hilbench_textbook":
            y_hat_textbook = y_hat
    try:
        from padasip.filters import FilterRLS
    except ImportError:
        out["padasip"] = {"available": False, "note": "pip install hilbench[bench] (padasip>=1.2)"}
        return out
    import padasip

    def padasip_run() -> tuple[np.ndarray, np.ndarray]:
        f = FilterRLS(n_par, mu=LAMBDA, eps=1.0 / DELTA, w="zeros")
        y_p, _, w_hist = f.run(y, phi)
        return y_p, np.vstack([w_hist[1:], f.w[None, :]])  # w_history holds w before each update

    C.note(f"[online] padasip FilterRLS, {samples:.3g} samples x {repeats} ...")
    results: list[tuple[np.ndarray, np.ndarray]] = []
    best, times = C.best_of(repeats, lambda: results.append(padasip_run()))
    y_p, w_p = results[-1]
    m = min(10_000, samples)
    agree = float(np.max(np.abs(y_p[:m] - y_hat_textbook[:m])))
    out["padasip"] = {
        "available": True,
        "version": getattr(padasip, "__version__", None) or _dist_version("padasip"),
        "what": f"FilterRLS(n={n_par}, mu={LAMBDA}, eps={1.0 / DELTA:g}).run(d, x)",
        "best_s": best,
        "times_s": times,
        "samples_per_s": samples / best,
        "us_per_sample": 1e6 * best / samples,
        "final_parameter_error_max_abs": float(np.max(np.abs(w_p[-1] - theta_true)))
        if np.all(np.isfinite(w_p[-1])) else None,
        "all_finite": bool(np.all(np.isfinite(w_p))),
        "max_abs_diff_y_hat_vs_hilbench_textbook_first_samples": agree,
        "compared_samples": m,
    }
    out["ratio_vs_padasip"] = {
        "textbook": out["hilbench_textbook"]["samples_per_s"] / out["padasip"]["samples_per_s"],
        "default": out["hilbench_default"]["samples_per_s"] / out["padasip"]["samples_per_s"],
        "note": "hilbench block-mode samples/s over padasip's samples/s, same data and parameter count",
    }
    return out


def _dist_version(name: str) -> str | None:
    try:
        from importlib.metadata import version

        return version(name)
    except Exception:  # noqa: BLE001
        return None


def oiir_data(n: int) -> tuple[Any, np.ndarray, np.ndarray]:
    """Front end with the rig's FPMPI, a 4 Hz 0-2.5 A drive, the output through 40 Hz dynamics."""
    from scipy import signal as sps

    from hilbench.online.oiir import FPMPIFrontEnd

    fe = FPMPIFrontEnd(3.0, np.array(IN_EXP), np.array(IN_W), np.array(OP_R), 37.0 * np.array(OP_W))
    t = np.arange(n) / FS_OIIR
    u = 1.25 - 1.25 * np.cos(2 * np.pi * 4.0 * t)
    wn = 2 * math.pi * 40.0
    bd, ad, _ = sps.cont2discrete(([wn**2], [1.0, 2 * 0.6 * wn, wn**2]), 1.0 / FS_OIIR, method="zoh")
    u_r = fe.simulate(u)
    y = sps.lfilter(np.ravel(bd), np.ravel(ad), np.concatenate([[0.0], u_r[:-1]]))
    y += 0.03 * np.random.default_rng(C.SEED).standard_normal(n)
    return fe, u, y


def bench_oiir(samples: int, step_samples: int, repeats: int) -> dict[str, Any]:
    from hilbench.online.oiir import OIIR, re_n2_pct

    fe, u, y = oiir_data(samples)
    oiir = OIIR(fe, M=3, N=5, lam=0.995)
    C.note("[online] OIIR: warm-up (numba compile) ...")
    oiir.run(u[:1000], y[:1000])
    oiir.step(float(u[0]), float(y[0]))
    C.note(f"[online] OIIR block mode, {samples:.3g} samples x {repeats} ...")
    block_best, block_times = C.best_of(repeats, lambda: oiir.run(u, y, decimate=10), setup=oiir.reset)
    oiir.reset()
    res = oiir.run(u, y)
    u_list, y_list = u[:step_samples].tolist(), y[:step_samples].tolist()

    def steps() -> None:
        step = oiir.step
        for uk, yk in zip(u_list, y_list):
            step(uk, yk)

    C.note(f"[online] OIIR step mode, {step_samples:.3g} samples x {repeats} ...")
    step_best, step_times = C.best_of(repeats, steps, setup=oiir.reset)
    return {
        "chain": "FPMPI (8-term fractional polynomial, 10 one-sided play operators) -> regressor shift "
                 "-> RLS update of 9 OIIR weights (M = 3, N = 5), per sample",
        "block_mode": {
            "what": "OIIR.run(u, y, decimate=10) on one array",
            "samples": samples,
            "best_s": block_best,
            "times_s": block_times,
            "samples_per_s": samples / block_best,
            "ns_per_sample": 1e9 * block_best / samples,
        },
        "step_mode": {
            "what": "OIIR.step(u, y) called once per sample from Python",
            "samples": step_samples,
            "best_s": step_best,
            "times_s": step_times,
            "samples_per_s": step_samples / step_best,
            "us_per_sample": 1e6 * step_best / step_samples,
        },
        "online_re_n2_pct": re_n2_pct(y, res["y_m"]),
    }


def run(samples: int = 200_000, oiir_samples: int = 1_000_000, step_samples: int = 20_000, repeats: int = 3,
        workdir: str | Path | None = None) -> dict[str, Any]:
    tmp = None
    if workdir is None:
        tmp = C.make_tempdir("hilbench-bench-online-")
        workdir = tmp.name
    C.use_private_numba_cache(workdir)
    try:
        rls = bench_rls(samples, repeats)
        oiir = bench_oiir(oiir_samples, step_samples, repeats)
    finally:
        if tmp is not None:
            tmp.cleanup()
    ratio = rls.get("ratio_vs_padasip", {}).get("textbook")
    return {
        "benchmark": "online",
        "environment": C.environment(),
        "rls": rls,
        "oiir": oiir,
        "targets": {"ratio_vs_padasip_min": TARGET_RATIO_VS_PADASIP},
        "meets_target": {"ratio_vs_padasip": None if ratio is None else bool(ratio >= TARGET_RATIO_VS_PADASIP)},
    }


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=200_000, help="RLS samples (default 2*10^5)")
    ap.add_argument("--oiir-samples", type=int, default=1_000_000, help="OIIR block-mode samples (default 10^6)")
    ap.add_argument("--step-samples", type=int, default=20_000, help="OIIR step-mode samples (default 2*10^4)")
    ap.add_argument("--repeats", type=int, default=3, help="best of this many (default 3)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    a = parse_args(argv)
    print(json.dumps(run(a.samples, a.oiir_samples, a.step_samples, a.repeats), indent=2))


if __name__ == "__main__":
    main()
