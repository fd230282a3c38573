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

import sys
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from hilbench.errors import ConfigError
from hilbench.schema import Key, check_table
from hilbench.sim import trajectories
from hilbench.sim.dynamics import discretize_dynamics

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

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
}

ACTUATOR_SCHEMA = {
    "driver": Key("str", required=True),
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
    "driver": Key("str", required=True),
    "description": Key("str", default=""),
    "scale": Key("number", default=1.0, doc="physical value per raw unit (real drivers)"),
    "offset": Key("number", default=0.0, doc="physical value at raw zero (real drivers)"),
    "noise_std": Key("number", default=0.0, minimum=0, doc="white noise, channel unit (simulated)"),
    "quantization": Key("number", default=0.0, minimum=0, doc="resolution, channel unit"),
    "range": Key("pair", default=None, doc="[low, high] measurable range, channel unit"),
    "out_of_range": Key("str", default="clip", choices=("clip", "nan")),
    "url": Key("str", default=""),
}

_ENABLED = {"enabled": Key("bool", default=True)}

TRAJECTORY_SCHEMA = {
    "kind": Key(
        "str",
        required=True,
        choices=("constant", "ramp", "cooling", "sine", "steps", "step", "placed-weight"),
    ),
    "value": Key("number", doc="constant level"),
    "start": Key("number"),
    "end": Key("number"),
    "duration_s": Key("number", minimum=0, exclusive_minimum=True),
    "initial": Key("number", doc="cooling: value at t = 0"),
    "ambient": Key("number", doc="cooling: final value"),
    "time_constant_s": Key("number", minimum=0, exclusive_minimum=True),
    "mean": Key("number"),
    "amplitude": Key("number"),
    "period_s": Key("number", minimum=0, exclusive_minimum=True),
    "levels": Key("numbers"),
    "hold_s": Key("number", minimum=0, exclusive_minimum=True),
    "at_s": Key("number", minimum=0, doc="step / placed-weight: when"),
    "mass_kg": Key("number", minimum=0, doc="placed-weight: the weight"),
    "contacts": Key("int", default=2, minimum=1, doc="placed-weight: partial contacts while it settles"),
    "contact_interval_s": Key("number", default=0.5, minimum=0),
    "settle_hz": Key("number", default=8.0, minimum=0, exclusive_minimum=True),
    "damping": Key("number", default=0.15, minimum=0, maximum=0.99),
}

PLANT_SCHEMA: dict[str, dict[str, Key]] = {
    "amplifier": {
        **_ENABLED,
        "gain": Key("number", default=1.0, doc="drive unit per command unit"),
        "bandwidth_hz": Key("number", default=0.0, minimum=0, doc="first-order; 0 = unlimited"),
        "slew_rate": Key("number", default=0.0, minimum=0, doc="drive unit per s; 0 = unlimited"),
        "output_limit": Key("pair", default=None),
    },
    "delay": {**_ENABLED, "seconds": Key("number", default=0.0, minimum=0)},
    "hysteresis": {
        **_ENABLED,
        "model": Key(
            "str", required=True, choices=("linear", "play", "one-sided-play", "m-play", "duhem")
        ),
        "input_scale": Key("number", default=1.0, minimum=0, exclusive_minimum=True,
                           doc="command units per normalised input unit"),
        "output_scale": Key("number", default=1.0, doc="um per model output unit"),
        "linear_gain": Key("number", default=0.0, doc="p0: the linear term"),
        "thresholds": Key("numbers", default=[], minimum=0, doc="normalised input units"),
        "weights": Key("numbers", default=[]),
        "eta": Key("numbers", default=None, minimum=-1, doc="M-play delay coefficients (004)"),
        "input_exponents": Key("numbers", default=[], doc="FPMPI input polynomial exponents (000)"),
        "input_weights": Key("numbers", default=[]),
        "alpha": Key("number", minimum=0, exclusive_minimum=True, doc="Duhem (001)"),
        "beta": Key("number"),
        "shape": Key("str", default="none", choices=("none", "gompertz", "tanh", "dead-zone")),
        "k1": Key("number", default=0.0),
        "k2": Key("number", default=1.0),
        "mu": Key("numbers", default=[], doc="shape parameters: G/M two, D six (mu5..mu10)"),
        "n_dead_zone": Key("int", default=0, minimum=0, doc="D shape: operators per side"),
    },
    "asymmetry": {**_ENABLED, "coefficients": Key("numbers", required=True, doc="c0 + c1 v + c2 v^2 + ...")},
    "saturation": {**_ENABLED, "level": Key("number", required=True, minimum=0, exclusive_minimum=True)},
    "rate_dependence": {
        **_ENABLED,
        "mode": Key("str", default="damping", choices=("damping", "frequency-polynomial")),
        "gain": Key("number", default=1.0, doc="k"),
        "coefficient": Key("number", default=0.0, doc="c"),
        "exponent": Key("number", default=1.0, minimum=0, exclusive_minimum=True, doc="m"),
        "reference_rate": Key("number", default=1.0, minimum=0, exclusive_minimum=True,
                              doc="Q: normalised input units per s"),
        "k_poly": Key("numbers", default=[1.0], doc="k(f) coefficients, ascending powers of f in Hz"),
        "c_poly": Key("numbers", default=[0.0]),
        "m_poly": Key("numbers", default=[1.0]),
    },
    "dynamics": {
        **_ENABLED,
        "kind": Key("str", required=True, choices=("second-order", "transfer-function", "discrete")),
        "gain": Key("number", default=1.0),
        "zeta": Key("number", minimum=0),
        "natural_frequency_hz": Key("number", minimum=0, exclusive_minimum=True),
        "num": Key("numbers", doc="continuous numerator, descending powers of s"),
        "den": Key("numbers"),
        "b": Key("numbers", doc="discrete numerator, ascending powers of z^-1"),
        "a": Key("numbers"),
    },
    "creep": {
        **_ENABLED,
        "gains": Key("numbers", required=True, doc="fraction of the hysteresis output per element"),
        "time_constants_s": Key("numbers", required=True, minimum=0, exclusive_minimum=True),
    },
    "temperature": {
        **_ENABLED,
        "trajectory": Key("table", required=True),
        "reference_degC": Key("number", default=20.0),
        "gain_per_degC": Key("number", default=0.0),
        "strain_um_per_degC": Key("number", default=0.0),
    },
    "load": {
        **_ENABLED,
        "trajectory": Key("table", required=True),
        "gain_per_N": Key("number", default=0.0),
        "compliance_um_per_N": Key("number", default=0.0),
    },
}

PLAN_RUN_SCHEMA_KEYS = ("label", "sweep")  # plus the excitation's own keys, see hilbench.plan


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


@dataclass
class SensorConfig:
    channel: str
    unit: str
    driver: str
    description: str = ""
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
    description: str = ""
    paper: str = ""
    follows: str = ""
    choices: str = ""
    realtime: bool = False
    seed: int = 0

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
        return Path(__file__).resolve().parents[1] / "configs"


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


def read_toml(path: Path) -> tuple[str, dict[str, Any]]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("file not found", where=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read ({exc.__class__.__name__}: {exc})", where=str(path)) from None
    try:
        return text, tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"not valid TOML: {exc}", where=str(path)) from None


def _check_plant(plant: dict[str, Any], file: str, sample_rate_hz: float) -> dict[str, dict[str, Any]]:
    checked_top = check_table(
        plant, {name: Key("table") for name in PLANT_SCHEMA}, file=file, table="plant"
    )
    out: dict[str, dict[str, Any]] = {}
    for name, schema in PLANT_SCHEMA.items():
        table = checked_top[name]
        if table is None:
            continue
        values = check_table(table, schema, file=file, table=f"plant.{name}")
        if not values["enabled"]:
            continue
        if name in ("temperature", "load"):
            values["trajectory"] = check_table(
                values["trajectory"], TRAJECTORY_SCHEMA, file=file, table=f"plant.{name}.trajectory"
            )
            try:
                trajectories.validate(values["trajectory"])
            except ConfigError as exc:
                raise ConfigError(f"[plant.{name}.trajectory] {exc.message}", where=file) from None
        out[name] = values
    if "hysteresis" not in out:
        raise ConfigError("[plant] needs a [plant.hysteresis] table (model = 'linear' for none)", where=file)
    _check_plant_consistency(out, file, sample_rate_hz)
    return out


def _check_plant_consistency(plant: dict[str, dict[str, Any]], file: str, sample_rate_hz: float) -> None:
    h = plant["hysteresis"]
    if len(h["thresholds"]) != len(h["weights"]):
        raise ConfigError(
            f"[plant.hysteresis] thresholds has {len(h['thresholds'])} entries but weights has "
            f"{len(h['weights'])}; expected one weight per threshold",
            where=file,
        )
    if h["model"] == "m-play" and (h["eta"] is None or len(h["eta"]) != len(h["thresholds"])):
        raise ConfigError("[plant.hysteresis] eta: expected one M-play coefficient per threshold", where=file)
    if len(h["input_exponents"]) != len(h["input_weights"]):
        raise ConfigError("[plant.hysteresis] input_exponents and input_weights must have the same length", where=file)
    if h["model"] == "duhem":
        for key in ("alpha", "beta"):
            if h[key] is None:
                raise ConfigError(f"[plant.hysteresis] missing key {key!r} (needed by model 'duhem')", where=file)
        need = {"gompertz": 2, "tanh": 2, "dead-zone": 6, "none": 0}[h["shape"]]
        if len(h["mu"]) != need:
            raise ConfigError(
                f"[plant.hysteresis] mu: shape {h['shape']!r} needs {need} parameters, got {len(h['mu'])}", where=file
            )
    d = plant.get("dynamics")
    if d is not None:
        need_keys = {
            "second-order": ("zeta", "natural_frequency_hz"),
            "transfer-function": ("num", "den"),
            "discrete": ("b", "a"),
        }[d["kind"]]
        for key in need_keys:
            if d[key] is None:
                raise ConfigError(f"[plant.dynamics] missing key {key!r} (needed by kind {d['kind']!r})", where=file)
        try:
            discretize_dynamics(d, sample_rate_hz)
        except ConfigError as exc:
            raise ConfigError(exc.message, where=file) from None
    c = plant.get("creep")
    if c is not None and len(c["gains"]) != len(c["time_constants_s"]):
        raise ConfigError("[plant.creep] gains and time_constants_s must have the same length", where=file)


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
         "sensors": Key("tables", required=True), "plant": Key("table"), "plan": Key("table")},
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
    plant: dict[str, dict[str, Any]] = {}
    simulated = act["driver"] == "sim"
    if simulated:
        if top["plant"] is None:
            raise ConfigError("driver = 'sim' needs a [plant] table describing the simulated physics", where=file)
        plant = _check_plant(top["plant"], file, rig["sample_rate_hz"])
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
        actuator=ActuatorConfig(**act),
        sensors=sensors,
        plant=plant,
        plan=plan_runs,
    )
