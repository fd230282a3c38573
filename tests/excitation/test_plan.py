"""Plans: compact form, sweeps, plan files, and the limit check before anything moves."""

from __future__ import annotations

import pytest

from hilbench.rig.config import ActuatorConfig
from hilbench.errors import ConfigError, PlanLimitError
from hilbench.excitation.plan import check_plan, expand_runs, load_plan_file, parse_compact, plan_from_compact

ACT = ActuatorConfig(driver="sim", unit="A", min=-6.0, max=6.0, max_rate=100.0, rest=0.0)


def test_compact_form_with_sweep_and_list():
    table = parse_compact("triangle:frequency_hz=1,amplitudes=6/5/4")
    assert table == {"kind": "triangle", "frequency_hz": 1, "amplitudes": [6, 5, 4]}
    runs = plan_from_compact(["sine:amplitude=1|2|3,frequency_hz=1,cycles=2,label=amp"])
    assert [r.label for r in runs] == ["amp-amplitude=1", "amp-amplitude=2", "amp-amplitude=3"]
    assert [r.excitation.params["amplitude"] for r in runs] == [1.0, 2.0, 3.0]


def test_sweep_is_cartesian():
    runs = expand_runs([{"kind": "sine", "cycles": 1, "sweep": {"amplitude": [1, 2], "frequency_hz": [1, 10, 100]}}],
                       file="x")
    assert len(runs) == 6 and runs[-1].label == "sine-amplitude=2-frequency_hz=100"


def test_plan_file(tmp_path):
    path = tmp_path / "plan.toml"
    path.write_text('[[runs]]\nlabel = "a"\nkind = "step"\nlevels = [0.0, 1.0]\nhold_s = 0.5\n', encoding="utf-8")
    runs = load_plan_file(path)
    assert runs[0].label == "a" and runs[0].excitation.duration_s() == 1.0


def test_plan_file_bad_key_names_file_and_run(tmp_path):
    path = tmp_path / "plan.toml"
    path.write_text('[[runs]]\nkind = "sine"\namplitude = 1.0\nfreq = 3\ncycles = 1\n', encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_plan_file(path)
    line = info.value.line()
    assert str(path) in line and "runs[0]" in line and "'freq'" in line


def test_range_violation_names_run_time_and_value():
    runs = plan_from_compact(["sine:amplitude=2,frequency_hz=0.1,cycles=1", "sine:amplitude=6.5,frequency_hz=0.1,cycles=1"])
    with pytest.raises(PlanLimitError) as info:
        check_plan(runs, ACT, 1000.0)
    line = info.value.line()
    assert "plan run 2 'sine'" in line and "outside the actuator range [-6, 6] A" in line
    # sin reaches 6 A at asin(6/6.5)/(2 pi 0.1) s = 1.872 s
    t = float(line.split("t=")[1].split(" s")[0])
    assert t == pytest.approx(1.872, abs=2e-3)
    value = float(line.split("value ")[1].split(" A")[0])
    assert 6.0 < value < 6.01


def test_slew_violation():
    runs = plan_from_compact(["sine:amplitude=5,frequency_hz=10,cycles=1"])  # 314 A/s > 100 A/s
    with pytest.raises(PlanLimitError) as info:
        check_plan(runs, ACT, 1000.0)
    assert "above the slew limit max_rate = 100 A/s" in info.value.line()


def test_slew_checked_across_chunk_boundaries():
    runs = plan_from_compact(["step:levels=0/5,hold_s=65.536"])  # the jump falls on a chunk boundary
    with pytest.raises(PlanLimitError) as info:
        check_plan(runs, ACT, 1000.0)
    assert "t=65.536 s" in info.value.line()


def test_valid_plan_totals():
    runs = plan_from_compact(["sine:amplitude=1|2,frequency_hz=1,cycles=2"])
    totals = check_plan(runs, ACT, 1000.0)
    assert totals == {"runs": 2, "samples": 4002, "duration_s": pytest.approx(4.002)}


@pytest.mark.parametrize(
    "plan, rig",
    [
        ("paper-002-linear-identification.toml", "gmm-gu2016"),
        ("paper-002-validation.toml", "gmm-gu2016"),
        ("paper-001-characterisation.toml", "gmm-issf-duhem"),
        ("paper-000-rate-independent.toml", "gmm-fpmpi"),
    ],
)
def test_shipped_experiment_plans_fit_their_rigs(plan, rig):
    from pathlib import Path

    from hilbench.rig.config import load_rig

    cfg = load_rig(rig)
    runs = load_plan_file(Path(__file__).resolve().parents[2] / "experiments" / "plans" / plan)
    assert check_plan(runs, cfg.actuator, cfg.sample_rate_hz)["samples"] > 0


def test_ramped_sine_never_exceeds_its_end_amplitude():
    runs = plan_from_compact(["ramped-sine:amplitude_start=0.15,amplitude_end=1.5,offset=1.5,phase_deg=-90,frequency_hz=0.05,cycles=10"])
    x = runs[0].excitation.generate(1000.0)
    assert x.max() <= 3.0 and x.max() == pytest.approx(3.0, abs=1e-6)
