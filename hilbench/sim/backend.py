"""The simulated plant as one backend behind the device seam (driver name ``sim``).

:class:`SimulatedRig` satisfies the rig's protocols (:mod:`hilbench.rig.protocols`) structurally:
as a :class:`~hilbench.rig.protocols.LockstepPlant` it processes blocks of applied commands (sweeps,
offline runs), as an actuator and sensor it is stepped one sample at a time (fixed-rate loops,
emulators). It is registered under the ``hilbench.drivers`` entry-point group like every driver, so
the rig and the config reach it by name and never import it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from hilbench.errors import ConfigError
from hilbench.sim.plant import Plant
from hilbench.sim.schema import SensorModel, check_plant


class SimulatedRig:
    """A simulated actuator with its amplifier and sensors, behind the device protocols."""

    def __init__(self, plant: Plant, *, name: str = "sim", kind: str = "", unit: str = ""):
        self.plant = plant
        self.name = name
        self.kind = kind
        self.unit = unit
        self._latest: dict[str, float] = {}
        # Power-up: the plant sits at the actuator's rest value before anything moves.

    # -- Device ------------------------------------------------------------------------------------
    def identity(self) -> str:
        return f"hilbench simulated {self.kind or 'actuator'} '{self.name}'"

    def capabilities(self) -> dict[str, Any]:
        return {"effects": self.plant.effects, "sample_rate_hz": self.plant.sample_rate_hz,
                "channels": ["output", *sorted(c for c in self.plant.sensors if c != "output")]}

    def close(self) -> None:
        """Nothing to release: the plant lives in memory."""

    # -- LockstepPlant -----------------------------------------------------------------------------
    def process(self, applied: np.ndarray) -> dict[str, np.ndarray]:
        result = self.plant.simulate(applied)
        return {"output": result.output, **result.aux}

    def start_run(self) -> None:
        self.plant.start_run()

    # -- Actuator and Sensor, one sample at a time ---------------------------------------------------
    def write(self, value: float) -> None:
        result = self.plant.step(float(value))
        self._latest = {"output": float(result.output[0]), **{k: float(v[0]) for k, v in result.aux.items()}}

    def read(self) -> Mapping[str, float]:
        return self._latest

    def stop(self, success: bool) -> None:
        """The rig's safety path already ramped the command to rest; a simulation has no outputs to cut."""


@dataclass(frozen=True)
class SimDriver:
    """The registry entry of the simulated plant.

    Its settings table is ``{"plant": <the [plant] table>, "sample_rate_hz": fs}``; opening also
    takes the sensors (``sensors``: objects or tables with the sensor keys) and the ``seed``.
    """

    name: str = "sim"
    roles: tuple[str, ...] = ("actuator", "sensor", "lockstep")
    description: str = "the simulated plant composed from the [plant] effect tables"

    def problems(self, table: dict[str, Any]) -> list[str]:
        try:
            self.complete(table)
        except ConfigError as exc:
            return [exc.message]
        return []

    def complete(self, table: dict[str, Any]) -> dict[str, Any]:
        plant = table.get("plant")
        if plant is None:
            raise ConfigError("driver = 'sim' needs a [plant] table describing the simulated physics",
                              where=table.get("file") or None)
        return {**table, "plant": check_plant(plant, table.get("file", ""), float(table["sample_rate_hz"]))}

    def open(self, settings: dict[str, Any]) -> SimulatedRig:
        sensors = [SensorModel.of(s) for s in settings.get("sensors", [])]
        plant = Plant(settings["plant"], float(settings["sample_rate_hz"]), sensors, int(settings.get("seed", 0)))
        return SimulatedRig(plant, name=str(settings.get("name", "sim")), kind=str(settings.get("kind", "")),
                            unit=str(settings.get("unit", "")))


DRIVER = SimDriver()
