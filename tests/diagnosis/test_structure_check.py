"""The diagnosis knows the hysteresis inside the mechanics (issue 63 item 2, decision 0103).

On a short synthetic Bouc-Wen oscillator (the benchmark's structure and nominal parameters, a
5-150 Hz multisine across its ~40 Hz resonance, 2 % noise), ``hilbench diagnose --auto`` from
``bouc-wen`` proposes and adds ``restoring-force``; on a static Bouc-Wen loop followed by the same
resonance it tries the structure and rejects it by the held-out error (dynamics is the finding);
on a drive far below the resonance the structure is not tried, and the reason says why.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from hilbench.cli import app
from hilbench.diagnosis.diagnose import diagnose
from hilbench.diagnosis.structure_check import STRUCTURE, mechanics, structure_spec
from hilbench.identify.dataset import Dataset
from hilbench.identify.fitting import fit
from hilbench.models.model import Model, RunData

FS = 750.0
#: the benchmark's nominal parameters (SOURCE.md), w-form: m, c, k, alpha, gamma = beta gamma_b, delta = beta delta_b
NOMINAL = np.array([2.0, 10.0, 5e4, 5e4, 800.0, -1100.0])
SAMPLES = 3000


def multisine(n: int, seed: int = 3, rms: float = 50.0, band: tuple[float, float] = (5.0, 150.0)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FS
    freqs = np.arange(band[0], band[1], 2.5)
    u = np.sin(2 * np.pi * freqs[:, None] * t + rng.uniform(0, 2 * np.pi, freqs.size)[:, None]).sum(axis=0)
    return rms * u / u.std()


def oscillator(u: np.ndarray) -> np.ndarray:
    """The Bouc-Wen restoring-force oscillator's displacement (m) for the force ``u`` (N)."""
    model = Model("bouc-wen+restoring-force")
    model.prepare([RunData(np.array([-1.0, 1.0]), None, {}, FS)])
    model.set_shape(NOMINAL)
    model.weights = np.zeros(0)
    return model.simulate(RunData(u, None, {}, FS))


def noisy(y: np.ndarray, seed: int = 1) -> np.ndarray:
    return y + np.random.default_rng(seed).normal(0.0, 0.02 * y.std(), y.size)


def dataset(u: np.ndarray, y: np.ndarray) -> Dataset:
    return Dataset([Path("synthetic.h5")], [RunData(u, y, {}, FS, name="synthetic")], ["synthetic"], "N", "m")


def test_the_structure_spec_keeps_a_bouc_wen_base_and_puts_another_base_s_loop_in_bouc_wen():
    assert structure_spec("bouc-wen+dynamics") == "bouc-wen+restoring-force"
    assert structure_spec("bouc-wen(n=2)") == "bouc-wen(n=2)+restoring-force"
    assert structure_spec("pi(n=8)+dynamics+delay") == "bouc-wen+restoring-force"


def test_diagnose_auto_proposes_and_adds_the_restoring_force_on_an_imported_recording(tmp_path: Path):
    """The user's path: a CSV imported with ``hilbench import``, then ``diagnose --auto`` from bouc-wen."""
    u = multisine(SAMPLES)
    y = noisy(oscillator(u))
    csv = tmp_path / "boucwen.csv"
    np.savetxt(csv, np.column_stack([u, y]), delimiter=",", header="input[N],output[m]", comments="")
    runner = CliRunner()
    imported = runner.invoke(app, ["import", str(csv), "-o", str(tmp_path / "bw.h5"), "--rate", str(FS), "-q"])
    assert imported.exit_code == 0, imported.output
    result = runner.invoke(app, ["diagnose", str(tmp_path / "bw.h5"), "--model", "bouc-wen", "--auto", "--json", "-j", "1",
                                 "-q", "--from", "0"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    steps = doc["steps"]
    assert [s["added"] for s in steps] == [None, STRUCTURE], steps
    assert steps[1]["spec"] == "bouc-wen+restoring-force"
    before, after = steps[0]["validation"]["rmse"], steps[1]["validation"]["rmse"]
    assert after < before / 10, (before, after)  # 44x on this record: the static loop misses the resonance
    # the final model is the oscillator: its parameters near the nominal ones, nothing left to add to it
    params = {p["name"]: p["value"] for p in doc["model"]["parameters"]["shape"]}
    assert abs(params["k"] + params["alpha"] - 1e5) < 0.1e5, params
    assert abs(params["m"] - 2.0) < 0.2, params
    assert all("whole model" in u["reason"] for u in doc["untestable"])


def test_a_static_loop_before_the_resonance_keeps_dynamics_and_rejects_the_structure():
    """The same resonance after a static Bouc-Wen loop: the data show mechanics, so the structure is
    tried, and the held-out error rejects it; dynamics is the finding, as before the check existed."""
    u = multisine(SAMPLES)
    static = fit(dataset(u, oscillator(u)), "bouc-wen+dynamics", train_fraction=1.0).model
    y = noisy(static.simulate(RunData(u, None, {}, FS)))
    d = diagnose(dataset(u, y), "bouc-wen", jobs=1)
    assert d.best is not None and d.best.effect == "dynamics" and d.best.significant
    structure = next(c for c in d.effects if c.effect == STRUCTURE)
    assert not structure.significant
    ev = structure.evidence
    assert ev["mechanics"]["drive_power_share"] > 0.3 and ev["mechanics"]["residual_power_share"] > 0.8
    assert 35.0 < ev["mechanics"]["natural_frequency_hz"] < 45.0
    failed = [f["check"] for f in structure.failed_checks()]
    assert "2x_lower_than_any_effect" in failed, failed
    assert "best single effect" in structure.reasoned_explanation()


def test_no_structure_below_the_resonance_and_the_reason_says_why():
    """A 1-4 Hz drive of the same oscillator: its resonance lies far above what the drive excites,
    so the structure is not tried and the reason gives the resonance and the drive's share there."""
    u = multisine(SAMPLES, band=(1.0, 4.0))
    y = noisy(oscillator(u))
    base = fit(dataset(u, y), "bouc-wen+dynamics(natural_frequency_hz=40,zeta=0.1)")
    found = mechanics(base, [])
    assert not found.applies
    assert "outside the drive's band" in found.reason and "40 Hz" in found.reason, found.reason
    assert found.evidence["drive_power_share"] < 0.01


def test_the_summary_says_how_to_switch_to_a_replacing_candidate_and_how_to_add_an_effect():
    """A candidate that replaces the model (the structure, another base) is reached with --model or
    --auto; ``--add restoring-force`` is no effect to add."""
    from hilbench.cli.summaries import diagnosis_summary_lines

    metrics = {"rmse": 1.0, "erms_pct": 10.0}

    def doc(effect: str, evidence: dict) -> dict:
        cand = {"effect": effect, "significant": True, "expected_gain": 0.9, "explanation": "why",
                "evidence": {**evidence, "failed_checks": []}}
        return {"spec": "bouc-wen", "metrics": {"validation": metrics, "train": metrics}, "where": [],
                "effects": [cand], "untestable": []}

    switch = doc(STRUCTURE, {"spec": "bouc-wen+restoring-force", "replacement": "the structure"})
    verdict = next(line for line in diagnosis_summary_lines(switch) if line.startswith("verdict"))
    assert "--model 'bouc-wen+restoring-force' or --auto switches to it" in verdict, verdict
    add = doc("dynamics", {"spec": "bouc-wen+dynamics"})
    verdict = next(line for line in diagnosis_summary_lines(add) if line.startswith("verdict"))
    assert "--add dynamics or --auto adds it" in verdict, verdict
