"""The simulated plant: physics composed from the effect tables of a rig config.

:class:`Plant` turns the validated ``[plant]`` tables into the parameter and state arrays of
:func:`hilbench.sim.kernels.plant_block` and runs it in block mode (:meth:`Plant.simulate`) or step
mode (:meth:`Plant.step`). Both draw the sensor noise from the same seeded stream in the same order,
so a run is reproducible and block and step mode give the same samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hilbench.config import RigConfig, SensorConfig
from hilbench.errors import ConfigError
from hilbench.sim import kernels as K
from hilbench.sim import trajectories
from hilbench.sim.dynamics import discretize_dynamics

_EMPTY = np.zeros(0)

#: Plant table names as effect names of DESIGN.md (the tables use underscores).
EFFECT_OF_TABLE = {
    "hysteresis": "hysteresis",
    "asymmetry": "asymmetry",
    "saturation": "saturation",
    "rate_dependence": "rate-dependence",
    "dynamics": "dynamics",
    "creep": "creep",
    "delay": "delay",
    "temperature": "temperature",
    "load": "load",
    "amplifier": "amplifier",
}


@dataclass
class PlantOutput:
    """One block of simulated samples (arrays of equal length)."""

    output: np.ndarray  # measured displacement, um (sensor noise, quantisation, range applied)
    true_output: np.ndarray  # displacement before the sensor, um
    drive: np.ndarray  # amplifier output (A or V)
    aux: dict[str, np.ndarray]  # measured auxiliary channels (temperature, load, current)


class Plant:
    """A simulated actuator with its amplifier and sensors."""

    def __init__(self, plant: dict[str, dict[str, Any]], sample_rate_hz: float, sensors: list[SensorConfig], seed: int = 0):
        self.tables = plant
        self.sample_rate_hz = float(sample_rate_hz)
        self.sensors = {s.channel: s for s in sensors}
        self.seed = seed
        self.S = np.zeros(K.N_SCALARS)
        self._build()
        self.reset()

    @classmethod
    def from_rig(cls, rig: RigConfig) -> Plant:
        try:
            return cls(rig.plant, rig.sample_rate_hz, rig.sensors, rig.seed)
        except ConfigError as exc:
            if exc.where is None:
                raise ConfigError(exc.message, where=rig.path, hint=exc.hint) from None
            raise

    @property
    def effects(self) -> list[str]:
        """Effect names (DESIGN.md vocabulary) switched on in this plant."""
        names = [EFFECT_OF_TABLE[t] for t in self.tables]
        if self.tables["hysteresis"]["model"] == "linear":
            names.remove("hysteresis")
        return names

    # -- construction ---------------------------------------------------------------------------
    def _build(self) -> None:
        S, t, fs = self.S, self.tables, self.sample_rate_hz
        S[K.S_FS] = fs
        amp = t.get("amplifier")
        S[K.S_AMP_GAIN] = 1.0
        S[K.S_AMP_ALPHA] = 1.0
        S[K.S_AMP_SLEW] = math.inf
        S[K.S_AMP_LO], S[K.S_AMP_HI] = -math.inf, math.inf
        if amp is not None:
            S[K.S_AMP_ON] = 1.0
            S[K.S_AMP_GAIN] = amp["gain"]
            if amp["bandwidth_hz"] > 0:
                S[K.S_AMP_ALPHA] = 1.0 - math.exp(-2 * math.pi * amp["bandwidth_hz"] / fs)
            if amp["slew_rate"] > 0:
                S[K.S_AMP_SLEW] = amp["slew_rate"] / fs
            if amp["output_limit"] is not None:
                S[K.S_AMP_LO], S[K.S_AMP_HI] = amp["output_limit"]
        delay = t.get("delay")
        self.delay_samples = int(round(delay["seconds"] * fs)) if delay is not None else 0
        S[K.S_DELAY] = self.delay_samples

        h = t["hysteresis"]
        S[K.S_INPUT_SCALE] = h["input_scale"]
        S[K.S_OUT_SCALE] = h["output_scale"]
        S[K.S_P0] = h["linear_gain"]
        model = h["model"]
        self.op_r = np.asarray(h["thresholds"], float)
        self.op_w = np.asarray(h["weights"], float)
        if model == "linear":
            S[K.S_MODEL] = 0.0
            self.op_r = self.op_w = _EMPTY
        elif model == "duhem":
            S[K.S_MODEL] = 2.0
            S[K.S_DUHEM_ALPHA], S[K.S_DUHEM_BETA] = h["alpha"], h["beta"]
            S[K.S_DUHEM_K1], S[K.S_DUHEM_K2] = h["k1"], h["k2"]
            S[K.S_DUHEM_SHAPE] = {"none": 0.0, "gompertz": 1.0, "tanh": 2.0, "dead-zone": 3.0}[h["shape"]]
            if h["shape"] in ("gompertz", "tanh"):
                S[K.S_MU_A], S[K.S_MU_B] = h["mu"]
            self.op_r = self.op_w = _EMPTY
        else:
            S[K.S_MODEL] = 1.0
        eta_default = {"play": 1.0, "one-sided-play": 0.0}.get(model, 1.0)
        self.op_eta = (
            np.asarray(h["eta"], float) if model == "m-play" else np.full(self.op_r.shape, eta_default)
        )
        self.dz_r, self.dz_g = _EMPTY, _EMPTY
        if model == "duhem" and h["shape"] == "dead-zone":
            self.dz_r, self.dz_g = dead_zone_operators(h["mu"], h["n_dead_zone"])
        self.in_exp = np.asarray(h["input_exponents"], float)
        self.in_w = np.asarray(h["input_weights"], float)

        self.asym = np.asarray(t["asymmetry"]["coefficients"], float) if "asymmetry" in t else _EMPTY
        S[K.S_SAT_LEVEL] = t["saturation"]["level"] if "saturation" in t else 0.0

        rate = t.get("rate_dependence")
        self.rate_kp, self.rate_cp, self.rate_mp = np.ones(1), np.zeros(1), np.ones(1)
        if rate is not None:
            S[K.S_RATE_MODE] = 1.0 if rate["mode"] == "damping" else 2.0
            S[K.S_RATE_K], S[K.S_RATE_C] = rate["gain"], rate["coefficient"]
            S[K.S_RATE_M], S[K.S_RATE_Q] = rate["exponent"], rate["reference_rate"]
            self.rate_kp = np.asarray(rate["k_poly"], float)
            self.rate_cp = np.asarray(rate["c_poly"], float)
            self.rate_mp = np.asarray(rate["m_poly"], float)

        creep = t.get("creep")
        if creep is not None:
            self.creep_g = np.asarray(creep["gains"], float)
            self.creep_a = 1.0 - np.exp(-1.0 / (fs * np.asarray(creep["time_constants_s"], float)))
        else:
            self.creep_g = self.creep_a = _EMPTY

        dyn = t.get("dynamics")
        if dyn is not None:
            self.dyn_b, self.dyn_a = discretize_dynamics(dyn, fs)
            S[K.S_DYN_ON] = 1.0 if len(self.dyn_a) > 1 else 0.0
            if len(self.dyn_a) == 1:  # a pure gain
                S[K.S_OUT_SCALE] *= self.dyn_b[0]
        else:
            self.dyn_b, self.dyn_a = np.ones(1), np.ones(1)

        temp = t.get("temperature")
        if temp is not None:
            trajectories.validate(temp["trajectory"])
            S[K.S_TEMP_ON] = 1.0
            S[K.S_TEMP_REF] = temp["reference_degC"]
            S[K.S_TEMP_GAIN] = temp["gain_per_degC"]
            S[K.S_TEMP_STRAIN] = temp["strain_um_per_degC"]
        load = t.get("load")
        if load is not None:
            trajectories.validate(load["trajectory"])
            S[K.S_LOAD_ON] = 1.0
            S[K.S_LOAD_GAIN] = load["gain_per_N"]
            S[K.S_LOAD_COMPLIANCE] = load["compliance_um_per_N"]

        out = self.sensors["output"]
        S[K.S_NOISE_STD] = out.noise_std
        S[K.S_QUANT] = out.quantization
        S[K.S_RANGE_LO], S[K.S_RANGE_HI] = out.range if out.range is not None else (-math.inf, math.inf)
        S[K.S_RANGE_NAN] = 1.0 if out.out_of_range == "nan" else 0.0

    def reset(self) -> None:
        """Back to the virgin state: operators at zero, filters empty, noise stream restarted."""
        self.X = np.zeros(K.N_STATES)
        self.op_state = np.zeros(self.op_r.shape[0])
        self.creep_state = np.zeros(self.creep_g.shape[0])
        self.dyn_state = np.zeros(max(len(self.dyn_a) - 1, 1))
        self.delay_buf = np.zeros(max(self.delay_samples, 1))
        self.tp_state = np.zeros(K.N_TP)
        self.time_s = 0.0  # time of the next sample on the current run's clock
        self.samples = 0
        self._rng_output = np.random.default_rng([self.seed, 1])
        # One stream per channel, so block and step mode draw each channel's noise in the same order.
        self._rng_aux = {c: np.random.default_rng([self.seed, 2, k]) for k, c in enumerate(sorted(self.sensors))}

    def start_run(self) -> None:
        """Restart the run clock (trajectories of temperature and load start again); memory stays."""
        self.time_s = 0.0
        self.samples = 0

    # -- simulation -------------------------------------------------------------------------------
    def simulate(self, command: np.ndarray) -> PlantOutput:
        """Block mode: simulate len(command) samples from the current state."""
        u = np.ascontiguousarray(command, dtype=np.float64)
        n = u.shape[0]
        temperature = load = _EMPTY
        if "temperature" in self.tables or "load" in self.tables:  # the run clock only when needed
            t = (self.samples + np.arange(n)) / self.sample_rate_hz
            if "temperature" in self.tables:
                temperature = trajectories.evaluate(self.tables["temperature"]["trajectory"], t)
            if "load" in self.tables:
                load = trajectories.evaluate(self.tables["load"]["trajectory"], t)
        noise = self._rng_output.standard_normal(n) if self.S[K.S_NOISE_STD] > 0 else np.zeros(n)
        measured = np.empty(n)
        true = np.empty(n)
        drive = np.empty(n)
        K.plant_block(
            u, temperature, load, noise, self.S, self.in_exp, self.in_w, self.op_r, self.op_w, self.op_eta,
            self.asym, self.dz_r, self.dz_g, self.rate_kp, self.rate_cp, self.rate_mp, self.creep_g,
            self.creep_a, self.dyn_b, self.dyn_a, self.X, self.op_state, self.creep_state, self.dyn_state,
            self.delay_buf, self.tp_state, measured, true, drive,
        )
        self.samples += n
        self.time_s = self.samples / self.sample_rate_hz
        aux: dict[str, np.ndarray] = {}
        for channel, truth in (("temperature", temperature), ("load", load), ("current", drive)):
            sensor = self.sensors.get(channel)
            if sensor is not None:
                aux[channel] = self._read_aux(sensor, truth)
        return PlantOutput(measured, true, drive, aux)

    def step(self, command: float) -> PlantOutput:
        """Step mode: one sample through the same kernel."""
        return self.simulate(np.array([command], dtype=np.float64))

    def _read_aux(self, sensor: SensorConfig, truth: np.ndarray) -> np.ndarray:
        if sensor.noise_std > 0:
            value = truth + sensor.noise_std * self._rng_aux[sensor.channel].standard_normal(truth.shape[0])
        else:
            value = truth.copy()
        if sensor.quantization > 0:
            value = sensor.quantization * np.floor(value / sensor.quantization + 0.5)
        if sensor.range is not None:
            lo, hi = sensor.range
            if sensor.out_of_range == "nan":
                value = np.where((value < lo) | (value > hi), np.nan, value)
            else:
                value = np.clip(value, lo, hi)
        return value


def dead_zone_operators(mu: list[float], n: int) -> tuple[np.ndarray, np.ndarray]:
    """Thresholds and weights of 001's D shape function (eq. 28-31), i = -n..n.

    r_i = mu5 i, g_i = -mu6 exp(-mu7 i) for i >= 0; r_i = mu8 i, g_i = mu9 exp(-mu10 |i|) for i < 0.
    """
    mu5, mu6, mu7, mu8, mu9, mu10 = mu
    idx_pos = np.arange(0, n + 1, dtype=float)
    idx_neg = np.arange(-n, 0, dtype=float)
    r = np.concatenate([mu8 * idx_neg, mu5 * idx_pos])
    # Eq. 31 read with |i| (see configs/gmm-issf-duhem.toml, "choices"): weights decay on both sides.
    g = np.concatenate([mu9 * np.exp(-mu10 * np.abs(idx_neg)), -mu6 * np.exp(-mu7 * idx_pos)])
    return r, g
