"""Paper 003 (rate-dependent PI of a piezo stack): sines of 10-1500 Hz, rate-dependent vs rate-independent PI.

The procedure: unipolar sines of 50 V amplitude around 70 V (20-120 V) at 10-1500 Hz; the asymmetric
one-sided PI with the frequency-dependent damping of eq. 8-13
(``pi1+asymmetry+rate-dependence(form=frequency)``) is fitted on the first 70 % of every run and
judged on the last 30 % by e_max = max|e| / (max y - min y) and e_rms = rms e / (max y - min y) (Fig. 8:
e_max <= 6.5 %, e_rms <= 3 %); the rate-independent PI fitted at 10 Hz alone shows why the rate matters.

Shortened: 7 of the paper's frequencies, 10 cycles each but 2 cycles at 10 Hz (the rig samples at
50 kHz: 10 cycles at 10 Hz alone are 50 000 samples); ``--quick``: 10, 200 and 1500 Hz, 4 cycles.

Run: ``hilbench run experiments/paper-003-frequency-sweep.py --rig piezo-rate-pi``
"""

from hilbench.runners.script import Bench, current_bench

RIG = "piezo-rate-pi"
bench: Bench = current_bench()  # the bench `hilbench run` gives the script (also a global named bench)

frequencies = [10, 200, 1500] if bench.quick else [10, 50, 100, 200, 400, 800, 1500]
cycles = 4 if bench.quick else 10
runs = [f"sine:amplitude=50,offset=70,phase_deg=-90,cycles={2 if f == 10 else cycles},frequency_hz={f}"
        for f in frequencies]
sweep = bench.sweep(bench.plan(*runs), "frequency-sweep.h5", label="sine")

rate_dependent = bench.fit(sweep, "pi1+asymmetry+rate-dependence(form=frequency)")
rate_independent = bench.fit(sweep, "pi1+asymmetry", train=["1"])  # the 10 Hz run alone trains

table = {}
for f, rd, ri in zip(frequencies, rate_dependent.runs, rate_independent.runs):
    v = rd.metrics["validation"]
    ri_metrics = ri.metrics["validation"] or ri.metrics["train"]
    table[f"{f} Hz"] = {"e_max_pct": v["e_rel_pct"], "e_rms_pct": v["erms_pct"],
                        "rate_independent_e_max_pct": ri_metrics["e_rel_pct"]}
    bench.log(f"{f:5d} Hz: e_max {v['e_rel_pct']:.2f} %, e_rms {v['erms_pct']:.2f} % "
              f"(rate-independent PI from 10 Hz: e_max {ri_metrics['e_rel_pct']:.1f} %)")
worst_max = max(row["e_max_pct"] for row in table.values())
worst_rms = max(row["e_rms_pct"] for row in table.values())
bench.log(f"rate-dependent PI: e_max <= {worst_max:.2f} %, e_rms <= {worst_rms:.2f} % (paper 003, Fig. 8: 6.5 %, 3 %)")
bench.report(frequencies_hz=frequencies, errors=table, worst_e_max_pct=worst_max, worst_e_rms_pct=worst_rms,
             recording=str(sweep.file))
rate_dependent.save(bench.path("rate-dependent-pi.json"))
