"""hilbench linear: the papers' linear-dynamics methods reached from the command line."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from hilbench.cli import app
from hilbench.excitation.plan import load_plan_file
from hilbench.rig.config import load_rig
from hilbench.rig.rig import Rig
from hilbench.runners.sweep import run_plan

REPO = Path(__file__).resolve().parents[2]
PLAN_002 = REPO / "experiments" / "plans" / "paper-002-linear-identification.toml"


def _recording(tmp_path: Path) -> Path:
    out = tmp_path / "id.h5"
    run_plan(Rig(load_rig("gmm-gu2016")), load_plan_file(PLAN_002), out)
    return out


def test_linear_step_and_transfer_function_find_the_002_resonance(tmp_path):
    h5 = _recording(tmp_path)
    runner = CliRunner()
    step = runner.invoke(app, ["linear", str(h5), "--run", "step", "--method", "step", "--json"])
    assert step.exit_code == 0, step.output
    doc = json.loads(step.stdout)
    # paper 002 eq. 11: wn = 2 pi 3200 rad/s, zeta = 0.28 (configs/gmm-gu2016.toml)
    assert abs(doc["natural_frequency_hz"] - 3200.0) < 100.0 and abs(doc["zeta"] - 0.28) < 0.03
    assert doc["spec_part"].startswith("dynamics(natural_frequency_hz=")
    tf = runner.invoke(app, ["linear", str(h5), "--run", "noise", "--method", "transfer-function", "--json"])
    assert tf.exit_code == 0, tf.output
    fn = json.loads(tf.stdout)["natural_frequencies_hz"]
    assert any(abs(f - 3200.0) < 200.0 for f in fn), fn


def test_linear_refuses_bad_input_in_one_line(tmp_path):
    h5 = _recording(tmp_path)
    runner = CliRunner()
    for args, needle in ((["--run", "nope"], "no run 'nope'"), (["--run", "step", "--method", "foo"], "unknown method"),
                         (["--run", "step", "--method", "transfer-function", "--nb", "0"], "--nb")):
        result = runner.invoke(app, ["linear", str(h5), *args])
        assert result.exit_code == 2, result.output
        assert needle in result.output and "Traceback" not in result.output
