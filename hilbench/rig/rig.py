"""A rig: the actuator, its sensors, the backends behind them and the one path every command takes.

All commands pass through :meth:`Rig.apply`: clamp to the actuator's ``[min, max]``, slew-limit to
``max_rate`` (:mod:`hilbench.rig.safety`), and what was really applied is what gets recorded as
``input``. :meth:`Rig.stop` makes the actuator safe by ramping to ``rest`` at ``max_rate`` through
the same path, then tells the device to stop.

Backends are reached through the protocols of :mod:`hilbench.rig.protocols` and opened through the
driver registry, so the rig imports no backend: the simulated plant (``driver = "sim"``) is a
:class:`~hilbench.rig.protocols.LockstepPlant` processed in blocks; real devices (``device =
"NAME"`` naming a ``[devices.NAME]`` table) are written and read one sample at a time.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np
from typing_extensions import Self

from hilbench.errors import ConfigError
from hilbench.recording.hdf5 import CANONICAL_CHANNELS, ChannelSpec
from hilbench.rig.config import RigConfig, SensorConfig
from hilbench.rig.protocols import Actuator, Device, LockstepPlant, Sensor
from hilbench.rig.registry import get_driver
from hilbench.rig.safety import command_path, ramp

SIM = "sim"


def open_devices(config: RigConfig) -> dict[str, Device]:
    """Open every backend a rig config names: ``sim`` for the simulated plant, else its devices."""
    opened: dict[str, Device] = {}
    try:
        if config.actuator.driver == SIM:
            opened[SIM] = get_driver(SIM, where=config.path).open({
                "plant": config.plant, "sample_rate_hz": config.sample_rate_hz, "sensors": config.sensors,
                "seed": config.seed, "name": config.name, "kind": config.actuator.kind, "unit": config.actuator.unit,
            })
        for name, table in config.devices.items():
            settings = {k: v for k, v in table.items() if k != "driver"}
            opened[name] = get_driver(table["driver"], where=config.path).open(settings)
    except BaseException:
        for device in opened.values():
            device.close()
        raise
    return opened


class Rig:
    """The actuator path and the measurement of one rig.

    ``devices`` (name -> device) replaces opening them from the config: a test or a script can put
    any object that satisfies the protocols behind a config's device names. ``lockstep=False``
    drives a simulated plant one sample at a time through its ``write``/``read`` instead of in
    blocks (the per-sample path real devices take; the fixed-rate loop's benchmark uses it).
    """

    def __init__(self, config: RigConfig, devices: Mapping[str, Device] | None = None, *, lockstep: bool = True):
        self.config = config
        self.actuator = config.actuator
        self.sample_rate_hz = config.sample_rate_hz
        self.devices_by_name: dict[str, Device] = dict(devices) if devices is not None else open_devices(config)
        self._last = np.array([float(self.actuator.rest)])
        self._one = np.zeros(1)  # apply_value's buffers: one command in ...
        self._one_out = np.zeros(1)  # ... one applied value out
        self.clamped_samples = 0
        #: real devices: the unrecorded ramps (to a run's first value, to rest) are written at the
        #: sample rate, so the slew limit holds in wall-clock time too; False only for emulated rigs
        #: in tests, whose plant advances one sample per write whatever the time.
        self.pace = True
        act_name = SIM if self.actuator.driver == SIM else self.actuator.device
        self.actuator_name = act_name
        actuator = self._device(act_name, "actuator")
        use_lockstep = isinstance(actuator, LockstepPlant) and (lockstep or not isinstance(actuator, Actuator))
        self.lockstep: LockstepPlant | None = actuator if use_lockstep else None  # type: ignore[assignment]
        if self.lockstep is None and not isinstance(actuator, Actuator):
            raise ConfigError(f"device {act_name!r} ({type(actuator).__name__}) cannot drive an actuator "
                              "(it has no write/stop)", where=config.path)
        self.actuator_device = actuator
        # Sensors read per sample, grouped by device so each device is read once a sample:
        # (device name, device, its sensors).
        self._reads: list[tuple[str, Sensor, list[SensorConfig]]] = []
        if self.lockstep is None:
            groups: dict[str, list[SensorConfig]] = {}
            for s in config.sensors:
                groups.setdefault(s.device or SIM, []).append(s)
            for name, sensors in groups.items():
                device = self._device(name, "sensor")
                if not isinstance(device, Sensor):
                    raise ConfigError(f"device {name!r} ({type(device).__name__}) cannot measure (it has no read)",
                                      where=config.path)
                self._reads.append((name, device, sensors))
        # Bring the actuator to its rest value as a powered-up actuator would be.
        self._drive(np.full(1, self.actuator.rest))

    def _device(self, name: str, role: str) -> Device:
        if name not in self.devices_by_name:
            raise ConfigError(f"the {role} names device {name!r}, which is not open; devices: "
                              f"{', '.join(self.devices_by_name) or 'none'}", where=self.config.path)
        return self.devices_by_name[name]

    # -- description ----------------------------------------------------------------------------
    @property
    def max_step(self) -> float:
        """The slew limit per sample, actuator unit."""
        return self.actuator.max_rate / self.sample_rate_hz

    @property
    def last_applied(self) -> float:
        return float(self._last[0])

    @property
    def safety_state(self) -> np.ndarray:
        """The safety path's state: a (1,) array holding the last applied command. A compiled loop
        that runs the safety path itself (the fused closed loop) updates this same array, so the
        rig's slew limit carries on across it and Python-driven samples."""
        return self._last

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
        """What the recording keeps of each device: role, driver, identity, firmware, capabilities."""
        cfg = self.config
        act_caps = {"unit": cfg.actuator.unit, "min": cfg.actuator.min, "max": cfg.actuator.max,
                    "max_rate": cfg.actuator.max_rate}
        entries = []
        act = self.actuator_device
        firmware_sim = "hilbench-sim"
        simulated = cfg.actuator.driver == SIM  # lock-step or stepped per sample, the same plant
        caps = act.capabilities()
        entries.append({
            "role": "actuator", "driver": cfg.actuator.driver, "device": cfg.actuator.device or SIM,
            "identity": act.identity(), "firmware": str(caps.get("firmware", firmware_sim if simulated else "")),
            "capabilities": {**act_caps, **caps},
        })
        for s in cfg.sensors:
            dev = act if simulated else self.devices_by_name[s.device]
            sensor_caps = dev.capabilities()
            identity = f"hilbench simulated sensor '{s.channel}'" if simulated else dev.identity()
            entries.append({
                "role": "sensor", "channel": s.channel, "driver": s.driver, "device": s.device or SIM,
                "identity": identity,
                "firmware": str(sensor_caps.get("firmware", firmware_sim if simulated else "")),
                "capabilities": {"unit": s.unit, "range": s.range, "noise_std": s.noise_std,
                                 "quantization": s.quantization,
                                 **({} if simulated else sensor_caps)},
            })
        return entries

    # -- the actuator path ------------------------------------------------------------------------
    def apply(self, command: np.ndarray) -> np.ndarray:
        """Clamp and slew-limit a block of commands; returns what is really applied."""
        command = np.ascontiguousarray(command, dtype=np.float64)
        out = np.empty_like(command)
        self.clamped_samples += command_path(
            command, self.actuator.min, self.actuator.max, self.max_step, self._last, out
        )
        return out

    def apply_value(self, command: float) -> float:
        """:meth:`apply` of one command (the same path, without allocating): the value to write."""
        self._one[0] = command
        self.clamped_samples += command_path(
            self._one, self.actuator.min, self.actuator.max, self.max_step, self._last, self._one_out
        )
        return float(self._one_out[0])

    @property
    def sensor_reads(self) -> list[tuple[str, Sensor, list[SensorConfig]]]:
        """Per-sample path: (device name, device, its sensors), each device read once a sample."""
        return self._reads

    def measure(self, applied: np.ndarray) -> dict[str, np.ndarray]:
        """Drive the backend with applied commands (from :meth:`apply`) and read every sensor channel."""
        if self.lockstep is not None:
            return self.lockstep.process(applied)
        n = applied.shape[0]
        out = {s.channel: np.empty(n) for _, _, sensors in self._reads for s in sensors}
        write = self.actuator_device.write  # type: ignore[union-attr]
        for k in range(n):
            write(float(applied[k]))
            for _, device, sensors in self._reads:
                values = device.read()
                for s in sensors:
                    raw = values.get(s.source or s.channel, np.nan)
                    out[s.channel][k] = s.offset + s.scale * raw
        return out

    def resync(self, value: float) -> None:
        """The device reports it holds ``value`` (after a block it played itself stopped part-way):
        the actuator path continues from there, so a ramp to rest starts where the actuator is."""
        self._last[0] = min(max(float(value), self.actuator.min), self.actuator.max)

    def ramp_to(self, target: float) -> int:
        """Move to ``target`` at ``max_rate`` through the actuator path, unrecorded; returns samples used."""
        commands = ramp(self.last_applied, target, self.max_step)
        if commands.shape[0]:
            self._drive(self.apply(commands))
        return int(commands.shape[0])

    def _drive(self, applied: np.ndarray) -> None:
        """Move without recording: a simulated plant must still live through the samples; real
        devices only need the actuator written (a failed sensor must not stop a ramp to rest)."""
        if self.lockstep is not None:
            self.measure(applied)  # the one path a simulated plant moves through, recorded or not
            return
        write = self.actuator_device.write  # type: ignore[union-attr]
        paced = self.pace and applied.shape[0] > 1
        # Paced at the sample rate (absolute deadlines): the slew limit holds in real time.
        period = 1.0 / self.sample_rate_hz
        t0 = time.perf_counter()
        for k, value in enumerate(applied):
            if paced:
                wait = t0 + k * period - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            try:
                write(float(value))
            except BaseException:
                # apply() booked the whole block; the device got only up to this value (or the one
                # before): the actuator path continues from here, so a ramp to rest starts where
                # the actuator is, not where the block would have ended
                self._last[0] = float(value)
                raise

    def start_run(self, first_value: float) -> None:
        """Approach the run's first value, then restart the run clock."""
        self.ramp_to(first_value)
        if self.lockstep is not None:
            self.lockstep.start_run()

    def stop(self, success: bool) -> None:
        """End of work: on failure (``success=False``) make safe by ramping to rest, then stop the device.

        On failure a real device first gets the last applied value again: the write that failed may
        or may not have landed, and from either value the ramp's first step is then within the slew
        limit.
        """
        try:
            if not success and self.lockstep is None:
                self._drive(np.full(1, self.last_applied))
        except Exception:  # noqa: BLE001, S110 - the ramp below is tried anyway and raises if the device is gone
            pass
        try:
            if not success or self.last_applied != self.actuator.rest:
                self.ramp_to(self.actuator.rest)
        finally:
            stop = getattr(self.actuator_device, "stop", None)
            if stop is not None:
                stop(success)

    def close(self) -> None:
        """Release every device (transports closed); safe to call twice."""
        for device in self.devices_by_name.values():
            device.close()
        self.devices_by_name = {}

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
