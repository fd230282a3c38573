"""The README's Python example runs as written from an empty directory (a fresh process), and the
API's verbs are the commands' own: the fit it prints is the fit `hilbench fit --json` reports."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def readme_example() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return text.split("## Python API", 1)[1].split("```python", 1)[1].split("```", 1)[0]


def test_the_readme_python_example_runs_from_an_empty_directory(tmp_path: Path) -> None:
    code = readme_example()
    assert "import hilbench" in code and "hilbench.fit(" in code and "hilbench.diagnose(" in code
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.splitlines()
    assert lines[0].startswith("Run('0001-sine', complete, 4001 samples at 1000 Hz")
    assert lines[1].startswith("FitResult('pi' fitted on 1 run(s): validation rmse")
    assert lines[2].startswith("Diagnosis('pi+") and "added" in lines[2]
    assert float(lines[3]) < 0.5  # um: the effects --auto added explain most of pi's error on the demo stack
    single = subprocess.run([sys.executable, "-m", "hilbench.cli", "fit", "work/sweep.h5", "-m", "pi", "--json"],
                            cwd=tmp_path, capture_output=True, text=True, timeout=300)
    rmse = json.loads(single.stdout)["metrics"]["validation"]["rmse"]
    assert f"validation rmse {rmse:.4g} um" in lines[1]
