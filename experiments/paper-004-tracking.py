"""Paper 004 (PMPI model of a piezo stack): identify the PMPI model, then track 50 + 50 sin(2 pi t - pi/2) um.

The procedure: an attenuated triangle whose amplitude falls 10 -> 2 V while its frequency rises
0.5 -> 2 Hz (9 cycles) identifies the M-play + cubic polynomial model (``pmpi``, eq. 5-7) on its first
70 %; the last 30 % validates it by MRE = max|e| / max|y| (Table 2: 0.44 %), against PI and Gu's PI
(PI + memoryless polynomial). The paper then tracks y_r = 50 + 50 sin(2 pi t - pi/2) um with the
inverse PMPI as a feed-forward compensator (``bench.track``), reported as MRE and mean |e| (Fig. 14).

``--quick``: 5 cycles of the triangle, PMPI only.

Run: ``hilbench run experiments/paper-004-tracking.py --rig piezo-pmpi``
"""

import numpy as np

from hilbench.runners.script import Bench, current_bench

RIG = "piezo-pmpi"
bench: Bench = current_bench()  # the bench `hilbench run` gives the script (also a global named bench)

cycles = 5 if bench.quick else 9
sweep = bench.sweep(f"attenuated-triangle:amplitude_start=10,amplitude_end=2,frequency_start_hz=0.5,"
                    f"frequency_end_hz=2,cycles={cycles}", "identification.h5", label="attenuated-triangle")

mre = {}
for spec in (["pmpi"] if bench.quick else ["pi", "pi+asymmetry", "pmpi"]):  # PI, Gu-PI, PMPI
    result = bench.fit(sweep, spec)
    mre[spec] = result.metrics["validation"]["mre_pct"]
    bench.log(f"{spec}: validation MRE {mre[spec]:.2f} %")
pmpi = result  # the last one fitted
eta = {p.name: p.value for p in pmpi.model.shape_params()}
etas = ", ".join(f"{k} {v:.3f}" for k, v in sorted(eta.items()) if k.startswith("eta_"))
bench.log(f"pmpi: MRE {mre['pmpi']:.2f} % (paper 004, Table 2: 0.44 %); {etas}")
model_file = pmpi.save(bench.path("pmpi.json"))
bench.report(mre_pct=mre, model=str(model_file), recording=str(sweep.file))

# Tracking (paper 004, sec. 5): y_r = 50 + 50 sin(2 pi t - pi/2) um, the inverse PMPI as feed-forward.
fs = bench.config.sample_rate_hz
t = np.arange(int((2 if bench.quick else 5) * fs)) / fs
reference_um = 50.0 + 50.0 * np.sin(2 * np.pi * t - np.pi / 2)
tracked = bench.track(reference_um, pmpi.model, output="tracking.h5")
m = tracked.metrics
bench.log(f"tracking 50 + 50 sin(2 pi t - pi/2) um with the inverse PMPI: MRE {m['mre_pct']:.3f} % "
          f"(paper 004 Fig. 14: 1.07 %), mean |e| {m['mean_abs_error']:.3f} um")
bench.report(tracking=tracked.to_json())
