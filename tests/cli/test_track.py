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


# -- reachability and health (issue 58) ---------------------------------------------------------------

def _recorded_output_range(fitted: tuple[Path, Path]) -> tuple[float, float]:
    sweep = Recording(fitted[1].parent / "sweep.h5")
    values = [run.channel("output") for run in sweep]
    return float(min(v.min() for v in values)), float(max(v.max() for v in values))


def _sine_over(lo: float, hi: float, cycles: int = 2) -> str:
    """A 1 Hz sine from lo to hi (um), starting at lo."""
    return (f"sine:amplitude={(hi - lo) / 2:.6g},offset={(hi + lo) / 2:.6g},frequency_hz=1,phase_deg=-90,"
            f"cycles={cycles}")


def test_track_refuses_an_unreachable_reference_before_the_rig_moves(fitted: tuple[Path, Path], tmp_path: Path) -> None:
    """On main a reference twice the recorded output range ran with the command pinned at a limit,
    exit 0, status complete; now it is refused in one line naming the range and the first sample."""
    rig, model = fitted
    y_lo, y_hi = _recorded_output_range(fitted)
    mid, span = (y_lo + y_hi) / 2, y_hi - y_lo
    out = tmp_path / "x.h5"
    result = CliRunner().invoke(app, ["track", str(rig), "--model", str(model), "-o", str(out),
                                      "--reference", _sine_over(mid - span, mid + span)])
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.output
    line = lines[0]
    assert "reachable output range" in line and " um" in line
    assert "sample " in line and "t = " in line and "asks for" in line and "--allow-clip" in line
    assert not out.exists()  # refused before a run was written (and before the rig moved)
    # the same with --json: one JSON document with the error
    again = CliRunner().invoke(app, ["track", str(rig), "--model", str(model), "-o", str(out), "--json",
                                     "--reference", _sine_over(mid - span, mid + span)])
    assert again.exit_code == 2 and json.loads(again.stdout)["exit"] == 2


def test_track_allow_clip_is_recorded(fitted: tuple[Path, Path], tmp_path: Path) -> None:
    rig, model = fitted
    y_lo, y_hi = _recorded_output_range(fitted)
    mid, span = (y_lo + y_hi) / 2, y_hi - y_lo
    out = tmp_path / "clip.h5"
    result = CliRunner().invoke(app, ["track", str(rig), "--model", str(model), "-o", str(out), "--allow-clip",
                                      "--reference", _sine_over(mid - span, mid + span), "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    clipped = doc["reference_clipped"]
    lo, hi = clipped["reachable_um"]
    assert clipped["samples"] > 0 and clipped["original_range_um"][1] > hi and clipped["original_range_um"][0] < lo
    # the model reaches beyond what the rig's output sensor measures (-5..200 um): the sensor bounds it
    assert [lo, hi] == [-5.0, 200.0]
    assert any("output sensor's range" in note for note in doc["compensator"]["notes"])
    run = Recording(out).run(doc["run"])
    assert json.loads(run.attrs["reference_clipped"]) == clipped
    reference = run.channel("reference")
    assert reference.max() == pytest.approx(hi) and reference.min() == pytest.approx(lo)
    assert json.loads(run.attrs["health"]) == doc["health"]
    text = CliRunner().invoke(app, ["track", str(rig), "--model", str(model), "-o", str(out), "--allow-clip",
                                    "--reference", _sine_over(mid - span, mid + span)])
    assert text.exit_code == 0 and "reference clipped:" in text.output


def test_track_strict_fails_a_slew_limited_run_with_exit_3(fitted: tuple[Path, Path], tmp_path: Path) -> None:
    """A 25 Hz sine over 80 % of the range needs ~4x the amplifier's 500 V/s: the safety path slews
    most samples (counted apart from the limits), the run is recorded and reported degraded, and
    --strict turns that into exit status 3."""
    rig, model = fitted
    y_lo, y_hi = _recorded_output_range(fitted)
    mid, span = (y_lo + y_hi) / 2, y_hi - y_lo
    out = tmp_path / "fast.h5"
    fast = _sine_over(mid - 0.4 * span, mid + 0.4 * span, cycles=20).replace("frequency_hz=1", "frequency_hz=25")
    args = ["track", str(rig), "--model", str(model), "-o", str(out), "--reference", fast]
    result = CliRunner().invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    health = json.loads(result.stdout)["health"]
    assert health["degraded"] and health["slew_limited_pct"] > 1.0 and health["at_limit_samples"] == 0
    assert any("slew-limited" in r for r in health["reasons"])
    strict = CliRunner().invoke(app, [*args, "--strict"])
    assert strict.exit_code == 3, strict.output
    assert "DEGRADED" in strict.output and "Traceback" not in strict.output
    run = Recording(out).run("0002-track")
    assert run.status == "complete" and json.loads(run.attrs["health"])["degraded"]


def test_track_reports_health_and_strict_passes_a_healthy_run(fitted: tuple[Path, Path], tmp_path: Path) -> None:
    rig, model = fitted
    y_lo, y_hi = _recorded_output_range(fitted)
    mid, span = (y_lo + y_hi) / 2, y_hi - y_lo
    out = tmp_path / "ok.h5"
    reference = _sine_over(mid - 0.4 * span, mid + 0.4 * span)  # 80 % of the recorded range
    result = CliRunner().invoke(app, ["track", str(rig), "--model", str(model), "-o", str(out), "--json", "--strict",
                                      "--reference", reference])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    health = doc["health"]
    fit = json.loads(model.read_text())["metrics"]["validation"]["erms_pct"]
    assert health["model_erms_pct"] == pytest.approx(fit) and health["model_erms_split"] == "validation"
    assert health["erms_pct"] == pytest.approx(doc["metrics"]["erms_pct"])
    # the model's error is compared on the reference's span (decision 0116): its rmse over the span
    # the tracking erms_pct is a share of (rmse / erms_pct)
    rmse = json.loads(model.read_text())["metrics"]["validation"]["rmse"]
    ref_span = 100.0 * doc["metrics"]["rmse"] / doc["metrics"]["erms_pct"]
    assert health["model_rmse_um"] == pytest.approx(rmse)
    assert health["model_erms_on_reference_pct"] == pytest.approx(100.0 * rmse / ref_span, rel=1e-6)
    m = health["model_erms_on_reference_pct"]
    assert health["erms_allowed_pct"] == pytest.approx(max(2.0 * m, m + 0.3))
    assert health["at_limit_pct"] <= 1.0 and health["slew_limited_pct"] <= 1.0
    assert not health["degraded"] and health["reasons"] == []
    assert "reference_clipped" not in doc
    run = Recording(out).run(doc["run"])
    assert json.loads(run.attrs["health"]) == health
    assert "reference_clipped" not in run.attrs
    text = CliRunner().invoke(app, ["track", str(rig), "--model", str(model), "-o", str(out), "--reference", reference])
    assert text.exit_code == 0
    assert "health:" in text.output and "slew-limited" in text.output and "- ok" in text.output
    assert "operating range" in text.output and "reachable output" in text.output


def test_track_runs_a_figure_eight_on_a_planned_path_and_refuses_beyond_its_loop(tmp_path: Path) -> None:
    """gmm-issf-duhem as simulated loops as a figure eight over +-6 A. 80 % of the recorded output lies
    far beyond the part of that range where duhem-d's loop is monotone: refused on main (naming that
    part), it now runs on a path planned over the whole reference, said in a note, within the model's
    own error (decision 0118). A reference beyond the whole loop is refused in one line naming the
    reachable range, before anything moves."""
    runner = CliRunner()
    sweep = runner.invoke(app, ["sweep", "gmm-issf-duhem", "-e", "sine:amplitude=6,frequency_hz=1,cycles=2",
                                "-o", str(tmp_path / "gmm.h5"), "--json", "--quiet"])
    assert sweep.exit_code == 0, sweep.output
    fit = runner.invoke(app, ["fit", str(tmp_path / "gmm.h5"), "--model", "duhem-d", "-o", str(tmp_path / "d.json"),
                              "--json", "--quiet"])
    assert fit.exit_code == 0, fit.output
    out = tmp_path / "t.h5"
    result = runner.invoke(app, ["track", "gmm-issf-duhem", "--model", str(tmp_path / "d.json"), "-o", str(out),
                                 "--reference", "sine:amplitude=53,offset=-60,frequency_hz=1,cycles=2"])
    assert result.exit_code == 0, result.output
    assert "path planned over the whole reference" in result.output and "- ok" in result.output
    beyond = tmp_path / "beyond.h5"
    refused = runner.invoke(app, ["track", "gmm-issf-duhem", "--model", str(tmp_path / "d.json"), "-o", str(beyond),
                                  "--reference", "sine:amplitude=80,offset=-60,frequency_hz=1,cycles=2"])
    assert refused.exit_code == 2, refused.output
    lines = refused.output.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in refused.output
    assert "reachable output range of 'duhem-d'" in lines[0] and "6.5" not in lines[0]
    assert not beyond.exists()


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
