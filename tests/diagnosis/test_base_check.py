"""The wrong base is an effect too: a PMPI model on a Duhem-like rig is diagnosed as the wrong base."""

from __future__ import annotations

from pathlib import Path

import pytest

from hilbench.diagnosis.diagnose import diagnose
from hilbench.excitation.plan import plan_from_compact
from hilbench.rig.config import load_rig
from hilbench.rig.rig import Rig
from hilbench.runners.sweep import run_plan


@pytest.fixture(scope="module")
def duhem_sweep(tmp_path_factory) -> Path:
    """The magnetostrictive ISSF-Duhem rig (unbiased: butterfly loops) under sines and triangles."""
    out = tmp_path_factory.mktemp("base-check") / "duhem.h5"
    plan = plan_from_compact(["sine:amplitude=3|6,offset=0,frequency_hz=1,cycles=2",
                              "triangle:amplitudes=6/4/2,frequency_hz=1"])
    run_plan(Rig(load_rig("gmm-issf-duhem")), plan, out)
    return out


def test_pmpi_on_the_duhem_rig_is_a_wrong_base_and_duhem_fits(duhem_sweep):
    d = diagnose(duhem_sweep, "pmpi")
    best = d.best
    assert best is not None and best.effect == "base" and best.significant, [c.to_json() for c in d.effects]
    suggested = best.evidence["suggested_base"]
    tried = best.evidence["bases_tried"]
    # duhem-d, or another base within 2x of its error (the acceptance)
    assert suggested == "duhem-d" or tried[suggested] <= 2.0 * tried["duhem-d"]
    old, new = best.evidence["validation_rmse"]
    assert new * 2.0 <= old
    # not the current family at too few operators: pmpi at twice its operators stays far above (decision 0077)
    finer = best.evidence["finer_base"]
    assert finer["spec"].startswith("pmpi(n=20)") and new * 2.0 <= finer["validation_rmse"], finer


def test_a_right_base_is_not_called_wrong(tmp_path):
    out = tmp_path / "duhem.h5"
    run_plan(Rig(load_rig("gmm-issf-duhem")), plan_from_compact(["sine:amplitude=3|6,frequency_hz=1,cycles=2"]), out)
    d = diagnose(out, "duhem-d")
    assert all(c.effect != "base" or not c.significant for c in d.effects)


def test_hysteresis_on_a_linear_model_takes_the_loop_shape_the_data_show(duhem_sweep):
    """An unbiased magnetostrictive rig's loops are butterflies (strain even in the current): play
    operators cannot make one, so hysteresis tried as ``pi`` alone explained almost nothing and an
    even polynomial (asymmetry) ranked first. Hysteresis is tried in each family of loop shape and
    the Duhem with a dead zone, chosen on held-back training rows, removes nearly all the error."""
    d = diagnose(duhem_sweep, "linear")
    best = d.best
    table = [(c.effect, c.spec, round(c.expected_gain, 3), c.significant) for c in d.effects]
    assert best is not None and best.effect == "hysteresis" and best.significant, table
    assert best.spec.split("+")[0] in ("duhem-d", "duhem-g"), table
    old, new = best.evidence["validation_rmse"]
    assert new * 10.0 <= old, table
