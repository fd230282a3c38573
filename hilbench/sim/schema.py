"""The simulated plant's tables: what a ``[plant]`` table of a rig config may hold, and its checks.

The simulated physics is composed from effect tables (the effect names of DESIGN.md: hysteresis,
asymmetry, saturation, rate-dependence, dynamics, creep, delay, temperature, load, plus the
amplifier). The rig config hands its ``[plant]`` table to :func:`check_plant` through the driver
registry (the simulated plant is the backend named ``sim``), so the config never imports the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hilbench.errors import ConfigError
from hilbench.schema import Key, check_table
from hilbench.sim import trajectories
from hilbench.sim.dynamics import discretize_dynamics
from hilbench.sim.preisach import preisach_grid


@dataclass(frozen=True)
class SensorModel:
    """How a simulated sensor reads its channel: noise, resolution and measurable range."""

    channel: str
    noise_std: float = 0.0  # white noise, channel unit
    quantization: float = 0.0  # resolution, channel unit
    range: tuple[float, float] | None = None  # measurable [low, high], channel unit
    out_of_range: str = "clip"  # "clip" or "nan"

    @classmethod
    def of(cls, sensor: Any) -> SensorModel:
        """From any object with the sensor keys of a rig config (a ``SensorConfig``)."""
        rng = getattr(sensor, "range", None)
        return cls(sensor.channel, float(getattr(sensor, "noise_std", 0.0)), float(getattr(sensor, "quantization", 0.0)),
                   tuple(rng) if rng is not None else None, getattr(sensor, "out_of_range", "clip"))


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
            "str", required=True,
            choices=("linear", "play", "one-sided-play", "m-play", "duhem", "preisach", "bouc-wen"),
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
        "beta": Key("number", doc="Duhem (001) or Bouc-Wen beta (1/normalised input unit^n)"),
        "shape": Key("str", default="none", choices=("none", "gompertz", "tanh", "dead-zone")),
        "k1": Key("number", default=0.0),
        "k2": Key("number", default=1.0),
        "mu": Key("numbers", default=[], doc="shape parameters: G/M two, D six (mu5..mu10)"),
        "n_dead_zone": Key("int", default=0, minimum=0, doc="D shape: operators per side"),
        # Bouc-Wen: z' = A u' - beta |u'| |z|^(n-1) z - gamma u' |z|^n, output linear_gain u + z_weight z
        "a": Key("number", default=1.0, minimum=0, exclusive_minimum=True, doc="Bouc-Wen A"),
        "gamma": Key("number", default=0.0, doc="Bouc-Wen gamma; |gamma| <= beta"),
        "n": Key("number", default=1.0, minimum=1.0, doc="Bouc-Wen exponent"),
        "z_weight": Key("number", default=1.0, doc="Bouc-Wen: weight of z in the output; +1 the stop-like "
                        "y = k u + z (loop of z clockwise), -1 the piezo form y = d u - h (Low & Guo 1995): lags"),
        # Preisach: relay hysterons on a grid, factorised Gaussian density (hilbench.sim.preisach)
        "levels": Key("int", default=40, minimum=2, maximum=400, doc="Preisach: grid cells per axis"),
        "switching_range": Key("pair", default=[-1.0, 1.0], doc="Preisach: [low, high] of alpha and beta, "
                               "normalised input units"),
        "coercive_mean": Key("number", default=0.2, minimum=0, doc="Preisach: mean relay half-width"),
        "coercive_std": Key("number", default=0.15, minimum=0, exclusive_minimum=True),
        "interaction_std": Key("number", default=1.0, minimum=0, exclusive_minimum=True,
                               doc="Preisach: spread of the relay centres"),
        "scatter_seed": Key("int", default=0, minimum=0, doc="Preisach: 0 cell centres, else fields "
                            "scattered within their cells by this seed"),
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

def check_plant(plant: dict[str, Any], file: str, sample_rate_hz: float) -> dict[str, dict[str, Any]]:
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
    if h["model"] == "bouc-wen":
        _check_bouc_wen(h, file)
    if h["model"] == "preisach":
        lo, hi = h["switching_range"]
        if not lo < hi:
            raise ConfigError(f"[plant.hysteresis] switching_range = [{lo}, {hi}]: expected low < high", where=file)
        try:
            preisach_grid(h)
        except ConfigError as exc:
            raise ConfigError(exc.message, where=file) from None
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


def _check_bouc_wen(h: dict[str, Any], file: str) -> None:
    """z stays bounded by (A / (beta + gamma))^(1/n) for beta >= |gamma| and beta + gamma > 0 (the
    usual condition; Ismail, Ikhouane, Rodellar, Arch. Comput. Methods Eng. 16 (2009), sec. 3)."""
    beta, gamma = h["beta"], h["gamma"]
    if beta is None:
        raise ConfigError("[plant.hysteresis] missing key 'beta' (needed by model 'bouc-wen')", where=file)
    if beta < abs(gamma):
        raise ConfigError(f"[plant.hysteresis] beta = {beta} < |gamma| = {abs(gamma)}: Bouc-Wen needs "
                          "beta >= |gamma| for a bounded z", where=file)
    if not beta + gamma > 0:
        raise ConfigError(f"[plant.hysteresis] beta + gamma = {beta + gamma}: Bouc-Wen needs beta + gamma > 0 "
                          "for a bounded z", where=file)
