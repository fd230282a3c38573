"""The README tour runs from an empty directory: no file of the source tree is needed.

The lines of the tour that work on hilbench's own rigs and plans run as written (a real process in
an empty temporary folder); the import line runs on a CSV written here, with µm and a Latin-1
header. Lines that need your measured files or hardware, and the slow diagnosis and demo, are left
to their own tests.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUN_AS_WRITTEN = ("rigs", "sweep gmm-issf-duhem", "sweep gmm-gu2016 --plan", "sweep piezo-pmpi --plan",
                  "show sweep.h5", "plot sweep.h5", "import data.csv", "fit sweep.h5", "batch example", "batch fit")


def tour_lines() -> list[list[str]]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    block = text.split("## A tour of the command line", 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    lines = []
    for line in block.splitlines():
        command = re.sub(r"\s+#.*$", "", line).strip()
        if command.startswith("hilbench ") and command[len("hilbench "):].startswith(RUN_AS_WRITTEN):
            lines.append(shlex.split(command)[1:])
    return lines


def test_tour_runs_from_an_empty_directory(tmp_path):
    lines = tour_lines()
    assert len(lines) >= 11, lines  # the tour still has the lines this test runs
    rows = "\n".join(f"{k / 100:.2f};{k % 10};{(k % 10) * 0.5:.2f}" for k in range(200))
    (tmp_path / "data.csv").write_bytes(("time[s];input[V];output[µm]\n" + rows + "\n").encode("latin-1"))
    for argv in lines:
        proc = subprocess.run([sys.executable, "-m", "hilbench.cli", *argv], cwd=tmp_path, capture_output=True,
                              text=True, timeout=900)
        assert proc.returncode == 0, (argv, proc.stderr[-2000:])
        assert "Traceback" not in proc.stderr
    shown = subprocess.run([sys.executable, "-m", "hilbench.cli", "show", "measured.h5", "--json"], cwd=tmp_path,
                           capture_output=True, text=True, timeout=300)
    units = {c["name"]: c["units"] for c in json.loads(shown.stdout)["runs"][0]["channels"]}
    assert units == {"time": "s", "input": "V", "output": "um"}
    for name in ("sweep.h5", "id.h5", "track.h5", "loop.png", "fit.json", "fit.png", "results/results.parquet",
                 "results/report.html"):
        assert (tmp_path / name).is_file(), name
