"""Speed of ``hilbench.diagnosis.diagnose.diagnose`` on a 200k-sample recording with every candidate effect testable.

    python benchmarks/bench_diagnosis.py                     # full size: 2 runs x 10^5 samples at 1 kHz
    python benchmarks/bench_diagnosis.py --samples 20000     # quick
    python benchmarks/bench_diagnosis.py --profile           # add a cProfile of diagnose(path, "pi")
    python benchmarks/bench_diagnosis.py --jobs 4            # worker processes of the timed run

Prints one JSON document on stdout; progress on stderr. Never fails on timing (``meets_target``).
Each diagnosis runs twice: in one process (``jobs=1``, where the per-candidate fit times are taken)
and with ``jobs`` worker processes (default one per core), whose document must equal the first;
where ``jobs`` is 1 (one core), the first run is both.

The recording: a simulated rig (PI with 3 play operators, 1 kHz, sensor noise 0.01 um) with hidden
creep, asymmetry and a temperature effect; the temperature sensor follows a slow sine (30 +- 5 degC,
period 60 s). The input repeats 1 s holds at random levels (steps into and out of them) and whole
sines at 1, 3 and 7 Hz, so every candidate of ``diagnose`` is testable: asymmetry, saturation,
rate-dependence (both forms), dynamics, creep, delay and the ``temperature`` channel.

Per-candidate fit times come from wrapping ``hilbench.diagnosis.diagnose.fit`` (the module attribute the
diagnosis calls) with a timer for the duration of the call; hilbench itself is not changed.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

FS = 1000.0
TARGET_S = 20.0  # issue 11: diagnosis of 2*10^5 samples with all effects
TARGET_AUTO_S = 120.0  # issue 11: --auto
RIG = """
[rig]
name = "bench-diagnosis"
description = "benchmark rig for diagnose(): PI + hidden creep, asymmetry and temperature"
sample_rate_hz = 1000.0
seed = 7

[actuator]
driver = "sim"
unit = "V"
min = -10.0
max = 10.0
max_rate = 100000.0
rest = 0.0

[[sensors]]
channel = "output"
unit = "um"
driver = "sim"
noise_std = 0.01

[[sensors]]
channel = "temperature"
unit = "degC"
driver = "sim"
noise_std = 0.01

[plant.hysteresis]
model = "play"
linear_gain = 1.0
thresholds = [0.5, 1.0, 2.0]
weights = [0.5, 0.3, 0.2]

[plant.creep]
gains = [0.1]
time_constants_s = [0.5]

[plant.asymmetry]
coefficients = [0.0, 0.0, 0.05, 0.01]

[plant.temperature]
reference_degC = 25.0
gain_per_degC = 0.02
strain_um_per_degC = 0.5
trajectory = { kind = "sine", mean = 30.0, amplitude = 5.0, period_s = 60.0 }
"""


def excitation(n: int, seed: int) -> np.ndarray:
    """n samples: 1 s holds at random levels between whole sines at 1, 3 and 7 Hz (amplitudes 3-6 V)."""
    rng = np.random.default_rng(seed)
    parts: list[np.ndarray] = []
    total = 0
    while total < n:
        for f in rng.permutation([1.0, 3.0, 7.0]):
            t = np.arange(int(FS * max(1.0, 2.0 / f))) / FS
            parts.append(np.full(int(FS), rng.uniform(-6, 6)))
            parts.append(rng.uniform(3, 6) * np.sin(2 * np.pi * f * t))
            total += parts[-1].size + parts[-2].size
    return np.concatenate(parts)[:n]


def make_recording(folder: Path, samples: int, runs: int = 2) -> Path:
    from hilbench.rig.config import load_rig
    from hilbench.recording.hdf5 import RecordingWriter
    from hilbench.sim.plant import Plant

    rig = folder / "bench-diagnosis.toml"
    rig.write_text(textwrap.dedent(RIG), encoding="utf-8")
    plant = Plant.from_rig(load_rig(rig))
    out = folder / "bench-diagnosis.h5"
    writer = RecordingWriter(out)
    units = {"time": "s", "input": "V", "output": "um", "temperature": "degC"}
    per_run = samples // runs
    for k in range(runs):
        n = per_run if k < runs - 1 else samples - per_run * (runs - 1)
        u = excitation(n, k)
        plant.reset()
        sim = plant.simulate(u)
        data = {"time": np.arange(u.size) / FS, "input": u, "output": sim.output, **sim.aux}
        writer.write_run(f"run{k}", data, units, experiment="bench", excitation="{}", sample_rate_hz=FS)
    return out


class FitTimer:
    """Wraps ``fit`` where the diagnosis refits candidates (``hilbench.diagnosis.refit``) for the duration of a ``with`` block; records (spec, seconds)."""

    def __init__(self) -> None:
        self.calls: list[dict[str, Any]] = []

    def __enter__(self) -> FitTimer:
        import hilbench.diagnosis.refit as D

        self._mod, self._orig = D, D.fit

        def timed(paths: Any, spec: str, **kw: Any) -> Any:
            t0 = time.perf_counter()
            res = self._orig(paths, spec, **kw)
            self.calls.append({"spec": spec, "seconds": time.perf_counter() - t0})
            return res

        D.fit = timed
        return self

    def __exit__(self, *exc: Any) -> None:
        self._mod.fit = self._orig

    @property
    def total(self) -> float:
        return float(sum(c["seconds"] for c in self.calls))


def _cprofile(fn: Any, top: int = 25) -> list[dict[str, Any]]:
    prof = cProfile.Profile()
    prof.enable()
    fn()
    prof.disable()
    st = pstats.Stats(prof, stream=io.StringIO())
    rows = []
    for (file, line, name), (cc, nc, tt, ct, _) in st.stats.items():  # type: ignore[attr-defined]
        rows.append({"function": f"{Path(file).name}:{line}:{name}", "calls": nc, "own_s": tt, "cumulative_s": ct})
    by_own = sorted(rows, key=lambda r: -r["own_s"])[:top]
    by_cum = sorted(rows, key=lambda r: -r["cumulative_s"])[:top]
    return [{"by_own_time": by_own}, {"by_cumulative_time": by_cum}]


def _same(a: Any, b: Any) -> bool:
    """The two diagnoses' JSON documents are equal (the result may not depend on ``jobs``)."""
    return json.dumps(a.to_json(), sort_keys=True) == json.dumps(b.to_json(), sort_keys=True)


def _run(folder: Path, samples: int, profile: bool, auto: bool, jobs: int) -> dict[str, Any]:
    from hilbench.diagnosis.diagnose import diagnose
    from hilbench.identify.fitting import fit

    C.note(f"bench_diagnosis: writing a {samples}-sample recording")
    t0 = time.perf_counter()
    path = make_recording(folder, samples)
    record_s = time.perf_counter() - t0

    # warm-up: numba compile / cache load of the kernels the fits use, on a small recording
    C.note("bench_diagnosis: warm-up (numba compile or cache load) on a 4000-sample recording")
    warm = folder / "warm"
    warm.mkdir()
    t0 = time.perf_counter()
    diagnose(make_recording(warm, 4000), "pi")
    warmup_s = time.perf_counter() - t0

    # one process first: the per-candidate fit times are measured in it (worker processes keep
    # their own timers); then the same diagnosis with `jobs` worker processes, whose result must
    # be the same document
    C.note("bench_diagnosis: diagnose(path, 'pi', jobs=1)")
    with FitTimer() as timer:
        t0 = time.perf_counter()
        d = diagnose(path, "pi", jobs=1)
        serial_s = time.perf_counter() - t0
    if jobs > 1:
        C.note(f"bench_diagnosis: diagnose(path, 'pi', jobs={jobs})")
        t0 = time.perf_counter()
        dp = diagnose(path, "pi", jobs=jobs)
        seconds = time.perf_counter() - t0
    else:  # one process is all there is (one core): the run with `jobs` is the one above
        dp, seconds = d, serial_s
    # calls: fit_or_evaluate's own fit is not through diagnosis.fit; the base is reused (refitted),
    # so every timed call is a candidate refit
    per_effect = []
    calls = list(timer.calls)
    for c in d.effects:
        from hilbench.diagnosis.refit import effect_specs  # the specs the candidate was tried as

        specs = effect_specs(d.spec, c.effect)
        mine = [x for x in calls if x["spec"] in specs]
        per_effect.append({"effect": c.effect, "specs_fitted": [x["spec"] for x in mine],
                           "fit_s": float(sum(x["seconds"] for x in mine)), "significant": c.significant,
                           "expected_gain": c.expected_gain})
    per_effect.sort(key=lambda r: -r["fit_s"])
    base_t0 = time.perf_counter()
    fit(path, "pi")
    base_fit_s = time.perf_counter() - base_t0
    result: dict[str, Any] = {
        "seconds": seconds,
        "jobs": jobs,
        "seconds_one_process": serial_s,
        "same_result_as_one_process": _same(d, dp),
        "candidates_tested": len(d.effects),
        "fits_of_candidates": len(calls),
        "candidate_fits_s": timer.total,
        "base_fit_s_separately": base_fit_s,
        # one process: base fit, alternative bases, residual statistics, where(), explanations
        "rest_s": serial_s - timer.total,
        "per_candidate": per_effect,
        "untestable": d.untestable,
        "significant": [c.effect for c in d.effects if c.significant],
        "validation_rmse_um": d.metrics["validation"]["rmse"],
    }
    out: dict[str, Any] = {
        "environment": C.environment(),
        "recording": {"samples": samples, "runs": 2, "sample_rate_hz": FS, "write_s": record_s,
                      "hidden_effects": ["creep", "asymmetry", "temperature"],
                      "excitation": "1 s holds at random levels between whole sines at 1, 3, 7 Hz"},
        "warmup_s": warmup_s,
        "all_candidates": result,
    }
    if auto:
        C.note("bench_diagnosis: diagnose(path, 'pi', auto=True, jobs=1)")
        with FitTimer() as timer:
            t0 = time.perf_counter()
            da = diagnose(path, "pi", auto=True, jobs=1)
            auto_serial_s = time.perf_counter() - t0
        if jobs > 1:
            C.note(f"bench_diagnosis: diagnose(path, 'pi', auto=True, jobs={jobs})")
            t0 = time.perf_counter()
            dap = diagnose(path, "pi", auto=True, jobs=jobs)
            auto_s = time.perf_counter() - t0
        else:
            dap, auto_s = da, auto_serial_s
        out["auto"] = {
            "seconds": auto_s,
            "jobs": jobs,
            "seconds_one_process": auto_serial_s,
            "same_result_as_one_process": _same(da, dap),
            "rounds": len(da.rounds),
            "steps": [{"spec": s["spec"], "added": s["added"], "validation_rmse": s["validation"].get("rmse")}
                      for s in da.steps],
            "fits": len(timer.calls) + 1,  # + the start fit (fit_or_evaluate)
            "fits_s": timer.total,
            "slowest_fits": sorted(timer.calls, key=lambda c: -c["seconds"])[:5],
            "final_spec": da.spec,
        }
    out["meets_target"] = {f"diagnose_under_{TARGET_S:g}s": seconds <= TARGET_S}
    if auto:
        out["meets_target"][f"auto_under_{TARGET_AUTO_S:g}s"] = out["auto"]["seconds"] < TARGET_AUTO_S
    if profile or seconds >= TARGET_S:
        C.note("bench_diagnosis: cProfile of diagnose(path, 'pi')")
        out["profile"] = _cprofile(lambda: diagnose(path, "pi", jobs=1))  # workers escape cProfile
    out["summary"] = {"diagnose_s": seconds, "jobs": jobs, "diagnose_one_process_s": serial_s,
                      "candidates": len(d.effects), "fits": len(calls),
                      "slowest_candidate": per_effect[0] if per_effect else None,
                      "auto_s": out.get("auto", {}).get("seconds"),
                      "auto_one_process_s": out.get("auto", {}).get("seconds_one_process")}
    return out


def run(samples: int = 200_000, profile: bool = False, auto: bool = True,
        workdir: str | Path | None = None, jobs: int | None = None) -> dict[str, Any]:
    from hilbench.diagnosis.workers import default_jobs

    tmp = C.make_tempdir("hilbench-bench-diagnosis-")
    if workdir is None:
        workdir = tmp.name
    C.use_private_numba_cache(workdir)
    try:
        return _run(Path(tmp.name), samples, profile, auto, jobs or default_jobs())
    finally:
        tmp.cleanup()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="speed of hilbench diagnose on a 200k-sample recording")
    ap.add_argument("--samples", type=int, default=200_000, help="total samples of the recording (2 runs)")
    ap.add_argument("--profile", action="store_true", help="add a cProfile of diagnose (always when > 30 s)")
    ap.add_argument("--no-auto", action="store_true", help="skip diagnose(..., auto=True)")
    ap.add_argument("--jobs", type=int, default=None, help="worker processes of the timed diagnosis (default: one per core)")
    a = ap.parse_args(argv)
    print(json.dumps(run(a.samples, a.profile, not a.no_auto, jobs=a.jobs), indent=2))


if __name__ == "__main__":
    main()
