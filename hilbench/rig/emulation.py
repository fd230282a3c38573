"""An emulated rig: every device of a real-rig config served by its emulator, backed by one plant.

:func:`start_emulators` builds ONE :class:`~hilbench.sim.world.SimWorld` from the config's
``[plant]`` (its sample rate, ``[[sensors]]`` noise/quantisation/range and ``seed``, through the
simulated backend ``sim`` of the driver registry), then starts the emulator of every
``[devices.NAME]`` through its driver entry (``DRIVER.emulator(settings, world)``): the Modbus
module's analog output moves the plant that the CANopen or Keyence sensor then reads, as on a
bench. The result tells what to put in the config to reach them (:attr:`EmulatedRig.settings`) and
gives that config (:meth:`EmulatedRig.config_for_emulators`), so a real-rig config can be dry-run.

What changes in a device's settings to reach its emulator, by setting name (not by driver, so a
third-party driver with an emulator works the same way):

* ``url``: the emulator's own (a pty path, ``tcp://127.0.0.1:PORT``, ``socket://127.0.0.1:PORT``);
  a ``tcp://`` address is served on 127.0.0.1 on a free port, never on the configured host or port;
* ``interface``/``channel`` (python-can): the ``virtual`` interface on a channel of its own, so two
  emulated rigs never share a bus.

Limits: the world gives physical values (um, A, degC), so the rig-level ``scale``/``offset`` of a
``[[sensors]]`` table should be 1/0 in a config meant for emulation (driver-level scales, such as
the Modbus module's counts or a CANopen PV scale, are honoured by the emulators themselves).
"""

from __future__ import annotations

import dataclasses
import uuid
from dataclasses import dataclass, field
from typing import Any

from typing_extensions import Self

from hilbench.errors import ConfigError
from hilbench.rig.config import RigConfig
from hilbench.rig.registry import get_driver
from hilbench.sim.world import SimWorld


@dataclass
class EmulatedRig:
    """Running emulators of one rig config and the world behind them; close() stops them all."""

    config: RigConfig
    world: SimWorld
    #: device name -> the running emulator (``.url``, ``.close()``, its fault injection)
    emulators: dict[str, Any] = field(default_factory=dict)
    #: device name -> the settings that point the device at its emulator (url, interface, channel)
    settings: dict[str, dict[str, Any]] = field(default_factory=dict)

    def config_for_emulators(self) -> RigConfig:
        """The rig config with every device's settings pointing at its running emulator."""
        devices = {name: {**table, **self.settings.get(name, {})} for name, table in self.config.devices.items()}
        return dataclasses.replace(self.config, devices=devices)

    def describe(self) -> dict[str, Any]:
        """JSON-ready: per device, its driver and the settings to use (what ``hilbench emulate`` prints)."""
        return {"rig": self.config.name, "sample_rate_hz": self.config.sample_rate_hz,
                "devices": {name: {"driver": self.config.devices[name]["driver"], **s}
                            for name, s in self.settings.items()}}

    def close(self) -> None:
        """Stop every emulator (idempotent); the first error is raised after all were tried."""
        first: BaseException | None = None
        for emulator in reversed(list(self.emulators.values())):
            try:
                emulator.close()
            except BaseException as exc:  # noqa: BLE001 - close the others, then report
                first = first or exc
        self.emulators = {}
        if first is not None:
            raise first

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def build_world(config: RigConfig) -> SimWorld:
    """The config's ``[plant]`` as one world (sample rate, sensors and seed from the config)."""
    if not config.plant:
        raise ConfigError("emulating a rig needs a [plant] table: the physics behind the emulated devices",
                          where=config.path, hint="add [plant.hysteresis] (see configs/*.toml for examples)")
    sim = get_driver("sim", where=config.path).open({
        "plant": config.plant, "sample_rate_hz": config.sample_rate_hz, "sensors": config.sensors,
        "seed": config.seed, "name": config.name, "kind": config.actuator.kind, "unit": config.actuator.unit,
    })
    return SimWorld(sim.plant, rest=config.actuator.rest)


def _emulator_settings(name: str, table: dict[str, Any], known: set[str], token: str) -> dict[str, Any]:
    """The device's settings as its emulator should be started with (local transports only)."""
    settings = {k: v for k, v in table.items() if k != "driver"}
    url = settings.get("url")
    if isinstance(url, str) and url.startswith("tcp://"):
        settings["url"] = "tcp://127.0.0.1:0"  # a free local port, whatever host the real device has
    if "interface" in known and "channel" in known:  # a python-can bus
        settings["interface"] = "virtual"
        settings["channel"] = f"hilbench-emulate-{token}-{name}"
    return settings


def start_emulators(config: RigConfig) -> EmulatedRig:
    """Start the emulator of every device of ``config`` on one simulated plant.

    Raises :class:`~hilbench.errors.ConfigError` when the config has no ``[plant]``, or names a
    driver without an emulator; emulators already started are closed again on any failure.
    """
    if not config.devices:
        raise ConfigError("the rig has no [devices.NAME] tables to emulate (a simulated rig needs no emulators)",
                          where=config.path)
    world = build_world(config)
    rig = EmulatedRig(config, world)
    token = uuid.uuid4().hex[:8]
    try:
        for name, table in config.devices.items():
            driver = get_driver(table["driver"], where=f"{config.path}: [devices.{name}]")
            start = getattr(driver, "emulator", None)
            if start is None:
                raise ConfigError(f"[devices.{name}] driver {table['driver']!r} has no emulator", where=config.path)
            known = {s.name for s in getattr(driver, "settings", ())} or set(table)
            settings = _emulator_settings(name, table, known, token)
            emulator = start(settings, world)
            rig.emulators[name] = emulator
            point: dict[str, Any] = {}
            if "url" in known:
                point["url"] = str(emulator.url)
            if str(settings.get("interface")) == "virtual" and "interface" in known and "channel" in known:
                point["interface"], point["channel"] = settings["interface"], settings["channel"]
            rig.settings[name] = point
    except BaseException:
        rig.close()
        raise
    return rig
