"""End-to-end CLI on simulated rigs: JSON output, and one-line errors with exit status 2."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
from typer.testing import CliRunner

from hilbench.cli import app
from tests.conftest import MINIMAL_RIG, require_real_data

runner = CliRunner()


def run_ok(*args: str) -> dict:
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)  # exactly one JSON document on stdout


def run_error(*args: str) -> str:
    result = runner.invoke(app, list(args))
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    lines = result.stderr.strip().splitlines()
    assert lines[0].startswith("error: ") and len(lines) <= 2, lines
    return lines[0]


def test_sweep_show_json(tmp_path):
    out = tmp_path / "s.h5"
    doc = run_ok("sweep", "gmm-issf-duhem", "-e", "sine:amplitude=1|2,frequency_hz=1,cycles=2", "-o", str(out), "-q")
    assert doc["status"] == "complete" and [r["label"] for r in doc["runs"]] == ["sine-amplitude=1", "sine-amplitude=2"]
    shown = run_ok("show", str(out))
    assert shown["format"] == "hilbench-recording" and shown["format_version"] == 1
    run = shown["runs"][1]
    assert run["status"] == "complete" and run["n_samples"] == 2001 and run["sample_rate_hz"] == 1000.0
    assert [(c["name"], c["units"]) for c in run["channels"]] == [("time", "s"), ("input", "A"), ("output", "um")]
    assert run["excitation"]["amplitude"] == 2


def test_sweep_appends_and_plan_file(tmp_path):
    out = tmp_path / "s.h5"
    plan = tmp_path / "plan.toml"
    plan.write_text('[[runs]]\nlabel = "steps"\nkind = "step"\nlevels = [0.0, 1.0, 0.0]\nhold_s = 0.2\nrise_s = 0.01\n', encoding="utf-8")
    run_ok("sweep", "gmm-issf-duhem", "--plan", str(plan), "-o", str(out), "-q")
    run_ok("sweep", "gmm-issf-duhem", "--plan", str(plan), "-o", str(out), "-q")
    assert [r["name"] for r in run_ok("show", str(out))["runs"]] == ["0001-steps", "0002-steps"]


def test_sweep_check_only(tmp_path):
    doc = run_ok("sweep", "piezo-rate-pi", "--check")
    assert doc["plan_ok"] and doc["runs"] == 7


def test_rigs_lists_papers():
    rigs = run_ok("rigs")
    assert {r["paper"] for r in rigs} >= {"000", "001", "002", "003", "004"}


# -- bad input: one line naming file/key/value, exit 2, nothing half-written ---------------------


def test_unknown_config_key(write_rig, tmp_path):
    rig = write_rig(base=MINIMAL_RIG.replace("seed = 7", "seed = 7\ncolour = 'red'"))
    line = run_error("sweep", str(rig), "-e", "sine:amplitude=1,frequency_hz=1,cycles=1", "-o", str(tmp_path / "o.h5"))
    assert str(rig) in line and "[rig]: unknown key 'colour'" in line
    assert not (tmp_path / "o.h5").exists()


def test_missing_config_key(write_rig):
    rig = write_rig(base=MINIMAL_RIG.replace("sample_rate_hz = 1000.0\n", ""))
    assert "[rig]: missing key 'sample_rate_hz'" in run_error("sweep", str(rig))


def test_wrong_type(write_rig):
    rig = write_rig(base=MINIMAL_RIG.replace("noise_std = 0.01", "noise_std = 'low'"))
    assert "[sensors[0]] noise_std: expected a finite number >= 0, got 'low'" in run_error("sweep", str(rig))


def test_inverted_limits(write_rig):
    rig = write_rig(base=MINIMAL_RIG.replace("min = -10.0", "min = 10.0").replace("max = 10.0", "max = -10.0"))
    assert "min 10 must be less than max -10" in run_error("sweep", str(rig))


def test_plan_outside_limits(tmp_path):
    out = tmp_path / "o.h5"
    line = run_error("sweep", "gmm-issf-duhem", "-e", "sine:amplitude=7,frequency_hz=1,cycles=1", "-o", str(out))
    assert "plan run 1 'sine' at t=" in line and "outside the actuator range [-6.5, 6.5] A" in line
    assert not out.exists()


def test_missing_files(tmp_path):
    assert "nothere.toml: no such file" in run_error("sweep", str(tmp_path / "nothere.toml"))
    assert "none.h5: file not found" in run_error("show", str(tmp_path / "none.h5"))
    line = run_error("import", str(tmp_path / "none.csv"), "-o", str(tmp_path / "i.h5"))
    assert "none.csv: file not found" in line


def test_csv_missing_column(tmp_path):
    csv = tmp_path / "d.csv"
    csv.write_text("time[s],input[V]\n0,1\n0.1,2\n", encoding="utf-8")
    out = tmp_path / "i.h5"
    line = run_error("import", str(csv), "-o", str(out))
    assert "d.csv" in line and "missing column 'output'" in line
    assert not out.exists()


def test_csv_non_numeric_cell(tmp_path):
    csv = tmp_path / "d.csv"
    csv.write_text("time[s],input[V],output[um]\n0,1,2\n0.1,abc,3\n", encoding="utf-8")
    line = run_error("import", str(csv), "-o", str(tmp_path / "i.h5"))
    assert "d.csv" in line and "line 3" in line and "'abc'" in line


def test_csv_non_increasing_time(tmp_path):
    csv = tmp_path / "d.csv"
    csv.write_text("time[s],input[V],output[um]\n0,1,2\n0.2,1,3\n0.1,1,3\n", encoding="utf-8")
    line = run_error("import", str(csv), "-o", str(tmp_path / "i.h5"))
    assert "d.csv" in line and "increasing" in line and "line 4" in line


def test_debug_shows_traceback(write_rig):
    rig = write_rig(base=MINIMAL_RIG.replace("min = -10.0", "min = 20.0"))
    result = runner.invoke(app, ["--debug", "sweep", str(rig)])
    assert result.exit_code == 2 and "Traceback" in result.stderr


# -- import and plot the measured data (skipped without ../shared/data/real) ----------------------


def test_import_and_plot_real_data(tmp_path):
    real = require_real_data()
    out = tmp_path / "real.h5"
    csv = real / "piezo-stack-150V-1Hz" / "hysteresis_v_150_1hz.csv"
    doc = run_ok("import", str(csv), "-o", str(out), "--run", "stack-150V",
                 "--map", "1=time[s]", "--map", "2=output[um]", "--map", "3=input[V]")
    assert doc["runs"] == ["0001-stack-150V"]
    mat = real / "piezo-dspace-preisach" / "20_hz_no_lp.mat"
    run_ok("import", str(mat), "-o", str(out), "--map", "Y(3)=input[V]", "--map", "Y(1)=output[um]")
    shown = run_ok("show", str(out))
    assert [(r["n_samples"], r["sample_rate_hz"]) for r in shown["runs"]] == [(50001, 5000.0), (40001, 10000.0)]
    with h5py.File(out, "r") as f:
        assert f["runs/0001-stack-150V/input"].attrs["units"] == "V"
    png = tmp_path / "loops.png"
    plotted = run_ok("plot", str(out), "-o", str(png))
    assert Path(plotted["png"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_demo(tmp_path):
    """The whole loop: sweep, fit, diagnose, add the hidden effects, falling-error table, report."""
    doc = run_ok("demo", "--output-dir", str(tmp_path), "-q")
    assert doc["status"] == "complete" and len(doc["runs"]) == 4
    assert Path(doc["png"]).stat().st_size > 20_000
    assert all(r["status"] == "complete" for r in doc["runs"])
    steps = doc["diagnosis"]["steps"]
    # the rig's hidden effects, added one by one or as a jointly judged pair
    added = {part for s in steps[1:] for part in s["added"].split("+")}
    assert steps[0]["spec"] == "pi" and added == {"asymmetry", "temperature"}
    assert steps[-1]["validation"]["rmse"] < steps[0]["validation"]["rmse"] / 10
    assert Path(doc["report"]).read_text().startswith("<!DOCTYPE html>")
