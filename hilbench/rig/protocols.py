"""The device seam: what the rig asks of a backend, as structural ``Protocol``s.

A driver satisfies these by shape alone, so driver modules never import hilbench (DESIGN.md,
"Drivers and rigs"). The rig is the only caller: every command reaches a device through its safety
path (:mod:`hilbench.rig.safety`), never directly.

* :class:`Actuator` takes commands in the actuator's unit (A or V) one sample at a time and makes
  itself safe on ``stop(False)``.
* :class:`Sensor` returns its channels (name -> physical value) when read.
* :class:`Player` runs a whole waveform on the device (a controller's wave generator and data
  recorder) because per-sample serial I/O cannot reach kHz rates.
* :class:`SampleClock` is a DAQ whose hardware sample clock can pace the fixed-rate loop: the
  runner waits for its next tick instead of its own deadline (:mod:`hilbench.runners.pacing`).
* :class:`LockstepPlant` is a simulated backend: it processes a block of applied commands and
  returns every measured channel for those samples, sample-exact with stepping it one by one.
* :class:`DriverEntry` is what a device family registers under the ``hilbench.drivers`` entry-point
  group: its name, its roles, how to check a settings table and how to open a device.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Device(Protocol):
    """Anything the rig talks to; its identity and capabilities go into every recording."""

    def identity(self) -> str: ...

    def capabilities(self) -> dict[str, Any]: ...

    def close(self) -> None: ...


@runtime_checkable
class Actuator(Device, Protocol):
    def write(self, value: float) -> None:
        """Apply one command, in the actuator's unit (A or V)."""
        ...

    def stop(self, success: bool) -> None:
        """End of work; ``success=False`` makes the device safe (its own ramp to rest, outputs off)."""
        ...


@runtime_checkable
class Sensor(Device, Protocol):
    def read(self) -> Mapping[str, float]:
        """The latest value of each channel the device measures, in physical units."""
        ...


@runtime_checkable
class Player(Device, Protocol):
    def play(self, waveform: np.ndarray, rate_hz: float) -> Mapping[str, np.ndarray]:
        """Run ``waveform`` (actuator unit) at ``rate_hz`` on the device; return the recorded channels."""
        ...


@runtime_checkable
class SampleClock(Device, Protocol):
    def sample_clock_hz(self) -> float | None:
        """Hz of the sample clock that times the device's per-sample I/O in its present mode; None
        when nothing does (software-timed, on demand)."""
        ...

    def sample_clock(self) -> str:
        """What the clock is, in a few words, for the recording (e.g. the DAQmx timing it uses)."""
        ...

    def wait_for_next_sample_clock(self) -> bool:
        """Return at the clock's next tick; True when the device reports the tick had already gone
        by when the wait began (the loop was late). The next ``read()`` returns that tick's sample."""
        ...


@runtime_checkable
class LockstepPlant(Device, Protocol):
    """A simulated backend, advanced by the rig in blocks of applied commands."""

    def process(self, applied: np.ndarray) -> dict[str, np.ndarray]:
        """Advance by ``len(applied)`` samples; return every sensor channel for them."""
        ...

    def start_run(self) -> None:
        """Restart the run clock (trajectories of temperature and load); memory stays."""
        ...


@runtime_checkable
class DriverEntry(Protocol):
    """A registered device family (``drivers.base.DriverSpec`` has this shape)."""

    name: str
    roles: tuple[str, ...]

    def problems(self, table: dict[str, Any]) -> list[str]:
        """What is wrong with a device's settings table; empty when it can be opened."""
        ...

    def complete(self, table: dict[str, Any]) -> dict[str, Any]:
        """The settings with defaults filled in."""
        ...

    def open(self, settings: dict[str, Any]) -> Any:
        """Open the device (a transport is connected here, never on load or check)."""
        ...
