"""Randomized cases for the diagnosis: a simulated actuator with a hidden effect, recorded as a bench would.

    from diagnosis_cases import draw_case, write_case
    case = draw_case(17)                      # deterministic per seed
    paths, kwargs = write_case(case, folder)  # one HDF5 recording; diagnose(paths, case.spec, **kwargs)

Each case draws, from its seed alone:

* the **base hysteresis** of the plant and the start spec that matches it: ``play`` -> ``pi``,
  ``one-sided-play`` -> ``pi1`` (unipolar drive), ``m-play`` -> ``pmpi`` (unipolar drive), ``duhem``
  with the Gompertz / modified-tanh / dead-zone / no shape function -> ``duhem-g`` / ``duhem-m`` /
  ``duhem-d`` / ``duhem-d``; with the hidden effect ``hysteresis`` the start spec is ``linear``;
* the **hidden effect** (the effect names of DESIGN.md; ``none`` for a clean case; two for a
  two-effect case) and its **form** (:data:`FORMS`), with a strength drawn from a physical range;
* the **sample rate** (500 Hz - 5 kHz), the **units** (A or V input; um output), the output span
  (5-150 um), the **sensor noise** (0.1-2 % of the output span, white), sometimes **quantisation**
  (a 12-16 bit converter over the sensor's range), the drive frequencies (spread 3-15x);
* the **measurement program** of every run: a rest at the start, sometimes a power-on step held
  before the excitation, then 3-7 segments drawn from triangles, triangle staircases, sines, ramped
  sines, band-limited noise, multi-tone, step staircases and chirps (``hilbench.excitation.signals``),
  sometimes with holds between them; the whole command is clamped to the actuator's range and
  slew-limited (the rig's command path), so what is recorded is what was applied;
* the **split**: one run with a training fraction, two runs (train / test) or three (two train, one
  test).

What the program must contain is decided by the hidden effect's physics, never by what the diagnosis
needs: creep is seen on holds (creep cases get at least two holds of 0.6 s or more per run), rate
dependence needs several drive rates (every program has a spread of 3x or more), a channel effect
needs the channel to move (the hidden form is the channel's trajectory). A frequency-dependent gain
is defined for periodic drives only (the plant estimates the drive frequency from the last half
cycle, as paper 003 does; band-limited noise would make that estimate jump to the sample rate),
so its programs replace noise, multi-tone and chirp segments by sines. Strengths are drawn from a
physical range; the hidden effect's own contribution (the output with the effect minus without it,
less what an offset and a gain of the base output explain) must have at least
:data:`MIN_SNR` times the sensor noise's rms: if it does not, the noise is lowered (not below 0.1 %
of the span), then the strength raised, step by step. The ratio reached is stored (``snr``).

**Forms the simulated plant cannot produce** are made by the generator around the plant
(documented per form in :data:`FORMS`): a saturation of the *drive* with a knee of variable
sharpness (the plant is fed the saturated drive, the recording keeps the command), a knee-shaped
saturation of the *output* other than the plant's tanh, a *logarithmic* creep law, and a *sensor*
delay (the measured displacement is shifted by a fractional number of samples). When an output-side
stage is done after the plant, the plant's creep and dynamics are moved after it too (the same
discrete filters), so the physical order of the chain is kept. The sensor (noise, quantisation)
is always applied last, by the generator.

**Two suites.** ``draw_case(seed)`` is the classic suite, whose seeds the tests and
``diagnosis_regressions.py`` pin: its draws never change. ``draw_case(seed, "widened")`` (issue 62,
item 4) draws from a stream of its own, with two more bases, ``preisach`` -> ``pi`` and
``bouc-wen`` -> ``bouc-wen`` (:func:`_widened_base_table`; decision 0109), two more soft knees of the
output saturation (``output-arctan``, ``output-exp``: :data:`FORMS_WIDENED`), and creep paired with
a slow channel (temperature or load, every form) in :data:`P_SLOW_PAIR_WIDENED` of its two-effect
cases. Multi-tone and band-limited noise segments are in both suites' programs.

Clean cases (``hidden = ("none",)``) have the base only; about a quarter of all cases (clean ones
included) record a lab temperature channel that drifts but that the actuator does not depend on.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

#: the hidden effect's contribution must reach this multiple of the sensor noise's rms
MIN_SNR = 5.0

#: effect -> form -> how it is produced (plant table, or the generator around the plant)
FORMS: dict[str, dict[str, str]] = {
    "hysteresis": {
        "play": "[plant.hysteresis] model = 'play'; start spec 'linear'",
        "one-sided-play": "[plant.hysteresis] model = 'one-sided-play' (unipolar drive); start spec 'linear'",
        "m-play": "[plant.hysteresis] model = 'm-play' (unipolar drive); start spec 'linear'",
        "duhem": "[plant.hysteresis] model = 'duhem' (a shape function drawn); start spec 'linear'",
    },
    "asymmetry": {
        "even-2": "[plant.asymmetry] c2 v^2",
        "even-4": "[plant.asymmetry] c4 v^4",
        "even-2+4": "[plant.asymmetry] c2 v^2 + c4 v^4 (signs drawn)",
        "even-6": "[plant.asymmetry] c2 v^2 + c6 v^6",
    },
    "saturation": {
        "input-knee": "generator: the drive is u_sat = L s(u / L), s(x) = x / (1 + |x|^p)^(1/p), p 1.5-6; the recording keeps the command",
        "output-tanh": "[plant.saturation] level: tanh of the hysteresis output",
        "output-knee": "generator: y = L s(y / L) on the plant's output (p 1.5-8); creep/dynamics moved after it",
    },
    "rate-dependence": {
        "velocity-damping": "[plant.rate_dependence] mode = 'damping': c |dv/dt / Q|^m sign(dv/dt), m 0.6-1.6",
        "frequency-gain": "[plant.rate_dependence] mode = 'frequency-polynomial': gain k(f) = 1 + k1 f, sometimes a width c(f)",
    },
    "dynamics": {
        "resonance-above-drive": "[plant.dynamics] second-order, fn 3-60x the highest drive frequency, zeta 0.03-0.3 (rung by corners and steps)",
        "resonance-near-drive": "[plant.dynamics] second-order, fn 1.3-3x the highest drive frequency, zeta 0.2-0.7",
    },
    "creep": {
        "kelvin-voigt-decades": "[plant.creep] 2-4 Kelvin-Voigt elements, time constants a decade apart",
        "logarithmic": "generator: y + gamma sum_j dy_j log10(1 + (t - t_j) / tau0) (superposed log-law step responses)",
    },
    "delay": {
        "amplifier": "[plant.delay] seconds (whole samples) between command and drive",
        "sensor": "generator: the measured output lags by a fractional number of samples (linear interpolation)",
    },
    "temperature": {
        "ramp": "[plant.temperature] trajectory ramp (warm-up), gain and thermal strain; channel recorded",
        "cooling": "[plant.temperature] trajectory cooling (exponential), gain and thermal strain; channel recorded",
        "cycling": "[plant.temperature] trajectory sine, gain and thermal strain; channel recorded",
    },
    "load": {
        "steps": "[plant.load] trajectory steps of a load, gain and compliance; load cell recorded",
        "sine": "[plant.load] trajectory sine, gain and compliance; load cell recorded",
        "placed-weight": "[plant.load] trajectory placed-weight (paper 000's transient); load cell recorded",
    },
}

#: the widened suite (issue 62, item 4): two more bases, two more soft knees of the output
FORMS_WIDENED: dict[str, dict[str, str]] = {
    **FORMS,
    "hysteresis": {
        **FORMS["hysteresis"],
        "preisach": "[plant.hysteresis] model = 'preisach' (relay grid, Gaussian density); start spec 'linear'",
        "bouc-wen": "[plant.hysteresis] model = 'bouc-wen' (n = 1, piezo form y = k u - z); start spec 'linear'",
    },
    "saturation": {
        **FORMS["saturation"],
        "output-arctan": "generator: y = L (2/pi) arctan(pi y / (2 L)) on the plant's output; creep/dynamics moved after it",
        "output-exp": "generator: y = L sgn(y) (1 - exp(-|y| / L)) on the plant's output; creep/dynamics moved after it",
    },
}

#: the effects a case may hide, with the plant families they are drawn with (a base that already
#: contains an effect never hides it: pmpi has the cubic polynomial, the Duhem shape functions
#: shape the anhysteretic curve, so asymmetry and saturation are not hidden under them)
FAMILIES = ("play", "one-sided-play", "m-play", "duhem")
ALLOWED = {
    "hysteresis": FAMILIES,
    "asymmetry": ("play", "one-sided-play"),
    "saturation": ("play", "one-sided-play", "m-play"),
    "rate-dependence": FAMILIES,
    "dynamics": FAMILIES,
    "creep": FAMILIES,
    "delay": FAMILIES,
    "temperature": FAMILIES,
    "load": FAMILIES,
}
FAMILIES_WIDENED = (*FAMILIES, "preisach", "bouc-wen")
#: a Preisach base saturates by itself once the drive sweeps its relays, and a hidden saturation on it
#: is the confusable case of issue 62; Bouc-Wen is centrally symmetric like the play operator
ALLOWED_WIDENED = {e: (*fams, "preisach", "bouc-wen") if e != "hysteresis" else FAMILIES_WIDENED
                   for e, fams in ALLOWED.items()}
#: widened: a two-effect case is creep with a slow channel this often (every pairing drawn)
P_SLOW_PAIR_WIDENED = 0.4
SUITES = ("classic", "widened")
UNIPOLAR = {"one-sided-play", "m-play"}
DUHEM_SPEC = {"gompertz": "duhem-g", "tanh": "duhem-m", "dead-zone": "duhem-d", "none": "duhem-d"}
BASE_SPEC = {"play": "pi", "one-sided-play": "pi1", "m-play": "pmpi", "preisach": "pi", "bouc-wen": "bouc-wen"}

#: shares of the case kinds
P_CLEAN = 0.15
P_TWO = 0.15


@dataclass
class Case:
    seed: int
    hidden: list[str]  # effect names; ["none"] for a clean case
    forms: dict[str, str]  # hidden effect -> form drawn
    family: str  # the plant's hysteresis model
    spec: str  # the start spec given to the diagnosis
    sample_rate_hz: float
    input_unit: str  # "A" or "V"
    actuator_range: tuple[float, float]  # command limits, input unit
    max_rate: float  # slew limit of the command path, input unit per s
    tables: dict[str, dict[str, Any]]  # [plant] tables (unchecked), shared by every run
    run_tables: list[dict[str, dict[str, Any]]]  # per run: tables that override (aux trajectories)
    pre: list[dict[str, Any]]  # generator stages before the plant (on the drive)
    post: list[dict[str, Any]]  # generator stages after the plant (on the true output), in order
    runs: list[dict[str, Any]]  # per run: label, pieces (excitation tables and holds)
    split: dict[str, Any]  # diagnose kwargs: train/test labels or train_fraction
    noise_std_um: float
    quantization_um: float
    output_span_um: float
    aux_sensors: dict[str, dict[str, float]]  # channel -> noise_std, quantization
    frequencies_hz: tuple[float, float]
    snr: dict[str, float] = field(default_factory=dict)  # hidden effect -> contribution rms / noise
    strength: dict[str, dict[str, Any]] = field(default_factory=dict)  # hidden effect -> parameters
    notes: list[str] = field(default_factory=list)
    suite: str = "classic"  # SUITES: which draw this is

    @property
    def kind(self) -> str:
        return "clean" if self.hidden == ["none"] else ("two" if len(self.hidden) > 1 else "single")

    @property
    def label(self) -> str:
        return "+".join(f"{h}:{self.forms.get(h, '-')}" for h in self.hidden)

    def to_json(self) -> dict[str, Any]:
        return json.loads(json.dumps(asdict(self), default=float))

    def samples(self) -> int:
        return sum(command(self, k).size for k in range(len(self.runs)))


# -- small helpers -------------------------------------------------------------------------------
def _logu(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def knee(x: np.ndarray, level: float, p: float) -> np.ndarray:
    """Odd saturating knee: ``level * s(x / level)``, s(z) = z / (1 + |z|^p)^(1/p); p large = sharp."""
    z = x / level
    return level * z / (1.0 + np.abs(z) ** p) ** (1.0 / p)


def soft_knee(x: np.ndarray, level: float, shape: str) -> np.ndarray:
    """The widened suite's other odd knees, unit slope at 0 and asymptote ``level``: ``arctan``
    L (2/pi) arctan(pi x / (2 L)) and ``exp`` L sgn(x) (1 - exp(-|x| / L))."""
    if shape == "arctan":
        return level * (2.0 / math.pi) * np.arctan(0.5 * math.pi * x / level)
    if shape == "exp":
        return level * np.sign(x) * -np.expm1(-np.abs(x) / level)
    raise ValueError(shape)


def _slew(u: np.ndarray, max_step: float) -> np.ndarray:
    out = np.empty_like(u)
    y = u[0]
    for k in range(u.size):
        y += min(max(u[k] - y, -max_step), max_step)
        out[k] = y
    return out


def _checked(tables: dict[str, dict[str, Any]], fs: float) -> dict[str, dict[str, Any]]:
    from hilbench.sim.schema import check_plant

    return check_plant(json.loads(json.dumps(tables)), "<diagnosis case>", fs)


# -- the measurement program ---------------------------------------------------------------------
def _segment(rng: np.random.Generator, kind: str, f: float, center: float, amp: float, lo: float, hi: float,
             remaining: float, fs: float) -> dict[str, Any] | None:
    cycles = int(rng.integers(2, 7))
    cycles = min(cycles, int(remaining * f))
    if cycles < 1:
        return None
    dur = cycles / f
    if kind == "triangle":
        return {"kind": "triangle", "frequency_hz": f, "offset": center, "amplitude": amp, "cycles": cycles}
    if kind == "triangle-staircase":
        n = max(cycles, 3) if 3 / f <= remaining else cycles
        amps = np.linspace(amp, amp * rng.uniform(0.15, 0.4), n)
        if rng.random() < 0.3:
            amps = amps[::-1]
        return {"kind": "triangle", "frequency_hz": f, "offset": center, "amplitudes": [float(a) for a in amps]}
    if kind == "sine":
        return {"kind": "sine", "frequency_hz": f, "offset": center, "amplitude": amp, "cycles": cycles}
    if kind == "ramped-sine":
        cycles = max(cycles, min(3, int(remaining * f)))
        a0, a1 = amp, amp * rng.uniform(0.15, 0.5)
        if rng.random() < 0.4:
            a0, a1 = a1, a0
        return {"kind": "ramped-sine", "frequency_hz": f, "offset": center, "amplitude_start": a0,
                "amplitude_end": a1, "cycles": cycles}
    if kind == "noise":
        top = min(f * rng.uniform(1.5, 4.0), fs / 20)
        band = [0.0, top] if rng.random() < 0.6 else [f / 3.0, top]
        if band[1] <= band[0]:
            band = [0.0, top]
        return {"kind": "noise", "rms": amp / 2.5, "band_hz": band, "duration_s": max(dur, 4.0 / f), "offset": center,
                "seed": int(rng.integers(0, 2**31 - 1)), "order": 4}
    if kind == "multitone":
        n = int(rng.integers(2, 4))
        freqs = sorted({round(f * r, 4) for r in [1.0, *rng.uniform(1.7, 4.5, n - 1)]})
        w = rng.uniform(0.3, 1.0, len(freqs))
        return {"kind": "multitone", "frequencies_hz": freqs, "amplitudes": [float(amp * x / w.sum()) for x in w],
                "phases_rad": [float(x) for x in rng.uniform(0, 2 * np.pi, len(freqs))], "offset": center,
                "duration_s": max(dur, 3.0 / f)}
    if kind == "step-staircase":
        n = int(rng.integers(3, 7))
        levels = rng.uniform(lo, hi, n)
        hold = max(0.5 / f, 0.05)
        if n * hold > remaining:
            n = max(int(remaining / hold), 1)
        return {"kind": "step", "levels": [float(x) for x in levels[:n]], "hold_s": hold}
    if kind == "chirp":
        return {"kind": "chirp", "amplitude": amp, "f_start_hz": f, "f_end_hz": f * rng.uniform(2.0, 4.0),
                "duration_s": max(dur, 4.0 / f), "offset": center}
    raise ValueError(kind)


SEGMENT_KINDS = ("triangle", "triangle-staircase", "sine", "ramped-sine", "noise", "multitone", "step-staircase",
                 "chirp")
SEGMENT_P = np.array([0.18, 0.14, 0.16, 0.14, 0.12, 0.12, 0.08, 0.06])


def _program(rng: np.random.Generator, fs: float, duration_s: float, lo: float, hi: float, unipolar: bool,
             f_lo: float, f_hi: float, min_holds: int, periodic: bool = False,
             kinds: tuple[str, ...] | None = None) -> list[dict[str, Any]]:
    """One run: rest, sometimes a power-on step, segments at drive frequencies spanning f_lo..f_hi
    (of ``kinds`` only when given, drawn alike), sometimes holds between them (at least ``min_holds``)."""
    pieces: list[dict[str, Any]] = []
    rest = 0.0
    pieces.append({"kind": "hold", "level": rest, "duration_s": rng.uniform(0.15, 0.8)})
    if rng.random() < 0.5:
        level = rng.uniform(lo + 0.2 * (hi - lo), hi - 0.2 * (hi - lo)) if unipolar else rng.uniform(0.3, 0.8) * hi * rng.choice([-1, 1])
        pieces.append({"kind": "hold", "level": float(level), "duration_s": rng.uniform(0.3, 1.5), "power_on": True})
    t = sum(p["duration_s"] for p in pieces)
    # the first two segments at the ends of the frequency range, the rest anywhere in it
    freqs = [f_lo, f_hi]
    rng.shuffle(freqs)
    holds = 0
    n_seg = 0
    hold_p = 0.35
    while t < duration_s and n_seg < 9:
        f = freqs[n_seg] if n_seg < 2 else _logu(rng, f_lo, f_hi)
        kind = str(rng.choice(SEGMENT_KINDS, p=SEGMENT_P)) if kinds is None else str(rng.choice(kinds))
        if periodic and kind in ("noise", "multitone", "chirp"):
            kind = "sine"
        if unipolar:
            center = 0.5 * (lo + hi) * rng.uniform(0.85, 1.15)
            amp = min(center - lo, hi - center) * rng.uniform(0.6, 1.0)
        else:
            center = hi * rng.uniform(-0.1, 0.1)
            amp = (hi - abs(center)) * rng.uniform(0.5, 1.0)
        seg = _segment(rng, kind, f, center, amp, lo, hi, max(duration_s - t, 1.0 / f), fs)
        if seg is None:
            break
        seg["segment"] = kind
        pieces.append(seg)
        n_seg += 1
        from hilbench.excitation.signals import make_excitation

        table = {k: v for k, v in seg.items() if k != "segment"}
        t += make_excitation(table).duration_s()
        left_for_holds = min_holds - holds
        if rng.random() < hold_p or (left_for_holds > 0 and t < duration_s):
            d = rng.uniform(0.6, 2.5) if min_holds else rng.uniform(0.3, 1.5)
            pieces.append({"kind": "hold", "level": float(rng.uniform(lo + 0.05 * (hi - lo), hi - 0.05 * (hi - lo))),
                           "duration_s": float(d)})
            holds += 1
            t += d
    while holds < min_holds:  # a program cut short by its length still gets its holds
        pieces.append({"kind": "hold", "level": float(rng.uniform(lo + 0.05 * (hi - lo), hi - 0.05 * (hi - lo))),
                       "duration_s": float(rng.uniform(0.6, 2.0))})
        holds += 1
    return pieces


def command(case: Case, k: int) -> np.ndarray:
    """The command of run k as applied: pieces concatenated, clamped to the range, slew-limited."""
    from hilbench.excitation.signals import make_excitation

    fs = case.sample_rate_hz
    parts = []
    for p in case.runs[k]["pieces"]:
        if p["kind"] == "hold":
            parts.append(np.full(max(round(p["duration_s"] * fs), 1), float(p["level"])))
        else:
            table = {key: v for key, v in p.items() if key != "segment"}
            parts.append(make_excitation(table).generate(fs))
    u = np.clip(np.concatenate(parts), *case.actuator_range)
    return _slew(u, case.max_rate / fs)


# -- the plant and the stages around it ----------------------------------------------------------
def _plant_tables(case: Case, k: int, tables: dict[str, dict[str, Any]] | None = None) -> dict[str, dict[str, Any]]:
    t = json.loads(json.dumps(case.tables if tables is None else tables))
    for name, table in case.run_tables[k].items():
        if name in t:
            t[name] = {**t[name], **table}
    return t


def _kv_creep(y: np.ndarray, gains: list[float], taus: list[float], fs: float) -> np.ndarray:
    from scipy.signal import lfilter

    out = y.copy()
    for g, tau in zip(gains, taus):
        a = 1.0 - math.exp(-1.0 / (fs * tau))
        # state[n] = state[n-1] + a (g y[n] - state[n-1])  (the plant's recursion)
        out += lfilter([a * g], [1.0, -(1.0 - a)], y)
    return out


def _log_creep(y: np.ndarray, gamma: float, tau0: float, fs: float) -> np.ndarray:
    from scipy.signal import fftconvolve

    dy = np.diff(y, prepend=y[0])
    kernel = gamma * np.log10(1.0 + np.arange(y.size) / fs / tau0)
    return y + fftconvolve(dy, kernel)[: y.size]


def _shift(y: np.ndarray, seconds: float, fs: float) -> np.ndarray:
    d = seconds * fs
    idx = np.arange(y.size) - d
    return np.interp(idx, np.arange(y.size), y, left=y[0])


def _apply_post(y: np.ndarray, post: list[dict[str, Any]], fs: float) -> np.ndarray:
    from scipy.signal import lfilter

    from hilbench.sim.dynamics import discretize_dynamics

    for st in post:
        if st["stage"] == "output-knee":
            shape = st.get("shape", "algebraic")
            y = knee(y, st["level"], st["p"]) if shape == "algebraic" else soft_knee(y, st["level"], shape)
        elif st["stage"] == "kv-creep":
            y = _kv_creep(y, st["gains"], st["time_constants_s"], fs)
        elif st["stage"] == "log-creep":
            y = _log_creep(y, st["gamma"], st["tau0_s"], fs)
        elif st["stage"] == "dynamics":
            b, a = discretize_dynamics({"gain": 1.0, **st["table"]}, fs)
            y = lfilter(b, a, y)
        elif st["stage"] == "sensor-delay":
            y = _shift(y, st["seconds"], fs)
        else:
            raise ValueError(st["stage"])
    return y


def _apply_pre(u: np.ndarray, pre: list[dict[str, Any]]) -> np.ndarray:
    for st in pre:
        if st["stage"] == "input-knee":
            u = knee(u, st["level"], st["p"])
        else:
            raise ValueError(st["stage"])
    return u


def simulate(case: Case, k: int, *, tables: dict[str, dict[str, Any]] | None = None,
             pre: list[dict[str, Any]] | None = None, post: list[dict[str, Any]] | None = None,
             seed: int | None = None) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Run k through pre stages, the plant (from rest) and post stages: (command, true output um, aux readings)."""
    from hilbench.sim.plant import Plant
    from hilbench.sim.schema import SensorModel

    fs = case.sample_rate_hz
    u = command(case, k)
    t = _checked(_plant_tables(case, k, tables), fs)
    sensors = [SensorModel("output")]
    for ch, s in case.aux_sensors.items():
        if ch in t:
            sensors.append(SensorModel(ch, s["noise_std"], s["quantization"]))
    plant = Plant(t, fs, sensors, seed=(case.seed * 7 + k) if seed is None else seed)
    sim = plant.simulate(_apply_pre(u, case.pre if pre is None else pre))
    y = _apply_post(sim.true_output, case.post if post is None else post, fs)
    return u, y, sim.aux


def _sensor(case: Case, y: np.ndarray, k: int) -> np.ndarray:
    rng = np.random.default_rng([case.seed, 11, k])
    m = y + case.noise_std_um * rng.standard_normal(y.size)
    if case.quantization_um > 0:
        m = case.quantization_um * np.floor(m / case.quantization_um + 0.5)
    return m


# -- drawing a case ----------------------------------------------------------------------------------
def _base_table(rng: np.random.Generator, family: str, u_max: float) -> tuple[dict[str, Any], str, str]:
    """The hysteresis table (output_scale 1; set later), the start spec, a note."""
    if family == "duhem":
        shape = str(rng.choice(["gompertz", "tanh", "dead-zone", "none"], p=[0.3, 0.2, 0.35, 0.15]))
        alpha = _logu(rng, 2.0, 8.0)  # per normalised input unit: loop half-width ~ 1/alpha
        ratio = rng.uniform(0.8, 1.6)
        t: dict[str, Any] = {"model": "duhem", "input_scale": u_max, "alpha": alpha, "beta": alpha * ratio,
                             "shape": shape, "k1": rng.uniform(0.3, 1.5), "k2": rng.uniform(0.5, 2.0)}
        if shape in ("gompertz", "tanh"):
            t["mu"] = [_logu(rng, 0.4, 1.5) / ratio, rng.uniform(0.0, 1.0)]
        elif shape == "dead-zone":  # paper 001's Table 1 in normalised units (u / u_max, u_max = 6 A), +-30 %
            j = lambda x: float(x * rng.uniform(0.7, 1.3))
            t.update(k1=j(2.979), k2=j(0.778), alpha=j(0.575 * 6.0), beta=j(1.859 * 6.0), n_dead_zone=6,
                     mu=[j(0.452 / 6.0), j(2.378), j(0.098), j(0.587 / 6.0), j(3.997), j(0.214)])
        return t, DUHEM_SPEC[shape], f"duhem shape {shape}"
    if family in ("preisach", "bouc-wen"):
        return _widened_base_table(rng, family, u_max)
    n = int(rng.integers(3, 9))
    top = 0.9 if family != "play" else 0.85
    r = np.sort(rng.uniform(0.03, top, n))
    w = np.exp(-rng.uniform(0.5, 3.0) * r) * rng.uniform(0.4, 1.4, n)
    t = {"model": family, "input_scale": u_max, "thresholds": [float(x) for x in r],
         "weights": [float(x) for x in w], "linear_gain": float(rng.uniform(0.15, 1.2) * w.sum())}
    if family == "m-play":
        t["eta"] = [float(x) for x in rng.uniform(-0.3, 1.0, n)]
    return t, BASE_SPEC[family], f"{n} operators"


def _widened_base_table(rng: np.random.Generator, family: str, u_max: float) -> tuple[dict[str, Any], str, str]:
    """Preisach and Bouc-Wen bases of the widened suite (bipolar drive, normalised by u_max).

    Preisach: relays over +-1.1 of the drive's range, coercive fields 0.1-0.4 (a loop of a fifth to
    four fifths of the range's half-width), an interaction spread of 0.8-3 (wide: the major loop is
    PI-like inside the drive, with the soft flattening a finite spread gives at its ends) and a
    reversible part; start spec ``pi``, the Preisach model whose density is constant along the
    interaction axis, what a bench engineer starts a Preisach-like actuator with (decision 0109).
    Bouc-Wen: the piezo form y = k u - z (Low & Guo 1995: the output lags), n = 1 (the fit base's
    default), A = 1, beta 1.5-8, gamma/beta -0.5..0.9, k 1-1.5x the steepest slope of z so that y
    rises with u; start spec ``bouc-wen``.
    """
    if family == "preisach":
        t: dict[str, Any] = {"model": "preisach", "input_scale": u_max, "levels": int(rng.integers(40, 61)),
                             "switching_range": [-1.1, 1.1], "coercive_mean": rng.uniform(0.1, 0.4),
                             "coercive_std": rng.uniform(0.05, 0.2), "interaction_std": _logu(rng, 0.8, 3.0),
                             "scatter_seed": int(rng.integers(1, 2**31 - 1)),
                             "linear_gain": rng.uniform(0.2, 1.0)}
        return t, BASE_SPEC[family], f"preisach {t['levels']} levels, interaction spread {t['interaction_std']:.2f}"
    beta = _logu(rng, 1.5, 8.0)
    gamma = beta * rng.uniform(-0.5, 0.9)
    z_max = 1.0 / (beta + gamma)
    slope = 1.0 + (beta + abs(gamma)) * z_max  # the largest dz/du (A = 1, n = 1) right after a reversal
    t = {"model": "bouc-wen", "input_scale": u_max, "a": 1.0, "beta": beta, "gamma": gamma, "n": 1.0,
         "z_weight": -1.0, "linear_gain": slope * rng.uniform(1.0, 1.5)}
    return t, BASE_SPEC[family], f"bouc-wen beta {beta:.2f} gamma {gamma:.2f}"


def _projection_residual(c: np.ndarray, y_base: np.ndarray) -> np.ndarray:
    """c less its least-squares fit by an offset and a gain of y_base (what the base absorbs trivially)."""
    A = np.column_stack([np.ones_like(y_base), y_base])
    coef, *_ = np.linalg.lstsq(A, c, rcond=None)
    return c - A @ coef


class _Draw:
    """Per-effect parameters drawn once; ``build(mult)`` gives the tables/stages at a strength multiple."""

    def __init__(self, effect: str, form: str, rng: np.random.Generator, ctx: dict[str, Any]):
        self.effect, self.form, self.ctx = effect, form, ctx
        self.p: dict[str, Any] = {}
        r = rng
        c = ctx
        if effect == "asymmetry":
            order = {"even-2": [2], "even-4": [4], "even-2+4": [2, 4], "even-6": [2, 6]}[form]
            signs = r.choice([-1.0, 1.0], len(order))
            shares = r.uniform(0.4, 1.0, len(order))
            self.p = {"orders": order, "coef": [float(s * x / shares.sum()) for s, x in zip(signs, shares)],
                      "s": _logu(r, 0.03, 0.2)}
        elif effect == "saturation":
            if form == "input-knee":
                self.p = {"ell": r.uniform(0.55, 1.1), "p": r.uniform(1.5, 6.0)}
            elif form == "output-tanh":
                self.p = {"ell": r.uniform(0.6, 1.3)}
            elif form == "output-knee":
                self.p = {"ell": r.uniform(0.55, 1.1), "p": r.uniform(1.5, 8.0)}
            else:  # output-arctan, output-exp (widened suite)
                self.p = {"ell": r.uniform(0.55, 1.1)}
        elif effect == "rate-dependence":
            if form == "velocity-damping":
                self.p = {"s": _logu(r, 0.03, 0.25), "m": r.uniform(0.6, 1.6)}
            else:
                self.p = {"s": _logu(r, 0.05, 0.3) * r.choice([-1.0, 1.0]),
                          "width": _logu(r, 0.02, 0.15) if r.random() < 0.5 else 0.0}
        elif effect == "dynamics":
            fmax = c["f_hi"] * 1.5  # the highest tone of a segment can reach above f_hi
            cap = c["fs"] / 8.0
            if form == "resonance-above-drive":
                self.p = {"fn": min(_logu(r, 3.0 * fmax, 60.0 * fmax), cap), "zeta": _logu(r, 0.03, 0.3)}
            else:
                self.p = {"fn": min(_logu(r, 1.3 * fmax, 3.0 * fmax), cap), "zeta": r.uniform(0.2, 0.7)}
        elif effect == "creep":
            if form == "kelvin-voigt-decades":
                n = int(r.integers(2, 5))
                tau1 = _logu(r, 0.01, 0.3)
                taus = [tau1 * 10.0**i * r.uniform(0.7, 1.4) for i in range(n)]
                taus = [min(x, 3.0 * c["run_s"]) for x in taus]
                g = r.uniform(0.5, 1.5, n)
                self.p = {"taus": taus, "shares": [float(x / g.sum()) for x in g], "s": _logu(r, 0.04, 0.2)}
            else:
                self.p = {"gamma": _logu(r, 0.008, 0.04), "tau0": _logu(r, 0.001, 0.05)}
        elif effect == "delay":
            self.p = {"seconds": _logu(r, 0.0003, 0.005)}
        elif effect in ("temperature", "load"):
            self.p = {"s": _logu(r, 0.04, 0.2) * r.choice([-1.0, 1.0]),
                      "offset_share": r.uniform(0.0, 1.0) if r.random() < 0.6 else 0.0,
                      "traj": [self._trajectory(r, effect, form, c["runs_s"][k]) for k in range(c["n_runs"])]}

    @staticmethod
    def _trajectory(r: np.random.Generator, effect: str, form: str, run_s: float) -> dict[str, Any]:
        if effect == "temperature":
            t0 = r.uniform(20.0, 30.0)
            dT = r.uniform(3.0, 15.0)
            if form == "ramp":
                return {"kind": "ramp", "start": t0, "end": t0 + dT, "duration_s": run_s * r.uniform(0.5, 1.2)}
            if form == "cooling":
                return {"kind": "cooling", "initial": t0 + dT, "ambient": t0, "time_constant_s": run_s * r.uniform(0.2, 0.8)}
            return {"kind": "sine", "mean": t0 + dT / 2, "amplitude": dT / 2, "period_s": run_s * r.uniform(0.3, 1.0)}
        fmax = r.uniform(10.0, 100.0)
        if form == "steps":
            n = int(r.integers(3, 7))
            levels = list(r.uniform(0.0, fmax, n))
            levels[int(r.integers(0, n))] = 0.0
            return {"kind": "steps", "levels": [float(x) for x in levels], "hold_s": run_s / n}
        if form == "sine":
            return {"kind": "sine", "mean": fmax / 2, "amplitude": fmax / 2, "period_s": run_s * r.uniform(0.25, 1.0)}
        mass = fmax / 9.80665
        return {"kind": "placed-weight", "mass_kg": mass, "at_s": run_s * r.uniform(0.2, 0.6),
                "contacts": int(r.integers(1, 3)), "contact_interval_s": r.uniform(0.1, 0.6), "settle_hz": r.uniform(3.0, 15.0), "damping": r.uniform(0.05, 0.3)}

    def channel_range(self) -> float:
        span = 0.0
        for tr in self.p.get("traj", []):
            t = np.linspace(0.0, self.ctx["run_s"], 2000)
            from hilbench.sim.trajectories import evaluate

            span = max(span, float(np.ptp(evaluate(tr, t))))
        return max(span, 1e-9)

    def build(self, mult: float) -> dict[str, Any]:
        """{'tables': {...}, 'run_tables': [per run], 'pre': [...], 'post': [...], 'params': {...}}"""
        c, p, e, f = self.ctx, self.p, self.effect, self.form
        out: dict[str, Any] = {"tables": {}, "run_tables": [{} for _ in range(c["n_runs"])], "pre": [], "post": []}
        h_max, span_um = c["h_max"], c["span_um"]  # model units (before output_scale), um
        if e == "asymmetry":
            vmax = 1.0
            coef = [0.0] * (max(p["orders"]) + 1)
            for o, x in zip(p["orders"], p["coef"]):
                coef[o] = x * p["s"] * mult * c["h_span"] / vmax**o
            out["tables"]["asymmetry"] = {"coefficients": coef}
            out["params"] = {"coefficients": coef}
        elif e == "saturation":
            ell = p["ell"] / mult
            if f == "input-knee":
                out["pre"].append({"stage": "input-knee", "level": ell * c["u_max"], "p": p["p"]})
            elif f == "output-tanh":
                out["tables"]["saturation"] = {"level": ell * h_max}
            elif f == "output-knee":
                out["post"].append({"stage": "output-knee", "level": ell * c["y_max_um"], "p": p["p"]})
            else:
                out["post"].append({"stage": "output-knee", "shape": f.removeprefix("output-"),
                                    "level": ell * c["y_max_um"]})
            out["params"] = {"level_over_max": ell, **({"p": p["p"]} if "p" in p else {})}
        elif e == "rate-dependence":
            if f == "velocity-damping":
                q = 2.0 * math.pi * c["f_hi"] * 0.5 * c["v_span"]
                out["tables"]["rate_dependence"] = {"mode": "damping", "gain": 1.0, "coefficient": p["s"] * mult * h_max,
                                                    "exponent": p["m"], "reference_rate": q}
            else:
                k1 = p["s"] * mult / c["f_hi"]
                k1 = max(k1, -0.8 / (1.5 * c["f_hi"]))  # the gain stays positive up to 1.5 f_hi
                out["tables"]["rate_dependence"] = {"mode": "frequency-polynomial", "k_poly": [1.0, k1],
                                                    "c_poly": [0.0, p["width"] * mult * h_max / c["f_hi"]],
                                                    "m_poly": [1.0]}
            out["params"] = dict(out["tables"]["rate_dependence"])
        elif e == "dynamics":
            fn = max(p["fn"] / mult, 1.2 * c["f_hi"])
            zeta = p["zeta"] / (mult if f == "resonance-above-drive" else 1.0)
            out["tables"]["dynamics"] = {"kind": "second-order", "natural_frequency_hz": fn, "zeta": max(zeta, 0.01)}
            out["params"] = {"natural_frequency_hz": fn, "zeta": max(zeta, 0.01)}
        elif e == "creep":
            if f == "kelvin-voigt-decades":
                gains = [x * p["s"] * mult for x in p["shares"]]
                out["tables"]["creep"] = {"gains": gains, "time_constants_s": p["taus"]}
                out["params"] = {"gains": gains, "time_constants_s": p["taus"]}
            else:
                out["post"].append({"stage": "log-creep", "gamma": p["gamma"] * mult, "tau0_s": p["tau0"]})
                out["params"] = {"gamma_per_decade": p["gamma"] * mult, "tau0_s": p["tau0"]}
        elif e == "delay":
            sec = p["seconds"] * mult
            if f == "amplifier":
                n = max(1, round(sec * c["fs"]))
                out["tables"]["delay"] = {"seconds": n / c["fs"]}
                out["params"] = {"seconds": n / c["fs"], "samples": n}
            else:
                sec = max(sec, 0.5 / c["fs"])
                out["post"].append({"stage": "sensor-delay", "seconds": sec})
                out["params"] = {"seconds": sec, "samples": sec * c["fs"]}
        elif e in ("temperature", "load"):
            rng_ch = self.channel_range()
            gain = p["s"] * mult / rng_ch
            offset = p["offset_share"] * abs(p["s"]) * mult * span_um / rng_ch
            if e == "temperature":
                tab = {"trajectory": p["traj"][0], "reference_degC": float(p["traj"][0].get("start", p["traj"][0].get(
                    "ambient", p["traj"][0].get("mean", 25.0)))), "gain_per_degC": gain, "strain_um_per_degC": offset}
            else:
                tab = {"trajectory": p["traj"][0], "gain_per_N": gain, "compliance_um_per_N": offset}
            out["tables"][e] = tab
            out["run_tables"] = [{e: {"trajectory": tr}} for tr in p["traj"]]
            out["params"] = {k: v for k, v in tab.items() if k != "trajectory"} | {"trajectories": p["traj"]}
        return out


def _merge(case: Case, builds: list[dict[str, Any]]) -> None:
    """Put the effects' tables and stages into the case, keeping the chain's physical order: an
    output-side generator stage that is not linear (the output knee) goes before creep and dynamics,
    so these move out of the plant after it (the same discrete filters)."""
    pre, post = [], []
    for b in builds:
        for name, t in b["tables"].items():
            case.tables[name] = t
        for k, rt in enumerate(b["run_tables"]):
            for name, t in rt.items():
                case.run_tables[k][name] = t
        pre += b["pre"]
        post += b["post"]
    if any(st["stage"] == "output-knee" for st in post):
        moved = []
        if "creep" in case.tables:
            cr = case.tables.pop("creep")
            moved.append({"stage": "kv-creep", "gains": cr["gains"], "time_constants_s": cr["time_constants_s"]})
        if "dynamics" in case.tables:
            moved.append({"stage": "dynamics", "table": case.tables.pop("dynamics")})
        post = [st for st in post if st["stage"] == "output-knee"] + moved + \
            [st for st in post if st["stage"] != "output-knee"]
    order = {"output-knee": 0, "kv-creep": 1, "log-creep": 2, "dynamics": 3, "sensor-delay": 4}
    case.pre = pre
    case.post = sorted(post, key=lambda st: order[st["stage"]])


#: two slow effects at once (issue 62): creep with a channel that moves slowly too, the channel's
#: form fixed, creep's form and everything else drawn per seed (:func:`draw_slow_pair`)
SLOW_PAIRS: dict[str, tuple[list[str], dict[str, str]]] = {
    "creep+warming": (["creep", "temperature"], {"temperature": "ramp"}),
    "creep+load-staircase": (["creep", "load"], {"load": "steps"}),
    "creep+placed-weight": (["creep", "load"], {"load": "placed-weight"}),
    "warming": (["temperature"], {"temperature": "ramp"}),  # the same drift without creep
}
#: each kind's stream: the first three in the order they were drawn in before the fourth came (a kind
#: added later must not move the draws of the others)
_SLOW_PAIR_STREAMS = ("creep+load-staircase", "creep+warming", "warming", "creep+placed-weight")


def draw_slow_pair(seed: int, kind: str) -> Case:
    """A case of :data:`SLOW_PAIRS` ``kind`` from its seed: the hidden effects fixed, their strengths,
    the base, the program (creep: two holds or more), the split and the sensor drawn as
    :func:`draw_case` draws them, from a stream of its own (seed n here is not case n there)."""
    if kind not in SLOW_PAIRS:
        raise ValueError(f"slow pair kind: {kind!r}, expected one of {', '.join(SLOW_PAIRS)}")
    hidden, forms = SLOW_PAIRS[kind]
    return _draw(np.random.default_rng([20240611, 62, _SLOW_PAIR_STREAMS.index(kind), seed]), seed,
                 list(hidden), dict(forms))


def draw_case(seed: int, suite: str = "classic") -> Case:
    """A case from its seed alone (module docstring); ``suite`` 'widened' draws from
    :data:`FAMILIES_WIDENED` and :data:`FORMS_WIDENED`, with creep paired with a slow channel in
    :data:`P_SLOW_PAIR_WIDENED` of its two-effect cases, from a stream of its own: the classic draws
    (the seeds the tests and regressions pin) stay what they were, and widened seed n is not classic
    seed n."""
    if suite not in SUITES:
        raise ValueError(f"suite: {suite!r}, expected one of {', '.join(SUITES)}")
    rng = case_rng(seed, suite)
    return _draw(rng, seed, draw_hidden(rng, suite), {}, suite)


def case_rng(seed: int, suite: str = "classic") -> np.random.Generator:
    """The stream a case of ``suite`` is drawn from (the widened suite's is its own)."""
    return np.random.default_rng([20240611, 62, 4, seed] if suite == "widened" else [20240611, seed])


def draw_hidden(rng: np.random.Generator, suite: str = "classic") -> list[str]:
    """The hidden effects, the first draws of a case: ``['none']``, one effect or two."""
    u = rng.random()
    if u < P_CLEAN:
        return ["none"]
    if u < P_CLEAN + P_TWO:
        if suite == "widened" and rng.random() < P_SLOW_PAIR_WIDENED:
            return ["creep", str(rng.choice(["temperature", "load"]))]
        pool = [e for e in ALLOWED if e != "hysteresis"]
        return [str(x) for x in rng.choice(pool, 2, replace=False)]
    return [str(rng.choice(list(ALLOWED)))]


def _draw(rng: np.random.Generator, seed: int, hidden: list[str], fixed_forms: dict[str, str],
          suite: str = "classic", families: tuple[str, ...] | None = None,
          segments: tuple[str, ...] | None = None) -> Case:
    """The rest of a case once its hidden effects are chosen (forms in ``fixed_forms`` are not drawn;
    the family among ``families`` and the segments among ``segments`` when given)."""
    suite_families, allowed, forms_of = ((FAMILIES_WIDENED, ALLOWED_WIDENED, FORMS_WIDENED) if suite == "widened"
                                         else (FAMILIES, ALLOWED, FORMS))
    # the family: one that every hidden effect may be drawn with
    fams = [f for f in (families or suite_families) if all(h == "none" or f in allowed[h] for h in hidden)]
    family = str(rng.choice(fams, p=None))
    forms: dict[str, str] = {}
    for h in hidden:
        if h == "hysteresis":
            forms[h] = family
        elif h in fixed_forms:
            forms[h] = fixed_forms[h]
        elif h != "none":
            forms[h] = str(rng.choice(list(forms_of[h])))
    unipolar = family in UNIPOLAR
    unit = ("V" if rng.random() < 0.8 else "A") if unipolar else ("A" if rng.random() < 0.7 else "V")
    u_max = _logu(rng, 0.5, 6.0) if unit == "A" else _logu(rng, 5.0, 150.0)
    lo, hi = (0.0, u_max) if unipolar else (-u_max, u_max)
    fs = float(rng.choice([500.0, 1000.0, 2000.0, 2500.0, 5000.0], p=[0.2, 0.35, 0.2, 0.1, 0.15]))
    layout = str(rng.choice(["fraction", "two-runs", "three-runs"], p=[0.35, 0.45, 0.2]))
    n_runs = {"fraction": 1, "two-runs": 2, "three-runs": 3}[layout]
    total = _logu(rng, 12000, 36000)
    run_s = total / n_runs / fs
    f_lo = _logu(rng, max(0.1, 5.0 / run_s), max(0.2, 12.0 / run_s))
    f_hi = min(f_lo * _logu(rng, 3.0, 15.0), fs / 60.0)
    f_lo = min(f_lo, f_hi / 3.0)
    min_holds = 2 if "creep" in hidden else 0
    runs = []
    for k in range(n_runs):
        label = {1: ["run"], 2: ["train", "test"], 3: ["train-a", "train-b", "test"]}[n_runs][k]
        runs.append({"label": label, "pieces": _program(rng, fs, run_s, lo, hi, unipolar, f_lo, f_hi, min_holds,
                                                        periodic=forms.get("rate-dependence") == "frequency-gain",
                                                        kinds=segments)})
    split: dict[str, Any] = ({"train_fraction": float(round(rng.uniform(0.55, 0.75), 3))} if layout == "fraction" else
                             {"train": [r["label"] for r in runs[:-1]], "test": [runs[-1]["label"]]})
    hyst, spec, note = _base_table(rng, family, u_max)
    if "hysteresis" in hidden:
        spec = "linear"
    rise = rng.uniform(0.001, 0.01)  # a full-range step takes 1-10 ms
    case = Case(seed=seed, hidden=hidden, forms=forms, family=family, spec=spec, sample_rate_hz=fs, input_unit=unit,
                actuator_range=(lo, hi), max_rate=0.0, tables={"hysteresis": hyst},
                run_tables=[{} for _ in range(n_runs)], pre=[], post=[], runs=runs, split=split, noise_std_um=0.0,
                quantization_um=0.0, output_span_um=0.0, aux_sensors={}, frequencies_hz=(f_lo, f_hi), notes=[note],
                suite=suite)
    # the slew limit: fast enough for every smooth segment (1.2x its steepest slope)
    case.max_rate = 1e12
    smooth = 0.0
    from hilbench.excitation.signals import make_excitation

    for r in runs:
        for p in r["pieces"]:
            if p["kind"] != "hold" and p["kind"] != "step":
                x = make_excitation({k: v for k, v in p.items() if k != "segment"}).generate(fs)
                smooth = max(smooth, float(np.max(np.abs(np.diff(x)))) * fs if x.size > 1 else 0.0)
    case.max_rate = max((hi - lo) / rise, 1.2 * smooth)
    # scale the output: span drawn 5-150 um
    _, y1, _ = simulate(case, 0, tables={"hysteresis": {**hyst, "output_scale": 1.0}}, pre=[], post=[])
    span_target = _logu(rng, 5.0, 150.0)
    h_span = float(np.ptp(y1)) or 1.0
    hyst["output_scale"] = span_target / h_span
    case.output_span_um = span_target
    ctx = {"fs": fs, "f_hi": f_hi, "f_lo": f_lo, "run_s": run_s, "runs_s": [run_s] * n_runs, "n_runs": n_runs,
           "h_max": float(np.max(np.abs(y1))), "h_span": h_span, "span_um": span_target,
           "y_max_um": float(np.max(np.abs(y1))) * hyst["output_scale"], "u_max": u_max,
           "v_span": (hi - lo) / u_max}
    # an irrelevant, drifting lab temperature channel in about a quarter of the cases
    aux_sensors: dict[str, dict[str, float]] = {}
    if "temperature" not in hidden and rng.random() < 0.25:
        t0 = rng.uniform(20, 26)
        case.tables["temperature"] = {"trajectory": {"kind": "ramp", "start": t0, "end": t0 + rng.uniform(0.3, 2.0),
                                                     "duration_s": run_s}, "gain_per_degC": 0.0,
                                      "strain_um_per_degC": 0.0, "reference_degC": t0}
        case.notes.append("a drifting lab temperature recorded; the actuator does not depend on it")
    for ch in ("temperature", "load"):
        if ch in hidden or ch in case.tables:
            if ch == "temperature":
                q = 0.0625 if rng.random() < 0.3 else 0.0
                aux_sensors[ch] = {"noise_std": _logu(rng, 0.005, 0.05), "quantization": q}
            else:
                aux_sensors[ch] = {"noise_std": _logu(rng, 0.02, 0.5), "quantization": 0.0}
    case.aux_sensors = aux_sensors
    # the hidden effects: strength drawn, raised only if the effect would drown at the lowest noise
    floor, ceiling = 0.001 * span_target, 0.02 * span_target
    draws = [_Draw(h, forms[h], rng, ctx) for h in hidden if h not in ("none", "hysteresis")]
    base_tables = json.loads(json.dumps(case.tables))
    y_base = np.concatenate([simulate(case, k, tables=base_tables, pre=[], post=[])[1] for k in range(n_runs)])
    mults, contribs = [], {}
    for d in draws:
        mult = 1.0
        for _ in range(10):
            contrib = _contribution(case, d, mult, y_base, base_tables)
            if contrib >= 1.1 * MIN_SNR * floor:
                break
            mult *= 1.6
        mults.append(mult)
        contribs[d.effect] = contrib
        case.strength[d.effect] = {"multiplier": mult, **d.build(mult)["params"]}
    if "hysteresis" in hidden:
        us = np.concatenate([command(case, k) for k in range(n_runs)])
        contribs["hysteresis"] = float(np.sqrt(np.mean(_projection_residual(y_base, us) ** 2)))
    # the sensor: noise 0.1-2 % of the span; with a hidden effect, drawn as the weakest effect's
    # contribution over a ratio of 5-50 (within the same bounds); sometimes quantised
    if contribs:
        ratio = _logu(rng, MIN_SNR, 50.0)
        case.noise_std_um = float(np.clip(min(contribs.values()) / ratio, floor, ceiling))
    else:
        case.noise_std_um = _logu(rng, 0.001, 0.02) * span_target
    if rng.random() < 0.4:
        bits = int(rng.choice([12, 14, 16]))
        q = 2.0 * span_target * rng.uniform(1.0, 2.0) / 2**bits
        case.quantization_um = q if q <= 3.0 * case.noise_std_um else 0.0
    case.snr = {h: round(c / case.noise_std_um, 3) for h, c in contribs.items()}
    _merge(case, [d.build(m) for d, m in zip(draws, mults)])
    return case


def _contribution(case: Case, d: _Draw, mult: float, y_base: np.ndarray, base_tables: dict[str, dict[str, Any]]) -> float:
    """rms of what effect ``d`` at ``mult`` adds to the base output, less an offset and a gain of it."""
    n_runs = len(case.runs)
    trial = Case(**{**case.__dict__, "tables": json.loads(json.dumps(base_tables)),
                    "run_tables": [{} for _ in range(n_runs)], "pre": [], "post": []})
    _merge(trial, [d.build(mult)])
    y = np.concatenate([simulate(trial, k)[1] for k in range(n_runs)])
    return float(np.sqrt(np.mean(_projection_residual(y - y_base, y_base) ** 2)))


def write_case(case: Case, folder: str | Path, simulate_run: Any = None, prefix: str = "case",
               experiment: str = "diagnosis-case") -> tuple[list[Path], dict[str, Any]]:
    """Simulate every run and write one HDF5 recording; (paths, diagnose keyword arguments).
    ``simulate_run(case, k) -> (u, y, aux)`` replaces :func:`simulate` (another generator's plant)."""
    from hilbench.recording.hdf5 import RecordingWriter

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{prefix}-{case.seed:05d}.h5"
    if path.exists():
        path.unlink()
    writer = RecordingWriter(path)
    fs = case.sample_rate_hz
    units = {"time": "s", "input": case.input_unit, "output": "um", "temperature": "degC", "load": "N"}
    for k, run in enumerate(case.runs):
        u, y, aux = (simulate_run or simulate)(case, k)
        data = {"time": np.arange(u.size) / fs, "input": u, "output": _sensor(case, y, k), **aux}
        excitation = json.dumps([{kk: v for kk, v in p.items()} for p in run["pieces"]], default=float)
        writer.write_run(run["label"], data, {c: units[c] for c in data}, experiment=experiment,
                         excitation=excitation, sample_rate_hz=fs)
    return [path], dict(case.split)


if __name__ == "__main__":  # a quick look at some draws
    import sys

    for s in range(int(sys.argv[1]) if len(sys.argv) > 1 else 10):
        c = draw_case(s, sys.argv[2] if len(sys.argv) > 2 else "classic")
        print(s, c.kind, c.label, c.family, c.spec, c.sample_rate_hz, c.input_unit, len(c.runs), c.samples(),
              {k: round(v, 1) for k, v in c.snr.items()}, f"noise {c.noise_std_um / c.output_span_um:.4f}")
