"""Paper 002 (Gu 2016), sec. 3.2-3.3: identify MPI hysteresis + second-order dynamics of a GMA.

The procedure:

1. the small step of the linear identification (0.726 A, ``plans/paper-002-linear-identification.toml``):
   K, zeta and omega_n from its overshoot and peak time (eq. 9-10; :func:`hilbench.identify.step_response`);
2. the amplitude-decreasing 1 Hz sine (6.5 -> 0.5 A, sec. 3.2.2) identifies the MPI weights with the
   dynamics of step 1 fixed (``mpi+dynamics(natural_frequency_hz=...,zeta=...)+delay``);
3. validation on the runs of Fig. 10-11 (``plans/paper-002-validation.toml``): 2.5-4 A at 1 Hz and
   3 A at 10-100 Hz; the paper reports a maximum error below 2.5 % of the output range.

Shortened for a run under a minute: 9 cycles of the decreasing sine (as the paper), 2 cycles per
validation sine (the paper shows 3), 40 operators; ``--quick``: 5 cycles, 1 Hz sines at 2.5 and 4 A
and 3 A at 10 and 100 Hz, 20 operators.

Run: ``hilbench run experiments/paper-002-identification.py --rig gmm-gu2016``
"""

import numpy as np

from hilbench.identify import step_response
from hilbench.runners.script import Bench, current_bench

RIG = "gmm-gu2016"
bench: Bench = current_bench()  # the bench `hilbench run` gives the script (also a global named bench)

# 1. the step (sec. 3.2.1)
step = bench.sweep({"kind": "step", "levels": [0.0, 0.726, 0.0], "hold_s": [0.005, 0.02, 0.02], "rise_s": 0.00005},
                   "identification.h5", label="step")
run = bench.runs(step)[-1]
t = np.arange(len(run)) / run.sample_rate_hz
identified = step_response(t, run.output, u_step=0.726, u=run.input)
fn, zeta = identified.natural_frequency_hz, identified.zeta
bench.log(f"step: K {identified.gain:.3f} um/A, fn {fn:.0f} Hz (eq. 11: 3200), zeta {zeta:.3f} (0.28), "
          f"overshoot {identified.overshoot_pct:.1f} %")

# 2. the amplitude-decreasing sine (sec. 3.2.2), into the same recording: the actuator's memory carries over
cycles = 5 if bench.quick else 9
bench.sweep(f"ramped-sine:amplitude_start=6.5,amplitude_end=0.5,frequency_hz=1,cycles={cycles}",
            "identification.h5", label="ramped-sine")

# 3. validation runs (Fig. 10-11)
if bench.quick:
    validation = ["sine:amplitude=2.5|4,frequency_hz=1,cycles=2", "sine:amplitude=3,frequency_hz=10|100,cycles=3"]
else:
    validation = ["sine:amplitude=2.5|3|3.5|4,frequency_hz=1,cycles=2", "sine:amplitude=3,frequency_hz=10|50|100,cycles=3"]
bench.sweep(bench.plan(*validation), "identification.h5")

n = 20 if bench.quick else 40
spec = f"mpi(n={n})+dynamics(natural_frequency_hz={fn:.1f},zeta={zeta:.4f})+delay"
result = bench.fit(step.file, spec, train=["step", "ramped-sine"])
errors = {r.data.name: r.metrics["validation"]["e_rel_pct"] for r in result.runs if r.role == "validation"}
for name, e in errors.items():
    bench.log(f"  {name}: max error {e:.2f} % of the range")
worst = max(errors.values())
bench.log(f"{spec}: worst validation error {worst:.2f} % of the range (paper 002: < 2.5 %)")
bench.report(step=identified.to_table(), spec=spec, max_error_pct=worst, errors_pct=errors,
             recording=str(step.file))
result.save(bench.path("mpi-dynamics.json"))
