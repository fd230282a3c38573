"""Shared fixtures: small rig configs written to tmp_path, the real-data folder."""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def real_data_dir() -> Path | None:
    """../shared/data/real next to the checkout, or $HILBENCH_REAL_DATA; None when absent."""
    candidates = [REPO.parent / "shared" / "data" / "real"]
    if os.environ.get("HILBENCH_REAL_DATA"):
        candidates.insert(0, Path(os.environ["HILBENCH_REAL_DATA"]))
    return next((c for c in candidates if c.is_dir()), None)


def require_real_data() -> Path:
    """The real-data folder, or skip the test when it is absent."""
    folder = real_data_dir()
    if folder is None:
        pytest.skip("real data folder ../shared/data/real not found (set HILBENCH_REAL_DATA)")
    return folder


MINIMAL_RIG = """
[rig]
name = "mini"
sample_rate_hz = 1000.0
seed = 7

[actuator]
driver = "sim"
unit = "V"
min = -10.0
max = 10.0
max_rate = 1000.0
rest = 0.0

[[sensors]]
channel = "output"
unit = "um"
driver = "sim"
noise_std = 0.01

[plant.hysteresis]
model = "play"
linear_gain = 1.0
thresholds = [0.5, 1.0, 2.0]
weights = [0.5, 0.3, 0.2]
"""


@pytest.fixture
def write_rig(tmp_path: Path):
    """Write a rig TOML (default: a minimal PI rig plus `extra` text) and return its path."""

    def _write(extra: str = "", base: str = MINIMAL_RIG, name: str = "rig.toml") -> Path:
        path = tmp_path / name
        path.write_text(textwrap.dedent(base) + "\n" + textwrap.dedent(extra), encoding="utf-8")
        return path

    return _write
