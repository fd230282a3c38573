"""The simulated plant: physics composed from the effect tables of a rig config.

:class:`Plant` turns the validated ``[plant]`` tables into the parameter and state arrays of
:func:`hilbench.sim.kernels.plant_step` (views of one flat buffer) and runs it in block mode
(:meth:`Plant.simulate`, :func:`~hilbench.sim.kernels.plant_block`) or step mode (:meth:`Plant.step`,
and :meth:`Plant.step_value`, the fast path: one numba call, well under a microsecond). Step mode
takes the sensor noise and the temperature/load trajectories from batches prepared ahead from the
same seeded streams; block mode uses up a batch's remaining draws first, so a run is reproducible
and block and step mode, in any mix, give the same samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hilbench.sim.schema import SensorModel
from hilbench.effects import effect_of_plant_table
from hilbench.errors import ConfigError
from hilbench.sim import kernels as K
from hilbench.sim import trajectories
from hilbench.sim.dynamics import discretize_dynamics
from hilbench.sim.preisach import preisach_grid

_EMPTY = np.zeros(0)

@dataclass
class PlantOutput:
    """One block of simulated samples (arrays of equal length)."""

    output: np.ndarray  # measured displacement, um (sensor noise, quantisation, range applied)
    true_output: np.ndarray  # displacement before the sensor, um
    drive: np.ndarray  # amplifier output (A or V)
    aux: dict[str, np.ndarray]  # measured auxiliary channels (temperature, load, current)


class Plant:
    """A simulated actuator with its amplifier and sensors."""

    def __init__(self, plant: dict[str, dict[str, Any]], sample_rate_hz: float, sensors: list[Any], seed: int = 0):
        self.tables = plant
        self.sample_rate_hz = float(sample_rate_hz)
        self.sensors = {s.channel: SensorModel.of(s) for s in sensors}
        self.seed = seed
        self.S = np.zeros(K.N_SCALARS)
        self._build()
        self.reset()

    @classmethod
    def from_rig(cls, rig: Any) -> Plant:
        """From a rig config (any object with ``plant``, ``sample_rate_hz``, ``sensors``, ``seed``, ``path``)."""
        try:
            return cls(rig.plant, rig.sample_rate_hz, rig.sensors, rig.seed)
        except ConfigError as exc:
            if exc.where is None:
                raise ConfigError(exc.message, where=rig.path, hint=exc.hint) from None
            raise

    @property
    def effects(self) -> list[str]:
        """Effect names (DESIGN.md vocabulary) switched on in this plant."""
        names = [effect_of_plant_table(t) for t in self.tables]
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
        elif model == "preisach":
            S[K.S_MODEL] = 3.0
            self.relay_a, self.relay_b, self.op_w, self.op_state0 = preisach_grid(h)
            self.op_r = _EMPTY
        elif model == "bouc-wen":
            S[K.S_MODEL] = 4.0
            bw = (h["a"], h["beta"], h["gamma"], h["n"])
            S[K.S_BW_A], S[K.S_BW_BETA], S[K.S_BW_GAMMA], S[K.S_BW_N] = bw
            S[K.S_BW_DU_MAX] = K.bouc_wen_du_max(*bw)
            S[K.S_BW_W] = h["z_weight"]
            self.op_r = self.op_w = _EMPTY
        else:
            S[K.S_MODEL] = 1.0
        if model != "preisach":
            self.relay_a = self.relay_b = _EMPTY
            self.op_state0 = np.zeros(self.op_r.shape[0])
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

    #: samples of noise and trajectories prepared at once for step mode
    STEP_BATCH = 1024

    def reset(self) -> None:
        """Back to the virgin state: operators at zero, filters empty, noise stream restarted."""
        self._pack()
        self.samples = 0
        self._rng_output = np.random.default_rng([self.seed, 1])
        # One stream per channel, so block and step mode draw each channel's noise in the same order.
        self._rng_aux = {c: np.random.default_rng([self.seed, 2, k]) for k, c in enumerate(sorted(self.sensors))}
        # Step mode reads the sensor noise and the temperature/load trajectories from a batch prepared
        # ahead (columns pos..STEP_BATCH-1 not used yet); block mode takes the batch's unused noise first,
        # so both draw each stream in the same order.
        self._aux_rows = {}
        for channel in ("temperature", "load", "current"):
            sensor = self.sensors.get(channel)
            if sensor is not None and (channel == "current" or channel in self.tables):
                self._aux_rows[channel] = K.B_LOAD + 1 + len(self._aux_rows)
        self._batch = np.zeros((K.B_LOAD + 1 + len(self._aux_rows), self.STEP_BATCH))
        self._pos = self.STEP_BATCH  # empty

    def _pack(self) -> None:
        """Parameters and fresh state as views of one flat buffer (see :data:`K.PLANT_ARRAYS`)."""
        arrays = {name: getattr(self, name) for name in K.PLANT_ARRAYS[:K.N_PARAM_ARRAYS]}
        arrays["X"] = np.zeros(K.N_STATES)
        arrays["op_state"] = self.op_state0  # play outputs at 0, or the Preisach relays demagnetised
        arrays["creep_state"] = np.zeros(self.creep_g.shape[0])
        arrays["dyn_state"] = np.zeros(max(len(self.dyn_a) - 1, 1))
        arrays["delay_buf"] = np.zeros(max(self.delay_samples, 1))
        arrays["tp_state"] = np.zeros(K.N_TP)
        arrays["out"] = np.zeros(2)
        sizes = [arrays[name].shape[0] for name in K.PLANT_ARRAYS]
        ends = np.cumsum(sizes)
        self._layout = np.ravel(np.column_stack([ends - sizes, ends])).astype(np.int64)
        self._flat = np.zeros(int(ends[-1]))
        for k, name in enumerate(K.PLANT_ARRAYS):
            view = self._flat[self._layout[2 * k] : self._layout[2 * k + 1]]
            view[:] = np.asarray(arrays[name], dtype=np.float64)
            setattr(self, name, view)
        self._out = self.out

    def step_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """``(F, L)`` for :func:`hilbench.sim.kernels.plant_step_flat` (e.g. in a compiled closed
        loop); the plant's parameters and state, shared with this object."""
        return self._flat, self._layout

    @property
    def time_s(self) -> float:
        """Time of the next sample on the current run's clock, s."""
        return self.samples / self.sample_rate_hz

    def start_run(self) -> None:
        """Restart the run clock (trajectories of temperature and load start again); memory stays."""
        self.samples = 0
        if self._pos < self.STEP_BATCH:
            self._fill_trajectories(self._pos)

    # -- simulation -------------------------------------------------------------------------------
    def _trajectory(self, name: str, t: np.ndarray) -> np.ndarray:
        return trajectories.evaluate(self.tables[name]["trajectory"], t)

    def _fill_trajectories(self, first: int) -> None:
        """Temperature and load of the batch's columns first.. (sample ``self.samples`` at ``first``)."""
        if "temperature" in self.tables or "load" in self.tables:
            t = (self.samples + np.arange(self.STEP_BATCH - first)) / self.sample_rate_hz
            if "temperature" in self.tables:
                self._batch[K.B_TEMPERATURE, first:] = self._trajectory("temperature", t)
            if "load" in self.tables:
                self._batch[K.B_LOAD, first:] = self._trajectory("load", t)

    def _refill(self) -> None:
        """The next STEP_BATCH samples' noise (same streams, same order as block mode) and trajectories."""
        n = self.STEP_BATCH
        if self.S[K.S_NOISE_STD] > 0:
            self._batch[K.B_NOISE] = self._rng_output.standard_normal(n)
        for channel, row in self._aux_rows.items():
            if self.sensors[channel].noise_std > 0:
                self._batch[row] = self._rng_aux[channel].standard_normal(n)
        self._fill_trajectories(0)
        self._pos = 0

    def _draw(self, rng: np.random.Generator, row: int, n: int) -> np.ndarray:
        """n standard-normal draws of a stream: the step batch's unused ones first."""
        k = min(n, self.STEP_BATCH - self._pos)
        if k == n:
            return self._batch[row, self._pos : self._pos + n].copy()
        return np.concatenate([self._batch[row, self._pos :], rng.standard_normal(n - k)])

    def draw_inputs(self, n: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The next n samples' per-sample inputs, drawn from the plant's seeded streams in the order
        block mode draws them, and consumed (the streams advance as if n samples were simulated).

        Returns ``B`` (3, n): rows :data:`K.B_NOISE` (the output sensor's standard-normal draws, zeros
        when it is noiseless), :data:`K.B_TEMPERATURE` (degC) and :data:`K.B_LOAD` (N) (their true
        trajectories, zeros when the plant has no such stage), and the auxiliary sensors' draws by
        channel (noisy sensors only). A compiled loop that calls :func:`K.plant_step` itself (the
        fused closed loop) takes its inputs from here, so it reproduces :meth:`simulate`.
        """
        B = np.zeros((K.B_LOAD + 1, n))
        if "temperature" in self.tables or "load" in self.tables:  # the run clock only when needed
            t = (self.samples + np.arange(n)) / self.sample_rate_hz
            if "temperature" in self.tables:
                B[K.B_TEMPERATURE] = self._trajectory("temperature", t)
            if "load" in self.tables:
                B[K.B_LOAD] = self._trajectory("load", t)
        if self.S[K.S_NOISE_STD] > 0:
            B[K.B_NOISE] = self._draw(self._rng_output, K.B_NOISE, n)
        aux_noise = {channel: self._draw(self._rng_aux[channel], row, n)
                     for channel, row in self._aux_rows.items() if self.sensors[channel].noise_std > 0}
        self._pos = min(self.STEP_BATCH, self._pos + n)
        return B, aux_noise

    def read_aux(self, channel: str, truth: np.ndarray, noise: np.ndarray | None) -> np.ndarray:
        """What the auxiliary sensor ``channel`` reads for the true values ``truth`` (its unit) with
        its standard-normal draws ``noise`` (None: noiseless): noise, quantisation, range."""
        return self._read_aux(self.sensors[channel], truth, noise)

    def simulate(self, command: np.ndarray) -> PlantOutput:
        """Block mode: simulate len(command) samples from the current state."""
        u = np.ascontiguousarray(command, dtype=np.float64)
        n = u.shape[0]
        B, aux_noise = self.draw_inputs(n)
        temperature, load, noise = B[K.B_TEMPERATURE], B[K.B_LOAD], B[K.B_NOISE]
        measured = np.empty(n)
        true = np.empty(n)
        drive = np.empty(n)
        K.plant_block(
            u, temperature, load, noise, self.S, self.in_exp, self.in_w, self.op_r, self.op_w, self.op_eta,
            self.relay_a, self.relay_b, self.asym, self.dz_r, self.dz_g, self.rate_kp, self.rate_cp, self.rate_mp, self.creep_g,
            self.creep_a, self.dyn_b, self.dyn_a, self.X, self.op_state, self.creep_state, self.dyn_state,
            self.delay_buf, self.tp_state, measured, true, drive,
        )
        self.samples += n
        aux: dict[str, np.ndarray] = {}
        for channel, truth in (("temperature", temperature), ("load", load), ("current", drive)):
            sensor = self.sensors.get(channel)
            if sensor is None:
                continue
            if channel != "current" and channel not in self.tables:
                aux[channel] = _EMPTY.copy()  # a sensor of a quantity the plant does not model
                continue
            aux[channel] = self._read_aux(sensor, truth, aux_noise.get(channel))
        return PlantOutput(measured, true, drive, aux)

    def step_value(self, command: float) -> float:
        """Step mode, fast path: one sample through :func:`K.plant_step`; the measured output, um.

        The same samples as :meth:`simulate` (and :meth:`step`); the auxiliary sensors' noise is
        drawn but their readings are not formed (use :meth:`step` for them).
        """
        pos = self._pos
        if pos == self.STEP_BATCH:
            self._refill()
            pos = 0
        y = _plant_step_flat(self._flat, self._layout, self._batch, pos, command)
        self._pos = pos + 1
        self.samples += 1
        return y

    def step(self, command: float) -> PlantOutput:
        """Step mode: one sample through the same per-sample kernel as :meth:`simulate`."""
        measured = self.step_value(float(command))
        pos = self._pos - 1
        out = self._out
        aux: dict[str, np.ndarray] = {}
        for channel, sensor in self.sensors.items():
            if channel == "current":
                truth = out[1]
            elif channel in ("temperature", "load"):
                if channel not in self.tables:
                    aux[channel] = _EMPTY.copy()
                    continue
                truth = self._batch[K.B_TEMPERATURE if channel == "temperature" else K.B_LOAD, pos]
            else:
                continue
            noise = self._batch[self._aux_rows[channel], pos]
            aux[channel] = np.array([_read_scalar(sensor, float(truth), float(noise))])
        return PlantOutput(np.array([measured]), np.array([out[0]]), np.array([out[1]]), aux)

    def _read_aux(self, sensor: SensorModel, truth: np.ndarray, noise: np.ndarray | None) -> np.ndarray:
        if sensor.noise_std > 0 and noise is not None and noise.shape[0] == truth.shape[0]:
            value = truth + sensor.noise_std * noise
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


_plant_step_flat = K.plant_step_flat


def _read_scalar(sensor: SensorModel, truth: float, noise: float) -> float:
    """:meth:`Plant._read_aux` of one sample (the same arithmetic, so the same value)."""
    value = truth + sensor.noise_std * noise if sensor.noise_std > 0 else truth
    if sensor.quantization > 0:
        value = sensor.quantization * math.floor(value / sensor.quantization + 0.5)
    if sensor.range is not None:
        lo, hi = sensor.range
        if value < lo or value > hi:
            value = math.nan if sensor.out_of_range == "nan" else min(max(value, lo), hi)
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
