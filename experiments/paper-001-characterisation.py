"""Paper 001 (ISSF-Duhem), sec. 3.1: characterise a Terfenol-D actuator, fit the D-model, report E_relative.

The procedure: 1 Hz sines of 1-6 A (Fig. 5) and the triangle of decreasing amplitude 6..1 A (Fig. 6);
the dead-zone ISSF-Duhem model (``duhem-d``) is fitted on the 2-5 A sines and judged on the triangle,
which it never saw, by E_relative = max|e| / (max y - min y) (eq. 23; Table 2 reports 1.53 %).

Run: ``hilbench run experiments/paper-001-characterisation.py --rig gmm-issf-duhem``
(``--quick``: 2 cycles per sine instead of 3, the triangle kept whole).
"""

from hilbench.runners.script import Bench, current_bench

RIG = "gmm-issf-duhem"
bench: Bench = current_bench()  # the bench `hilbench run` gives the script (also a global named bench)

cycles = 2 if bench.quick else 3
plan = bench.plan(
    f"sine:amplitude=1|2|3|4|5|6,frequency_hz=1,cycles={cycles}",  # Fig. 5
    "triangle:frequency_hz=1,amplitudes=6/5/4/3/2/1",  # Fig. 6
)
sweep = bench.sweep(plan, "characterisation.h5")

# Train on the 2-5 A sines (the paper's identification range), validate on the triangle.
train = [f"sine-amplitude={a}" for a in (2, 3, 4, 5)]
result = bench.fit(sweep, "duhem-d", train=train, test=["triangle"])
triangle = next(r for r in result.runs if r.data.name.endswith("triangle"))
e_rel = triangle.metrics["validation"]["e_rel_pct"]
alpha = result.model.base.param("alpha")

bench.log(f"duhem-d on the triangle: E_relative {e_rel:.3f} % (paper 001, Table 2: 1.53 %); alpha {alpha:.3f} (Table 1: 0.575)")
bench.report(e_relative_pct=e_rel, alpha=alpha, recording=str(sweep.file),
             train_rmse_um=result.metrics["train"]["rmse"], validation_rmse_um=result.metrics["validation"]["rmse"])
result.save(bench.path("duhem-d.json"))
