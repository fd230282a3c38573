"""The driver registry: device families found under the ``hilbench.drivers`` entry-point group.

hilbench's own device families (the simulated plant ``sim`` and the modules of ``drivers/``) are
registered in ``pyproject.toml`` like any third party's. When the package metadata is missing or
stale (a source tree run without installing), the built-in ones are still found by module path, so
the rig never needs to import a backend by name: the config and the rig know drivers only through
this lookup and the protocols of :mod:`hilbench.rig.protocols`.
"""

from __future__ import annotations

import functools
import importlib
from importlib import metadata
from typing import Any

from hilbench.errors import ConfigError
from hilbench.rig.protocols import DriverEntry

GROUP = "hilbench.drivers"

#: Built-in families by entry-point value, used when the installed metadata does not list them.
BUILTIN: dict[str, str] = {
    "sim": "hilbench.sim.backend:DRIVER",
    "pi-gcs": "drivers.pi_gcs:DRIVER",
    "keyence-lk": "drivers.keyence_lk:DRIVER",
    "modbus-aio": "drivers.modbus_aio:DRIVER",
    "canopen-sensor": "drivers.canopen_sensor:DRIVER",
    "ni-daqmx": "drivers.ni_daqmx:DRIVER",
}


def _load(value: str) -> Any:
    module, _, attr = value.partition(":")
    return getattr(importlib.import_module(module), attr)


@functools.lru_cache(maxsize=1)
def entry_points() -> dict[str, str]:
    """Registered family name -> ``module:attribute``; the installed ones win over the built-in list."""
    found = dict(BUILTIN)
    for ep in metadata.entry_points(group=GROUP):
        found[ep.name] = ep.value
    return found


def driver_names() -> list[str]:
    return sorted(entry_points())


def get_driver(name: str, *, where: str | None = None) -> DriverEntry:
    """The registered family ``name``; a :class:`ConfigError` listing the known ones otherwise."""
    points = entry_points()
    if name not in points:
        raise ConfigError(f"unknown driver {name!r}; registered drivers: {', '.join(sorted(points))}", where=where,
                          hint="a third-party driver registers under the 'hilbench.drivers' entry-point group")
    try:
        entry = _load(points[name])
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"driver {name!r} ({points[name]}) cannot be loaded: {exc}", where=where) from None
    if not isinstance(entry, DriverEntry):
        raise ConfigError(f"driver {name!r} ({points[name]}) does not have the shape of a driver entry "
                          "(name, roles, problems, complete, open)", where=where)
    return entry


def clear_cache() -> None:
    """Forget the entry points read so far (tests that register a driver at run time)."""
    entry_points.cache_clear()
