"""A rig: the actuator, its sensors and the one path every actuator command takes.

All commands pass through :meth:`Rig.apply`: clamp to the actuator's ``[min, max]``, slew-limit to
``max_rate``, and what was really applied is what gets recorded as ``input``. :meth:`Rig.stop`
makes the actuator safe by ramping to ``rest`` at ``max_rate``.

A rig with ``driver = "sim"`` runs the simulated plant of :mod:`hilbench.sim.plant`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hilbench.config import RigConfig
from hilbench.errors import ConfigError
from hilbench.recording import CANONICAL_CHANNELS, ChannelSpec
from hilbench.sim.kernels import command_path
from hilbench.sim.plant import Plant


class Rig:
    def __init__(self, config: RigConfig):
        self.config = config
        self.actuator = config.actuator
        self.fs = config.sample_rate_hz
        if not config.simulated:
            raise ConfigError(
                f"actuator driver {config.actuator.driver!r} has no adapter in this version; "
                "use driver = 'sim' with a [plant] table",
                where=config.path,
            )
        self.plant = Plant.from_rig(config)
        self._last = np.array([self.actuator.rest])
        self.clamped_samples = 0
        # Bring the plant to its rest state as a powered-up actuator would be.
        self.plant.simulate(np.full(1, self.actuator.rest))

    # -- description ----------------------------------------------------------------------------
    @property
    def max_step(self) -> float:
        return self.actuator.max_rate / self.fs

    @property
    def last_applied(self) -> float:
        return float(self._last[0])

    def channels(self) -> list[ChannelSpec]:
        specs = [
            ChannelSpec("time", "s", CANONICAL_CHANNELS["time"][1]),
            ChannelSpec("input", self.actuator.unit, CANONICAL_CHANNELS["input"][1]),
        ]
        for s in self.config.sensors:
            description = s.description or CANONICAL_CHANNELS.get(s.channel, ("", s.channel))[1]
            specs.append(ChannelSpec(s.channel, s.unit, description))
        return specs

    def devices(self) -> list[dict[str, Any]]:
        cfg = self.config
        effects = self.plant.effects
        actuator = {
            "role": "actuator",
            "driver": "sim",
            "identity": f"hilbench simulated {cfg.actuator.kind or 'actuator'} '{cfg.name}'",
            "firmware": "hilbench-sim",
            "capabilities": {"unit": cfg.actuator.unit, "min": cfg.actuator.min, "max": cfg.actuator.max,
                             "max_rate": cfg.actuator.max_rate, "effects": effects},
        }
        sensors = [
            {"role": "sensor", "channel": s.channel, "driver": "sim", "identity": f"hilbench simulated sensor '{s.channel}'",
             "firmware": "hilbench-sim", "capabilities": {"unit": s.unit, "range": s.range, "noise_std": s.noise_std,
                                                          "quantization": s.quantization}}
            for s in cfg.sensors
        ]
        return [actuator, *sensors]

    # -- the actuator path ------------------------------------------------------------------------
    def apply(self, command: np.ndarray) -> np.ndarray:
        """Clamp and slew-limit a block of commands; returns what is really applied."""
        command = np.ascontiguousarray(command, dtype=np.float64)
        out = np.empty_like(command)
        self.clamped_samples += command_path(
            command, self.actuator.min, self.actuator.max, self.max_step, self._last, out
        )
        return out

    def measure(self, applied: np.ndarray) -> dict[str, np.ndarray]:
        """Drive the plant with applied commands and read every sensor channel."""
        result = self.plant.simulate(applied)
        return {"output": result.output, **result.aux}

    def ramp_to(self, target: float) -> int:
        """Move to ``target`` at ``max_rate`` through the plant, unrecorded; returns samples used."""
        distance = abs(target - self.last_applied)
        n = int(math.ceil(distance / self.max_step)) if distance > 0 else 0
        if n:
            self.measure(self.apply(np.linspace(self.last_applied, target, n + 1)[1:]))
        return n

    def start_run(self, first_value: float) -> None:
        """Approach the run's first value, then restart the run clock."""
        self.ramp_to(first_value)
        self.plant.start_run()

    def stop(self, success: bool) -> None:
        """End of work: on failure (``success=False``) make safe by ramping to rest."""
        if not success or self.last_applied != self.actuator.rest:
            self.ramp_to(self.actuator.rest)
