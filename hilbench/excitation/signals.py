"""The papers' excitations, generated in chunks so a run of any length stays in bounded memory.

Every excitation is built from a table (TOML, or the compact command-line form of
:mod:`hilbench.excitation.plan`) whose ``kind`` picks the signal:

=====================  ============================================================================
kind                   what it is (and where the papers use it)
=====================  ============================================================================
sine                   offset + amplitude sin(2 pi f t + phase); 001 (1-6 A, 1 Hz), 003 (10-1500 Hz)
ramped-sine            sine whose amplitude grows or shrinks linearly (arithmetically per cycle);
                       000 (0.3 -> 3 A at 0.05 Hz), 002 (amplitude-decreasing 1 Hz sine)
triangle               triangle with the sine's amplitude/phase convention; ``amplitudes`` gives a
                       staircase of maxima, one per cycle (001: 6..1 A; Preisach identification)
noise                  band-limited white noise of given rms in a band; 002 and 000 dynamics
step                   levels each held for ``hold_s``; 002 step-response identification
multitone              sum of sines; 002's 4 sin(8.80 t) + 2.5 sin(2.51 t + pi/2)
chirp                  sine sweep from ``f_start_hz`` to ``f_end_hz``, linear or logarithmic
attenuated-triangle    triangle cycles from ``base`` up to a decaying peak with a changing
                       frequency: 004's frequency-converting attenuated triangle
=====================  ============================================================================

Amplitudes and offsets are in the actuator's command unit (A or V); times in s; frequencies in Hz
unless the name says rad/s.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from hilbench.errors import ConfigError
from hilbench.schema import Key, check_table

DEFAULT_CHUNK = 65536


class Excitation:
    """A signal over time, generated chunk by chunk at a given sample rate."""

    kind = ""
    schema: dict[str, Key] = {}

    def __init__(self, params: Mapping[str, Any]):
        self.params = dict(params)

    # -- overridden by kinds ----------------------------------------------------------------
    def duration_s(self) -> float:
        raise NotImplementedError

    def values(self, t: np.ndarray) -> np.ndarray:
        """Signal at times ``t`` (s); stateless kinds implement this."""
        raise NotImplementedError

    # -- shared -----------------------------------------------------------------------------
    def n_samples(self, sample_rate_hz: float) -> int:
        return int(round(self.duration_s() * sample_rate_hz)) + 1

    def chunks(self, sample_rate_hz: float, chunk: int = DEFAULT_CHUNK) -> Iterator[np.ndarray]:
        n = self.n_samples(sample_rate_hz)
        for start in range(0, n, chunk):
            stop = min(n, start + chunk)
            yield self.values(np.arange(start, stop, dtype=np.float64) / sample_rate_hz)

    def generate(self, sample_rate_hz: float) -> np.ndarray:
        """The whole signal as one array (for short runs, tests and plots)."""
        return np.concatenate(list(self.chunks(sample_rate_hz)))

    def describe(self) -> dict[str, Any]:
        return {"kind": self.kind, **{k: v for k, v in self.params.items() if v is not None}}

    def to_json(self) -> str:
        return json.dumps(self.describe())

    def __repr__(self) -> str:
        return f"Excitation({self.to_json()})"


def _span(params: Mapping[str, Any], frequency_hz: float) -> float:
    if params.get("duration_s") is not None:
        return float(params["duration_s"])
    return float(params["cycles"]) / frequency_hz


def _one_of_cycles_duration(p: dict[str, Any]) -> str | None:
    if p.get("cycles") is None and p.get("duration_s") is None:
        return "give either 'cycles' or 'duration_s'"
    if p.get("cycles") is not None and p.get("duration_s") is not None:
        return "give either 'cycles' or 'duration_s', not both"
    return None


_PERIODIC = {
    "frequency_hz": Key("number", required=True, minimum=0, exclusive_minimum=True, doc="Hz"),
    "offset": Key("number", default=0.0),
    "phase_deg": Key("number", default=0.0, doc="phase of the first sample, deg"),
    "cycles": Key("number", minimum=0, exclusive_minimum=True),
    "duration_s": Key("number", minimum=0, exclusive_minimum=True),
}


def _triangle_wave(theta: np.ndarray) -> np.ndarray:
    """Unit triangle with the sine's phase convention: 0 at theta=0, +1 at pi/2, -1 at 3pi/2."""
    return (2.0 / np.pi) * np.arcsin(np.clip(np.sin(theta), -1.0, 1.0))


class Sine(Excitation):
    kind = "sine"
    schema = {"amplitude": Key("number", required=True, minimum=0), **_PERIODIC}
    check = staticmethod(_one_of_cycles_duration)

    def duration_s(self) -> float:
        return _span(self.params, self.params["frequency_hz"])

    def values(self, t: np.ndarray) -> np.ndarray:
        p = self.params
        return p["offset"] + p["amplitude"] * np.sin(2 * np.pi * p["frequency_hz"] * t + np.radians(p["phase_deg"]))


class RampedSine(Excitation):
    kind = "ramped-sine"
    schema = {
        "amplitude_start": Key("number", required=True, minimum=0),
        "amplitude_end": Key("number", required=True, minimum=0),
        **_PERIODIC,
    }
    check = staticmethod(_one_of_cycles_duration)

    def duration_s(self) -> float:
        return _span(self.params, self.params["frequency_hz"])

    def values(self, t: np.ndarray) -> np.ndarray:
        p = self.params
        # The envelope moves linearly in time (no jump at cycle boundaries whatever the phase) and
        # passes through amplitude_start at the first positive peak and amplitude_end at the last,
        # so the cycle peaks form the arithmetic series of 000 and 002.
        n_cycles = self.duration_s() * p["frequency_hz"]
        first_peak = ((90.0 - p["phase_deg"]) / 360.0) % 1.0  # in cycles
        span = max(math.floor(n_cycles - first_peak - 1e-9), 1)  # cycles between first and last peak
        slope = (p["amplitude_end"] - p["amplitude_start"]) / span
        # Clipped to [start, end] so no sample exceeds the largest requested amplitude.
        lo, hi = sorted((p["amplitude_start"], p["amplitude_end"]))
        amp = np.clip(p["amplitude_start"] + slope * (t * p["frequency_hz"] - first_peak), lo, hi)
        return p["offset"] + amp * np.sin(2 * np.pi * p["frequency_hz"] * t + np.radians(p["phase_deg"]))


class Triangle(Excitation):
    kind = "triangle"
    schema = {
        "amplitude": Key("number", minimum=0),
        "amplitudes": Key("numbers", minimum=0, doc="staircase: one amplitude per cycle"),
        **_PERIODIC,
    }

    @staticmethod
    def check(p: dict[str, Any]) -> str | None:
        if (p["amplitude"] is None) == (p["amplitudes"] is None):
            return "give either 'amplitude' or a staircase 'amplitudes', not both or neither"
        if p["amplitudes"] is not None:
            if not p["amplitudes"]:
                return "'amplitudes' must not be empty"
            if p["cycles"] is not None or p["duration_s"] is not None:
                return "a staircase triangle runs one cycle per entry of 'amplitudes'; drop 'cycles'/'duration_s'"
            return None
        return _one_of_cycles_duration(p)

    def duration_s(self) -> float:
        p = self.params
        if p["amplitudes"] is not None:
            return len(p["amplitudes"]) / p["frequency_hz"]
        return _span(p, p["frequency_hz"])

    def values(self, t: np.ndarray) -> np.ndarray:
        p = self.params
        theta = 2 * np.pi * p["frequency_hz"] * t + np.radians(p["phase_deg"])
        if p["amplitudes"] is not None:
            amps = np.asarray(p["amplitudes"], dtype=float)
            cycle = np.clip((t * p["frequency_hz"]).astype(np.int64), 0, len(amps) - 1)
            amp = amps[cycle]
        else:
            amp = p["amplitude"]
        return p["offset"] + amp * _triangle_wave(theta)


class Noise(Excitation):
    kind = "noise"
    schema = {
        "rms": Key("number", required=True, minimum=0, doc="rms of the noise, command unit"),
        "band_hz": Key("pair", required=True, minimum=0, doc="[low, high] Hz; low 0 = low-pass"),
        "duration_s": Key("number", required=True, minimum=0, exclusive_minimum=True),
        "offset": Key("number", default=0.0),
        "seed": Key("int", default=0),
        "order": Key("int", default=4, minimum=1, maximum=12),
    }

    @staticmethod
    def check(p: dict[str, Any]) -> str | None:
        lo, hi = p["band_hz"]
        if not hi > lo:
            return f"band_hz: expected low < high, got {p['band_hz']}"
        return None

    def duration_s(self) -> float:
        return float(self.params["duration_s"])

    def _sos(self, sample_rate_hz: float) -> np.ndarray:
        from scipy import signal as sps

        lo, hi = self.params["band_hz"]
        nyq = sample_rate_hz / 2
        if hi >= nyq:
            raise ConfigError(
                f"noise band_hz high edge {hi:g} Hz must be below the Nyquist frequency {nyq:g} Hz "
                f"of the rig's sample rate"
            )
        order = self.params["order"]
        if lo <= 0:
            return sps.butter(order, hi, btype="lowpass", fs=sample_rate_hz, output="sos")
        return sps.butter(order, [lo, hi], btype="bandpass", fs=sample_rate_hz, output="sos")

    def chunks(self, sample_rate_hz: float, chunk: int = DEFAULT_CHUNK) -> Iterator[np.ndarray]:
        from scipy import signal as sps

        sos = self._sos(sample_rate_hz)
        # Scale so the filtered unit white noise has the requested rms: var = sum(h^2).
        # The impulse response decays within some tens of periods of the lowest band edge.
        lo, hi = self.params["band_hz"]
        n_impulse = int(min(2_000_000, max(4096, 40 * sample_rate_hz / (lo if lo > 0 else hi))))
        impulse = np.zeros(n_impulse)
        impulse[0] = 1.0
        gain = self.params["rms"] / math.sqrt(float(np.sum(sps.sosfilt(sos, impulse) ** 2)))
        rng = np.random.default_rng(self.params["seed"])
        zi = np.zeros((sos.shape[0], 2))
        n = self.n_samples(sample_rate_hz)
        for start in range(0, n, chunk):
            white = rng.standard_normal(min(chunk, n - start))
            filtered, zi = sps.sosfilt(sos, white, zi=zi)
            yield self.params["offset"] + gain * filtered


class Step(Excitation):
    kind = "step"
    schema = {
        "levels": Key("numbers", required=True, doc="values held one after the other"),
        "hold_s": Key("number-or-numbers", required=True, minimum=0, exclusive_minimum=True),
        "rise_s": Key("number", default=0.0, minimum=0, doc="linear transition time at each change, within the hold"),
    }

    @staticmethod
    def check(p: dict[str, Any]) -> str | None:
        if not p["levels"]:
            return "'levels' must not be empty"
        if isinstance(p["hold_s"], list) and len(p["hold_s"]) != len(p["levels"]):
            return f"'hold_s' has {len(p['hold_s'])} entries but 'levels' has {len(p['levels'])}"
        return None

    def _holds(self) -> np.ndarray:
        hold = self.params["hold_s"]
        return np.asarray(hold if isinstance(hold, list) else [hold] * len(self.params["levels"]), dtype=float)

    def duration_s(self) -> float:
        return float(self._holds().sum())

    def values(self, t: np.ndarray) -> np.ndarray:
        edges = np.cumsum(self._holds())
        levels = np.asarray(self.params["levels"], dtype=float)
        index = np.clip(np.searchsorted(edges, t, side="right"), 0, len(edges) - 1)
        out = levels[index]
        rise = self.params["rise_s"]
        if rise > 0:
            # Each change starts at the hold boundary and reaches the new level after rise_s.
            starts = np.concatenate([[0.0], edges[:-1]])
            since = t - starts[index]
            previous = levels[np.maximum(index - 1, 0)]
            ramping = (index > 0) & (since < rise)
            frac = np.clip(since / rise, 0.0, 1.0)
            out = np.where(ramping, previous + (out - previous) * frac, out)
        return out


class Multitone(Excitation):
    kind = "multitone"
    schema = {
        "amplitudes": Key("numbers", required=True),
        "frequencies_hz": Key("numbers", minimum=0),
        "omegas_rad_s": Key("numbers", minimum=0),
        "phases_rad": Key("numbers"),
        "offset": Key("number", default=0.0),
        "duration_s": Key("number", required=True, minimum=0, exclusive_minimum=True),
    }

    @staticmethod
    def check(p: dict[str, Any]) -> str | None:
        if (p["frequencies_hz"] is None) == (p["omegas_rad_s"] is None):
            return "give either 'frequencies_hz' or 'omegas_rad_s'"
        freqs = p["frequencies_hz"] if p["frequencies_hz"] is not None else p["omegas_rad_s"]
        if len(freqs) != len(p["amplitudes"]):
            return "'amplitudes' and the frequencies must have the same length"
        if p["phases_rad"] is not None and len(p["phases_rad"]) != len(p["amplitudes"]):
            return "'phases_rad' must have one entry per tone"
        return None

    def duration_s(self) -> float:
        return float(self.params["duration_s"])

    def values(self, t: np.ndarray) -> np.ndarray:
        p = self.params
        omegas = (
            2 * np.pi * np.asarray(p["frequencies_hz"], float)
            if p["frequencies_hz"] is not None
            else np.asarray(p["omegas_rad_s"], float)
        )
        phases = np.asarray(p["phases_rad"] if p["phases_rad"] is not None else [0.0] * len(omegas), float)
        out = np.full_like(t, p["offset"])
        for a, w, ph in zip(p["amplitudes"], omegas, phases):
            out += a * np.sin(w * t + ph)
        return out


class Chirp(Excitation):
    kind = "chirp"
    schema = {
        "amplitude": Key("number", required=True, minimum=0),
        "f_start_hz": Key("number", required=True, minimum=0, exclusive_minimum=True),
        "f_end_hz": Key("number", required=True, minimum=0, exclusive_minimum=True),
        "duration_s": Key("number", required=True, minimum=0, exclusive_minimum=True),
        "offset": Key("number", default=0.0),
        "method": Key("str", default="linear", choices=("linear", "logarithmic")),
    }

    def duration_s(self) -> float:
        return float(self.params["duration_s"])

    def values(self, t: np.ndarray) -> np.ndarray:
        from scipy import signal as sps

        p = self.params
        wave = sps.chirp(t, p["f_start_hz"], p["duration_s"], p["f_end_hz"], method=p["method"], phi=-90)
        return p["offset"] + p["amplitude"] * wave


class AttenuatedTriangle(Excitation):
    kind = "attenuated-triangle"
    schema = {
        "base": Key("number", default=0.0, doc="valley of every cycle"),
        "amplitude_start": Key("number", required=True, minimum=0, doc="peak above base, first cycle"),
        "amplitude_end": Key("number", required=True, minimum=0, doc="peak above base, last cycle"),
        "frequency_start_hz": Key("number", required=True, minimum=0, exclusive_minimum=True),
        "frequency_end_hz": Key("number", required=True, minimum=0, exclusive_minimum=True),
        "cycles": Key("int", required=True, minimum=1),
    }

    def _cycles(self) -> tuple[np.ndarray, np.ndarray]:
        p = self.params
        frac = np.linspace(0.0, 1.0, p["cycles"])
        amps = p["amplitude_start"] + (p["amplitude_end"] - p["amplitude_start"]) * frac
        freqs = p["frequency_start_hz"] + (p["frequency_end_hz"] - p["frequency_start_hz"]) * frac
        return amps, freqs

    def duration_s(self) -> float:
        return float(np.sum(1.0 / self._cycles()[1]))

    def values(self, t: np.ndarray) -> np.ndarray:
        amps, freqs = self._cycles()
        periods = 1.0 / freqs
        starts = np.concatenate([[0.0], np.cumsum(periods)[:-1]])
        k = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(amps) - 1)
        phase = np.clip((t - starts[k]) / periods[k], 0.0, 1.0)  # 0..1 within the cycle
        return self.params["base"] + amps[k] * (1.0 - np.abs(2.0 * phase - 1.0))


KINDS: dict[str, type[Excitation]] = {
    cls.kind: cls for cls in (Sine, RampedSine, Triangle, Noise, Step, Multitone, Chirp, AttenuatedTriangle)
}


def make_excitation(table: Mapping[str, Any], *, file: str = "<excitation>", where: str = "excitation") -> Excitation:
    """Build an excitation from a table with a ``kind`` key, validating every parameter."""
    params = dict(table)
    kind = params.pop("kind", None)
    if kind not in KINDS:
        raise ConfigError(
            f"[{where}] kind: expected one of {', '.join(KINDS)}, got {kind!r}", where=file
        )
    cls = KINDS[kind]
    checked = check_table(params, cls.schema, file=file, table=where, extra_check=getattr(cls, "check", None))
    return cls(checked)
