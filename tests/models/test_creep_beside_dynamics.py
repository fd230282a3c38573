"""Creep beside dynamics is slower than the dynamics' settling (decision 0111).

A creep element free to go down to a few samples fits the transients after steps as a lag and moves
the resonance to match; beside ``dynamics`` its time constants start at
CREEP_BESIDE_DYNAMICS_MIN_TAU_S, the time the diagnosis gives a resonance to settle.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from hilbench.excitation.plan import expand_runs
from hilbench.identify.fitting import fit
from hilbench.models import Model
from hilbench.models.effect_components import CREEP_BESIDE_DYNAMICS_MIN_TAU_S
from hilbench.models.model import RunData
from hilbench.rig.config import load_rig
from hilbench.rig.rig import Rig
from hilbench.runners.sweep import run_plan

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import tracking_cases as TC


def _prepared(spec: str, fs: float = 20000.0, seconds: float = 2.0) -> Model:
    t = np.arange(int(fs * seconds)) / fs
    u = 5.0 * np.sin(2 * np.pi * 3.0 * t)
    model = Model(spec)
    model.prepare([RunData(u, 2.0 * u, {}, fs, name="r")])
    return model


@pytest.mark.parametrize("form", ["", "(form=output)"])
def test_searched_time_constants_start_at_the_floor_beside_dynamics_only(form: str) -> None:
    beside = _prepared(f"pi+creep{form}+dynamics").effect("creep")
    alone = _prepared(f"pi+creep{form}").effect("creep")
    assert min(p.lower for p in beside.params) == pytest.approx(CREEP_BESIDE_DYNAMICS_MIN_TAU_S)
    assert all(p.value > p.lower for p in beside.params)  # started off the bound
    assert min(p.lower for p in alone.params) == pytest.approx(10.0 / 20000.0)


def test_the_bank_starts_at_the_floor_beside_dynamics() -> None:
    beside = _prepared("pi+creep(form=bank)+dynamics").effect("creep").time_constants()
    alone = _prepared("pi+creep(form=bank)").effect("creep").time_constants()
    assert beside[0] == pytest.approx(CREEP_BESIDE_DYNAMICS_MIN_TAU_S)
    assert alone[0] == pytest.approx(3.0 / 20000.0)
    assert beside[-1] == pytest.approx(alone[-1])


def _resolved_creep_rigs(count: int) -> list[int]:
    """Generated play rigs whose only effect besides the dynamics is creep, the resonance sampled at
    least ten times a period (resolved), the first ``count`` from seed 100."""
    seeds = []
    for seed in range(100, 400):
        d = TC.draw(seed)
        if d.family == "play" and d.effects == ["creep"] and d.sample_rate_hz >= 10.0 * d.natural_frequency_hz:
            seeds.append(seed)
        if len(seeds) == count:
            break
    return seeds


def test_creep_beside_dynamics_leaves_the_resonance_to_the_dynamics(tmp_path: Path) -> None:
    """On generated rigs with creep and a resonance, swept with holds shorter than the creep: the
    damping ratio is found within 10 % and every creep element is slower than the floor. Without the
    floor an element went to 10 samples and the damping was 17 % off on two of these three rigs."""
    for seed in _resolved_creep_rigs(3):
        d = TC.draw(seed)
        rig = tmp_path / f"rig-{seed}.toml"
        rig.write_text(d.toml, encoding="utf-8")
        rec = tmp_path / f"sweep-{seed}.h5"
        cfg = load_rig(rig)
        assert run_plan(Rig(cfg), expand_runs(cfg.plan, file=str(rig)), rec).status == "complete"
        model = fit([str(rec)], d.spec + "+dynamics+creep").model
        zeta = model.effect("dynamics").param("zeta")
        assert abs(zeta / d.zeta - 1.0) <= 0.10, (seed, zeta, d.zeta)
        assert min(model.effect("creep").time_constants()) >= CREEP_BESIDE_DYNAMICS_MIN_TAU_S
