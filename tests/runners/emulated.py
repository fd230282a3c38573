"""Helpers of the emulated-rig acceptance tests: the rigs, the reduced 001 plan, the sim reference."""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from hilbench.excitation.plan import PlannedRun, plan_from_compact
from hilbench.recording.hdf5 import Recording
from hilbench.rig.config import RigConfig, load_rig
from hilbench.rig.emulation import EmulatedRig, start_emulators
from hilbench.rig.rig import Rig
from hilbench.runners.sweep import run_plan

REPO = Path(__file__).resolve().parents[2]
RIGS = {
    "pi-gcs": REPO / "tests" / "runners" / "rigs" / "gmm-pi-gcs.toml",
    "modbus-canopen": REPO / "configs" / "templates" / "gmm-modbus-canopen.toml",
    "modbus-keyence": REPO / "configs" / "templates" / "gmm-modbus-keyence.toml",
}
NOISE_STD_UM = 0.05  # the [[sensors]] output noise_std of gmm-issf-duhem


def reduced_001_plan() -> list[PlannedRun]:
    """The 001 sweep shortened: 2/4/6 A sines (one 1 Hz cycle each) and a 6/3 A 1 Hz triangle."""
    return plan_from_compact(["sine:amplitude=2|4|6,frequency_hz=1,cycles=1",
                              "triangle:frequency_hz=1,amplitudes=6/3"])


def sim_reference(config: RigConfig) -> RigConfig:
    """The same rig on the pure simulated backend: same plant, sensors, seed, limits."""
    return dataclasses.replace(
        config, actuator=dataclasses.replace(config.actuator, driver="sim", device=""),
        sensors=[dataclasses.replace(s, driver="sim", device="") for s in config.sensors], devices={})


def with_device_settings(config: RigConfig, name: str, **settings: Any) -> RigConfig:
    devices = {k: dict(v) for k, v in config.devices.items()}
    devices[name].update(settings)
    return dataclasses.replace(config, devices=devices)


@contextmanager
def emulated(kind: str, **device_settings: dict[str, Any]) -> Iterator[tuple[EmulatedRig, Rig]]:
    """Emulators of a rig and the Rig opened on them; everything closed afterwards."""
    config = load_rig(RIGS[kind])
    for name, settings in device_settings.items():
        config = with_device_settings(config, name, **settings)
    emu = start_emulators(config)
    rig = None
    try:
        rig = Rig(emu.config_for_emulators())
        yield emu, rig
    finally:
        try:
            if rig is not None:
                rig.close()
        finally:
            emu.close()


def record_sim(config: RigConfig, runs: list[PlannedRun], out: Path) -> Path:
    run_plan(Rig(sim_reference(config)), runs, out)
    return out


def rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


def ramp_ok(values: list[float], max_step: float, lo: float, hi: float, tol: float) -> bool:
    """Every value inside [lo, hi] and no step above max_step (tol: the device's quantisation)."""
    v = np.asarray(values, dtype=np.float64)
    return bool(v.min() >= lo - tol and v.max() <= hi + tol and np.max(np.abs(np.diff(v)), initial=0) <= max_step + tol)


def first_line(reason: str) -> str:
    return reason.split("\n", 1)[0]


def recorded(path: Path) -> list[Any]:
    return list(Recording(path))


def config_file(emu: EmulatedRig, template: Path, folder: Path, rate_hz: float | None = None) -> Path:
    """A real-rig config as a user writes it to reach the emulators: the template with the urls that
    `hilbench emulate` prints copied into its device tables (and ``sample_rate_hz`` when given)."""
    text = template.read_text(encoding="utf-8")
    for name, settings in emu.settings.items():
        if "url" not in settings:
            continue
        table = re.search(rf"^\[devices\.{re.escape(name)}\]$(.*?)(?=^\[)", text, flags=re.S | re.M)
        assert table is not None, name
        body = re.sub(r'^url = ".*"$', f'url = "{settings["url"]}"', table.group(1), count=1, flags=re.M)
        text = text[:table.start(1)] + body + text[table.end(1):]
    if rate_hz is not None:
        text = re.sub(r"^(\[rig\]\n)", rf"\1sample_rate_hz = {rate_hz!r}\n", text, count=1, flags=re.M)
    path = folder / "rig.toml"
    path.write_text(text, encoding="utf-8")
    return path
