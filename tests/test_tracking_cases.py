"""The randomized tracking benchmark's rigs (benchmarks/tracking_cases.py): deterministic per seed,
loadable, and within the ranges the generator promises. Fast: no sweep, no fit, no tracking."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import tracking_cases as TC

from hilbench.excitation.plan import check_plan, expand_runs, plan_from_compact
from hilbench.rig.config import load_rig


def test_fifty_drawn_rigs_load_and_respect_their_ranges(tmp_path: Path) -> None:
    families, units, polarities = set(), set(), set()
    for seed in range(50):
        text = TC.draw_rig(seed)
        assert TC.draw_rig(seed) == text, f"seed {seed}: not deterministic"
        path = tmp_path / f"rig-{seed}.toml"
        path.write_text(text, encoding="utf-8")
        rig = load_rig(path)
        fs = rig.sample_rate_hz
        assert rig.simulated and 1000.0 <= fs <= 50000.0
        act = rig.actuator
        assert act.unit in ("V", "A")
        assert act.min in (0.0, -act.max) and act.max > 0
        units.add(act.unit)
        polarities.add("bipolar" if act.min < 0 else "unipolar")
        h = rig.plant["hysteresis"]
        families.add(h["model"])
        if h["model"] in ("one-sided-play", "m-play"):
            assert act.min == 0.0, f"seed {seed}: {h['model']} is driven unipolar"
        dyn = rig.plant["dynamics"]
        fn = dyn["natural_frequency_hz"]
        assert 100.0 <= fn <= 5000.0 and fn < fs / 2, f"seed {seed}: fn {fn} Hz at fs {fs} Hz"
        for channel in ("temperature", "load"):
            assert (channel in rig.plant) == (rig.sensor(channel) is not None)
        # the plan is the rig's own characterisation sweep and passes the limit checks
        runs = expand_runs(rig.plan, file=str(path))
        totals = check_plan(runs, act, fs)
        assert 5000 <= totals["samples"] <= 150000, f"seed {seed}: {totals['samples']} samples"
        d = TC.draw(seed)
        assert max(d.drive_hz) <= min(fn / 4.0, fs / 40.0) * 1.001
        refs = TC.references(d, -1.0, 9.0)
        assert [r["kind"] for r in refs] == [*TC.REFERENCE_KINDS, "beyond-reach"]
        for r in refs[:-1]:
            assert r["reachable"] and -1.0 - 1e-9 <= r["low"] < r["high"] <= 9.0 + 1e-9
            assert 0.4 <= (r["high"] - r["low"]) / 10.0 <= 0.9
        assert not refs[-1]["reachable"] and refs[-1]["high"] - refs[-1]["low"] == 20.0
        for r in refs:  # the compact forms track() reads, within the share drawn
            x = plan_from_compact([r["compact"]])[0].excitation.generate(fs)
            assert r["low"] - 1e-4 <= x.min() and x.max() <= r["high"] + 1e-4, f"seed {seed}: {r['compact']}"
    assert families == {"play", "one-sided-play", "m-play", "duhem"}
    assert units == {"V", "A"} and polarities == {"bipolar", "unipolar"}


def test_the_quasi_static_range_lies_inside_what_a_sweep_records(tmp_path: Path) -> None:
    """The references' range is what the plant holds on a slow full-range triangle: inside the range
    the rig's sweep records (which also holds the overshoot where fast runs start) give or take the
    sensor's noise (a lightly damped rig's sweep overshoots to twice it), and far wider than the noise."""
    import numpy as np

    from hilbench.recording.hdf5 import Recording
    from hilbench.rig.rig import Rig
    from hilbench.runners.sweep import run_plan

    for seed in (0, 2, 5):
        d = TC.draw(seed)
        path = tmp_path / f"rig-{seed}.toml"
        path.write_text(d.toml, encoding="utf-8")
        rig = load_rig(path)
        with Rig(rig) as opened:
            run_plan(opened, expand_runs(rig.plan, file=str(path)), tmp_path / f"sweep-{seed}.h5")
        y = np.concatenate([run.channel("output") for run in Recording(tmp_path / f"sweep-{seed}.h5")])
        lo, hi = float(np.nanmin(y)), float(np.nanmax(y))
        q_lo, q_hi = TC.quasi_static_range(str(path), d)
        assert q_lo < q_hi
        slack = 3.0 * d.noise_std_um
        assert lo - slack <= q_lo and q_hi <= hi + slack, f"seed {seed}: [{q_lo}, {q_hi}] in [{lo}, {hi}]"
        assert q_hi - q_lo >= 20.0 * d.noise_std_um, f"seed {seed}: [{q_lo}, {q_hi}]"
