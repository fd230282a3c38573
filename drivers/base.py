"""The driver contract as the drivers see it: what a device-family module exposes.

Drivers speak transports only (pyserial, pymodbus, python-can, canopen) and never import hilbench.
hilbench sees a device through typed ``Protocol``s (``hilbench/rig/protocols.py``) that the device
classes here satisfy structurally:

* every device: ``identity() -> str``, ``capabilities() -> dict``, ``close()``;
* an actuator: ``write(value)`` (physical unit, A or V), ``stop(success)`` (False = make safe:
  ramp to rest at the configured rate);
* a sensor: ``read() -> dict[str, float]`` (channel name -> physical value);
* a player (a controller with a wave generator and data recorder): ``play(waveform, rate_hz) ->
  dict[str, numpy array]``.

Each driver module defines one :class:`DriverSpec` named ``DRIVER`` and registers it under the
``hilbench.drivers`` entry-point group (``pyproject.toml``), so a third party adds a device family
by shipping a module with a ``DRIVER`` and an entry point, without touching hilbench.

An emulator speaks the device's real protocol on a real transport (a pty or loopback socket for
serial, a Modbus server on 127.0.0.1, a python-can virtual bus). It is backed by a :class:`World`:
the physics behind the device (hilbench passes its simulated plant; driver tests may pass anything
that satisfies the protocol).
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np

T = TypeVar("T")


# -- errors ------------------------------------------------------------------------------------------
class DeviceError(Exception):
    """A device refused, answered garbage or reported an error. ``device`` names it."""

    def __init__(self, device: str, message: str):
        self.device = device
        self.message = " ".join(str(message).split())
        super().__init__(f"{device}: {self.message}")


class DeviceTimeout(DeviceError):
    """A device did not answer in time (after the bounded retries)."""


class DeviceLost(DeviceError):
    """The transport closed or the device stopped answering for good (lost heartbeat, EOF)."""


#: the pause before the first retry of a timed-out request (s), doubled before each further one
DEFAULT_BACKOFF_S = 0.02


def retry_budget_s(attempts: int, timeout_s: float, backoff_s: float = DEFAULT_BACKOFF_S) -> float:
    """The longest :func:`retry` takes over one request that never gets an answer (s): ``attempts``
    timeouts and the back-off pauses between them."""
    tries = max(1, int(attempts))
    return tries * float(timeout_s) + float(backoff_s) * (2 ** (tries - 1) - 1)


def retry(call: Callable[[], T], *, device: str, what: str, attempts: int = 3, backoff_s: float = DEFAULT_BACKOFF_S,
          retry_on: tuple[type[BaseException], ...] = (DeviceTimeout,)) -> T:
    """Call ``call`` up to ``attempts`` times, sleeping ``backoff_s * 2**k`` between tries.

    Only the exceptions in ``retry_on`` are retried (timeouts by default: a garbled or refused
    command is not made right by sending it again). The last failure is re-raised as
    :class:`DeviceTimeout` naming the device, what was attempted and how many tries it took.
    """
    last: BaseException | None = None
    for k in range(attempts):
        try:
            return call()
        except retry_on as exc:  # noqa: PERF203 - a bounded retry loop
            last = exc
            if k + 1 < attempts:
                time.sleep(backoff_s * (2**k))
    message = getattr(last, "message", str(last))
    raise DeviceTimeout(device, f"{what}: no valid answer after {attempts} tries ({message})") from last


class Lazy:
    """A function named ``module:function``, imported on the first call: a driver names its emulator
    this way, so opening a real device never loads (or depends on) the emulated one."""

    def __init__(self, entry: str):
        self.entry = entry

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        module, _, function = self.entry.partition(":")
        return getattr(importlib.import_module(module), function)(*args, **kwargs)

    def __repr__(self) -> str:
        return f"Lazy({self.entry!r})"


# -- settings -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Setting:
    """One key of a device's driver table in a rig config."""

    name: str
    kind: type  # str, float, int or bool
    required: bool = False
    default: Any = None
    doc: str = ""


@dataclass(frozen=True)
class DriverSpec:
    """What a device-family module registers: its name, roles, settings, and how to open it."""

    name: str
    roles: tuple[str, ...]  # among "actuator", "sensor", "player"
    settings: tuple[Setting, ...]
    open: Callable[[dict[str, Any]], Any]  # complete settings -> device object
    emulator: Callable[..., Any] | None = None  # start_emulator(settings, world) -> Emulator (see Lazy)
    description: str = ""
    transports: tuple[str, ...] = field(default_factory=tuple)  # e.g. ("serial", "socket://")
    #: what to install before the driver can open a device, when an optional dependency is missing
    #: (e.g. "pip install 'hilbench[nidaqmx]'"); "" when everything it needs is importable
    install_hint: str = ""

    def problems(self, table: dict[str, Any]) -> list[str]:
        """What is wrong with a driver table (unknown, missing or mistyped keys); empty when fine.

        Used by ``hilbench sweep --check`` without opening any transport.
        """
        known = {s.name: s for s in self.settings}
        out: list[str] = []
        for key in table:
            if key not in known:
                out.append(f"unknown key {key!r} for driver {self.name!r}; allowed: {', '.join(known)}")
        for s in self.settings:
            if s.name not in table:
                if s.required:
                    out.append(f"missing key {s.name!r} for driver {self.name!r} ({s.doc or s.kind.__name__})")
                continue
            value = table[s.name]
            ok = isinstance(value, s.kind) and not (s.kind in (int, float) and isinstance(value, bool))
            if s.kind is float and isinstance(value, int) and not isinstance(value, bool):
                ok = True
            if not ok:
                out.append(f"key {s.name!r} for driver {self.name!r}: expected {s.kind.__name__}, got {value!r}")
        return out

    def complete(self, table: dict[str, Any]) -> dict[str, Any]:
        """The table with defaults filled in (call :meth:`problems` first)."""
        out = {s.name: s.default for s in self.settings if s.default is not None}
        out.update(table)
        return out


# -- emulation ------------------------------------------------------------------------------------------
@runtime_checkable
class World(Protocol):
    """The physics behind an emulated device.

    ``command`` is called when the emulated actuator's input changes at the loop's sample rate: it
    advances the world by one sample. ``read`` returns the latest value of a channel in physical
    units (``output`` um, ``current`` A, ``temperature`` degC, ...). ``play`` runs a whole waveform
    at once (a controller's wave generator) and returns every channel it recorded.
    """

    def command(self, value: float) -> None: ...

    def read(self, channel: str) -> float: ...

    def play(self, waveform: np.ndarray, rate_hz: float) -> dict[str, np.ndarray]: ...


class Emulator(Protocol):
    """A running emulator: where to reach it and how to stop it."""

    url: str  # what to put in the rig config's driver table

    def close(self) -> None: ...
