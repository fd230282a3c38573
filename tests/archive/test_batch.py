"""`hilbench batch` over a generated archive: every row, failures with reasons, resume, same rows as
the single commands, Ctrl-C, each run alone. The engine runs a real local Dask cluster."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hilbench.archive.example import write_example_archive
from hilbench.archive.results import COLUMN_NAMES, read_table
from hilbench.archive.tasks import row_fields

HILBENCH = [sys.executable, "-m", "hilbench.cli"]
RECORDINGS = 50


def first_days(archive: Path, folder: Path, count: int) -> Path:
    """A folder holding copies of the archive's first ``count`` days."""
    folder.mkdir()
    for path in sorted(archive.glob("stack-*.h5"))[:count]:
        shutil.copy(path, folder / path.name)
    return folder


def hilbench(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*HILBENCH, *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def archive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """50 simulated days (some warm, every third loaded) and two damaged files: one cut short, one not HDF5."""
    folder = tmp_path_factory.mktemp("archive")
    paths = write_example_archive(folder / "stack", RECORDINGS, seconds=2.0, seed=3)
    cut = folder / "stack" / "cut-short.h5"
    cut.write_bytes(paths[0].read_bytes()[:4000])
    (folder / "stack" / "not-hdf5.h5").write_bytes(os.urandom(3000))
    return folder / "stack"


@pytest.fixture(scope="module")
def fitted(archive: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("fit") / "results"
    done = hilbench("batch", "fit", str(archive), "-m", "pi", "-o", str(out), "--workers", "2", "--json")
    assert done.returncode == 0, done.stderr
    return out, json.loads(done.stdout)


def test_every_recording_has_a_row_and_the_damaged_ones_say_why(fitted: tuple[Path, dict]) -> None:
    out, summary = fitted
    rows = read_table(out / "results.parquet")
    assert len(rows) == RECORDINGS + 2 == summary["rows"] == summary["tasks"]
    assert list(rows[0]) == COLUMN_NAMES
    failed = {r["name"]: r["error"] for r in rows if r["status"] == "failed"}
    assert set(failed) == {"cut-short.h5", "not-hdf5.h5"}
    assert "cut short" in failed["cut-short.h5"]
    assert "not a readable HDF5 file" in failed["not-hdf5.h5"]
    done = [r for r in rows if r["status"] == "done"]
    assert all(math.isfinite(r["validation_rmse"]) and r["validation_rmse"] < 2.0 for r in done)
    assert all(len(r["content_hash"]) == 64 for r in rows)
    loaded = [r for r in done if "load" in json.loads(r["aux_means"])]
    assert len(loaded) == RECORDINGS // 3  # every third day carries the weight: 5 kg, 49 N
    assert all(abs(json.loads(r["aux_means"])["load"] - 49.05) < 0.5 for r in loaded)
    assert len({r["worker"] for r in done}) == 2  # both workers of the local cluster took tasks
    with open(out / "results.csv", encoding="utf-8") as f:
        assert sum(1 for _ in f) == RECORDINGS + 3  # header + a row each
    report = (out / "report.html").read_text(encoding="utf-8")
    assert "Parameters over the archive" in report and "cut-short.h5" in report


def test_a_rerun_does_no_work(archive: Path, fitted: tuple[Path, dict], tmp_path: Path) -> None:
    out, first = fitted
    again = hilbench("batch", "fit", str(archive), "-m", "pi", "-o", str(out), "--json")
    assert again.returncode == 0, again.stderr
    summary = json.loads(again.stdout)
    assert summary["computed"] == 0 and summary["skipped_already_done"] == RECORDINGS + 2
    assert summary["cluster"] == {}  # no cluster was even started
    before = {r["key"]: r["validation_rmse"] for r in read_table(out / "results.parquet")}
    assert len(before) == RECORDINGS + 2
    # other options are other results: the same archive with another split is computed again
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    other = hilbench("batch", "fit", str(archive), "-m", "pi", "--train-fraction", "0.5", "-o", str(copy), "--json")
    assert json.loads(other.stdout)["computed"] == RECORDINGS + 2


def test_a_row_is_what_the_single_command_prints(archive: Path, fitted: tuple[Path, dict]) -> None:
    out, _ = fitted
    rows = {r["name"]: r for r in read_table(out / "results.parquet")}
    name = sorted(rows)[7]
    single = hilbench("fit", str(archive / name), "-m", "pi", "--json")
    assert single.returncode == 0, single.stderr
    expected = row_fields("fit", json.loads(single.stdout))
    row = rows[name]
    for column in ("train_rmse", "validation_rmse", "validation_erms_pct", "validation_re_n2_pct", "final_spec"):
        assert row[column] == expected[column], column
    assert json.loads(row["parameters"]) == json.loads(expected["parameters"])


def test_identical_files_are_computed_once_and_listed_twice(archive: Path, tmp_path: Path) -> None:
    folder = tmp_path / "two"
    folder.mkdir()
    source = sorted(archive.glob("stack-*.h5"))[0]
    shutil.copy(source, folder / "a.h5")
    shutil.copy(source, folder / "copy-of-a.h5")
    done = hilbench("batch", "fit", str(folder), "-m", "pi", "-o", str(tmp_path / "out"), "--workers", "1", "--json")
    summary = json.loads(done.stdout)
    assert summary["computed"] == 1 and summary["rows"] == 2
    rows = read_table(tmp_path / "out" / "results.parquet")
    assert [r["name"] for r in rows] == ["a.h5", "copy-of-a.h5"]
    assert rows[0]["validation_rmse"] == rows[1]["validation_rmse"]


DAYS = 4  # the days the Ctrl-C test diagnoses


def test_ctrl_c_keeps_every_finished_row_and_a_rerun_finishes(archive: Path, tmp_path: Path) -> None:
    # four days: the SIGINT comes within 0.1 s of the second row, while the third (one worker, one
    # thread: a task at a time, seconds each) runs, so it always leaves days undone for the rerun
    folder = first_days(archive, tmp_path / "four", DAYS)
    out = tmp_path / "out"
    args = ["batch", "diagnose", str(folder), "-m", "pi", "-o", str(out), "--workers", "1"]
    process = subprocess.Popen([*HILBENCH, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)
    rows_file = out / "rows.jsonl"
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and not (rows_file.exists() and rows_file.read_text().count("\n") >= 2):
        time.sleep(0.1)
    os.killpg(process.pid, signal.SIGINT)  # what the terminal does on Ctrl-C: the whole group
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    kept = read_table(out / "results.parquet")
    assert 2 <= len(kept) < DAYS and all(r["status"] == "done" for r in kept)
    assert json.loads((out / "summary.json").read_text())["interrupted"] is True
    again = hilbench(*args, "--json")
    summary = json.loads(again.stdout)
    assert summary["skipped_already_done"] == len(kept) and summary["computed"] == DAYS - len(kept)
    assert len(read_table(out / "results.parquet")) == DAYS


def test_each_run_is_its_own_row(tmp_path: Path) -> None:
    recording = tmp_path / "two-runs.h5"
    swept = hilbench("sweep", "piezo-demo", "-q", "-o", str(recording),
                     "-e", "sine:amplitude=30,offset=50,phase_deg=-90,frequency_hz=1,cycles=3",
                     "-e", "sine:amplitude=45,offset=50,phase_deg=-90,frequency_hz=2,cycles=5")
    assert swept.returncode == 0, swept.stderr
    out = tmp_path / "out"
    done = hilbench("batch", "fit", str(recording), "-m", "pi", "--each", "run", "-o", str(out), "--workers", "1",
                    "--json")
    assert done.returncode == 0, done.stderr
    rows = read_table(out / "results.parquet")
    assert [r["run"] for r in rows] == ["0001-sine", "0002-sine"]
    assert all(r["status"] == "done" and r["runs"] == 1 for r in rows)
    assert [r["samples"] for r in rows] == [3001, 2501]  # each read alone: 3 s and 2.5 s at 1 kHz
    assert rows[0]["content_hash"] == rows[1]["content_hash"] and rows[0]["key"] != rows[1]["key"]


@pytest.mark.parametrize("args, where", [
    (["batch", "fit", "no-such-folder", "-m", "pi"], "SOURCE"),
    (["batch", "fit", ".", "-m", "pi", "--workers", "0"], "--workers"),
    (["batch", "fit", ".", "-m", "nonsense-base"], "--model"),
    (["batch", "fit", ".", "-m", "pi", "--each", "day"], "--each"),
    (["batch", "online", ".", "--forgetting", "1.5"], "--forgetting"),
    (["batch", "fit", ".", "-m", "pi", "--scheduler", "tcp://127.0.0.1:9"], "--scheduler"),
])
def test_bad_input_is_one_line_and_exit_2(args: list[str], where: str, archive: Path, tmp_path: Path) -> None:
    args = [str(archive) if a == "." else a for a in args]
    done = subprocess.run([*HILBENCH, *args], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert not any(tmp_path.iterdir())  # refused before anything was written (the default output folder)
    lines = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and where in lines[0], done.stderr
    assert "Traceback" not in done.stderr


def test_online_rows_are_what_the_single_command_prints(archive: Path, tmp_path: Path) -> None:
    folder = first_days(archive, tmp_path / "two", 2)
    out = tmp_path / "out"
    done = hilbench("batch", "online", str(folder), "--global-starts", "2", "-o", str(out), "--workers", "1", "--json")
    assert done.returncode == 0, done.stderr
    rows = read_table(out / "results.parquet")
    assert [r["status"] for r in rows] == ["done", "done"]
    single = hilbench("online", str(folder / rows[1]["name"]), "--global-starts", "2", "--json")
    assert single.returncode == 0, single.stderr
    expected = row_fields("online", json.loads(single.stdout))
    for column in ("online_re_n2_pct", "offline_re_n2_pct", "persistence_re_n2_pct", "train_rmse", "final_spec"):
        assert rows[1][column] == expected[column], column
    assert rows[1]["online_re_n2_pct"] < rows[1]["persistence_re_n2_pct"]  # the identifier predicts better than y(k-1)


def test_docs_list_every_column() -> None:
    from hilbench.archive.results import COLUMNS

    text = (Path(__file__).resolve().parents[2] / "docs" / "archive.md").read_text(encoding="utf-8")
    for name, kind, meaning in COLUMNS:
        assert f"| `{name}` | {kind} | {meaning} |" in text, name


def test_options_are_the_single_commands_and_a_wrong_one_is_named() -> None:
    from hilbench.archive.tasks import default_options
    from hilbench.errors import UserError

    assert default_options("fit", {"model": "pi"}) == {"model": "pi", "train": [], "test": [], "train_fraction": None}
    assert default_options("online", {"model": "front.json"})["online_model"] == "front.json"
    for command, given, where in (("fit", {"model": "pi", "auto": True}, "auto"), ("diagnose", {}, "model"),
                                  ("plot", {}, "plot")):
        try:
            default_options(command, given)
        except UserError as exc:
            assert where in exc.line()
        else:
            raise AssertionError((command, given))
