"""The verdicts of ``hilbench online`` as functions, on synthetic signals: the offline free run's
check (scored, static fallback, refused) and online against y(k-1) (better, or worse and why)."""

from __future__ import annotations

import numpy as np

from hilbench.cli.online_commands import input_extrapolation, offline_verdict, persistence_verdict
from hilbench.online.oiir import persistence

FS = 1000.0


def _sine(n: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n) / FS
    u = 10.0 * np.sin(2 * np.pi * 2.0 * t)
    return u, 0.5 * u + 0.01 * np.random.default_rng(0).standard_normal(n)


def test_offline_scored_when_sound_fallback_when_dynamics_diverge_refused_when_both():
    u, y = _sine()
    rows = np.ones(y.size, bool)
    stable = np.array([0.9 + 0.1j, 0.9 - 0.1j])
    check, scored = offline_verdict(y, y * 1.02, y, rows, stable, None, "um")
    assert check["status"] == "ok" and scored is not None and check["reasons"] == []
    exploding = y * np.exp(np.arange(y.size) / 100.0)
    check, scored = offline_verdict(y, exploding, y * 0.98, rows, np.array([1.0005, 0.5]), None, "um")
    assert check["status"] == "static-fallback" and np.allclose(scored, y * 0.98)
    assert any("|z| = 1.0005" in r for r in check["reasons"]) and any("diverges" in r for r in check["reasons"])
    why = input_extrapolation(np.zeros(100), u, "V")
    assert why is not None and "0..0 V" in why and "held still" in why
    check, scored = offline_verdict(y, np.full(y.size, np.inf), y * 1e6, rows, stable, why, "um")
    assert check["status"] == "refused" and scored is None
    assert any("static FPMPI alone diverges too" in r for r in check["reasons"]) and why in check["reasons"]
    assert input_extrapolation(u, u[:100], "V") is None  # within the fitted inputs: nothing to say


def test_persistence_verdict_names_an_episode_or_the_steady_state():
    u, y = _sine()
    per = persistence(y)
    rows = np.arange(y.size) >= 1
    counters = {"divergence_resets": 1, "predictions_bounded": 3, "poles_projected": 7}
    good = y + 0.001
    doc = persistence_verdict(y, good, per, rows, FS, u, counters, np.zeros(9), 3, 5, None, "um")
    assert doc["verdict"] == "better" and doc["reasons"] == []
    episode = good.copy()
    episode[1200:1500] += 2.0  # a bad stretch in the second quarter, fine elsewhere
    doc = persistence_verdict(y, episode, per, rows, FS, u, counters, np.zeros(9), 3, 5, None, "um")
    assert doc["verdict"] == "worse" and doc["worst_quarter"] == 2
    assert doc["reasons"][0].startswith("an episode, not the steady state")
    assert any("1 divergence resets, 3 predictions held" in r for r in doc["reasons"])
    steady = y + 0.5 * np.sin(np.arange(y.size))  # worse everywhere
    w = np.array([0, 0, 0, 0, 0.7, 0.3, 0, 0, 0.0])  # sum q = 1: an integrator
    doc = persistence_verdict(y, steady, per, rows, FS, u, {}, w, 3, 5, None, "um")
    assert doc["reasons"][0].startswith("the steady state too")
    assert any("500 samples per cycle" in r for r in doc["reasons"])  # 2 Hz at 1 kHz
    assert any("sum q = 1" in r for r in doc["reasons"])
