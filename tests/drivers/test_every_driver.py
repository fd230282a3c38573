"""A meta-test over every registered driver (pymeasure-style): the shape of a driver entry, and that a
driver with an emulator opens against it and says who it is.

The drivers come from the registry, so a family registered only here, by a test entry point, is
checked like the shipped ones.
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np
import pytest

from hilbench.rig import registry
from hilbench.rig.protocols import Device, DriverEntry

KNOWN_ROLES = {"actuator", "sensor", "player", "lockstep"}
SHIPPED = {"sim", "pi-gcs", "keyence-lk", "modbus-aio", "canopen-sensor"}
try:  # ni-daqmx opens only with its optional package (pip install 'hilbench[nidaqmx]')
    import nidaqmx  # noqa: F401

    SHIPPED.add("ni-daqmx")
except ImportError:
    pass


class TrivialWorld:
    """A world in which the output is 2 um per unit of the last command."""

    def __init__(self) -> None:
        self.u = 0.0

    def command(self, value: float) -> None:
        self.u = float(value)

    def read(self, channel: str) -> float:
        return 2.0 * self.u if channel == "output" else 0.0

    def play(self, waveform: np.ndarray, rate_hz: float) -> dict[str, np.ndarray]:
        u = np.asarray(waveform, float)
        return {"output": 2.0 * u, "input": u}


class EchoDevice:
    def __init__(self, url: str) -> None:
        self.url = url

    def identity(self) -> str:
        return f"Test Echo at {self.url}"

    def capabilities(self) -> dict[str, Any]:
        return {}

    def read(self) -> dict[str, float]:
        return {"output": 0.0}

    def close(self) -> None:
        pass


class EchoEmulator:
    def __init__(self, settings: dict[str, Any], world: Any) -> None:
        self.url = "echo://emulated"
        self.closed = False

    def close(self) -> None:
        self.closed = True


def _test_only_driver() -> Any:
    from drivers.base import DriverSpec, Setting

    return DriverSpec(name="test-echo", roles=("sensor",), settings=(Setting("url", str, required=True, doc="where"),),
                      open=lambda settings: EchoDevice(settings["url"]), emulator=EchoEmulator,
                      description="registered by a test entry point", transports=("echo://",))


@pytest.fixture(autouse=True)
def test_entry_point(monkeypatch):
    monkeypatch.setitem(sys.modules, "tests_echo_driver", type("module", (), {"DRIVER": _test_only_driver()}))
    monkeypatch.setitem(registry.BUILTIN, "test-echo", "tests_echo_driver:DRIVER")
    registry.clear_cache()
    yield
    registry.clear_cache()


def names() -> list[str]:
    return sorted(SHIPPED | {"test-echo"})


def test_the_registry_lists_the_shipped_drivers_and_the_test_one():
    assert set(names()) <= set(registry.driver_names())


@pytest.mark.parametrize("name", names())
def test_every_driver_has_the_shape_of_a_driver_entry(name):
    driver = registry.get_driver(name)
    assert isinstance(driver, DriverEntry)
    assert driver.name == name
    assert driver.roles and set(driver.roles) <= KNOWN_ROLES
    assert callable(driver.open) and callable(driver.complete)
    wrong = driver.problems({"no_such_setting_anywhere": 1})
    assert isinstance(wrong, list) and wrong  # an unknown key (or a missing table) is a problem
    settings = getattr(driver, "settings", None)
    if settings is not None:  # a DriverSpec: every required setting is reported missing by name
        required = [s.name for s in settings if s.required]
        missing = driver.problems({})
        assert all(any(repr(r) in p for p in missing) for r in required), missing
        defaults = driver.complete({})
        assert all(defaults[s.name] == s.default for s in settings if s.default is not None)


def _minimal_table(driver: Any) -> dict[str, Any]:
    """The required settings with placeholders an emulator accepts."""
    placeholder = {str: "unused", int: 1, float: 1.0, bool: False}
    table = {s.name: placeholder[s.kind] for s in driver.settings if s.required}
    if "python-can" in getattr(driver, "transports", ()):
        table["channel"] = f"hilbench-meta-{driver.name}"  # a virtual bus of its own
    return table


def _pointed_at(driver: Any, table: dict[str, Any], url: str) -> dict[str, Any]:
    """The table with the emulator's address where the driver takes it."""
    known = {s.name for s in driver.settings}
    out = dict(table)
    if "url" in known:
        out["url"] = url
    elif {"interface", "channel"} <= known:
        out["interface"], _, out["channel"] = url.partition(":")
    return out


@pytest.mark.parametrize("name", names())
def test_a_driver_with_an_emulator_opens_against_it_and_names_itself(name):
    driver = registry.get_driver(name)
    start = getattr(driver, "emulator", None)
    if start is None:
        assert name == "sim"  # the simulated plant is not a device behind a transport
        return
    table = _minimal_table(driver)
    emulator = start(driver.complete(table), TrivialWorld())
    try:
        assert isinstance(emulator.url, str) and emulator.url
        device = driver.open(driver.complete(_pointed_at(driver, table, emulator.url)))
        try:
            assert isinstance(device, Device)
            identity = device.identity()
            assert isinstance(identity, str) and identity.strip()
            assert isinstance(device.capabilities(), dict)
            if hasattr(device, "read") and "sensor" in driver.roles:
                values = device.read()
                assert values and all(isinstance(v, float) and not math.isinf(v) for v in values.values())
        finally:
            device.close()
    finally:
        emulator.close()
