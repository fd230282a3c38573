"""The benchmark scripts still run and print one JSON document (no timing is asserted)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def test_run_all_quick_prints_json():
    out = subprocess.run([sys.executable, str(BENCH / "run_all.py"), "--quick"], capture_output=True, text=True,
                         timeout=600, check=True)
    document = json.loads(out.stdout)
    summary = document["summary"]
    assert summary["plant_block_samples_per_s"] > 0 and summary["plant_ratio_vs_loop"] > 0
    # the peer computes the same physics: otherwise its speed would mean nothing
    assert summary["plant_peer_max_abs_diff_um"] < 1e-9
    assert document["meets_target"]["recording.long_run_complete"] is True
