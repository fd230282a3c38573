"""Identification speed and error: hilbench's separable least squares against a global optimizer.

Three measurements, in one run:

1. ``pi_weight_fit``: ``fit_model(Model("pi"), ...)`` with 10 play operators on 2*10^5 samples of the
   benchmark rig (``_common.py``: a PI plant, 20 kHz). PI has no shape parameters, so this is the
   operator columns plus the exact bounded weight solve. Best of 3 after a warm-up. Peer, same run:
   ``scipy.optimize.lsq_linear`` (bvls) on hilbench's own design matrix (the solve alone).
   Target < 0.3 s.
2. ``pmpi``: ``fit_model(Model("pmpi"), ...)`` on 10^5 samples of the piezo-pmpi rig (paper 004),
   trained on the first 70 %, validated on the last 30 %, against
   ``scipy.optimize.differential_evolution`` over ALL the paper's PMPI parameters at once (the NM-DE
   identification of 004 without its simplex step): p0, alpha1 and alpha2 of p(r_i) = alpha1
   exp(-alpha2 r_i), eta_1..eta_10, a1, a2, a3, with the thresholds r_i = 0..9 V of Table 4 fixed. The
   DE objective is the free-run simulation SSE on the same training rows, computed by one fused numba
   loop (about 1 ms per evaluation on 7*10^4 samples).
3. ``duhem_d``: ``fit_model(Model("duhem-d"), ...)`` on the gmm-issf-duhem rig (paper 001): trained
   on the 1 Hz sines of 2, 3, 4, 5 A recorded in sequence, validated on the 6..1 A triangle recorded
   after them (memory carried between runs: ``chain=True``, ``simulate_runs``), against
   differential evolution over the paper's 10 D-model parameters (k1, k2, alpha, beta, mu5..mu10,
   n = 6, eq. 17 and 26-31, eq. 31 read with |i| as configs/gmm-issf-duhem.toml says), again with a
   fused numba forward model.

DE settings: popsize 15, polish=False, workers=1, a fixed seed, ``maxiter`` large; it stops at its
own convergence test (scipy's default tol) or when its wall time reaches ``de_budget_ratio`` (default
20) times hilbench's fit time, whichever comes first. The DE run "with the same wall time as
hilbench" is the same seeded run read at the last generation completed within hilbench's fit time
(DE with a fixed seed is deterministic, so that is exactly what a separate run stopped then gives).

The hilbench fits are measured twice: in this process (BLAS with its default threads), and again on the
same seeded data in a child process with one BLAS thread (``OPENBLAS_NUM_THREADS=1``), the setting DE
with workers=1 runs in; on a busy machine the two differ several-fold (see README.md).

Target (issue): hilbench at least 10x faster than DE at equal or lower validation error.
Prints one JSON document on stdout; progress on stderr. Never fails on timing.

    python benchmarks/bench_identification.py [--pi-samples 200000] [--pmpi-samples 100000]
        [--duhem-cycles 3] [--de-budget-ratio 20] [--repeats 3] [--seed 1]
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

TARGET_PI_FIT_S = 0.3
TARGET_SPEEDUP = 10.0
#: "equal" validation error: hilbench's rmse within this relative margin of DE's counts as equal
EQUAL_ERROR_REL = 0.01

PMPI_THRESHOLDS_V = [float(k) for k in range(10)]  # 004 Table 4: r_i = 0..9 V
PMPI_TRUTH = {  # configs/piezo-pmpi.toml (004 Table 4), for the record only: the search never sees it
    "p0": 4.770, "alpha1": 6.904, "alpha2": 0.517,
    **{f"eta_{i + 1}": e for i, e in enumerate([0.849, 0.043, 0.276, 0.376, 0.336, 0.443, 0.561, 0.335, 0.158, 0.040])},
    "a1": 0.037, "a2": -0.647, "a3": 0.0,
}
PMPI_BOUNDS = {"p0": (0.0, 10.0), "alpha1": (0.0, 20.0), "alpha2": (0.0, 2.0),
               **{f"eta_{i + 1}": (-0.99, 1.5) for i in range(10)},
               "a1": (-1.0, 1.0), "a2": (-5.0, 5.0), "a3": (-10.0, 10.0)}

DUHEM_N = 6  # dead-zone operators per side, fixed as in 001 Table 1
DUHEM_TRUTH = {"k1": 2.979, "k2": 0.778, "alpha": 0.575, "beta": 1.859, "mu5": 0.452, "mu6": 2.378,
               "mu7": 0.098, "mu8": 0.587, "mu9": 3.997, "mu10": 0.214}  # configs/gmm-issf-duhem.toml
DUHEM_BOUNDS = {"k1": (0.0, 10.0), "k2": (0.0, 5.0), "alpha": (0.01, 5.0), "beta": (0.01, 10.0),
                "mu5": (0.01, 2.0), "mu6": (0.0, 10.0), "mu7": (0.0, 1.0), "mu8": (0.01, 2.0),
                "mu9": (0.0, 10.0), "mu10": (0.0, 1.0)}

_KERNELS: dict[str, Any] = {}


def peer_kernels() -> dict[str, Any]:
    """The DE peer's fused numba forward models (compiled on first use, after the cache is set up)."""
    if _KERNELS:
        return _KERNELS
    from numba import njit

    @njit(cache=False)
    def pmpi_forward(u, r, p, out, y, n_fit):  # noqa: ANN001, ANN202
        """004 eq. 5-7: p0 u + sum_i alpha1 exp(-alpha2 r_i) F_{r_i,eta_i}(u) + a1 u^3 + a2 u^2 + a3.

        p = [p0, alpha1, alpha2, eta_1..eta_n, a1, a2, a3]; operators start at 0 (eq. 5). Writes the
        output into ``out`` when it has n samples, returns the SSE against ``y`` over the first n_fit.
        """
        n_ops = r.shape[0]
        p0 = p[0]
        al1 = p[1]
        al2 = p[2]
        a1 = p[3 + n_ops]
        a2 = p[4 + n_ops]
        a3 = p[5 + n_ops]
        w = np.empty(n_ops)
        er = np.empty(n_ops)
        st = np.zeros(n_ops)
        for i in range(n_ops):
            w[i] = al1 * math.exp(-al2 * r[i])
            er[i] = p[3 + i] * r[i]
        write = out.shape[0] == u.shape[0]
        n = u.shape[0] if write else n_fit
        sse = 0.0
        for k in range(n):
            x = u[k]
            h = p0 * x + (a1 * x + a2) * x * x + a3
            for i in range(n_ops):
                o = min(x + er[i], st[i])
                o = max(x - r[i], o)
                st[i] = o
                h += w[i] * o
            if write:
                out[k] = h
            if k < n_fit:
                e = h - y[k]
                sse += e * e
        return sse

    @njit(cache=False)
    def dmodel_forward(u, p, nd, out, y, n_fit):  # noqa: ANN001, ANN202
        """001 eq. 17, 26-31: w' = alpha |u'| (beta/alpha u - w), y = k1 u + k2 sum_i g_i Gamma_ri(w).

        p = [k1, k2, alpha, beta, mu5..mu10]; r_i = mu5 i, g_i = -mu6 exp(-mu7 i) for i = 0..n;
        r_i = mu8 i, g_i = mu9 exp(-mu10 |i|) for i = -n..-1. w is integrated exactly for an input
        linear between samples, from w = 0 (the rig starts at rest, u = 0).
        """
        k1 = p[0]
        k2 = p[1]
        alpha = p[2]
        beta = p[3]
        m = 2 * nd + 1
        r = np.empty(m)
        g = np.empty(m)
        for j in range(m):
            i = j - nd
            if i >= 0:
                r[j] = p[4] * i
                g[j] = -p[5] * math.exp(-p[6] * i)
            else:
                r[j] = p[7] * i
                g[j] = p[8] * math.exp(-p[9] * (-i))
        ba = beta / alpha
        w = 0.0
        u_prev = u[0]
        write = out.shape[0] == u.shape[0]
        n = u.shape[0] if write else n_fit
        sse = 0.0
        for k in range(n):
            du = u[k] - u_prev
            if du != 0.0:
                s = 1.0 if du > 0.0 else -1.0
                w = ba * u[k] - s * ba / alpha + (w - (ba * u_prev - s * ba / alpha)) * math.exp(-alpha * abs(du))
            u_prev = u[k]
            z = 0.0
            for j in range(m):
                rj = r[j]
                if rj > 0.0:
                    z += g[j] * max(w - rj, 0.0)
                elif rj < 0.0:
                    z += g[j] * min(w - rj, 0.0)
                else:
                    z += g[j] * w
            h = k1 * u[k] + k2 * z
            if write:
                out[k] = h
            if k < n_fit:
                e = h - y[k]
                sse += e * e
        return sse

    _KERNELS.update(pmpi_forward=pmpi_forward, dmodel_forward=dmodel_forward)
    return _KERNELS


# -- data from the simulated rigs ---------------------------------------------------------------------


def record(rig: Any, excitation: Any) -> tuple[np.ndarray, np.ndarray]:
    """One run through the rig's command path: (applied input, measured output)."""
    u = excitation.generate(rig.sample_rate_hz)
    rig.start_run(float(u[0]))
    applied = rig.apply(u)
    return applied, rig.measure(applied)["output"]


def compact_run(spec: str) -> Any:
    from hilbench.excitation.plan import plan_from_compact

    return plan_from_compact([spec])[0].excitation


def pmpi_data(samples: int) -> dict[str, Any]:
    """``samples`` of the piezo-pmpi rig under 004's frequency-converting attenuated triangle (Fig. 15),
    with as many cycles as it takes (10 -> 2 V peaks, 0.5 -> 2 Hz)."""
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig

    cfg = load_rig("piezo-pmpi")
    rig = Rig(cfg)
    fs = cfg.sample_rate_hz
    cycles = 9
    while True:
        spec = (f"attenuated-triangle:amplitude_start=10,amplitude_end=2,frequency_start_hz=0.5,"
                f"frequency_end_hz=2,cycles={cycles}")
        exc = compact_run(spec)
        if exc.n_samples(fs) >= samples:
            break
        cycles = max(cycles + 1, int(cycles * samples / exc.n_samples(fs)) + 1)
    u, y = record(rig, exc)
    return {"rig": "piezo-pmpi", "excitation": spec, "sample_rate_hz": fs, "u": u[:samples], "y": y[:samples]}


def duhem_data(cycles: float) -> dict[str, Any]:
    """001 sec. 3.1 on the gmm-issf-duhem rig: 1 Hz sines of 2, 3, 4, 5 A, then the 6..1 A triangle,
    recorded one after the other on the same rig (the actuator's memory carries over)."""
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig

    cfg = load_rig("gmm-issf-duhem")
    rig = Rig(cfg)
    fs = cfg.sample_rate_hz
    specs = [f"sine:amplitude={a},frequency_hz=1,cycles={cycles:g}" for a in (2, 3, 4, 5)]
    specs.append("triangle:frequency_hz=1,amplitudes=6/5/4/3/2/1")
    runs = []
    for spec in specs:
        u, y = record(rig, compact_run(spec))
        runs.append((spec, u, y))
    # The DE peer simulates the runs as one concatenated record: that is only the rig's history if no
    # unrecorded ramp lay between them (each run ends where the next begins: at 0 A).
    gaps = [abs(float(runs[i][1][-1]) - float(runs[i + 1][1][0])) for i in range(len(runs) - 1)]
    return {"rig": "gmm-issf-duhem", "runs": runs, "sample_rate_hz": fs, "max_gap_between_runs_A": max(gaps)}


# -- helpers --------------------------------------------------------------------------------------------


def fmetrics(y: np.ndarray, yhat: np.ndarray) -> dict[str, float]:
    from hilbench.identify.metrics import metrics

    return metrics(y, yhat)


class DERecorder:
    """Callback of differential_evolution: best-so-far per generation, stop at the wall-time budget."""

    def __init__(self, budget_s: float, n_fit: int):
        self.t0 = time.perf_counter()
        self.budget_s = budget_s
        self.n_fit = n_fit
        self.history: list[tuple[float, float, np.ndarray]] = []  # (seconds, best sse, best x)
        self.stopped_by_budget = False

    def __call__(self, intermediate_result: Any) -> bool:  # scipy >= 1.12 passes an OptimizeResult
        t = time.perf_counter() - self.t0
        self.history.append((t, float(intermediate_result.fun), np.array(intermediate_result.x)))
        if len(self.history) % 100 == 0:
            C.note(f"    DE generation {len(self.history)}: {t:.1f} s, train rmse "
                   f"{math.sqrt(intermediate_result.fun / self.n_fit):.4g} um")
        if t >= self.budget_s:
            self.stopped_by_budget = True
            return True
        return False

    def at_time(self, seconds: float) -> tuple[float, float, np.ndarray] | None:
        """The last generation finished within ``seconds`` of the start."""
        best = None
        for entry in self.history:
            if entry[0] <= seconds:
                best = entry
        return best

    def first_reaching(self, sse: float) -> float | None:
        return next((t for t, f, _ in self.history if f <= sse), None)


def run_de(objective: Any, bounds: list[tuple[float, float]], budget_s: float, n_fit: int, seed: int,
           popsize: int = 15) -> tuple[Any, DERecorder, float]:
    from scipy.optimize import differential_evolution

    recorder = DERecorder(budget_s, n_fit)
    res = differential_evolution(objective, bounds, popsize=popsize, maxiter=1_000_000, polish=False, seed=seed,
                                 workers=1, updating="immediate", callback=recorder)
    seconds = time.perf_counter() - recorder.t0
    return res, recorder, seconds


def comparison(hil: dict[str, Any], de: dict[str, Any], de_same: dict[str, Any] | None, de_rec: DERecorder,
               n_fit: int, single: dict[str, Any] | None = None) -> dict[str, Any]:
    ratio = de["seconds"] / hil["seconds"]
    single_ok = bool(single) and "seconds" in single
    ratio_1 = de["seconds"] / single["seconds"] if single_ok else None  # type: ignore[index]
    h_val, d_val = hil["validation_rmse_um"], de["validation_rmse_um"]
    match_sse = n_fit * (hil["train_rmse_um"] * (1 + EQUAL_ERROR_REL)) ** 2
    t_match = de_rec.first_reaching(match_sse)
    t_match_strict = de_rec.first_reaching(n_fit * hil["train_rmse_um"] ** 2)
    return {
        "ratio_de_over_hilbench_seconds": ratio,
        "ratio_de_over_hilbench_blas_1_thread_seconds": ratio_1,
        "hilbench_validation_rmse_over_de": h_val / d_val if d_val > 0 else float("inf"),
        "de_seconds_to_reach_hilbench_train_rmse_plus_1pct": t_match,
        "ratio_time_to_match": (t_match / hil["seconds"]) if t_match is not None else None,
        "de_seconds_to_reach_hilbench_train_rmse": t_match_strict,
        "same_wall_time_validation_rmse_um": {
            "hilbench": h_val, "de": de_same["validation_rmse_um"] if de_same else None},
        "meets_target": {
            "faster_10x": bool(ratio >= TARGET_SPEEDUP),
            "equal_or_lower_error": bool(h_val <= d_val * (1 + EQUAL_ERROR_REL)),
            "strictly_lower_error": bool(h_val < d_val),
            "faster_10x_blas_1_thread": bool(ratio_1 is not None and ratio_1 >= TARGET_SPEEDUP),
            "equal_or_lower_error_blas_1_thread": bool(
                single_ok and single["validation_rmse_um"] <= d_val * (1 + EQUAL_ERROR_REL)),  # type: ignore[index]
        },
        "note": "ratio = DE wall time (to its convergence or its budget) / hilbench fit time; the "
                "*_blas_1_thread figures use the fit time of the same fit in a child process with one BLAS "
                "thread (DE runs on one core: workers=1); "
                "equal_or_lower_error compares validation rmse, 'equal' = within 1 %; "
                "ratio_time_to_match = DE time until its best training rmse first came within 1 % of "
                "hilbench's / hilbench time (null: never within the DE run)",
    }


# -- 1. PI weight fit ----------------------------------------------------------------------------------


def pi_data(workdir: Path, samples: int) -> dict[str, Any]:
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig

    cfg = load_rig(C.write_rig(workdir))
    rig = Rig(cfg)
    fs = cfg.sample_rate_hz
    spec = f"ramped-sine:amplitude_start=1.5,amplitude_end=0.2,frequency_hz=2,duration_s={samples / fs:g}"
    u, y = record(rig, compact_run(spec))
    return {"excitation": spec, "sample_rate_hz": fs, "u": u[:samples], "y": y[:samples]}


def n_play_operators(model: Any) -> int:
    """Play operators proper: thresholds > 0 (the r = 0 operator is the input itself, the linear term)."""
    return int(np.count_nonzero(np.asarray(model.base.constants["thresholds"], float) > 0))


def hilbench_pi(data: dict[str, Any], repeats: int) -> tuple[dict[str, Any], Any, Any]:
    from hilbench.identify import fit_model
    from hilbench.models import Model, RunData

    u, y, fs = data["u"], data["y"], data["sample_rate_hz"]
    samples = u.shape[0]
    run = RunData(u, y, {}, fs)
    mask = np.ones(samples, dtype=bool)
    C.note("[identification] PI weight fit: warm-up ...")
    t0 = time.perf_counter()
    probe = Model("pi")
    fit_model(probe, [RunData(u[:2000], y[:2000], {}, fs)], [mask[:2000]])
    warmup_s = time.perf_counter() - t0
    # 10 play operators (thresholds > 0) besides the linear term, as the issue asks
    n = len(probe.base.constants["thresholds"]) + (10 - n_play_operators(probe))
    spec = "pi" if n == len(probe.base.constants["thresholds"]) else f"pi(n={n})"
    holder: dict[str, Any] = {}

    def fit() -> None:
        m = Model(spec)
        holder["report"] = fit_model(m, [run], [mask])
        holder["model"] = m

    C.note(f"[identification] PI weight fit ({spec}), {samples:.3g} samples x {repeats} ...")
    best, times = C.best_of(repeats, fit)
    m, report = holder["model"], holder["report"]
    result = {
        "spec": spec,
        "samples": samples,
        "n_play_operators": n_play_operators(m),
        "n_weights": len(m.weight_names),
        "weight_names": m.weight_names,
        "warmup_s": warmup_s,
        "best_s": best,
        "times_s": times,
        "train_rmse_um": report.rmse,
    }
    return result, m, run


def bench_pi_fit(data: dict[str, Any], repeats: int) -> dict[str, Any]:
    from scipy import optimize

    hil, m, run = hilbench_pi(data, repeats)
    y = data["y"]
    # Peer: scipy's bounded least squares on the same design matrix (the solve alone).
    t0 = time.perf_counter()
    A, names, lower, upper = m.design(run)
    design_s = time.perf_counter() - t0
    holder: dict[str, Any] = {}

    def peer() -> None:
        holder["x"] = optimize.lsq_linear(A, y, bounds=(lower, upper), method="bvls", tol=1e-12).x

    C.note("[identification] PI weight fit: peer scipy lsq_linear ...")
    peer_best, peer_times = C.best_of(repeats, peer)
    peer_rmse = float(np.sqrt(np.mean((A @ holder["x"] - y) ** 2)))
    return {
        "what": "fit_model(Model(spec), [run], [all rows]) from a fresh Model: operator columns + exact "
                "bounded weight solve (pi has no shape parameters); best of repeats after a warm-up",
        "rig": "benchmark rig of _common.py (PI, 10 play operators, 2nd-order dynamics 500 Hz, 20 kHz)",
        "excitation": data["excitation"],
        **hil,
        "peer_scipy_lsq_linear": {
            "what": "scipy.optimize.lsq_linear(A, y, bounds, method='bvls') on hilbench's design matrix "
                    "(the weight solve alone; building A took design_s)",
            "design_s": design_s,
            "best_s": peer_best,
            "times_s": peer_times,
            "train_rmse_um": peer_rmse,
            "hilbench_fit_ratio": peer_best / hil["best_s"],
        },
        "target_s": TARGET_PI_FIT_S,
        "meets_target": bool(hil["best_s"] < TARGET_PI_FIT_S),
    }


# -- 2. PMPI -------------------------------------------------------------------------------------------------


def pmpi_split(data: dict[str, Any]) -> tuple[int, np.ndarray]:
    n = data["u"].shape[0]
    n_fit = int(0.7 * n)
    mask = np.zeros(n, dtype=bool)
    mask[:n_fit] = True
    return n_fit, mask


def hilbench_pmpi(data: dict[str, Any]) -> dict[str, Any]:
    from hilbench.identify import fit_model
    from hilbench.models import Model, RunData

    u, y, fs = data["u"], data["y"], data["sample_rate_hz"]
    n_fit, mask = pmpi_split(data)
    run = RunData(u, y, {}, fs)
    C.note("[identification] PMPI: hilbench warm-up ...")
    t0 = time.perf_counter()
    fit_model(Model("pmpi"), [RunData(u[:2000], y[:2000], {}, fs)], [mask[:2000]])
    warmup_s = time.perf_counter() - t0
    C.note(f"[identification] PMPI: hilbench fit_model on {n_fit} training samples ...")
    m = Model("pmpi")
    t0 = time.perf_counter()
    report = fit_model(m, [run], [mask])
    seconds = time.perf_counter() - t0
    yh = m.simulate(run)
    val = fmetrics(y[n_fit:], yh[n_fit:])
    hil = {
        "seconds": seconds,
        "warmup_s": warmup_s,
        "evaluations": report.evaluations,
        "train_rmse_um": fmetrics(y[:n_fit], yh[:n_fit])["rmse"],
        "validation_rmse_um": val["rmse"],
        "validation_mre_pct": val["mre_pct"],
        "validation": val,
        "shape": report.theta,
        "weights": dict(zip(m.weight_names, map(float, m.weights))),
        "normalisation": m.norm,
    }
    C.note(f"[identification] PMPI: hilbench {seconds:.2f} s, train rmse {hil['train_rmse_um']:.4g} um, "
           f"validation rmse {hil['validation_rmse_um']:.4g} um")
    return hil


def bench_pmpi(data: dict[str, Any], budget_ratio: float, seed: int,
               single_thread: dict[str, Any] | None) -> dict[str, Any]:
    K = peer_kernels()
    u, y, fs = data["u"], data["y"], data["sample_rate_hz"]
    n = u.shape[0]
    n_fit, _ = pmpi_split(data)
    hil = hilbench_pmpi(data)
    hil_s = hil["seconds"]

    # -- DE over all the paper's parameters -------------------------------------------------------
    r = np.asarray(PMPI_THRESHOLDS_V)
    u_all = np.ascontiguousarray(u)
    u_fit = np.ascontiguousarray(u[:n_fit])
    y_fit = np.ascontiguousarray(y[:n_fit])
    no_out = np.empty(0)
    names = list(PMPI_BOUNDS)
    bounds = [PMPI_BOUNDS[k] for k in names]
    truth = np.array([PMPI_TRUTH[k] for k in names])

    def objective(p: np.ndarray) -> float:
        return K["pmpi_forward"](u_fit, r, p, no_out, y_fit, n_fit)

    t0 = time.perf_counter()
    objective(truth)  # compile
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(20):
        objective(truth)
    eval_ms = (time.perf_counter() - t0) / 20 * 1e3
    truth_train_rmse = math.sqrt(objective(truth) / n_fit)

    def simulate(p: np.ndarray) -> np.ndarray:
        out = np.empty(n)
        K["pmpi_forward"](u_all, r, p, out, y, 0)
        return out

    def evaluate(p: np.ndarray) -> dict[str, Any]:
        out = simulate(p)
        val = fmetrics(y[n_fit:], out[n_fit:])
        return {"train_rmse_um": fmetrics(y[:n_fit], out[:n_fit])["rmse"], "validation_rmse_um": val["rmse"],
                "validation_mre_pct": val["mre_pct"]}

    budget = budget_ratio * hil_s
    C.note(f"[identification] PMPI: differential evolution, {len(names)} parameters, budget {budget:.0f} s ...")
    res, rec, de_s = run_de(objective, bounds, budget, n_fit, seed)
    de = {
        "seconds": de_s,
        "stop": "budget" if rec.stopped_by_budget else ("converged" if res.success else str(res.message)),
        "message": str(res.message),
        "generations": int(res.nit),
        "evaluations": int(res.nfev),
        "ms_per_evaluation": eval_ms,
        "compile_s": compile_s,
        **evaluate(res.x),
        "validation": fmetrics(y[n_fit:], simulate(res.x)[n_fit:]),
        "parameters": dict(zip(names, map(float, res.x))),
    }
    snap = rec.at_time(hil_s)
    de_same = None
    if snap is not None:
        de_same = {"seconds": snap[0], "generation": rec.history.index(snap) + 1, **evaluate(snap[2])}
    C.note(f"[identification] PMPI: DE {de_s:.1f} s ({de['stop']}), train rmse {de['train_rmse_um']:.4g} um, "
           f"validation rmse {de['validation_rmse_um']:.4g} um")
    return {
        "data": {"rig": data["rig"], "excitation": data["excitation"], "sample_rate_hz": fs, "samples": n,
                 "train": f"first 70 % ({n_fit} samples)", "validation": f"last 30 % ({n - n_fit} samples)"},
        "hilbench": {"what": "fit_model(Model('pmpi'), [run], [first 70 %]) from a fresh Model after a warm-up",
                     **hil},
        "hilbench_blas_1_thread": single_thread,
        "de": {"what": "scipy.optimize.differential_evolution over all PMPI parameters of 004 eq. 7 with "
                       "p(r_i) = alpha1 exp(-alpha2 r_i), r_i = 0..9 V fixed; objective = free-run SSE on the "
                       "training rows, fused numba loop",
               "settings": {"popsize": 15, "population": 15 * len(names), "polish": False, "workers": 1,
                            "seed": seed, "updating": "immediate", "tol": "scipy default (0.01)",
                            "budget_s": budget, "budget_ratio": budget_ratio},
               "bounds": dict(zip(names, bounds)),
               **de,
               "truth": dict(zip(names, truth.tolist())),
               "truth_train_rmse_um": truth_train_rmse},
        "de_same_wall_time": de_same,
        **comparison(hil, de, de_same, rec, n_fit, single_thread),
    }


# -- 3. D-model ------------------------------------------------------------------------------------------------


def duhem_runs(data: dict[str, Any]) -> tuple[list[Any], list[np.ndarray], int]:
    from hilbench.models import RunData

    fs = data["sample_rate_hz"]
    runs = [RunData(u, y, {}, fs, name=spec, chain=i > 0) for i, (spec, u, y) in enumerate(data["runs"])]
    masks = [np.full(len(r), i < len(runs) - 1) for i, r in enumerate(runs)]
    n_fit = sum(len(r) for r in runs[:-1])
    return runs, masks, n_fit


def hilbench_duhem(data: dict[str, Any]) -> dict[str, Any]:
    from hilbench.identify import fit_model
    from hilbench.models import Model, RunData

    fs = data["sample_rate_hz"]
    runs, masks, n_fit = duhem_runs(data)
    y_all = np.concatenate([r.output for r in runs])
    C.note("[identification] D-model: hilbench warm-up ...")
    t0 = time.perf_counter()
    short = RunData(runs[0].input[:500], runs[0].output[:500], {}, fs)
    fit_model(Model("duhem-d"), [short], [np.ones(500, dtype=bool)])
    warmup_s = time.perf_counter() - t0
    C.note(f"[identification] D-model: hilbench fit_model on {n_fit} training samples ...")
    m = Model("duhem-d")
    t0 = time.perf_counter()
    report = fit_model(m, runs, masks)
    seconds = time.perf_counter() - t0
    yh = np.concatenate(m.simulate_runs(runs))
    val = fmetrics(y_all[n_fit:], yh[n_fit:])
    hil = {
        "seconds": seconds,
        "warmup_s": warmup_s,
        "evaluations": report.evaluations,
        "train_rmse_um": fmetrics(y_all[:n_fit], yh[:n_fit])["rmse"],
        "validation_rmse_um": val["rmse"],
        "validation_e_rel_pct": val["e_rel_pct"],
        "validation": val,
        "shape": report.theta,
        "weights": dict(zip(m.weight_names, map(float, m.weights))),
    }
    C.note(f"[identification] D-model: hilbench {seconds:.2f} s, train rmse {hil['train_rmse_um']:.4g} um, "
           f"validation rmse {hil['validation_rmse_um']:.4g} um")
    return hil


def duhem_identifiable(de: dict[str, float], shape: dict[str, float], weights: dict[str, float]) -> dict[str, Any]:
    """Parameter error on what the data determine.

    The D-model's parameters are not identifiable one by one: scaling beta scales w, so mu5 and mu8
    (thresholds on w) and k2 mu6, k2 mu9 (weights) follow it. What is identifiable: alpha, k1, the
    threshold spacings on the scale of u, mu5 alpha / beta and mu8 alpha / beta (hilbench searches
    exactly these: spacing_pos, spacing_neg), and the decay rates mu7, mu10.
    """
    t = DUHEM_TRUTH

    def combos(p: dict[str, float]) -> dict[str, float]:
        return {"alpha": p["alpha"], "k1": p["k1"], "mu5_alpha_over_beta": p["mu5"] * p["alpha"] / p["beta"],
                "mu8_alpha_over_beta": p["mu8"] * p["alpha"] / p["beta"], "mu7": p["mu7"], "mu10": p["mu10"]}

    truth, found = combos(t), combos(de)
    out: dict[str, Any] = {"truth": truth, "de": found,
                           "de_rel_error": {k: abs(found[k] - truth[k]) / abs(truth[k]) for k in truth}}
    hil = {"alpha": shape.get("alpha"), "k1": weights.get("k1*u"), "mu5_alpha_over_beta": shape.get("spacing_pos"),
           "mu8_alpha_over_beta": shape.get("spacing_neg")}
    if all(v is not None for v in hil.values()):
        out["hilbench"] = hil
        out["hilbench_rel_error"] = {k: abs(v - truth[k]) / abs(truth[k]) for k, v in hil.items()}
    return out


def bench_duhem(data: dict[str, Any], budget_ratio: float, seed: int,
                single_thread: dict[str, Any] | None) -> dict[str, Any]:
    K = peer_kernels()
    fs = data["sample_rate_hz"]
    raw = data["runs"]
    runs, masks, n_fit = duhem_runs(data)
    u_all = np.ascontiguousarray(np.concatenate([r.input for r in runs]))
    y_all = np.concatenate([r.output for r in runs])
    y_train, y_val = y_all[:n_fit], y_all[n_fit:]
    hil = hilbench_duhem(data)
    hil_s = hil["seconds"]

    # -- DE over the paper's 10 parameters -------------------------------------------------------
    names = list(DUHEM_BOUNDS)
    bounds = [DUHEM_BOUNDS[k] for k in names]
    truth = np.array([DUHEM_TRUTH[k] for k in names])
    u_fit = np.ascontiguousarray(u_all[:n_fit])
    y_fit = np.ascontiguousarray(y_train)
    no_out = np.empty(0)

    def objective(p: np.ndarray) -> float:
        return K["dmodel_forward"](u_fit, p, DUHEM_N, no_out, y_fit, n_fit)

    t0 = time.perf_counter()
    objective(truth)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(50):
        objective(truth)
    eval_ms = (time.perf_counter() - t0) / 50 * 1e3
    truth_train_rmse = math.sqrt(objective(truth) / n_fit)

    def simulate(p: np.ndarray) -> np.ndarray:
        out = np.empty(u_all.shape[0])
        K["dmodel_forward"](u_all, p, DUHEM_N, out, y_all, 0)
        return out

    def evaluate(p: np.ndarray) -> dict[str, Any]:
        out = simulate(p)
        val = fmetrics(y_val, out[n_fit:])
        return {"train_rmse_um": fmetrics(y_train, out[:n_fit])["rmse"], "validation_rmse_um": val["rmse"],
                "validation_e_rel_pct": val["e_rel_pct"]}

    budget = budget_ratio * hil_s
    C.note(f"[identification] D-model: differential evolution, {len(names)} parameters, budget {budget:.0f} s ...")
    res, rec, de_s = run_de(objective, bounds, budget, n_fit, seed)
    de = {
        "seconds": de_s,
        "stop": "budget" if rec.stopped_by_budget else ("converged" if res.success else str(res.message)),
        "message": str(res.message),
        "generations": int(res.nit),
        "evaluations": int(res.nfev),
        "ms_per_evaluation": eval_ms,
        "compile_s": compile_s,
        **evaluate(res.x),
        "validation": fmetrics(y_val, simulate(res.x)[n_fit:]),
        "parameters": dict(zip(names, map(float, res.x))),
    }
    de["identifiable"] = duhem_identifiable(de["parameters"], hil["shape"], hil["weights"])
    snap = rec.at_time(hil_s)
    de_same = None
    if snap is not None:
        de_same = {"seconds": snap[0], "generation": rec.history.index(snap) + 1, **evaluate(snap[2])}
    C.note(f"[identification] D-model: DE {de_s:.1f} s ({de['stop']}), train rmse {de['train_rmse_um']:.4g} um, "
           f"validation rmse {de['validation_rmse_um']:.4g} um")
    return {
        "data": {"rig": data["rig"], "sample_rate_hz": fs,
                 "train": [spec for spec, _, _ in raw[:-1]], "validation": raw[-1][0],
                 "train_samples": n_fit, "validation_samples": int(u_all.shape[0] - n_fit),
                 "recorded": "in sequence on one rig; memory carried (chain=True, Model.simulate_runs)",
                 "max_gap_between_runs_A": data["max_gap_between_runs_A"]},
        "hilbench": {"what": "fit_model(Model('duhem-d'), runs, masks) from a fresh Model after a warm-up; "
                             "searches alpha and the two threshold spacings, the 2n+3 weights are exact",
                     **hil},
        "hilbench_blas_1_thread": single_thread,
        "de": {"what": "scipy.optimize.differential_evolution over the 10 D-model parameters of 001 "
                       "(n = 6 fixed); objective = free-run SSE over the chained training runs, fused numba loop",
               "settings": {"popsize": 15, "population": 15 * len(names), "polish": False, "workers": 1,
                            "seed": seed, "updating": "immediate", "tol": "scipy default (0.01)",
                            "budget_s": budget, "budget_ratio": budget_ratio},
               "bounds": dict(zip(names, bounds)),
               **de,
               "truth": dict(zip(names, truth.tolist())),
               "truth_train_rmse_um": truth_train_rmse},
        "de_same_wall_time": de_same,
        **comparison(hil, de, de_same, rec, n_fit, single_thread),
    }


# -- hilbench with one BLAS thread (child process) ---------------------------------------------------------

SINGLE_THREAD_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def hilbench_only(workdir: Path, pi_samples: int, pmpi_samples: int, duhem_cycles: float,
                  repeats: int) -> dict[str, Any]:
    """The hilbench fits alone, on the same (seeded, so identical) data: run in the child process."""
    pi, _, _ = hilbench_pi(pi_data(workdir, pi_samples), repeats)
    return {"pi": pi, "pmpi": hilbench_pmpi(pmpi_data(pmpi_samples)),
            "duhem_d": hilbench_duhem(duhem_data(duhem_cycles))}


def single_thread_fits(workdir: Path, pi_samples: int, pmpi_samples: int, duhem_cycles: float,
                       repeats: int) -> dict[str, Any]:
    """Run the hilbench fits in a child process whose BLAS has one thread (set before numpy loads).

    On a busy 2-core machine OpenBLAS's worker threads wait for a core at every call on the small
    matrices of a fit; with one thread the fit uses one core, as the DE peer (workers=1) does.
    """
    import os
    import subprocess

    env = {**os.environ, **SINGLE_THREAD_ENV}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--hilbench-only", "--workdir", str(workdir),
           "--pi-samples", str(pi_samples), "--pmpi-samples", str(pmpi_samples),
           "--duhem-cycles", repr(duhem_cycles), "--repeats", str(repeats)]
    C.note("[identification] hilbench fits again in a child process with one BLAS thread ...")
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        C.note(f"[identification] single-thread child failed:\n{proc.stderr[-2000:]}")
        return {"error": proc.stderr[-2000:]}
    for line in proc.stderr.splitlines():
        C.note("    child: " + line.strip())
    return {**json.loads(proc.stdout), "env": SINGLE_THREAD_ENV}


# -- the benchmark ---------------------------------------------------------------------------------------------


def run(pi_samples: int = 200_000, pmpi_samples: int = 100_000, duhem_cycles: float = 3.0,
        de_budget_ratio: float = 20.0, repeats: int = 3, seed: int = 1, single_thread: bool = True,
        workdir: str | Path | None = None) -> dict[str, Any]:
    tmp = None
    if workdir is None:
        tmp = C.make_tempdir("hilbench-bench-identification-")
        workdir = tmp.name
    C.use_private_numba_cache(workdir)
    try:
        return _run(pi_samples, pmpi_samples, duhem_cycles, de_budget_ratio, repeats, seed, single_thread,
                    Path(workdir))
    finally:
        if tmp is not None:
            tmp.cleanup()


def _pair(part: dict[str, Any]) -> dict[str, Any]:
    single = part.get("hilbench_blas_1_thread") or {}
    return {
        "hilbench_s": part["hilbench"]["seconds"],
        "hilbench_blas_1_thread_s": single.get("seconds"),
        "de_s": part["de"]["seconds"],
        "de_stop": part["de"]["stop"],
        "ratio": part["ratio_de_over_hilbench_seconds"],
        "ratio_blas_1_thread": part["ratio_de_over_hilbench_blas_1_thread_seconds"],
        "hilbench_train_rmse_um": part["hilbench"]["train_rmse_um"],
        "de_train_rmse_um": part["de"]["train_rmse_um"],
        "hilbench_validation_rmse_um": part["hilbench"]["validation_rmse_um"],
        "de_validation_rmse_um": part["de"]["validation_rmse_um"],
        "de_same_wall_time_validation_rmse_um": (part["de_same_wall_time"] or {}).get("validation_rmse_um"),
    }


def _run(pi_samples: int, pmpi_samples: int, duhem_cycles: float, de_budget_ratio: float, repeats: int,
         seed: int, single_thread: bool, workdir: Path) -> dict[str, Any]:
    import os

    load_start = os.getloadavg()
    t0 = time.perf_counter()
    pi = bench_pi_fit(pi_data(workdir, pi_samples), repeats)
    single = single_thread_fits(workdir, pi_samples, pmpi_samples, duhem_cycles, repeats) if single_thread else {}
    if single.get("pi"):
        pi["hilbench_blas_1_thread"] = {k: single["pi"][k] for k in ("best_s", "times_s", "train_rmse_um")}
    pmpi = bench_pmpi(pmpi_data(pmpi_samples), de_budget_ratio, seed, single.get("pmpi"))
    duhem = bench_duhem(duhem_data(duhem_cycles), de_budget_ratio, seed, single.get("duhem_d"))
    meets = {"pi_weight_fit": pi["meets_target"]}
    for key, part in (("pmpi", pmpi), ("duhem_d", duhem)):
        for k, v in part["meets_target"].items():
            meets[f"{key}.{k}"] = v
    env = C.environment()
    env.update({"blas_threads_env": {k: os.environ.get(k) for k in SINGLE_THREAD_ENV},
                "loadavg_at_start": list(load_start), "loadavg_at_end": list(os.getloadavg())})
    return {
        "benchmark": "identification",
        "environment": env,
        "elapsed_s": time.perf_counter() - t0,
        "pi_weight_fit": pi,
        "pmpi": pmpi,
        "duhem_d": duhem,
        "summary": {
            "pi_fit_s": pi["best_s"],
            "pi_fit_blas_1_thread_s": (pi.get("hilbench_blas_1_thread") or {}).get("best_s"),
            "pmpi": _pair(pmpi),
            "duhem_d": _pair(duhem),
        },
        "targets": {"pi_weight_fit_s_max": TARGET_PI_FIT_S, "speedup_vs_de_min": TARGET_SPEEDUP,
                    "equal_error_rel": EQUAL_ERROR_REL},
        "meets_target": meets,
    }


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pi-samples", type=int, default=200_000, help="PI weight fit samples (default 2*10^5)")
    ap.add_argument("--pmpi-samples", type=int, default=100_000, help="PMPI record length (default 10^5)")
    ap.add_argument("--duhem-cycles", type=float, default=3.0, help="cycles of each D-model training sine (default 3)")
    ap.add_argument("--de-budget-ratio", type=float, default=20.0,
                    help="DE wall-time budget as a multiple of hilbench's fit time (default 20)")
    ap.add_argument("--repeats", type=int, default=3, help="best of this many for the PI fit (default 3)")
    ap.add_argument("--seed", type=int, default=1, help="DE seed (default 1)")
    ap.add_argument("--no-single-thread", action="store_true",
                    help="skip the second measurement of the hilbench fits with one BLAS thread")
    ap.add_argument("--hilbench-only", action="store_true", help=argparse.SUPPRESS)  # the child process
    ap.add_argument("--workdir", help=argparse.SUPPRESS)
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    a = parse_args(argv)
    if a.hilbench_only:
        C.use_private_numba_cache(a.workdir)  # inherited from the parent when it set one
        result = hilbench_only(Path(a.workdir), a.pi_samples, a.pmpi_samples, a.duhem_cycles, a.repeats)
    else:
        result = run(a.pi_samples, a.pmpi_samples, a.duhem_cycles, a.de_budget_ratio, a.repeats, a.seed,
                     not a.no_single_thread)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
