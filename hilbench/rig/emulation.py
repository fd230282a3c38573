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

* ``url``: the emulator's own (a pty path, ``tcp://127.0.0.1:PORT``, ``socket://127.0.0.1:PORT``,
  ``grpc://127.0.0.1:PORT`` for an NI gRPC Device Server); a ``tcp://`` or ``grpc://`` address is
  served on 127.0.0.1 on a free port, never on the configured host or port;
  a driver with a ``tcp_port`` setting (a line-protocol emulator) serves its pty and 127.0.0.1 TCP
  on a free port, and a configured ``socket://`` url is pointed at the TCP one;
* ``interface``/``channel`` (python-can): the ``virtual`` interface on a channel of its own, so two
  emulated rigs never share a bus; with ``shared_can=True`` (``hilbench emulate`` without
  ``--dry-run``) python-can's ``udp_multicast`` interface instead, which other processes on this
  machine reach: an IPv6 interface-local group (``ff11::``, never sent on a wire, RFC 4291 2.7) or,
  without IPv6, the administratively scoped IPv4 group 239.255.72.66 with TTL 1 (the local subnet),
  and a free UDP ``port`` of its own (Linux delivers every group joined on a port to every socket on
  that port, so the port, not the group, keeps two rigs apart).

Limits: the world gives physical values (um, A, degC), so the rig-level ``scale``/``offset`` of a
``[[sensors]]`` table should be 1/0 in a config meant for emulation (driver-level scales, such as
the Modbus module's counts or a CANopen PV scale, are honoured by the emulators themselves).
"""

from __future__ import annotations

import dataclasses
import json
import re
import uuid
from pathlib import Path
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
    #: device name -> every way to reach its emulator: ``pty`` (path), ``tcp`` ("127.0.0.1:PORT"), ``port``
    endpoints: dict[str, dict[str, Any]] = field(default_factory=dict)

    def config_for_emulators(self) -> RigConfig:
        """The rig config with every device's settings pointing at its running emulator."""
        devices = {name: {**table, **self.settings.get(name, {})} for name, table in self.config.devices.items()}
        return dataclasses.replace(self.config, devices=devices)

    def describe(self) -> dict[str, Any]:
        """JSON-ready: per device, its driver and the settings to use (what ``hilbench emulate`` prints)."""
        return {"rig": self.config.name, "sample_rate_hz": self.config.sample_rate_hz,
                "devices": {name: {"driver": self.config.devices[name]["driver"], **s,
                                   **self.endpoints.get(name, {})}
                            for name, s in self.settings.items()}}

    def write_config(self, out: str | Path) -> Path:
        """Write the config file with every device's url (interface, channel) set to its emulator.

        The user's file is copied as text, so comments and layout stay; only the keys that reach the
        emulators change (a device table that lives in a base config gets an overriding table), and a
        relative ``extends`` path is made absolute so the copy reads the same base from anywhere.
        """
        out = Path(out)
        source = Path(self.config.path)
        text = source.read_text(encoding="utf-8")
        text = _absolute_extends(text, source.parent)
        for name, settings in self.settings.items():
            text = _set_device_keys(text, name, settings)
        header = (f"# Written by `hilbench emulate {source.name}`: every device url points at an emulator\n"
                  "# on this machine, reachable while that command runs. The original is left as it was.\n")
        out.write_text(header + text, encoding="utf-8")
        return out

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


def _toml_value(value: Any) -> str:
    """A TOML literal for a str, bool, int or float setting (a JSON string is a TOML basic string)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    return json.dumps(str(value))


def _set_device_keys(text: str, name: str, settings: dict[str, Any]) -> str:
    """``text`` with ``key = value`` set in its ``[devices.NAME]`` table (added when absent)."""
    header = re.compile(rf'^[ \t]*\[[ \t]*devices[ \t]*\.[ \t]*"?{re.escape(name)}"?[ \t]*\][ \t]*(#.*)?$', re.M)
    found = header.search(text)
    lines = [f"{key} = {_toml_value(value)}" for key, value in settings.items()]
    if found is None:  # the table is in a base config: override it here
        return text.rstrip("\n") + f"\n\n[devices.{name}]\n" + "\n".join(lines) + "\n"
    start = found.end()
    following = re.compile(r"^[ \t]*\[", re.M).search(text, start)
    end = following.start() if following else len(text)
    body = text[start:end]
    for key, line in zip(settings, lines):
        pattern = re.compile(rf"^[ \t]*{re.escape(key)}[ \t]*=.*$", re.M)
        if pattern.search(body):
            body = pattern.sub(lambda _m, line=line: line, body, count=1)
        else:
            body = body.rstrip("\n") + f"\n{line}\n" + ("\n" if following else "")
    return text[:start] + body + text[end:]


def _absolute_extends(text: str, folder: Path) -> str:
    """A relative ``extends = "file"`` that names a file beside the config, made absolute."""

    def absolute(match: re.Match[str]) -> str:
        base = match.group(2)
        for candidate in (folder / base, folder / f"{base}.toml"):
            if candidate.is_file():
                return f"{match.group(1)}{json.dumps(str(candidate.resolve()))}"
        return match.group(0)  # a built-in rig name: found from anywhere

    return re.sub(r'^([ \t]*extends[ \t]*=[ \t]*)"([^"\n]*)"', absolute, text, flags=re.M)


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


#: udp_multicast groups tried in order: IPv6 interface-local (stays on this host), then IPv4 site-local
UDP_MULTICAST_GROUPS = ("ff11::6869:6c62", "239.255.72.66")


def _shared_can_bus() -> dict[str, Any]:
    """A python-can ``udp_multicast`` channel and free port that this machine can open, for one rig."""
    import socket

    import can

    problems = []
    for group in UDP_MULTICAST_GROUPS:
        family = socket.AF_INET6 if ":" in group else socket.AF_INET
        try:
            with socket.socket(family, socket.SOCK_DGRAM) as probe:  # a UDP port nobody is bound to
                probe.bind(("", 0))
                port = int(probe.getsockname()[1])
            can.Bus(interface="udp_multicast", channel=group, port=port).shutdown()
        except (OSError, ValueError, can.CanError, ImportError) as exc:
            problems.append(f"{group}: {exc}")
            continue
        return {"interface": "udp_multicast", "channel": group, "port": port}
    raise ConfigError("no python-can udp_multicast bus can be opened here (" + "; ".join(problems) + ")",
                      hint="use --dry-run: it serves CANopen devices on a virtual bus in one process")


def _emulator_settings(name: str, table: dict[str, Any], known: set[str], token: str,
                       shared_can: dict[str, Any] | None = None) -> dict[str, Any]:
    """The device's settings as its emulator should be started with (local transports only)."""
    settings = {k: v for k, v in table.items() if k != "driver"}
    url = settings.get("url")
    if isinstance(url, str) and url.startswith(("tcp://", "grpc://")):
        # a free local port, whatever host the real device (or gRPC device server) has
        settings["url"] = url.split("://", 1)[0] + "://127.0.0.1:0"
    if "interface" in known and "channel" in known:  # a python-can bus
        settings.pop("port", None)
        if shared_can is not None and "port" in known:
            settings.update(shared_can)
        else:
            settings["interface"] = "virtual"
            settings["channel"] = f"hilbench-emulate-{token}-{name}"
    if "tcp_port" in known and settings.get("tcp_port") is None:
        settings["tcp_port"] = 0  # the pty and a free local TCP port: the config may name either
    return settings


def _endpoints(emulator: Any) -> dict[str, Any]:
    """Every way to reach a running emulator: its pty path and its 127.0.0.1 TCP host:port."""
    out: dict[str, Any] = {}
    url = str(getattr(emulator, "url", "") or "")
    if url.startswith("/dev/"):
        out["pty"] = url
    tcp = str(getattr(emulator, "tcp_url", "") or "") or (url if "://" in url else "")
    if tcp.startswith(("socket://", "tcp://", "grpc://")):
        host_port = tcp.split("://", 1)[1]
        out["tcp"] = host_port
        out["port"] = int(host_port.rsplit(":", 1)[1])
    return out


def start_emulators(config: RigConfig, shared_can: bool = False) -> EmulatedRig:
    """Start the emulator of every device of ``config`` on one simulated plant.

    ``shared_can``: serve python-can devices on a ``udp_multicast`` bus that other processes reach
    (one per device), not on an in-process virtual bus.

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
            settings = _emulator_settings(name, table, known, token,
                                          _shared_can_bus() if shared_can and {"interface", "channel", "port"} <= known
                                          else None)
            try:
                emulator = start(settings, world)
            except ValueError as exc:  # an emulator refusing a setting names the key and value
                raise ConfigError(f"[devices.{name}] {exc}", where=config.path) from None
            rig.emulators[name] = emulator
            point: dict[str, Any] = {}
            if "url" in known:
                configured = str(table.get("url", ""))
                tcp_url = getattr(emulator, "tcp_url", None)
                point["url"] = str(tcp_url if configured.startswith("socket://") and tcp_url else emulator.url)
            rig.endpoints[name] = _endpoints(emulator)
            if "interface" in known and "channel" in known:
                point["interface"], point["channel"] = settings["interface"], settings["channel"]
                if "port" in settings:
                    point["port"] = settings["port"]
                elif "port" in table:  # a udp_multicast port of the real bus means nothing on a virtual one
                    point["port"] = 0
            rig.settings[name] = point
    except BaseException:
        rig.close()
        raise
    return rig
