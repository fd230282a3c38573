"""Rig configurations (TOML): the actuator, its sensors, the sample rate, the drivers, the plant.

A rig config is validated completely on load; a bad one is refused with the file, the table and key,
and what was expected. ``driver = "sim"`` together with a ``[plant]`` table gives a simulated rig
whose physics is composed from the effect tables of :data:`PLANT_SCHEMA` (the effect names of
DESIGN.md: hysteresis, asymmetry, saturation, rate-dependence, dynamics, creep, delay, temperature,
load, plus the amplifier and the sensor).

Rigs are looked up by path, or by name among the built-in ones in ``configs/``
(``hilbench sweep gmm-gu2016``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from hilbench.errors import ConfigError
from hilbench.rig.registry import get_driver
from hilbench.schema import Key, check_table, read_toml

RIG_SCHEMA = {
    "name": Key("str", required=True),
    "description": Key("str", default=""),
    "paper": Key("str", default="", doc="paper the rig follows, by file number in shared/papers"),
    "follows": Key("str", default="", doc="table or equation the parameters come from"),
    "choices": Key("str", default="", doc="where the paper was ambiguous: what was chosen and why"),
    "sample_rate_hz": Key("number", required=True, minimum=0, exclusive_minimum=True),
    "realtime": Key("bool", default=False, doc="pace a simulated rig at its sample rate"),
    "seed": Key("int", default=0),
    "extends": Key("str", default="", doc="base rig (name or path) whose tables this file overrides"),
    "lock_memory": Key("bool", default=True, doc="real devices: lock the process's memory while a run's loop runs"),
    "loop_priority": Key("int", default=0, minimum=0, maximum=99,
                         doc="real devices: SCHED_FIFO priority of the loop's thread (0: the normal scheduler)"),
    "loop_cpu": Key("int", default=-1, minimum=-1, doc="real devices: the CPU the loop's thread runs on (-1: any)"),
}

ACTUATOR_SCHEMA = {
    "driver": Key("str", default="", doc="'sim' for the simulated plant; real devices name a [devices.NAME] table"),
    "device": Key("str", default="", doc="name of the [devices.NAME] table that drives the actuator"),
    "kind": Key("str", default="", doc="e.g. magnetostrictive, piezo stack"),
    "unit": Key("str", required=True, choices=("A", "V", "degC", "W")),
    "min": Key("number", required=True),
    "max": Key("number", required=True),
    "max_rate": Key("number", required=True, minimum=0, exclusive_minimum=True, doc="slew limit, unit/s"),
    "rest": Key("number", default=0.0, doc="safe value the actuator ramps to on stop"),
    "url": Key("str", default="", doc="transport URL for a real driver"),
}

SENSOR_SCHEMA = {
    "channel": Key("str", required=True),
    "unit": Key("str", required=True),
    "driver": Key("str", default="", doc="'sim' for the simulated plant; real devices name a [devices.NAME] table"),
    "device": Key("str", default="", doc="name of the [devices.NAME] table that measures the channel"),
    "source": Key("str", default="", doc="the device's own name of the channel (default: channel)"),
    "description": Key("str", default=""),
    "scale": Key("number", default=1.0, doc="physical value per raw unit (real drivers)"),
    "offset": Key("number", default=0.0, doc="physical value at raw zero (real drivers)"),
    "noise_std": Key("number", default=0.0, minimum=0, doc="white noise, channel unit (simulated)"),
    "quantization": Key("number", default=0.0, minimum=0, doc="resolution, channel unit"),
    "range": Key("pair", default=None, doc="[low, high] measurable range, channel unit"),
    "out_of_range": Key("str", default="clip", choices=("clip", "nan")),
    "url": Key("str", default=""),
}

PLAN_RUN_SCHEMA_KEYS = ("label", "sweep")  # plus the excitation's own keys, see hilbench.excitation.plan


@dataclass
class ActuatorConfig:
    driver: str
    unit: str
    min: float
    max: float
    max_rate: float
    rest: float
    kind: str = ""
    url: str = ""
    device: str = ""


@dataclass
class SensorConfig:
    channel: str
    unit: str
    driver: str
    description: str = ""
    device: str = ""
    source: str = ""
    scale: float = 1.0
    offset: float = 0.0
    noise_std: float = 0.0
    quantization: float = 0.0
    range: list[float] | None = None
    out_of_range: str = "clip"
    url: str = ""


@dataclass
class RigConfig:
    path: str
    text: str
    name: str
    sample_rate_hz: float
    actuator: ActuatorConfig
    sensors: list[SensorConfig]
    plant: dict[str, dict[str, Any]] = field(default_factory=dict)
    plan: list[dict[str, Any]] = field(default_factory=list)
    #: real devices by name: the [devices.NAME] tables, each with its ``driver`` and complete settings
    devices: dict[str, dict[str, Any]] = field(default_factory=dict)
    description: str = ""
    paper: str = ""
    follows: str = ""
    choices: str = ""
    realtime: bool = False
    seed: int = 0
    #: what the operating system is asked for the fixed-rate loop (hilbench.runners.loop_tuning)
    lock_memory: bool = True
    loop_priority: int = 0
    loop_cpu: int = -1

    @property
    def simulated(self) -> bool:
        return self.actuator.driver == "sim"

    def sensor(self, channel: str) -> SensorConfig | None:
        return next((s for s in self.sensors if s.channel == channel), None)


def _configs_folder() -> Path:
    """configs/ as installed (package data hilbench.configs), else next to the source tree."""
    try:
        return Path(str(resources.files("hilbench.configs")))
    except ModuleNotFoundError:
        # Running from a checkout whose hilbench/ shadows a non-editable install.
        return Path(__file__).resolve().parents[2] / "configs"


def builtin_rigs() -> dict[str, Path]:
    """Built-in rig configs by name (file stem)."""
    return {p.stem: p for p in sorted(_configs_folder().glob("*.toml"))}


def resolve_rig_path(name_or_path: str) -> Path:
    path = Path(name_or_path)
    if path.exists():
        return path
    rigs = builtin_rigs()
    if name_or_path in rigs:
        return rigs[name_or_path]
    raise ConfigError(
        f"no such file, and no built-in rig of that name; built-in rigs: {', '.join(sorted(rigs))}",
        where=name_or_path,
    )


def _check_devices(
    tables: dict[str, Any] | None, act: dict[str, Any], sensors: list[SensorConfig], file: str
) -> dict[str, dict[str, Any]]:
    """Check every ``[devices.NAME]`` table with its driver, and that each role names a device.

    Nothing is opened here: a driver says what is wrong with its settings without touching a
    transport, so ``sweep --check`` works with the hardware unplugged.
    """
    devices: dict[str, dict[str, Any]] = {}
    for name, table in (tables or {}).items():
        if not isinstance(table, dict):
            raise ConfigError(f"[devices.{name}]: expected a table with driver = '...' and its settings", where=file)
        driver_name = table.get("driver")
        if not isinstance(driver_name, str) or not driver_name:
            raise ConfigError(f"[devices.{name}] driver: expected the name of a registered driver", where=file)
        if driver_name == "sim":
            raise ConfigError(f"[devices.{name}]: the simulated plant is chosen with driver = 'sim' in [actuator] "
                              "and [[sensors]], its physics in [plant]", where=file)
        driver = get_driver(driver_name, where=f"{file}: [devices.{name}]")
        settings = {k: v for k, v in table.items() if k != "driver"}
        problems = driver.problems(settings)
        if problems:
            raise ConfigError(f"[devices.{name}] {problems[0]}", where=file)
        devices[name] = {"driver": driver_name, **driver.complete(settings)}

    def role(table: str, entry: dict[str, Any] | SensorConfig) -> str:
        get = entry.get if isinstance(entry, dict) else lambda k: getattr(entry, k)
        driver, device = get("driver"), get("device")
        if driver and device:
            raise ConfigError(f"[{table}]: give driver = 'sim' or device = 'NAME', not both", where=file)
        if device:
            if device not in devices:
                raise ConfigError(f"[{table}] device: no [devices.{device}] table; devices: "
                                  f"{', '.join(devices) or 'none'}", where=file)
            return str(devices[device]["driver"])
        if driver and driver != "sim":
            raise ConfigError(f"[{table}] driver {driver!r}: a real device is described in a [devices.NAME] table "
                              f"(driver = {driver!r} and its settings) and named here with device = 'NAME'",
                              where=file)
        if not driver:
            raise ConfigError(f"[{table}]: expected driver = 'sim' or device = 'NAME'", where=file)
        return str(driver)

    act["driver"] = role("actuator", act)
    for i, s in enumerate(sensors):
        s.driver = role(f"sensors[{i}]", s)
        if s.device and s.driver and "sensor" not in get_driver(s.driver).roles:
            raise ConfigError(f"[sensors[{i}]] device {s.device!r}: driver {s.driver!r} cannot measure", where=file)
    if act["device"] and "actuator" not in get_driver(act["driver"]).roles:
        raise ConfigError(f"[actuator] device {act['device']!r}: driver {act['driver']!r} cannot drive an actuator",
                          where=file)
    return devices


def _deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _read_with_bases(path: Path, seen: tuple[Path, ...] = ()) -> tuple[str, dict[str, Any]]:
    """Read a rig file; a ``[rig] extends`` names a base whose tables this file overrides."""
    text, data = read_toml(path)
    rig = data.get("rig")
    base_name = rig.get("extends") if isinstance(rig, dict) else None
    if "extends" in data:  # a top-level `extends = "rig"` (before the first table) means the same
        if base_name:
            raise ConfigError("extends is given twice, at the top and in [rig]; give it once", where=str(path))
        base_name = data.pop("extends")
        if base_name == "" or not isinstance(base_name, str):
            raise ConfigError(f"extends: expected a rig name or path, got {base_name!r}", where=str(path),
                              hint="e.g. extends = \"piezo-demo\"; built-in rigs: `hilbench rigs`")
        if isinstance(rig, dict):
            rig["extends"] = base_name
    if not base_name:
        return text, data
    if not isinstance(base_name, str):
        raise ConfigError(f"[rig] extends: expected a rig name or path, got {base_name!r}", where=str(path))
    local = path.parent / base_name
    base_path = local if local.exists() else (path.parent / f"{base_name}.toml")
    if not base_path.exists():
        base_path = resolve_rig_path(base_name)
    if base_path.resolve() in seen:
        raise ConfigError(f"[rig] extends: {base_name!r} extends itself in a loop", where=str(path))
    base_text, base_data = _read_with_bases(base_path, (*seen, path.resolve()))
    merged = _deep_merge(base_data, data)
    if not isinstance(merged.get("rig"), dict):
        raise ConfigError("[rig]: expected a table", where=str(path))
    merged["rig"] = {k: v for k, v in merged["rig"].items() if k != "extends"}
    return f"{text}\n# ---- extends {base_path.name} ----\n{base_text}", merged


def load_rig(name_or_path: str | Path) -> RigConfig:
    """Load and validate a rig config; raises :class:`ConfigError` with file, key and expectation."""
    path = resolve_rig_path(str(name_or_path))
    file = str(path)
    text, data = _read_with_bases(path)
    top = check_table(
        data,
        {"rig": Key("table", required=True), "actuator": Key("table", required=True),
         "sensors": Key("tables", required=True), "plant": Key("table"), "plan": Key("table"),
         "devices": Key("table"), "extends": Key("str", doc="base rig whose tables this file overrides")},
        file=file,
        table="",
    )
    rig = check_table(top["rig"], RIG_SCHEMA, file=file, table="rig")
    act = check_table(top["actuator"], ACTUATOR_SCHEMA, file=file, table="actuator")
    if not act["min"] < act["max"]:
        raise ConfigError(
            f"[actuator] min {act['min']:g} must be less than max {act['max']:g} (limits inverted?)", where=file
        )
    if not act["min"] <= act["rest"] <= act["max"]:
        raise ConfigError(
            f"[actuator] rest {act['rest']:g} must lie within [min, max] = [{act['min']:g}, {act['max']:g}]", where=file
        )
    sensors = []
    for i, s in enumerate(top["sensors"]):
        values = check_table(s, SENSOR_SCHEMA, file=file, table=f"sensors[{i}]")
        if values["range"] is not None and not values["range"][0] < values["range"][1]:
            raise ConfigError(f"[sensors[{i}]] range: expected low < high, got {values['range']}", where=file)
        sensors.append(SensorConfig(**values))
    channels = [s.channel for s in sensors]
    if "output" not in channels:
        raise ConfigError("[[sensors]]: expected a sensor with channel = 'output' (the displacement)", where=file)
    if len(set(channels)) != len(channels):
        raise ConfigError(f"[[sensors]]: channel names must be unique, got {channels}", where=file)
    reserved = {"time", "input", "lateness"}
    if reserved & set(channels):
        raise ConfigError(f"[[sensors]]: channel names {sorted(reserved)} are reserved", where=file)
    devices = _check_devices(top["devices"], act, sensors, file)
    plant: dict[str, dict[str, Any]] = {}
    simulated = act["driver"] == "sim"
    if top["plant"] is not None or simulated:
        # The simulated plant is the backend named "sim"; on a real rig a [plant] is what
        # `hilbench emulate` backs the emulators with. Either way it is checked by its backend.
        sim = get_driver("sim", where=file)
        plant = sim.complete({"plant": top["plant"], "sample_rate_hz": rig["sample_rate_hz"], "file": file})["plant"]
    if simulated:
        for s in sensors:
            if s.driver != "sim":
                raise ConfigError(f"sensor {s.channel!r}: a simulated rig needs driver = 'sim', got {s.driver!r}", where=file)
            if s.channel in ("temperature", "load") and s.channel not in plant:
                raise ConfigError(
                    f"sensor {s.channel!r} needs a [plant.{s.channel}] table with its trajectory", where=file
                )
    plan_runs: list[dict[str, Any]] = []
    if top["plan"] is not None:
        plan_table = check_table(top["plan"], {"runs": Key("tables", required=True)}, file=file, table="plan")
        plan_runs = [dict(r) for r in plan_table["runs"]]
    return RigConfig(
        path=file,
        text=text,
        name=rig["name"],
        description=rig["description"],
        paper=rig["paper"],
        follows=rig["follows"],
        choices=rig["choices"],
        sample_rate_hz=rig["sample_rate_hz"],
        realtime=rig["realtime"],
        seed=rig["seed"],
        lock_memory=rig["lock_memory"],
        loop_priority=rig["loop_priority"],
        loop_cpu=rig["loop_cpu"],
        actuator=ActuatorConfig(**act),
        sensors=sensors,
        plant=plant,
        plan=plan_runs,
        devices=devices,
    )
