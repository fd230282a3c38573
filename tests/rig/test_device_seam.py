"""The device seam: a backend written here, in the tests alone, runs a sweep through the rig.

Nothing in hilbench knows this backend: it satisfies the protocols of hilbench.rig.protocols by
shape, is registered like a third-party driver (through the registry's entry points), validated by
the config, and every command it receives has passed the rig's safety path.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import h5py
import json
import numpy as np
import pytest

from hilbench.rig import registry
from hilbench.rig.config import load_rig
from hilbench.rig.protocols import Actuator, DriverEntry, Sensor
from hilbench.rig.rig import Rig
from hilbench.excitation.plan import plan_from_compact
from hilbench.runners.sweep import run_plan


class SpringStage:
    """A stage that moves gain * command with a first-order lag; a sensor reads it in um."""

    def __init__(self, gain_um_per_v: float, fail_after: int | None = None):
        self.gain = gain_um_per_v
        self.position_um = 0.0
        self.writes: list[float] = []
        self.stopped: list[bool] = []
        self.fail_after = fail_after
        self.closed = False

    def identity(self) -> str:
        return "Test Instruments SpringStage SN 0001"

    def capabilities(self) -> dict[str, Any]:
        return {"firmware": "1.2.3", "gain_um_per_v": self.gain}

    def close(self) -> None:
        self.closed = True

    def write(self, value: float) -> None:
        self.writes.append(value)
        self.position_um += 0.5 * (self.gain * value - self.position_um)

    def stop(self, success: bool) -> None:
        self.stopped.append(success)

    def read(self) -> dict[str, float]:
        if self.fail_after is not None and len(self.writes) > self.fail_after:
            raise OSError("SpringStage: sensor cable unplugged")
        return {"position": self.position_um}


@dataclass
class SpringDriver:
    """A device family registered like any third party's."""

    name: str = "spring-stage"
    roles: tuple[str, ...] = ("actuator", "sensor")
    opened: list[SpringStage] = field(default_factory=list)

    def problems(self, table: dict[str, Any]) -> list[str]:
        extra = set(table) - {"gain_um_per_v", "fail_after"}
        missing = {"gain_um_per_v"} - set(table)
        return [f"unknown key {k!r}" for k in sorted(extra)] + [f"missing key {k!r}" for k in sorted(missing)]

    def complete(self, table: dict[str, Any]) -> dict[str, Any]:
        return dict(table)

    def open(self, settings: dict[str, Any]) -> SpringStage:
        stage = SpringStage(float(settings["gain_um_per_v"]), settings.get("fail_after"))
        self.opened.append(stage)
        return stage


RIG = """
[rig]
name = "spring"
sample_rate_hz = 1000.0

[devices.stage]
driver = "spring-stage"
gain_um_per_v = 2.0
{extra}

[actuator]
device = "stage"
unit = "V"
min = -5.0
max = 5.0
max_rate = 200.0
rest = 1.0

[[sensors]]
channel = "output"
unit = "um"
device = "stage"
source = "position"
scale = 1.0
offset = 0.0
"""


@pytest.fixture
def spring_driver(monkeypatch):
    driver = SpringDriver()
    assert isinstance(driver, DriverEntry)
    module = type("module", (), {"DRIVER": driver})
    import sys

    monkeypatch.setitem(sys.modules, "tests_spring_driver", module)
    monkeypatch.setitem(registry.BUILTIN, "spring-stage", "tests_spring_driver:DRIVER")
    registry.clear_cache()
    yield driver
    registry.clear_cache()


def _rig(tmp_path, extra: str = ""):
    path = tmp_path / "spring.toml"
    path.write_text(RIG.format(extra=extra), encoding="utf-8")
    return load_rig(path)


def test_a_test_backend_satisfies_the_protocols(spring_driver):
    stage = spring_driver.open({"gain_um_per_v": 1.0})
    assert isinstance(stage, Actuator) and isinstance(stage, Sensor)


def test_sweep_through_the_safety_path_of_a_test_backend(tmp_path, spring_driver):
    config = _rig(tmp_path)
    # 8 V amplitude on a +-5 V actuator: the plan check refuses it before anything moves ...
    with pytest.raises(Exception, match="outside the actuator range"):
        run_plan(Rig(config), plan_from_compact(["sine:amplitude=8,frequency_hz=2,cycles=1"]), tmp_path / "x.h5")
    stage_refused = spring_driver.opened[-1]
    assert all(w == 1.0 for w in stage_refused.writes)  # only the power-up rest value was written
    # ... a legal plan runs, and every command the device saw is inside the limits and slew rate.
    rig = Rig(config)
    out = tmp_path / "spring.h5"
    result = run_plan(rig, plan_from_compact(["sine:amplitude=4,frequency_hz=2,cycles=2"]), out)
    rig.close()
    stage = spring_driver.opened[-1]
    assert result.status == "complete"
    writes = np.array(stage.writes)
    assert writes.min() >= -5.0 and writes.max() <= 5.0
    assert np.max(np.abs(np.diff(writes))) <= 200.0 / 1000.0 * (1 + 1e-9)
    assert writes[-1] == 1.0 and stage.stopped == [True] and stage.closed  # back at rest, stopped, closed
    with h5py.File(out, "r") as f:
        run = f["runs"][next(iter(f["runs"]))]
        u, y = run["input"][:], run["output"][:]
        devices = json.loads(run.attrs["devices"])
    assert devices[0]["identity"] == "Test Instruments SpringStage SN 0001"
    assert devices[0]["driver"] == "spring-stage" and devices[0]["firmware"] == "1.2.3"
    # the recorded output is what the device measured for the recorded input (its lag law)
    pos = y[0]
    expected = [pos]
    for value in u[1:]:
        pos += 0.5 * (2.0 * value - pos)
        expected.append(pos)
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-12)


def test_a_failing_test_backend_is_made_safe_and_the_run_says_why(tmp_path, spring_driver):
    config = _rig(tmp_path, "fail_after = 600")
    rig = Rig(config)
    out = tmp_path / "fail.h5"
    with pytest.raises(OSError, match="sensor cable unplugged"):
        run_plan(rig, plan_from_compact(["sine:amplitude=4,frequency_hz=1,cycles=2"]), out, chunk_samples=100)
    stage = spring_driver.opened[-1]
    assert stage.writes[-1] == 1.0 and stage.stopped == [False]  # ramped to rest despite the dead sensor
    with h5py.File(out, "r") as f:
        run = f["runs"][next(iter(f["runs"]))]
        assert run.attrs["status"] == "failed"
        assert "sensor cable unplugged" in run.attrs["reason"]
        assert run["output"].shape[0] >= 500  # the chunks before the fault are kept


def test_the_config_checks_a_device_table_with_its_driver(tmp_path, spring_driver):
    path = tmp_path / "bad.toml"
    path.write_text(RIG.format(extra="gain = 3").replace("gain_um_per_v = 2.0\n", ""), encoding="utf-8")
    with pytest.raises(Exception, match=r"\[devices.stage\] unknown key 'gain'"):
        load_rig(path)


def test_an_unknown_driver_lists_the_registered_ones(tmp_path):
    path = tmp_path / "unknown.toml"
    path.write_text(RIG.format(extra="").replace('driver = "spring-stage"', 'driver = "nope"'), encoding="utf-8")
    with pytest.raises(Exception, match="unknown driver 'nope'; registered drivers: .*sim"):
        load_rig(path)
