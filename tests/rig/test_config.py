"""Rig configs: every built-in rig loads; every kind of bad config is refused in one line."""

from __future__ import annotations

from pathlib import Path

import pytest

from hilbench.rig.config import builtin_rigs, load_rig
from hilbench.errors import ConfigError

BUILTIN = sorted(builtin_rigs())


def test_builtin_rigs_are_the_papers_rigs():
    papers = {load_rig(name).paper for name in BUILTIN}
    assert {"000", "001", "002", "003", "004"} <= papers
    for name in BUILTIN:
        cfg = load_rig(name)
        assert cfg.simulated and cfg.follows, f"{name} must say which table/equation it follows"


@pytest.mark.parametrize("name", BUILTIN)
def test_builtin_rig_loads_and_builds(name):
    from hilbench.rig.rig import Rig

    rig = Rig(load_rig(name))
    assert rig.lockstep.plant.sample_rate_hz == rig.sample_rate_hz > 0
    assert rig.channels()[0].name == "time"


def _error(path: Path) -> str:
    with pytest.raises(ConfigError) as info:
        load_rig(path)
    line = info.value.line()
    assert "\n" not in line
    assert str(path) in line
    return line


def test_unknown_key_lists_the_allowed_ones(write_rig):
    path = write_rig(base=__import__("tests.conftest", fromlist=["MINIMAL_RIG"]).MINIMAL_RIG.replace(
        "max_rate = 1000.0", "max_rate = 1000.0\nmax_speed = 3"))
    line = _error(path)
    assert "[actuator]" in line and "'max_speed'" in line and "max_rate" in line


def test_missing_key(write_rig):
    from tests.conftest import MINIMAL_RIG

    line = _error(write_rig(base=MINIMAL_RIG.replace('unit = "V"\n', "")))
    assert "[actuator]" in line and "missing key 'unit'" in line


def test_wrong_type_names_key_and_value(write_rig):
    from tests.conftest import MINIMAL_RIG

    line = _error(write_rig(base=MINIMAL_RIG.replace("max = 10.0", 'max = "ten"')))
    assert "[actuator] max" in line and "'ten'" in line and "number" in line


def test_inverted_limits(write_rig):
    from tests.conftest import MINIMAL_RIG

    line = _error(write_rig(base=MINIMAL_RIG.replace("min = -10.0", "min = 20.0")))
    assert "min 20 must be less than max 10" in line


def test_rest_outside_limits(write_rig):
    from tests.conftest import MINIMAL_RIG

    line = _error(write_rig(base=MINIMAL_RIG.replace("rest = 0.0", "rest = 11.0")))
    assert "rest 11" in line


def test_negative_rate_refused(write_rig):
    from tests.conftest import MINIMAL_RIG

    line = _error(write_rig(base=MINIMAL_RIG.replace("max_rate = 1000.0", "max_rate = -1.0")))
    assert "max_rate" in line and "> 0" in line


def test_mismatched_weights(write_rig):
    from tests.conftest import MINIMAL_RIG

    line = _error(write_rig(base=MINIMAL_RIG.replace("weights = [0.5, 0.3, 0.2]", "weights = [0.5]")))
    assert "thresholds has 3 entries but weights has 1" in line


def test_unstable_dynamics_refused(write_rig):
    line = _error(write_rig('[plant.dynamics]\nkind = "discrete"\nb = [1.0]\na = [1.0, -1.5]\n'))
    assert "unstable" in line and "pole" in line


def test_sensor_without_trajectory(write_rig):
    line = _error(write_rig('[[sensors]]\nchannel = "temperature"\nunit = "degC"\ndriver = "sim"\n'))
    assert "[plant.temperature]" in line


def test_bad_toml_and_missing_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[rig\nname = 1", encoding="utf-8")
    assert "not valid TOML" in _error(bad)
    with pytest.raises(ConfigError) as info:
        load_rig(tmp_path / "nothere.toml")
    assert "nothere.toml" in info.value.line() and "built-in rigs" in info.value.line()


def test_disabled_effect_is_off(write_rig):
    cfg = load_rig(write_rig('[plant.creep]\nenabled = false\ngains = [0.1]\ntime_constants_s = [1.0]\n'))
    assert "creep" not in cfg.plant


def test_extends_overrides_tables(tmp_path, write_rig):
    write_rig(name="base.toml")
    child = tmp_path / "child.toml"
    child.write_text('[rig]\nname = "child"\nextends = "base.toml"\n[actuator]\nmax = 5.0\n', encoding="utf-8")
    cfg = load_rig(child)
    assert cfg.name == "child" and cfg.actuator.max == 5.0 and cfg.actuator.min == -10.0
    assert cfg.sample_rate_hz == 1000.0
    assert "extends base.toml" in cfg.text


def test_trajectory_missing_parameter(write_rig):
    line = _error(write_rig(
        '[plant.temperature]\ntrajectory = { kind = "cooling", initial = 40.0 }\n'
        '[[sensors]]\nchannel = "temperature"\nunit = "degC"\ndriver = "sim"\n'
    ))
    assert "[plant.temperature.trajectory]" in line and "'ambient'" in line and "'time_constant_s'" in line
