"""A simulated archive to try the batch commands on: one piezo stack recorded day after day.

The stack is the demo rig's (``piezo-demo``: play-operator hysteresis, an asymmetric polynomial, a
housing that warms while it is driven). Each recording is one simulated day: the stack ages (its
stroke falls by :data:`AGEING_PER_DAY` a day), the lab's morning temperature varies (some days
warmer), and on every third day a load sits on the stack (a constant weight, recorded by a load
cell). Each day drives the same 1 Hz sine. The recording's ``created`` attribute is set to its
simulated day (and ``example_archive`` says so), so the report draws the ageing against the date.
"""

from __future__ import annotations

import tempfile
from datetime import datetime, timedelta, timezone
from pathlib import Path

import h5py
import numpy as np

AGEING_PER_DAY = 0.002  # relative loss of stroke per day
FIRST_DAY = datetime(2026, 1, 5, 9, 0, tzinfo=timezone.utc)
SAMPLE_RATE_HZ = 1000.0  # the demo rig's


def _day_config(day: int, ambient_degC: float, load_kg: float, seconds: float, seed: int) -> str:
    """The demo rig on one day, as a config extending it (TOML)."""
    scale = 60.0 * (1.0 - AGEING_PER_DAY * day)
    cycles = max(1, int(round(seconds)))  # 1 Hz: a cycle a second
    text = f"""[rig]
name = "piezo-demo-day{day:03d}"
extends = "piezo-demo"
description = "example archive: piezo-demo on day {day}"
seed = {seed}

[plant.hysteresis]
model = "play"
input_scale = 100.0
output_scale = {scale!r}
linear_gain = 0.6
thresholds = [0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4]
weights = [0.30, 0.20, 0.15, 0.10, 0.08, 0.06, 0.04, 0.03]

[plant.temperature]
reference_degC = 22.0
gain_per_degC = 0.01
strain_um_per_degC = 0.3
trajectory = {{ kind = "cooling", initial = {ambient_degC!r}, ambient = {ambient_degC + 10.0!r}, time_constant_s = 60.0 }}

[[plan.runs]]
label = "sine"
kind = "sine"
offset = 50.0
amplitude = 45.0
phase_deg = -90.0
frequency_hz = 1.0
cycles = {cycles}
"""
    if load_kg > 0:
        text += f"""
[[sensors]]
channel = "output"
unit = "um"
driver = "sim"
description = "capacitive sensor"
noise_std = 0.02
quantization = 0.001
range = [-40.0, 150.0]

[[sensors]]
channel = "temperature"
unit = "degC"
driver = "sim"
description = "thermocouple on the housing"
noise_std = 0.02
quantization = 0.01

[[sensors]]
channel = "load"
unit = "N"
driver = "sim"
description = "load cell under the stack"
noise_std = 0.2
quantization = 0.05

[plant.load]
gain_per_N = 0.001
compliance_um_per_N = 0.05
trajectory = {{ kind = "constant", value = {load_kg * 9.81!r} }}
"""
    return text


def write_example_archive(folder: Path, recordings: int = 50, seconds: float = 4.0, seed: int = 0) -> list[Path]:
    """Write ``recordings`` simulated days of ``seconds`` each (1 kHz) into ``folder``; return their paths."""
    from hilbench.excitation.plan import expand_runs
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig
    from hilbench.runners.sweep import run_plan

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    written = []
    with tempfile.TemporaryDirectory() as tmp:
        for day in range(recordings):
            ambient = float(np.round(21.0 + rng.uniform(-2.0, 2.0) + (6.0 if rng.uniform() < 0.3 else 0.0), 2))
            load_kg = 5.0 if day % 3 == 2 else 0.0
            config_path = Path(tmp) / f"day{day:03d}.toml"
            config_path.write_text(_day_config(day, ambient, load_kg, seconds, seed * 1000 + day), encoding="utf-8")
            config = load_rig(config_path)
            when = FIRST_DAY + timedelta(days=day)
            out = folder / f"stack-{when:%Y-%m-%d}.h5"
            if out.exists():
                out.unlink()
            run_plan(Rig(config), expand_runs(config.plan, file=config.path), out, realtime=False)
            with h5py.File(out, "a") as f:
                f.attrs["created"] = when.isoformat(timespec="seconds")
                f.attrs["example_archive"] = (f"simulated day {day}: ambient {ambient} degC, load {load_kg} kg, stroke "
                                              f"{100 * (1 - AGEING_PER_DAY * day):.1f} % of day 0; 'created' is that day")
            written.append(out)
    return written
