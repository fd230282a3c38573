"""``hilbench track`` end to end on a simulated rig: JSON document, recording, figure, refusals."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest
from typer.testing import CliRunner

from hilbench.cli import app
from hilbench.identify.metrics import METRIC_KEYS
from hilbench.recording.hdf5 import Recording

RIG = """
[rig]
name = "piezo-track-cli"
extends = "piezo-pmpi"
sample_rate_hz = 2000.0

[actuator]
driver = "sim"
unit = "V"
min = -3.0
max = 13.0
max_rate = 500.0
rest = 0.0
"""
SINE = "sine:amplitude=50,offset=50,frequency_hz=1,phase_deg=-90,cycles=2"


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("track-cli")
    rig = folder / "rig.toml"
    rig.write_text(textwrap.dedent(RIG), encoding="utf-8")
    runner = CliRunner()
    sweep = runner.invoke(app, ["sweep", str(rig), "-o", str(folder / "sweep.h5"), "--json", "--quiet"])
    assert sweep.exit_code == 0, sweep.output
    fit = runner.invoke(app, ["fit", str(folder / "sweep.h5"), "--model", "pmpi", "-o", str(folder / "pmpi.json"),
                              "--json", "--quiet"])
    assert fit.exit_code == 0, fit.output
    return rig, folder / "pmpi.json"


def test_track_json_recording_and_figure(fitted: tuple[Path, Path], tmp_path: Path) -> None:
    rig, model = fitted
    out, png = tmp_path / "track.h5", tmp_path / "track.png"
    result = CliRunner().invoke(app, ["track", str(rig), "--model", str(model), "--reference", SINE, "--feedback",
                                      "-o", str(out), "--plot", str(png), "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert set(METRIC_KEYS) <= set(doc["metrics"])
    assert doc["metrics"]["mre_pct"] < 0.5
    assert doc["compensator"]["method"] == "im" and "feedback" in doc["compensator"]
    assert png.stat().st_size > 10_000
    run = Recording(out).run(doc["run"])
    assert run.status == "complete"
    assert {"reference", "error", "input", "output", "command", "lateness"} <= set(run.channels)
    # a recording's output channel as the reference: FILE.h5:RUN
    again = CliRunner().invoke(app, ["track", str(rig), "--model", str(model), "--reference", f"{out}:{doc['run']}",
                                     "-o", str(out), "--json"])
    assert again.exit_code == 0, again.output
    assert json.loads(again.stdout)["compensator"]["reference"]["kind"] == "recording"
    assert len(Recording(out)) == 2


@pytest.mark.parametrize("args, message", [
    (["--reference", "bogus:x=1"], "kind"),
    (["--reference", SINE, "--method", "fpmpi"], "fpmpi"),
    (["--reference", SINE, "--feedback", "--ki", "1e7"], "pole"),
    (["--reference", SINE, "--online"], "fpmpi"),
])
def test_track_refuses_with_one_line(fitted: tuple[Path, Path], tmp_path: Path, args: list[str], message: str) -> None:
    rig, model = fitted
    result = CliRunner().invoke(app, ["track", str(rig), "--model", str(model), "-o", str(tmp_path / "x.h5"), *args])
    assert result.exit_code == 2
    assert message in result.output
    assert "Traceback" not in result.output


def test_track_designs_the_feedback_and_states_its_margins(fitted: tuple[Path, Path], tmp_path: Path) -> None:
    """--feedback without gains: designed on the identified loop; the margins in JSON and text."""
    rig, model = fitted
    result = CliRunner().invoke(app, ["track", str(rig), "--model", str(model), "--reference", SINE, "--feedback",
                                      "-o", str(tmp_path / "d.h5"), "--json"])
    assert result.exit_code == 0, result.output
    fb = json.loads(result.stdout)["compensator"]["feedback"]
    assert fb["designed"] and fb["kp"] == 0.0 and fb["ki_per_s"] > 0
    assert fb["margins"]["gain_margin_db"] >= 6.0 - 0.05 and fb["margins"]["phase_margin_deg"] >= 45.0 - 0.5
    assert fb["margins"]["crossover_hz"] > 0 and fb["loop"]["local_gain_range"][1] >= 1.25
    assert "um" in fb["units"]
    text = CliRunner().invoke(app, ["track", str(rig), "--model", str(model), "--reference", SINE, "--feedback",
                                    "--ki", "100", "-o", str(tmp_path / "t.h5")])
    assert text.exit_code == 0, text.output
    assert "feedback (given, um/um)" in text.output and "gain margin" in text.output and "phase margin" in text.output


def test_track_gains_without_feedback_are_refused(fitted: tuple[Path, Path], tmp_path: Path) -> None:
    rig, model = fitted
    result = CliRunner().invoke(app, ["track", str(rig), "--model", str(model), "--reference", SINE, "--ki", "100",
                                      "-o", str(tmp_path / "x.h5")])
    assert result.exit_code == 2
    assert "--feedback" in result.output and "Traceback" not in result.output
