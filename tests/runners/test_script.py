"""`hilbench run SCRIPT.py`: the scripting API end to end through the real CLI, safety on every ending.

A test-only device (registered like a third party's driver) stands behind a real-rig config, so the
tests see every command the device received: the rig must end at rest, stopped and closed whether
the script completes, raises mid-sweep, raises between sweeps or is refused by hilbench.
"""

from __future__ import annotations

import json
import os
import sys
import textwrap
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from hilbench.cli import app
from hilbench.rig import registry

REPO = Path(__file__).resolve().parents[2]
EXPERIMENTS = sorted((REPO / "experiments").glob("*.py"))
runner = CliRunner()


class Stage:
    """A stage moving gain * command with a lag; remembers every command, stop and close."""

    def __init__(self) -> None:
        self.position_um = 0.0
        self.writes: list[float] = []
        self.stopped: list[bool] = []
        self.closed = False

    def identity(self) -> str:
        return "Test Instruments Stage SN 7"

    def capabilities(self) -> dict[str, Any]:
        return {"firmware": "0.1"}

    def close(self) -> None:
        self.closed = True

    def write(self, value: float) -> None:
        self.writes.append(value)
        self.position_um += 0.5 * (2.0 * value - self.position_um)

    def stop(self, success: bool) -> None:
        self.stopped.append(success)

    def read(self) -> dict[str, float]:
        return {"position": self.position_um}


class StageDriver:
    name = "script-test-stage"
    roles = ("actuator", "sensor")

    def __init__(self) -> None:
        self.opened: list[Stage] = []

    def problems(self, table: dict[str, Any]) -> list[str]:
        return [f"unknown key {k!r}" for k in table]

    def complete(self, table: dict[str, Any]) -> dict[str, Any]:
        return dict(table)

    def open(self, settings: dict[str, Any]) -> Stage:
        self.opened.append(Stage())
        return self.opened[-1]


STAGE_RIG = """
[rig]
name = "stage"
sample_rate_hz = 1000.0

[devices.stage]
driver = "script-test-stage"

[actuator]
device = "stage"
unit = "V"
min = -5.0
max = 5.0
max_rate = 100.0
rest = 1.0

[[sensors]]
channel = "output"
unit = "um"
device = "stage"
source = "position"
"""


@pytest.fixture
def stage(monkeypatch, tmp_path):
    driver = StageDriver()
    monkeypatch.setitem(sys.modules, "tests_script_stage", type("module", (), {"DRIVER": driver}))
    monkeypatch.setitem(registry.BUILTIN, "script-test-stage", "tests_script_stage:DRIVER")
    registry.clear_cache()
    config = tmp_path / "stage.toml"
    config.write_text(STAGE_RIG, encoding="utf-8")
    yield driver, config
    registry.clear_cache()


def script(tmp_path: Path, text: str, name: str = "experiment.py") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text), encoding="utf-8")
    return path


def run(*args: str):
    return runner.invoke(app, list(args))


def one_line_error(result, code: int) -> str:
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output
    lines = result.stderr.strip().splitlines()
    errors = [line for line in lines if line.startswith("error: ")]
    assert len(errors) == 1, lines
    return errors[0]


def statuses(path: Path) -> list[str]:
    with h5py.File(path, "r") as f:
        return [f["runs"][name].attrs["status"] for name in f["runs"]]


# -- a script end to end -------------------------------------------------------------------------


def test_run_a_tiny_script_on_a_simulated_rig(tmp_path):
    path = script(tmp_path, """
        from hilbench.runners.script import Bench, current_bench
        assert isinstance(bench, Bench) and current_bench() is bench
        plan = bench.plan("sine:amplitude=1|2,frequency_hz=2,cycles=2", {"kind": "step", "levels": [0, 0.5], "hold_s": 0.2, "rise_s": 0.01})
        sweep = bench.sweep(plan, "tiny.h5", label="tiny")
        print("printed by the script")
        fit = bench.fit(sweep, "pi", train=["1", "2"], test=["3"])
        bench.log("fitted")
        bench.report(runs=[r.label for r in sweep.runs], rmse=fit.metrics["train"]["rmse"], rig=bench.config.name,
                     args=bench.args, quick=bench.quick, at_rest=bench.rig.last_applied)
    """)
    out = tmp_path / "out"
    result = run("run", str(path), "--rig", "gmm-issf-duhem", "-o", str(out), "--quick", "--json", "--", "a1", "b2")
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)  # one JSON document; the script's print went to stderr
    assert "printed by the script" in result.stderr and "fitted" in result.stderr
    assert document["status"] == "complete" and document["rig"] == "gmm-issf-duhem"
    results = document["results"]
    assert results["runs"] == ["tiny-sine-amplitude=1", "tiny-sine-amplitude=2", "tiny-step"]
    assert results["args"] == ["a1", "b2"] and results["quick"] is True and results["rig"] == "gmm-issf-duhem"
    assert results["rmse"] > 0
    (recording,) = document["recordings"]
    assert Path(recording["file"]) == out / "tiny.h5"
    assert statuses(out / "tiny.h5") == ["complete"] * 3
    with h5py.File(out / "tiny.h5", "r") as f:
        run0 = f["runs"]["0001-tiny-sine-amplitude=1"]
        assert run0.attrs["experiment"] == "experiment"  # the script's name
        assert run0["input"].shape[0] == 1001


def test_the_rig_defaults_to_the_scripts_RIG_and_text_output(tmp_path):
    path = script(tmp_path, """
        RIG = "piezo-pmpi"
        bench.sweep("sine:amplitude=2,offset=3,frequency_hz=2,cycles=1", "x.h5")
        bench.report(rig=bench.config.name)
    """)
    result = run("run", str(path), "-o", str(tmp_path / "o"))
    assert result.exit_code == 0, result.output
    assert "complete on piezo-pmpi" in result.stdout and "rig = piezo-pmpi" in result.stdout


def test_a_script_runs_on_a_device_rig_and_leaves_it_at_rest(tmp_path, stage):
    driver, config = stage
    path = script(tmp_path, """
        bench.sweep("sine:amplitude=3,frequency_hz=2,cycles=2", "ok.h5")
        bench.sweep("sine:amplitude=2,offset=1,frequency_hz=2,cycles=1", "ok.h5")
    """)
    result = run("run", str(path), "--rig", str(config), "-o", str(tmp_path / "out"))
    assert result.exit_code == 0, result.output
    (device,) = driver.opened  # the rig was opened once for the whole script
    writes = np.array(device.writes)
    assert writes.min() >= -5.0 and writes.max() <= 5.0
    assert np.max(np.abs(np.diff(writes))) <= 100.0 / 1000.0 * (1 + 1e-9)
    assert writes[-1] == 1.0 and device.stopped[-1] is True and device.closed
    assert statuses(tmp_path / "out" / "ok.h5") == ["complete", "complete"]


# -- every way a script can end badly ------------------------------------------------------------------


def test_an_exception_mid_sweep_fails_the_run_and_makes_the_rig_safe(tmp_path, stage):
    driver, config = stage
    path = script(tmp_path, """
        def progress(index, label, done, total):
            if done >= 600:
                raise RuntimeError("the script's own check failed")

        bench.sweep("sine:amplitude=4,frequency_hz=1,cycles=2", "broken.h5", chunk_samples=100, progress=progress)
        bench.log("never reached")
    """, name="broken.py")
    result = run("run", str(path), "--rig", str(config), "-o", str(tmp_path / "out"))
    line = one_line_error(result, 1)
    assert line.startswith(f"error: {path}:4: RuntimeError: the script's own check failed")
    assert "never reached" not in result.output
    (device,) = driver.opened
    assert device.writes[-1] == 1.0 and False in device.stopped and device.closed  # ramped to rest, stopped, closed
    with h5py.File(tmp_path / "out" / "broken.h5", "r") as f:
        (name,) = list(f["runs"])
        assert f["runs"][name].attrs["status"] == "failed"
        assert "the script's own check failed" in f["runs"][name].attrs["reason"]
        assert f["runs"][name]["input"].shape[0] == 600  # the chunks before the failure are kept


def test_an_exception_between_sweeps_keeps_the_complete_recording_and_makes_safe(tmp_path, stage):
    driver, config = stage
    path = script(tmp_path, """
        bench.sweep("sine:amplitude=4,frequency_hz=2,cycles=1", "first.h5")
        values = {}
        values["missing"]
    """)
    result = run("run", str(path), "--rig", str(config), "-o", str(tmp_path / "out"))
    assert one_line_error(result, 1).startswith(f"error: {path}:4: KeyError: 'missing'")
    (device,) = driver.opened
    assert device.writes[-1] == 1.0 and device.stopped[-1] is False and device.closed
    assert statuses(tmp_path / "out" / "first.h5") == ["complete"]


def test_a_plan_outside_the_limits_is_refused_before_anything_moves(tmp_path, stage):
    driver, config = stage
    path = script(tmp_path, """
        bench.sweep("sine:amplitude=8,frequency_hz=1,cycles=1", "never.h5")
    """)
    result = run("run", str(path), "--rig", str(config), "-o", str(tmp_path / "out"))
    line = one_line_error(result, 2)
    assert "outside the actuator range" in line
    (device,) = driver.opened
    assert set(device.writes) == {1.0} and device.closed  # only the power-up rest value was written
    assert not (tmp_path / "out" / "never.h5").exists()


@pytest.mark.parametrize(("text", "expected"), [
    ("bench.plan(42)", "bench.plan() argument 1: expected a compact run string"),
    ("bench.plan('sine:amplitude=1,frequency_hz=1,cycles=1,bogus=3')", "bogus"),
    ("bench.sweep('sine:amplitude=1,frequency_hz=1,cycles=1', 'x.h5', speed=3)", "bench.sweep(): unknown option 'speed'"),
    ("bench.fit('absent.h5', 'pi')", "absent.h5"),
    ("def broken(:\n    pass", "experiment.py:1: invalid Python"),
])
def test_user_errors_in_a_script_are_one_line_with_status_2(tmp_path, text, expected):
    path = script(tmp_path, text)
    result = run("run", str(path), "--rig", "piezo-pmpi", "-o", str(tmp_path / "out"))
    assert expected in one_line_error(result, 2)


def test_command_line_errors_name_what_is_wrong(tmp_path):
    assert "no such script" in one_line_error(run("run", str(tmp_path / "absent.py"), "--rig", "piezo-pmpi"), 2)
    path = script(tmp_path, "pass\n")
    assert "no rig given" in one_line_error(run("run", str(path)), 2)
    assert "no-such-rig: no such file, and no built-in rig" in one_line_error(
        run("run", str(path), "--rig", "no-such-rig"), 2)


def test_bench_track_hands_the_reference_and_model_to_the_closed_loop(tmp_path, monkeypatch):
    from hilbench.online import tracking

    seen = {}

    def fake_track(rig, model, reference, **kw):
        seen.update(rig=rig.config.name, model=model, reference=list(reference), **kw)
        return "tracked"

    monkeypatch.setattr(tracking, "track", fake_track)
    path = script(tmp_path, """
        bench.report(can_track=bench.can_track, result=bench.track([0.0, 1.0], "fit.json", output="t.h5"))
    """)
    result = run("run", str(path), "--rig", "piezo-pmpi", "-o", str(tmp_path / "out"), "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["results"] == {"can_track": True, "result": "tracked"}
    # on real devices the rate is checked unless `hilbench run --allow-late` (a simulated rig ignores it)
    assert seen == {"rig": "piezo-pmpi", "model": "fit.json", "reference": [0.0, 1.0],
                    "output": tmp_path / "out" / "t.h5", "check_rate": True}


def test_a_second_rig_opened_by_the_script_is_closed_with_the_first(tmp_path, stage):
    driver, config = stage
    path = script(tmp_path, f"""
        other = bench.open_rig({str(config)!r})
        other.sweep("sine:amplitude=2,frequency_hz=2,cycles=1", "other.h5")
        raise SystemExit(3)
    """)
    result = run("run", str(path), "--rig", "piezo-pmpi", "-o", str(tmp_path / "out"))
    assert result.exit_code == 3
    (device,) = driver.opened
    assert device.writes[-1] == 1.0 and device.stopped[-1] is False and device.closed


# -- the papers' procedures --------------------------------------------------------------------------------

FULL = os.environ.get("HILBENCH_EXPERIMENTS", "") == "full"  # full size: each script under a minute


@pytest.mark.parametrize("path", EXPERIMENTS, ids=[p.stem for p in EXPERIMENTS])
def test_every_experiment_script_runs_on_its_simulated_rig(tmp_path, path):
    """Every experiments/*.py, with --quick (HILBENCH_EXPERIMENTS=full: at full size), on its own RIG."""
    from hilbench.runners.script import rig_named_by

    rig = rig_named_by(path)
    assert rig, f"{path.name} names no RIG"
    result = run("run", str(path), "--rig", rig, "-o", str(tmp_path), "--json", *([] if FULL else ["--quick"]))
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document["status"] == "complete" and document["recordings"] and document["results"]
    for recording in document["recordings"]:
        assert set(statuses(Path(recording["file"]))) == {"complete"}
    results = document["results"]
    # what each procedure reports, checked loosely against the papers (the reproductions test it closely)
    if path.stem.startswith("paper-001"):
        assert 0 < results["e_relative_pct"] < 1.53
    elif path.stem.startswith("paper-002"):
        assert results["step"]["natural_frequency_hz"] == pytest.approx(3200, rel=0.05)
        assert 0 < results["max_error_pct"] < 2.5
    elif path.stem.startswith("paper-003"):
        assert results["worst_e_max_pct"] < 6.5 and results["worst_e_rms_pct"] < 3.0
    elif path.stem.startswith("paper-004"):
        assert results["mre_pct"]["pmpi"] < 0.44
    elif path.stem.startswith("paper-000"):
        for channel in ("load", "temperature"):
            assert results[channel]["rmse_with_um"] < results[channel]["rmse_without_um"]
