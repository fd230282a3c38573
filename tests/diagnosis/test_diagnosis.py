"""`hilbench.diagnosis.diagnose`: where a model fails and which effect is missing, on simulated plants with a
hidden effect (one each, none, and two), started from a model without it."""

from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

from hilbench.rig.config import load_rig
from hilbench.diagnosis.diagnose import diagnose
from hilbench.diagnosis.refit import spec_with
from hilbench.diagnosis.rows import noise_floor
from hilbench.diagnosis.significance import improvement_test
from hilbench.recording.hdf5 import RecordingWriter
from hilbench.sim.plant import Plant
from tests.conftest import MINIMAL_RIG

FS = 1000.0

CREEP = """
[plant.creep]
gains = [0.1]
time_constants_s = [0.5]
"""
ASYMMETRY = """
[plant.asymmetry]
coefficients = [0.0, 0.0, 0.05, 0.01]
"""
TEMPERATURE = """
[[sensors]]
channel = "temperature"
unit = "degC"
driver = "sim"
noise_std = 0.01

[plant.temperature]
reference_degC = 25.0
gain_per_degC = 0.02
strain_um_per_degC = 0.5
trajectory = { kind = "ramp", start = 25.0, end = 35.0, duration_s = 8.0 }
"""


RATE = """
[plant.rate_dependence]
mode = "damping"
coefficient = 0.4
exponent = 1.0
reference_rate = 50.0
"""
DYNAMICS = """
[plant.dynamics]
kind = "second-order"
natural_frequency_hz = 30.0
zeta = 0.15
"""
DELAY = """
[plant.delay]
seconds = 0.004
"""
SATURATION = """
[plant.saturation]
level = 7.0
"""
LOAD = """
[[sensors]]
channel = "load"
unit = "N"
driver = "sim"
noise_std = 0.05

[plant.load]
gain_per_N = 0.004
compliance_um_per_N = 0.02
trajectory = { kind = "steps", levels = [0.0, 40.0, 15.0, 60.0, 25.0], hold_s = 1.6 }
"""

#: an M-play hysteresis (004's operator) in place of MINIMAL_RIG's play operators
MPLAY = """
[plant.hysteresis]
model = "m-play"
linear_gain = 0.8
thresholds = [0.4, 1.2, 2.5]
weights = [0.5, 0.3, 0.2]
eta = [0.6, 0.3, 0.0]
"""


def sines(seed: int, freqs: tuple[float, ...], steps: bool = False) -> np.ndarray:
    """Whole cycles of sines at ``freqs`` (shuffled, amplitudes 3-6 V, at least 1 s each), each
    followed by a 0.5 s hold at a random level when ``steps``."""
    rng = np.random.default_rng(seed)
    parts = []
    for f in rng.permutation(np.asarray(freqs, float)):
        t = np.arange(int(FS * max(1.0, 1.0 / f))) / FS
        parts.append(rng.uniform(3, 6) * np.sin(2 * np.pi * f * t))
        if steps:
            parts.append(np.full(int(0.5 * FS), rng.uniform(-6, 6)))
    return np.concatenate(parts)


def triangles(seed: int, freqs: tuple[float, ...], amplitudes: tuple[float, ...]) -> np.ndarray:
    """A triangle staircase (one cycle per amplitude, V, shuffled) at each frequency, each followed
    by a 0.4 s hold at a random level."""
    rng = np.random.default_rng(300 + seed)
    parts = []
    for f in rng.permutation(np.asarray(freqs, float)):
        n = int(round(FS / f))
        phase = np.arange(n) / n
        unit = np.where(phase < 0.25, 4 * phase, np.where(phase < 0.75, 2 - 4 * phase, 4 * phase - 4))
        parts += [a * unit for a in rng.permutation(np.asarray(amplitudes, float))]
        parts.append(np.full(int(0.4 * FS), rng.uniform(-3, 3)))
    return np.concatenate(parts)


def excitation(seed: int) -> np.ndarray:
    """8 s: steps held 1 s between 1 Hz and 3 Hz sines, so both halves of the split see holds, steps
    and two drive frequencies."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(FS)) / FS
    parts = []
    for k in range(2):
        parts += [np.full(int(FS), level) for level in rng.uniform(-6, 6, 2)]
        parts.append(5.0 * np.sin(2 * np.pi * 1.0 * t))
        parts.append(4.0 * np.sin(2 * np.pi * 3.0 * t))
    return np.concatenate(parts)


def make_recording(folder: Path, extra: str, name: str, excite=excitation) -> Path:
    """Two runs of :func:`excitation` on MINIMAL_RIG plus ``extra`` plant tables, each from rest."""
    rig = folder / f"{name}.toml"
    base = textwrap.dedent(MINIMAL_RIG)
    if "[plant.hysteresis]" in extra:  # the case brings its own hysteresis (MINIMAL_RIG's is its last table)
        base = base[: base.index("[plant.hysteresis]")]
    rig.write_text(base + "\n" + textwrap.dedent(extra), encoding="utf-8")
    plant = Plant.from_rig(load_rig(rig))
    out = folder / f"{name}.h5"
    writer = RecordingWriter(out)
    units = {"time": "s", "input": "V", "output": "um", "temperature": "degC", "load": "N"}
    for seed in (0, 1):
        u = excite(seed)
        plant.reset()
        sim = plant.simulate(u)
        data = {"time": np.arange(u.size) / FS, "input": u, "output": sim.output, **sim.aux}
        writer.write_run(f"run{seed}", data, units, experiment="test", excitation="{}", sample_rate_hz=FS)
    return out


CASES = {
    "creep": (CREEP, "pi", ["creep"]),
    "temperature": (TEMPERATURE, "pi", ["temperature"]),
    "asymmetry": (ASYMMETRY, "pi", ["asymmetry"]),
    "hysteresis": ("", "linear", ["hysteresis"]),
    "creep+asymmetry": (CREEP + ASYMMETRY, "pi", ["creep", "asymmetry"]),
    # velocity damping: smooth sines from 0.5 to 8 Hz, no steps (a step is an unbounded rate)
    "rate-dependence": (RATE, "pi", ["rate-dependence"], lambda s: sines(s, (0.5, 1, 2, 4, 8))),
    # a lightly damped 30 Hz resonance, rung by steps, at three drive frequencies
    "dynamics": (DYNAMICS, "pi", ["dynamics"], lambda s: sines(s, (1, 3, 7), steps=True)),
    # 4 ms of pure delay (4 samples)
    "delay": (DELAY, "pi", ["delay"], lambda s: sines(s, (1, 3, 7), steps=True)),
    # the output saturates at 7 um, below the ~11 um the hysteresis reaches at 6 V
    "saturation": (SATURATION, "pi", ["saturation"], lambda s: sines(s, (0.5, 1, 2), steps=True)),
    # load steps 0-60 N (4 %/10 N gain loss, 0.02 um/N compliance), with a load cell (0.05 N noise)
    "load": (LOAD, "pi", ["load"], lambda s: sines(s, (0.5, 1, 2), steps=True)),
    # second draws: other parameter values and other excitation seeds
    "rate-dependence/2": (RATE.replace("1.0\n", "1.5\n").replace("50.0", "100.0"), "pi", ["rate-dependence"],
                          lambda s: sines(s + 10, (0.5, 1, 2, 4, 8))),
    "dynamics/2": (DYNAMICS.replace("30.0", "60.0").replace("0.15", "0.3"), "pi", ["dynamics"],
                   lambda s: sines(s + 10, (1, 3, 7), steps=True)),
    "delay/2": (DELAY.replace("0.004", "0.002"), "pi", ["delay"], lambda s: sines(s + 10, (1, 3, 7), steps=True)),
    "saturation/2": (SATURATION.replace("7.0", "9.0"), "pi", ["saturation"],
                     lambda s: sines(s + 10, (0.5, 1, 2), steps=True)),
    "load/2": (LOAD.replace('{ kind = "steps", levels = [0.0, 40.0, 15.0, 60.0, 25.0], hold_s = 1.6 }',
                            '{ kind = "sine", mean = 30.0, amplitude = 30.0, period_s = 3.0 }'), "pi", ["load"],
               lambda s: sines(s + 10, (0.5, 1, 2), steps=True)),
    # third draws, unlike the rest: a quartic asymmetry; saturation of an M-play hysteresis under
    # triangles, where a cubic asymmetry fits as well and the residual's odd pattern decides
    "asymmetry/3": ("""
[plant.asymmetry]
coefficients = [0.0, 0.0, -0.06, 0.0, 0.002]
""", "pi", ["asymmetry"], lambda s: sines(s + 20, (0.5, 1, 2), steps=True)),
    "saturation/3": (SATURATION.replace("7.0", "8.5") + MPLAY, "pi", ["saturation"], lambda s: triangles(s, (0.5, 1.5), (7.0, 5.0, 3.0))),
    # second draws of the first four effects: a faster, weaker creep; a temperature that oscillates
    # and changes the gain more; an M-play hysteresis found from a linear start; two effects of
    # another kind together
    "creep/2": (CREEP.replace("[0.1]", "[0.06]").replace("[0.5]", "[0.25]"), "pi", ["creep"],
                lambda s: excitation(s + 10)),
    "temperature/2": (TEMPERATURE.replace("0.02\n", "0.04\n").replace(
        '{ kind = "ramp", start = 25.0, end = 35.0, duration_s = 8.0 }',
        '{ kind = "sine", mean = 30.0, amplitude = 6.0, period_s = 5.0 }'), "pi", ["temperature"],
        lambda s: sines(s + 10, (0.5, 1, 2), steps=True)),
    "hysteresis/2": (MPLAY, "linear", ["hysteresis"], lambda s: triangles(s, (0.5, 1.5), (6.0, 4.0, 2.0))),
    "saturation+delay": (SATURATION + DELAY.replace("0.004", "0.003"), "pi", ["saturation", "delay"],
                         lambda s: sines(s + 30, (1, 3, 7), steps=True)),
}
NEW = ["rate-dependence", "dynamics", "delay", "saturation", "load"]
NEW += [f"{c}/2" for c in NEW] + ["asymmetry/3", "saturation/3", "creep/2", "temperature/2", "hysteresis/2"]


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("diag")


@pytest.fixture(scope="module")
def auto_results(folder):
    """diagnose(..., auto=True) per case, computed once."""
    cache: dict[str, object] = {}

    def get(case: str):
        if case not in cache:
            extra, spec, _, *excite = CASES.get(case, ("", "pi", []))
            path = make_recording(folder, extra, case.replace("+", "_").replace("/", "_"), *excite)
            cache[case] = diagnose(path, spec, auto=True)
        return cache[case]

    return get


@pytest.mark.parametrize("case", ["creep", "temperature", "asymmetry", "hysteresis", *NEW])
def test_hidden_effect_ranked_first_and_auto_adds_it(case, auto_results):
    d = auto_results(case)
    first = d.rounds[0]
    hidden = CASES[case][2][0]
    assert first.effects[0].effect == hidden, [(c.effect, c.expected_gain, c.significant) for c in first.effects]
    best = first.effects[0]
    assert best.significant and best.expected_gain > 0.5 and best.evidence["p_value"] < 0.01
    assert best.explanation.endswith(hidden) or hidden in best.explanation
    added = [s["added"] for s in d.steps[1:]]
    assert hidden in added
    before, after = d.steps[0]["validation"]["rmse"], d.steps[-1]["validation"]["rmse"]
    assert before >= 3.0 * after, (before, after)
    # the final model has nothing significant left
    assert not any(c.significant for c in d.effects)


def test_clean_case_reports_nothing_significant(auto_results):
    d = auto_results("clean")
    assert d.effects and not any(c.significant for c in d.effects)
    assert len(d.steps) == 1 and d.steps[0]["added"] is None
    assert d.metrics["validation"]["rmse"] < 2.0 * d.noise


@pytest.mark.parametrize("case", ["creep+asymmetry", "saturation+delay"])
def test_two_hidden_effects(case, auto_results):
    d = auto_results(case)
    hidden = CASES[case][2]
    first = d.rounds[0]
    assert first.effects[0].effect in hidden and first.effects[0].significant
    added = [s["added"] for s in d.steps[1:]]
    assert set(hidden) <= set(added), added
    assert d.steps[0]["validation"]["rmse"] >= 3.0 * d.steps[-1]["validation"]["rmse"]


def test_json_document_and_untestable(auto_results):
    d = auto_results("temperature")
    doc = json.loads(json.dumps(d.to_json(), allow_nan=False))
    assert set(doc) == {"spec", "metrics", "where", "effects", "untestable", "steps", "model"}
    assert set(doc["metrics"]) == {"train", "validation"}
    # the final model's parameters with units (a batch row's, and a notebook's, `parameters`)
    assert doc["model"]["spec"] == doc["spec"]
    names = {p["name"] for p in doc["model"]["parameters"]["shape"] + doc["model"]["parameters"]["weights"]}
    assert any("temperature" in n for n in names), names
    assert all(p["unit"] for p in doc["model"]["parameters"]["weights"])
    assert doc["steps"][0]["spec"] == "pi" and doc["steps"][0]["added"] is None
    assert {"kind", "range", "share"} <= set(doc["where"][0])
    kinds = {w["kind"].split(":")[0] for w in doc["where"]}
    assert {"run", "time", "input", "rate"} <= kinds
    for e in doc["effects"]:
        assert {"effect", "significant", "expected_gain", "explanation", "evidence"} <= set(e)
    gains = [e["expected_gain"] for e in doc["effects"] if e["significant"]]
    assert gains == sorted(gains, reverse=True)
    # the first round saw the missing temperature effect through the channel's correlation
    ev = d.rounds[0].effects[0].evidence
    assert abs(ev["corr_e_channel"]) > 0.3
    assert {u["effect"] for u in doc["untestable"]} >= {"hysteresis"}


def test_untestable_single_frequency_and_no_holds(folder):
    rig = folder / "sine.toml"
    rig.write_text(textwrap.dedent(MINIMAL_RIG), encoding="utf-8")
    plant = Plant.from_rig(load_rig(rig))
    u = 5.0 * np.sin(2 * np.pi * 2.0 * np.arange(3000) / FS)
    sim = plant.simulate(u)
    out = folder / "sine.h5"
    RecordingWriter(out).write_run("sine", {"time": np.arange(u.size) / FS, "input": u, "output": sim.output},
                                   {"time": "s", "input": "V", "output": "um"}, experiment="t", excitation="{}",
                                   sample_rate_hz=FS)
    d = diagnose(out, "pi")
    reasons = {u["effect"]: u["reason"] for u in d.to_json()["untestable"]}
    assert "single drive frequency" in reasons["rate-dependence"]
    assert "cannot be separated from hysteresis" in reasons["rate-dependence"]
    assert "never holds still" in reasons["creep"]
    assert "dynamics" in reasons and "delay" in reasons
    assert "steps" not in d.to_json()


def test_add_shows_before_and_after(folder, auto_results):
    auto_results("creep")  # writes creep.h5
    d = diagnose(folder / "creep.h5", "pi", add="creep")
    # the plant's creep follows its hysteresis: held-back training rows prefer the output form
    assert [s["spec"] for s in d.steps] == ["pi", "pi+creep(form=output)"]
    assert d.steps[1]["validation"]["rmse"] < d.steps[0]["validation"]["rmse"] / 3
    assert d.spec == "pi+creep(form=output)" and [s["added"] for s in d.steps] == [None, "creep"]


def test_helpers():
    assert spec_with("linear+creep", "hysteresis") == "pi+creep"
    assert spec_with("pi", "temperature") == "pi+temperature"
    rng = np.random.default_rng(0)
    e = rng.normal(0, 0.5, 4000)
    assert abs(noise_floor(e, np.zeros(4000, int)) - 0.5) < 0.05
    p, _, _ = improvement_test(e, e + rng.normal(0, 0.01, 4000))
    assert p > 0.01  # noise alone does not pass
    p, better, n = improvement_test(e, 0.5 * e)
    assert p < 0.01 and better == n


def test_saved_model_file(folder, auto_results, tmp_path):
    from hilbench.identify.fitting import fit

    auto_results("asymmetry")  # writes asymmetry.h5
    path = folder / "asymmetry.h5"
    saved = fit(path, "pi").save(tmp_path / "fit.json")
    d = diagnose(path, str(saved))
    assert d.spec == "pi" and d.result.loaded_from == str(saved)
    assert d.effects[0].effect == "asymmetry" and d.effects[0].significant


def test_cli_diagnose_json_and_text(tmp_path):
    """`hilbench diagnose` prints one JSON document with the issue's keys, and a readable summary."""
    import json as _json

    from typer.testing import CliRunner

    from hilbench.cli import app

    runner = CliRunner()
    out = tmp_path / "d.h5"
    made = runner.invoke(app, ["sweep", "piezo-pmpi", "-e", "sine:amplitude=5,offset=5,phase_deg=-90,frequency_hz=1,cycles=4",
                               "-o", str(out), "-q", "--json"])
    assert made.exit_code == 0, made.output
    result = runner.invoke(app, ["diagnose", str(out), "--model", "linear", "--auto", "--json"])
    assert result.exit_code == 0, result.output
    doc = _json.loads(result.stdout)
    assert set(doc) >= {"spec", "metrics", "where", "effects", "untestable", "steps"}
    assert doc["steps"][0]["added"] is None and doc["steps"][1]["added"] == "hysteresis"
    assert doc["steps"][-1]["validation"]["rmse"] < doc["steps"][0]["validation"]["rmse"] / 3
    text = runner.invoke(app, ["diagnose", str(out), "--model", "linear"])
    assert text.exit_code == 0 and "verdict: hysteresis is missing" in text.stdout
    lines = text.stdout.splitlines()
    assert len(lines) < 40 and max(len(line) for line in lines) <= 200  # one screen
    (row,) = [ln for ln in lines if ln.split()[:2] == ["hysteresis", "found"]]
    verbose = runner.invoke(app, ["diagnose", str(out), "--model", "linear", "--verbose"])
    assert verbose.exit_code == 0 and "effects (best first):" in verbose.stdout and "significant" in verbose.stdout
    bad = runner.invoke(app, ["diagnose", str(out), "--model", "pi", "--add", "wobble"])
    assert bad.exit_code == 2 and "wobble" in bad.stderr and "effects:" in bad.stderr
    # --report DIR: the HTML page, its path printed (on stderr with --json, which keeps stdout one document)
    made = runner.invoke(app, ["diagnose", str(out), "--model", "linear", "--add", "hysteresis", "--json",
                               "--report", str(tmp_path / "rep")])
    assert made.exit_code == 0, made.output
    page = tmp_path / "rep" / "report.html"
    assert page.is_file() and "<img" in page.read_text(encoding="utf-8")
    assert _json.loads(made.stdout)["steps"][1]["added"] == "hysteresis" and str(page) in made.stderr
    (tmp_path / "a-file").write_text("x")
    bad = runner.invoke(app, ["diagnose", str(out), "--model", "linear", "--report", str(tmp_path / "a-file")])
    assert bad.exit_code == 2 and "a-file" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


def test_creep_needs_drift_on_holds(auto_results):
    """Delay and a resonance settle within the first tenth of a second of a hold: the creep low-pass
    may still buy some phase lag, but without drift along the holds it is not significant."""
    for case in ("delay", "dynamics"):
        creep = [c for c in auto_results(case).rounds[0].effects if c.effect == "creep"]
        assert creep and not creep[0].significant, creep[0].evidence
        assert not creep[0].evidence["checks"]["drift_on_holds"]
    creep = auto_results("creep").rounds[0].effects[0]
    assert creep.evidence["checks"]["drift_on_holds"] and creep.evidence["drift_over_rms"] > 1.0


def _sine_runs(folder: Path, extra: str, name: str, runs: dict[str, float]) -> Path:
    """One sine run per drive frequency (Hz), 5 V, whole cycles of at least 3 s, each from rest."""
    rig = folder / f"{name}.toml"
    rig.write_text(textwrap.dedent(MINIMAL_RIG) + "\n" + textwrap.dedent(extra), encoding="utf-8")
    plant = Plant.from_rig(load_rig(rig))
    out = folder / f"{name}.h5"
    writer = RecordingWriter(out)
    for label, f in runs.items():
        u = 5.0 * np.sin(2 * np.pi * f * np.arange(int(FS * math.ceil(3.0 * f) / f)) / FS)
        plant.reset()
        sim = plant.simulate(u)
        writer.write_run(label, {"time": np.arange(u.size) / FS, "input": u, "output": sim.output},
                         {"time": "s", "input": "V", "output": "um"}, experiment="t", excitation="{}",
                         sample_rate_hz=FS)
    return out


def test_delay_calibrated_across_validation_rates(folder):
    """Trained at one drive rate, a delay looks like loop width; the validation runs at two other
    rates calibrate it (the nearer) and confirm it (the farther)."""
    path = _sine_runs(folder, DELAY, "delay-rates", {"slow": 1.0, "mid": 3.0, "fast": 9.0})
    d = diagnose(path, "pi", train=["slow"], test=["mid", "fast"])
    best = d.best
    assert best is not None and best.effect == "delay" and best.significant, [
        (c.effect, c.expected_gain, c.evidence["checks"]) for c in d.effects]
    cal = best.evidence["rate_calibration"]
    assert cal["calibrated_on"] == ["0002-mid"] and cal["confirmed_on"] == ["0003-fast"]
    assert abs(cal["training_hz"] - 1.0) < 0.05 and abs(cal["confirm_hz"][0] - 9.0) < 0.3
    assert abs(best.fitted.model.effect("delay").param("seconds") - 0.004) < 0.001
    assert best.evidence["equivalent_lag_s"] > 0  # the measurement trails the model
    before, after = best.evidence["confirmation_rmse"]
    assert after < before / 3, (before, after)
    reasons = {u["effect"]: u["reason"] for u in d.untestable}
    assert "training rows hold a single drive frequency" in reasons["rate-dependence"]
    # --add delay takes the same calibrated shape
    added = diagnose(path, "pi", train=["slow"], test=["mid", "fast"], add="delay")
    assert added.spec.startswith("pi+delay(seconds=") and added.steps[1]["validation"]["rmse"] < \
        added.steps[0]["validation"]["rmse"] / 3
    # one other rate only: nothing left to confirm on
    one = diagnose(path, "pi", train=["slow"], test=["fast"])
    reasons = {u["effect"]: u["reason"] for u in one.untestable}
    assert "fewer than two other drive rates" in reasons["delay"]
    assert "delay" not in [c.effect for c in one.effects]


def test_aux_variation_separates_drift_from_noise():
    from hilbench.diagnosis.testability import aux_variation as _aux_variation
    from hilbench.diagnosis.thresholds import AUX_MIN_VARIATION

    rng = np.random.default_rng(3)
    n = 20000
    noise = [rng.normal(25.0, 0.15, n), rng.normal(25.0, 0.15, n)]
    assert _aux_variation(noise) < 1.0 < AUX_MIN_VARIATION  # pure noise: nothing to test
    drift = [25.0 + np.linspace(0, 1.5, n) + rng.normal(0, 0.15, n)]
    assert _aux_variation(drift) > 2 * AUX_MIN_VARIATION  # 1.5 degC under 0.15 degC noise: ~10
    steps = [np.repeat([20.0, 20.1, 20.0, 20.1], n // 4)]  # a quantised sensor flipping one step
    assert _aux_variation(steps) < 5.0


def test_tie_broken_by_the_residuals_pattern(auto_results):
    """Saturating M-play data: a cubic asymmetry lowers the error as much as saturation does; the
    residual is odd in the input, so saturation ranks first."""
    first = auto_results("saturation/3").rounds[0]
    sat = next(c for c in first.effects if c.effect == "saturation")
    asym = next(c for c in first.effects if c.effect == "asymmetry")
    assert sat.evidence["signature"] > asym.evidence["signature"] + 0.5  # odd vs even share of the error
    assert first.effects[0].effect == "saturation"


def test_cli_diagnose_bad_input_one_line(tmp_path):
    """No output channel, a spec that cannot be fitted, an unknown effect: one line naming what is
    available, exit 2."""
    from typer.testing import CliRunner

    from hilbench.cli import app

    runner = CliRunner()
    path = tmp_path / "no-output.h5"
    u = np.sin(np.arange(2000) / 100.0)
    RecordingWriter(path).write_run("r", {"time": np.arange(2000) / FS, "input": u, "displacement": 2 * u},
                                    {"time": "s", "input": "V", "displacement": "um"}, experiment="t",
                                    excitation="{}", sample_rate_hz=FS)
    cases = [
        (["--model", "pi"], ["no 'output' channel", "channels: time, input, displacement"]),
        (["--model", "pi+bogus"], ["'bogus'", "bases:", "effects:"]),
        (["--model", "pi(n=0)"], ["at least 1"]),
        (["--model", "pi+asymmetry(order=12)"], ["order must be 2 to 8"]),
    ]
    good = tmp_path / "good.h5"
    RecordingWriter(good).write_run("r", {"time": np.arange(2000) / FS, "input": u, "output": 2 * u},
                                    {"time": "s", "input": "V", "output": "um"}, experiment="t",
                                    excitation="{}", sample_rate_hz=FS)
    for args, needles in cases:
        target = path if "no 'output' channel" in needles[0] else good
        r = runner.invoke(app, ["diagnose", str(target), *args])
        assert r.exit_code == 2, (args, r.output)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and all(n in lines[0] for n in needles), (args, lines)
    r = runner.invoke(app, ["diagnose", str(good), "--model", "pi", "--add", "creeep"])
    assert r.exit_code == 2 and "creeep" in r.stderr and "creep" in r.stderr.replace("creeep", "")


def test_training_without_loops_is_noted(folder):
    """A run that only steps and holds trains a hysteresis base on no loop: the diagnosis says so
    (randomized seeds 1116 and 1147: training was one power-on step, validation drew 7 and 39 loops)."""
    from hilbench.diagnosis.testability import testable
    from hilbench.identify.fitting import fit

    rig = folder / "steps.toml"
    rig.write_text(textwrap.dedent(MINIMAL_RIG), encoding="utf-8")
    plant = Plant.from_rig(load_rig(rig))
    out = folder / "steps.h5"
    writer = RecordingWriter(out)
    t = np.arange(3000) / FS
    for label, u in {"step": np.where(t < 0.5, 0.0, 4.0), "sine": 4.0 * np.sin(2 * np.pi * 2.0 * t),
                     "triangle": 4.0 * (2 / np.pi) * np.arcsin(np.sin(2 * np.pi * 1.0 * t))}.items():
        plant.reset()
        writer.write_run(label, {"time": t, "input": u, "output": plant.simulate(u).output},
                         {"time": "s", "input": "V", "output": "um"}, experiment="t", excitation="{}",
                         sample_rate_hz=FS)
    stepped = fit(out, "pi", train=["step"], test=["sine"])
    notes = testable("pi", stepped).notes
    assert len(notes) == 1 and "the training rows draw 0 half cycles" in notes[0], notes
    assert not testable("pi", fit(out, "pi", train=["triangle"], test=["sine"])).notes
    assert not testable("linear", fit(out, "linear", train=["step"], test=["sine"])).notes  # no loops to learn
