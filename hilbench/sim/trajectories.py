"""Trajectories of the auxiliary quantities a simulated rig exposes: temperature (degC), load (N).

Evaluated on the run's time axis (s from the start of the run), vectorised, so block mode and step
mode agree. ``placed-weight`` reproduces the transient of paper 000 (Fig. 4): a weight set onto the
actuator lands in ``contacts`` partial contacts (000: front first, back second), each a lightly
damped second-order settling of its share of the weight.
"""

from __future__ import annotations

from typing import Any

import numpy as np

G_N_PER_KG = 9.80665


def _need(p: dict[str, Any], *keys: str) -> None:
    from hilbench.errors import ConfigError

    missing = [k for k in keys if p.get(k) is None]
    if missing:
        raise ConfigError(f"trajectory kind {p['kind']!r} needs {', '.join(repr(k) for k in missing)}")


def validate(p: dict[str, Any]) -> None:
    need = {
        "constant": ("value",),
        "ramp": ("start", "end", "duration_s"),
        "cooling": ("initial", "ambient", "time_constant_s"),
        "sine": ("mean", "amplitude", "period_s"),
        "steps": ("levels", "hold_s"),
        "step": ("start", "end", "at_s"),
        "placed-weight": ("mass_kg", "at_s"),
    }[p["kind"]]
    _need(p, *need)


def evaluate(p: dict[str, Any], t: np.ndarray) -> np.ndarray:
    kind = p["kind"]
    if kind == "constant":
        return np.full_like(t, p["value"], dtype=np.float64)
    if kind == "ramp":
        frac = np.clip(t / p["duration_s"], 0.0, 1.0)
        return p["start"] + (p["end"] - p["start"]) * frac
    if kind == "cooling":
        return p["ambient"] + (p["initial"] - p["ambient"]) * np.exp(-t / p["time_constant_s"])
    if kind == "sine":
        return p["mean"] + p["amplitude"] * np.sin(2 * np.pi * t / p["period_s"])
    if kind == "steps":
        levels = np.asarray(p["levels"], dtype=float)
        index = np.clip((t / p["hold_s"]).astype(np.int64), 0, len(levels) - 1)
        return levels[index]
    if kind == "step":
        return np.where(t >= p["at_s"], p["end"], p["start"])
    if kind == "placed-weight":
        out = np.zeros_like(t, dtype=np.float64)
        share = p["mass_kg"] * G_N_PER_KG / p["contacts"]
        wn = 2 * np.pi * p["settle_hz"]
        zeta = p["damping"]
        wd = wn * np.sqrt(1 - zeta**2)
        for k in range(p["contacts"]):
            tau = t - (p["at_s"] + k * p["contact_interval_s"])
            on = tau >= 0
            tt = np.where(on, tau, 0.0)
            settle = 1 - np.exp(-zeta * wn * tt) * (np.cos(wd * tt) + zeta / np.sqrt(1 - zeta**2) * np.sin(wd * tt))
            out += np.where(on, share * settle, 0.0)
        return out
    raise ValueError(f"unknown trajectory kind {kind!r}")
