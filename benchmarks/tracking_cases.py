"""Randomized simulated rigs for the tracking benchmark: a rig config TOML per seed, drawn from physics.

    from tracking_cases import draw, draw_rig, references
    text = draw_rig(17)                  # the rig config TOML, deterministic per seed
    d = draw(17)                         # the same draw with what the benchmark needs besides the TOML
    refs = references(d, y_lo, y_hi)     # the tracking references, once the sweep's output range is known

Each rig draws, from its seed alone (nothing here knows the compensator or the diagnosis):

* the **hysteresis base** of the plant (``[plant.hysteresis]``) and the start spec that matches it:
  ``play`` -> ``pi``, ``one-sided-play`` -> ``pi1``, ``m-play`` -> ``pmpi`` (both unipolar), ``duhem``
  with the Gompertz / modified-tanh / dead-zone / no shape function -> ``duhem-g`` / ``duhem-m`` /
  ``duhem-d`` / ``duhem-d``;
* the **actuator**: input unit V (piezo stack) or A (magnetostrictive, current driver), a unipolar
  (0..max) or bipolar (-max..max) range, 5-150 V or 0.5-6 A, a slew limit (a full-range change in
  0.2-3 ms, and at least 1.3x the steepest slope of the characterisation plan);
* the **sample rate** (1-50 kHz) and **second-order dynamics** with a natural frequency of
  100 Hz - 5 kHz, below 0.4x the sample rate (so below Nyquist), zeta 0.05-0.7;
* **creep** (2-3 Kelvin-Voigt elements a decade apart, 2-12 % in all) in half the rigs,
  **saturation** (tanh of the hysteresis output) in a third, an even **asymmetry** in a quarter of the
  play-operator rigs, a **temperature** (warm-up ramp, cooling or cycling, thermometer recorded)
  or **load** (steps or sine, load cell recorded) dependence in 40 %;
* the **output sensor**: displacement span 5-150 um, white noise 0.05-1 % of the span, a 12-16 bit
  quantisation in 40 % of the rigs;
* the **characterisation plan** (``[[plan.runs]]``, what ``hilbench sweep RIG`` plays): drive rates
  from a quasi-static rate up to a quarter of the natural frequency (and at most fs/40): sines at three
  amplitudes, full-range triangles at three rates, a decreasing triangle staircase (reversal curves),
  a logarithmic chirp towards the resonance (up to 0.6 fn) and a step staircase whose holds last
  the longest creep time constant (when there is creep) or 30 resonance periods, at most 1/16 of the
  smooth runs' length (so shorter than the longest creep on 81 of the 98 creep rigs of seeds 0-199,
  and shorter than the diagnosis' 0.2 s creep gate on 45 of them: there creep is untestable); 16 quasi-static
  cycles fill a budget of 20k-40k samples (fewer when the quasi-static rate is bounded 60x below the
  top rate, more when it is bounded 3x below it at a high sample rate), the steps add up to 3/8;
* the **references** (:func:`references`): sine, triangle, multi-tone, steps and attenuated
  triangle at drive rates inside the characterised band, each spanning a drawn share (40-90 %) of
  the output range the plant holds quasi-statically (:func:`quasi_static_range`), and one triangle
  beyond reach (twice that range).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

SEED_BASE = 20261206
FAMILIES = ("play", "one-sided-play", "m-play", "duhem")
P_FAMILY = (0.3, 0.2, 0.2, 0.3)
UNIPOLAR_ONLY = {"one-sided-play", "m-play"}
BASE_SPEC = {"play": "pi", "one-sided-play": "pi1", "m-play": "pmpi"}
DUHEM_SPEC = {"gompertz": "duhem-g", "tanh": "duhem-m", "dead-zone": "duhem-d", "none": "duhem-d"}
SAMPLE_RATES_HZ = (1000.0, 2000.0, 2500.0, 5000.0, 10000.0, 20000.0, 25000.0, 50000.0)
#: dynamics range (Hz) and how far below the sample rate it stays
FN_RANGE_HZ = (100.0, 5000.0)
FN_MAX_OVER_FS = 0.4
#: the share of the recorded output range a reachable reference spans
SHARE_RANGE = (0.4, 0.9)
#: the beyond-reach reference spans this multiple of the recorded range
BEYOND = 2.0
REFERENCE_KINDS = ("sine", "triangle", "multitone", "steps", "attenuated-triangle")


@dataclass
class RigDraw:
    seed: int
    name: str
    family: str
    spec: str  # the start spec of the diagnosis (the base matching the plant's hysteresis)
    unit: str
    bipolar: bool
    lo: float
    hi: float
    max_rate: float
    sample_rate_hz: float
    natural_frequency_hz: float
    zeta: float
    effects: list[str]  # the plant's effects besides hysteresis and dynamics
    output_span_um: float  # the drawn span of the hysteresis output over a full-range cycle
    noise_std_um: float
    drive_hz: tuple[float, float, float]  # quasi-static, middle, top drive rate
    plan: list[dict[str, Any]]  # [[plan.runs]] tables
    plant: dict[str, dict[str, Any]]  # [plant] tables
    sensors: list[dict[str, Any]]
    reference_draws: list[dict[str, Any]] = field(default_factory=list)  # shapes, scaled by references()
    toml: str = ""

    def summary(self) -> dict[str, Any]:
        d = asdict(self)
        for k in ("toml", "plan", "plant", "sensors", "reference_draws"):
            d.pop(k)
        return json.loads(json.dumps(d, default=float))


# -- helpers -------------------------------------------------------------------------------------
def _logu(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _r(x: float, digits: int = 6) -> float:
    """Rounded for the TOML (a few significant digits; the TOML is the rig)."""
    return float(f"{x:.{digits}g}")


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {v!r} to TOML")


def _table(header: str, values: dict[str, Any]) -> str:
    return "\n".join([header] + [f"{k} = {_toml_value(v)}" for k, v in values.items()]) + "\n"


def _hysteresis_span(table: dict[str, Any], lo: float, hi: float) -> tuple[float, float]:
    """Span and max |output| of the bare hysteresis (output_scale 1) over two full-range cycles."""
    from hilbench.sim.plant import Plant
    from hilbench.sim.schema import SensorModel, check_plant

    fs = 1000.0
    t = np.arange(2000) / fs
    u = lo + (hi - lo) * 0.5 * (1.0 - np.cos(2 * np.pi * t))  # from lo, two cycles lo..hi
    tables = check_plant({"hysteresis": {**table, "output_scale": 1.0}}, "<tracking rig>", fs)
    y = Plant(tables, fs, [SensorModel("output")]).simulate(u).true_output
    return float(np.ptp(y)) or 1.0, float(np.max(np.abs(y))) or 1.0


def _hysteresis(rng: np.random.Generator, family: str, u_max: float) -> tuple[dict[str, Any], str]:
    """The [plant.hysteresis] table (output_scale set later) and the matching start spec."""
    if family == "duhem":
        shape = str(rng.choice(["gompertz", "tanh", "dead-zone", "none"], p=[0.3, 0.2, 0.35, 0.15]))
        alpha = _logu(rng, 2.0, 8.0)  # per normalised input unit: loop half-width ~ 1/alpha
        ratio = rng.uniform(0.8, 1.6)
        t: dict[str, Any] = {"model": "duhem", "input_scale": _r(u_max), "alpha": _r(alpha), "beta": _r(alpha * ratio),
                             "shape": shape, "k1": _r(rng.uniform(0.3, 1.5)), "k2": _r(rng.uniform(0.5, 2.0))}
        if shape in ("gompertz", "tanh"):
            t["mu"] = [_r(_logu(rng, 0.4, 1.5) / ratio), _r(rng.uniform(0.0, 1.0))]
        elif shape == "dead-zone":  # paper 001's Table 1 in normalised units (u / 6 A), +-30 %
            def j(x: float) -> float:
                return _r(x * rng.uniform(0.7, 1.3))
            t.update(k1=j(2.979), k2=j(0.778), alpha=j(0.575 * 6.0), beta=j(1.859 * 6.0), n_dead_zone=6,
                     mu=[j(0.452 / 6.0), j(2.378), j(0.098), j(0.587 / 6.0), j(3.997), j(0.214)])
        return t, DUHEM_SPEC[shape]
    n = int(rng.integers(3, 9))
    top = 0.85 if family == "play" else 0.9
    r = np.sort(rng.uniform(0.03, top, n))
    w = np.exp(-rng.uniform(0.5, 3.0) * r) * rng.uniform(0.4, 1.4, n)
    t = {"model": family, "input_scale": _r(u_max), "linear_gain": _r(rng.uniform(0.15, 1.2) * w.sum()),
         "thresholds": [_r(x) for x in r], "weights": [_r(x) for x in w]}
    if family == "m-play":
        t["eta"] = [_r(x) for x in rng.uniform(-0.3, 1.0, n)]
    return t, BASE_SPEC[family]


# -- the draw ------------------------------------------------------------------------------------
def draw(seed: int) -> RigDraw:
    """A rig from its seed alone (module docstring)."""
    rng = np.random.default_rng([SEED_BASE, seed])
    family = str(rng.choice(FAMILIES, p=P_FAMILY))
    # the actuator: piezo stacks take volts, magnetostrictive rods amperes
    if family in UNIPOLAR_ONLY:
        bipolar = False
        unit = "V" if rng.random() < 0.75 else "A"
    elif family == "play":
        bipolar = rng.random() < 0.5
        unit = "V" if rng.random() < 0.5 else "A"
    else:
        bipolar = rng.random() < 0.75
        unit = "A" if rng.random() < 0.65 else "V"
    u_max = _logu(rng, 0.5, 6.0) if unit == "A" else _logu(rng, 5.0, 150.0)
    u_max = _r(u_max, 3)
    lo, hi = (-u_max, u_max) if bipolar else (0.0, u_max)
    fs = float(rng.choice(SAMPLE_RATES_HZ))
    fn = _r(_logu(rng, FN_RANGE_HZ[0], min(FN_RANGE_HZ[1], FN_MAX_OVER_FS * fs)), 4)
    zeta = _r(_logu(rng, 0.05, 0.7), 3)
    hyst, spec = _hysteresis(rng, family, u_max)
    span_um = _logu(rng, 5.0, 150.0)
    h_span, h_max = _hysteresis_span(hyst, lo, hi)
    hyst["output_scale"] = _r(span_um / h_span)
    plant: dict[str, dict[str, Any]] = {"hysteresis": hyst,
                                        "dynamics": {"kind": "second-order", "natural_frequency_hz": fn, "zeta": zeta}}
    effects: list[str] = []
    # drive rates: quasi-static up to a quarter of the resonance (and fs/40); a sample budget
    budget = _logu(rng, 20000.0, 40000.0)
    f_top = min(fn / 4.0, fs / 40.0)
    # 16 quasi-static cycles fill the budget, within 3-60x below the top rate
    f_qs = min(max(16.0 * fs / budget, f_top / 60.0), f_top / 3.0)
    f_mid = math.sqrt(f_qs * f_top)
    f_qs, f_mid, f_top = _r(f_qs, 4), _r(f_mid, 4), _r(f_top, 4)
    plan_s = 16.0 / f_qs  # the smooth runs' length, s
    taus: list[float] = []
    if rng.random() < 0.5:
        n = int(rng.integers(2, 4))
        tau1 = _logu(rng, 0.01, 0.3)
        taus = [_r(min(tau1 * 10.0**i * rng.uniform(0.7, 1.4), 2.0 * plan_s), 4) for i in range(n)]
        g = rng.uniform(0.5, 1.5, n)
        total = rng.uniform(0.02, 0.12)
        plant["creep"] = {"gains": [_r(total * x / g.sum(), 4) for x in g], "time_constants_s": taus}
        effects.append("creep")
    if rng.random() < 1.0 / 3.0:
        plant["saturation"] = {"level": _r(rng.uniform(0.7, 1.5) * h_max, 4)}
        effects.append("saturation")
    if family in ("play", "one-sided-play") and rng.random() < 0.25:
        order = int(rng.choice([2, 3]))
        coef = [0.0] * (order + 1)
        coef[order] = _r(float(rng.choice([-1.0, 1.0])) * _logu(rng, 0.03, 0.2) * h_span, 4)
        plant["asymmetry"] = {"coefficients": coef}
        effects.append("asymmetry")
    sensors: list[dict[str, Any]] = []
    noise = _logu(rng, 0.0005, 0.01) * span_um
    out_sensor: dict[str, Any] = {"channel": "output", "unit": "um", "driver": "sim",
                                  "description": "displacement sensor", "noise_std": _r(noise, 4)}
    if rng.random() < 0.4:
        bits = int(rng.choice([12, 14, 16]))
        q = 2.0 * span_um * rng.uniform(1.0, 2.0) / 2**bits
        if q <= 3.0 * noise:
            out_sensor["quantization"] = _r(q, 4)
    sensors.append(out_sensor)
    u_aux = rng.random()
    if u_aux < 0.2:
        kind = str(rng.choice(["ramp", "cooling", "sine"]))
        t0, dT = rng.uniform(20.0, 28.0), rng.uniform(3.0, 12.0)
        if kind == "ramp":
            traj = {"kind": "ramp", "start": _r(t0, 4), "end": _r(t0 + dT, 4), "duration_s": _r(plan_s * rng.uniform(0.1, 0.3), 4)}
        elif kind == "cooling":
            traj = {"kind": "cooling", "initial": _r(t0 + dT, 4), "ambient": _r(t0, 4),
                    "time_constant_s": _r(plan_s * rng.uniform(0.03, 0.1), 4)}
        else:
            traj = {"kind": "sine", "mean": _r(t0 + dT / 2, 4), "amplitude": _r(dT / 2, 4),
                    "period_s": _r(plan_s * rng.uniform(0.05, 0.15), 4)}
        s = float(rng.choice([-1.0, 1.0])) * rng.uniform(0.03, 0.15)
        plant["temperature"] = {"reference_degC": _r(t0, 4), "gain_per_degC": _r(s / dT, 4),
                                "strain_um_per_degC": _r(rng.uniform(0.0, 0.5) * abs(s) * span_um / dT, 4),
                                "trajectory": traj}
        sensors.append({"channel": "temperature", "unit": "degC", "driver": "sim", "description": "thermocouple",
                        "noise_std": _r(_logu(rng, 0.005, 0.05), 3)})
        effects.append("temperature")
    elif u_aux < 0.4:
        fmax = rng.uniform(10.0, 100.0)
        if rng.random() < 0.5:
            n = int(rng.integers(3, 6))
            levels = [0.0] + [_r(x, 4) for x in rng.uniform(0.0, fmax, n - 1)]
            traj = {"kind": "steps", "levels": levels, "hold_s": _r(plan_s * rng.uniform(0.02, 0.06), 4)}
        else:
            traj = {"kind": "sine", "mean": _r(fmax / 2, 4), "amplitude": _r(fmax / 2, 4),
                    "period_s": _r(plan_s * rng.uniform(0.05, 0.15), 4)}
        s = float(rng.choice([-1.0, 1.0])) * rng.uniform(0.03, 0.15)
        plant["load"] = {"gain_per_N": _r(s / fmax, 4), "compliance_um_per_N": _r(-rng.uniform(0.0, 0.5) * abs(s) * span_um / fmax, 4),
                         "trajectory": traj}
        sensors.append({"channel": "load", "unit": "N", "driver": "sim", "description": "load cell",
                        "noise_std": _r(_logu(rng, 0.02, 0.5), 3)})
        effects.append("load")
    # the plan: what a characterisation sweep of this actuator plays
    c = 0.5 * (lo + hi)
    a = 0.98 * 0.5 * (hi - lo)
    rise_full = _logu(rng, 0.0002, 0.003)
    top_chirp = min(3.0 * f_top, 0.6 * fn)
    max_slope = max(4.0 * a * f_top, 2.0 * math.pi * 0.5 * a * top_chirp)
    max_rate = _r(max((hi - lo) / rise_full, 1.3 * max_slope), 4)
    # holds: the longest creep time constant (creep), else 30 resonance periods; six of them fit in
    # three eighths of the smooth runs' length
    hold = _r(min(max(max(taus) if taus else 30.0 / fn, 0.01), plan_s / 16.0), 4)
    levels = [_r(x, 4) for x in rng.uniform(lo + 0.05 * (hi - lo), hi - 0.05 * (hi - lo), 6)]
    plan: list[dict[str, Any]] = [
        {"label": "sine", "kind": "sine", "offset": _r(c), "phase_deg": -90.0, "frequency_hz": f_qs, "cycles": 2,
         "sweep": {"amplitude": [_r(a * x) for x in (0.35, 0.7, 1.0)]}},
        {"label": "triangle", "kind": "triangle", "offset": _r(c), "amplitude": _r(a), "phase_deg": -90.0,
         "duration_s": _r(2.0 / f_qs), "sweep": {"frequency_hz": [f_qs, f_mid, f_top]}},
        {"label": "triangle-staircase", "kind": "triangle", "offset": _r(c), "phase_deg": 0.0,
         "frequency_hz": _r(2.0 * f_qs, 4), "amplitudes": [_r(a * x) for x in (1.0, 0.75, 0.5, 0.3, 0.15)]},
        {"label": "chirp", "kind": "chirp", "offset": _r(c), "amplitude": _r(0.5 * a), "f_start_hz": f_mid,
         "f_end_hz": _r(top_chirp, 4), "method": "logarithmic", "duration_s": _r(2.0 / f_qs)},
        {"label": "steps", "kind": "step", "levels": levels, "hold_s": hold, "rise_s": _r(1.05 * (hi - lo) / max_rate, 4)},
    ]
    d = RigDraw(seed=seed, name=f"tracking-rig-{seed}", family=family, spec=spec, unit=unit, bipolar=bipolar,
                lo=lo, hi=hi, max_rate=max_rate, sample_rate_hz=fs, natural_frequency_hz=fn, zeta=zeta,
                effects=effects, output_span_um=_r(span_um, 4), noise_std_um=out_sensor["noise_std"],
                drive_hz=(f_qs, f_mid, f_top), plan=plan, plant=plant, sensors=sensors)
    d.reference_draws = _reference_draws(rng, d)
    d.toml = _write_toml(d)
    return d


def _reference_draws(rng: np.random.Generator, d: RigDraw) -> list[dict[str, Any]]:
    """Shapes of the references in relative terms (share of the range, centre position in the free
    room, rates inside the characterised band); :func:`references` scales them to the recorded range."""
    f_qs, _, f_top = d.drive_hz
    fs = d.sample_rate_hz
    max_s = 60000.0 / fs  # at most 60k samples per reference

    def freq() -> float:
        return _r(_logu(rng, f_qs, f_top), 4)

    out = []
    for kind in REFERENCE_KINDS:
        r: dict[str, Any] = {"kind": kind, "share": _r(rng.uniform(*SHARE_RANGE), 4), "position": _r(rng.uniform(0.0, 1.0), 4)}
        if kind in ("sine", "triangle"):
            f = freq()
            r.update(frequency_hz=f, cycles=int(min(rng.integers(3, 7), max(1, int(max_s * f)))))
        elif kind == "multitone":
            n = int(rng.integers(2, 4))
            fr = sorted(_logu(rng, f_qs, f_top / 1.5) for _ in range(n))
            w = rng.uniform(0.3, 1.0, n)
            r.update(frequencies_hz=[_r(x, 4) for x in fr], weights=[_r(x / w.sum(), 4) for x in w],
                     phases_rad=[_r(x, 4) for x in rng.uniform(0, 2 * np.pi, n)],
                     duration_s=_r(min(3.0 / fr[0], max_s), 4))
        elif kind == "steps":
            n = int(rng.integers(4, 8))
            hold = min(_logu(rng, 1.0 / f_top, 2.0 / f_qs), max_s / n)
            r.update(levels=[_r(x, 4) for x in rng.uniform(0.0, 1.0, n)], hold_s=_r(hold, 4),
                     rise_s=_r(_logu(rng, 1.0, 5.0) / d.natural_frequency_hz, 4))
        else:
            f0, f1 = freq(), freq()
            cycles = int(rng.integers(4, 9))
            r.update(frequency_start_hz=f0, frequency_end_hz=f1, cycles=cycles,
                     end_share=_r(rng.uniform(0.15, 0.5), 4))
        out.append(r)
    out.append({"kind": "beyond-reach", "share": BEYOND, "position": 0.5, "frequency_hz": _r(f_qs, 4), "cycles": 2})
    return out


#: the quasi-static range: full-range triangles at the plan's quasi-static rate, at least this many
#: cycles after the approach, and as many as the longest reference lasts (a load or temperature
#: moves the range while a run goes on; at most :data:`REACH_MAX_CYCLES`); each cycle's output
#: smoothed over this share of a cycle (the sensor's noise)
REACH_CYCLES = 2
REACH_MAX_CYCLES = 40
REACH_SMOOTHING = 0.005


def reference_seconds(d: RigDraw) -> float:
    """How long the longest reachable reference of ``d`` lasts (s)."""
    out = 0.0
    for r in d.reference_draws:
        k = r["kind"]
        if k in ("sine", "triangle"):
            out = max(out, r["cycles"] / r["frequency_hz"])
        elif k == "multitone":
            out = max(out, r["duration_s"])
        elif k == "steps":
            out = max(out, len(r["levels"]) * r["hold_s"])
        elif k == "attenuated-triangle":
            out = max(out, r["cycles"] / min(r["frequency_start_hz"], r["frequency_end_hz"]))
    return out


def quasi_static_range(rig_path: str, d: RigDraw) -> tuple[float, float]:
    """The output range (um) the plant holds quasi-statically over its whole command range, whatever
    its load or temperature does while a reference runs: slow full-range triangles on a freshly opened
    rig (as every tracking run opens one) for as long as the longest reference lasts, each cycle's
    output smoothed against the sensor's noise; the range is the lowest of the cycles' maxima and the
    highest of their minima (one cycle's range where nothing drifts). What a reference can ask for all
    along; the range a sweep records also holds the overshoot where a fast run starts and noise
    peaks, which no reference can be held at."""
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig

    cfg = load_rig(rig_path)
    f_qs = d.drive_hz[0]
    cycles = int(min(REACH_MAX_CYCLES, max(REACH_CYCLES, math.ceil(reference_seconds(d) * f_qs) + 1)))
    with Rig(cfg) as rig:
        half = max(8, int(round(0.5 * rig.sample_rate_hz / f_qs)))
        up, down = np.linspace(d.lo, d.hi, half), np.linspace(d.hi, d.lo, half)
        start = np.linspace(rig.last_applied, d.lo, half)
        u = np.concatenate([start, *([up, down] * cycles)])
        y = rig.measure(rig.apply(u))["output"][half:].reshape(cycles, 2 * half)
    k = max(3, int(REACH_SMOOTHING * 2 * half))
    highs, lows = [], []
    for cycle in y:
        ys = np.convolve(cycle[np.isfinite(cycle)], np.ones(k) / k, mode="valid")
        highs.append(float(ys.max()))
        lows.append(float(ys.min()))
    return max(lows), min(highs)


def references(d: RigDraw, y_lo: float, y_hi: float) -> list[dict[str, Any]]:
    """The references of rig ``d`` for a recorded output range [y_lo, y_hi] (um): one dict per
    reference with ``kind``, ``reachable``, ``share``, ``low``/``high`` (um) and ``compact`` (the
    compact excitation form that :func:`hilbench.online.tracking.track` accepts)."""
    span = y_hi - y_lo
    out = []
    for r in d.reference_draws:
        s = r["share"] * span
        free = span - s  # negative beyond reach: centred on the range
        low = y_lo + r["position"] * free
        mid = low + 0.5 * s
        g = lambda x: f"{x:.6g}"  # noqa: E731
        k = r["kind"]
        if k == "sine":
            text = (f"sine:amplitude={g(s / 2)},offset={g(mid)},frequency_hz={g(r['frequency_hz'])},"
                    f"cycles={r['cycles']},phase_deg=-90")
        elif k in ("triangle", "beyond-reach"):
            text = (f"triangle:amplitude={g(s / 2)},offset={g(mid)},frequency_hz={g(r['frequency_hz'])},"
                    f"cycles={r['cycles']},phase_deg=-90")
        elif k == "multitone":
            amps = [s / 2 * w for w in r["weights"]]
            text = (f"multitone:amplitudes={'/'.join(g(x) for x in amps)},"
                    f"frequencies_hz={'/'.join(g(x) for x in r['frequencies_hz'])},"
                    f"phases_rad={'/'.join(g(x) for x in r['phases_rad'])},offset={g(mid)},duration_s={g(r['duration_s'])}")
        elif k == "steps":
            lv = [low + x * s for x in r["levels"]]
            text = f"step:levels={'/'.join(g(x) for x in lv)},hold_s={g(r['hold_s'])},rise_s={g(r['rise_s'])}"
        else:
            text = (f"attenuated-triangle:base={g(low)},amplitude_start={g(s)},amplitude_end={g(s * r['end_share'])},"
                    f"frequency_start_hz={g(r['frequency_start_hz'])},frequency_end_hz={g(r['frequency_end_hz'])},"
                    f"cycles={r['cycles']}")
        out.append({"kind": k, "reachable": k != "beyond-reach", "share": r["share"], "low": low, "high": low + s,
                    "compact": text})
    return out


def _write_toml(d: RigDraw) -> str:
    parts = [
        f"# Drawn by benchmarks/tracking_cases.py from seed {d.seed}: {d.family} hysteresis, "
        f"{'+'.join(d.effects) or 'no other effect'} besides second-order dynamics.\n",
        _table("[rig]", {"name": d.name,
                         "description": f"randomized tracking rig {d.seed}: {d.family}, {d.unit} "
                                        f"{'bipolar' if d.bipolar else 'unipolar'}, fn {d.natural_frequency_hz:g} Hz",
                         "sample_rate_hz": d.sample_rate_hz, "seed": d.seed}),
        _table("[actuator]", {"driver": "sim", "kind": "piezo stack" if d.unit == "V" else "magnetostrictive actuator",
                              "unit": d.unit, "min": float(d.lo), "max": float(d.hi), "max_rate": float(d.max_rate),
                              "rest": 0.0}),
    ]
    parts += [_table("[[sensors]]", s) for s in d.sensors]
    for name in ("hysteresis", "asymmetry", "saturation", "dynamics", "creep", "temperature", "load"):
        if name in d.plant:
            parts.append(_table(f"[plant.{name}]", d.plant[name]))
    parts += [_table("[[plan.runs]]", r) for r in d.plan]
    return "\n".join(parts)


def draw_rig(seed: int) -> str:
    """The rig config TOML of ``seed`` (deterministic)."""
    return draw(seed).toml


if __name__ == "__main__":  # a quick look at some draws
    import sys

    for s in range(int(sys.argv[1]) if len(sys.argv) > 1 else 10):
        x = draw(s)
        print(s, x.family, x.spec, x.unit, "bipolar" if x.bipolar else "unipolar", x.sample_rate_hz,
              x.natural_frequency_hz, x.effects, x.drive_hz)
