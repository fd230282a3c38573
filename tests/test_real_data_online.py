"""``hilbench online`` on third-party measured data (``../shared/data/real``; skipped when absent).

Issue 58: the online identifier and the offline Hammerstein model bounded on any data. On main the
piezo stack gave online 5.9e7 % and offline 6.7e9 % re_N2, the dSPACE 20 Hz capture's online
prediction went to inf, and nothing said why the online figure was worse than y(k-1). Here every
figure is finite and bounded (the identifier's guard, decision 0082), a diverging offline free run
is set aside or refused with its reason, and online is better than y(k-1) or the output says why
(decision 0083). Imported as the README says; ``--global-starts 4`` keeps each test short.

Measured (re_N2 %, online / offline / y(k-1), --global-starts 4; the README has the default):
stack 0.385 / 0.98 / 0.501; dSPACE 20 Hz 0.123 / 939 / 0.979; 100 Hz 0.278 / 193 / 4.90 (the offline
model is fitted on the staircase's first part, -90..-36 V, and says so); PNZT slow triangles online
better than y(k-1) in 10 of 10 tables (offline refused on 3: its free run diverges); PNZT creep
worse in 2 of 4 (37.7 and 59.3 % against 6.16 and 3.42 %), each with its reason (an episode: one
quarter of the scored rows holds most of the error).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from hilbench.cli import app
from hilbench.cli.online_commands import report_lines
from hilbench.recording.importers import import_files
from tests.conftest import require_real_data

runner = CliRunner()
FAST = ["--global-starts", "4", "-q", "--json"]
#: (folder, files, mapping) of each data set, as the README imports them
SETS = {
    "stack": ("piezo-stack-150V-1Hz", ["hysteresis_v_150_1hz.csv"], {"1": "time[s]", "2": "output[um]", "3": "input[V]"}),
    "dspace20": ("piezo-dspace-preisach", ["20_hz_no_lp.mat"], {"Y(3)": "input[V]", "Y(1)": "output[um]"}),
    "dspace100": ("piezo-dspace-preisach", ["100_hz_no_lp.mat"], {"Y(3)": "input[V]", "Y(1)": "output[um]"}),
    "pnzt-slow": ("pnzt-piezoceramic-aixacct", ["RMN_TRAP_SLOW.dat"], None),
    "pnzt-creep": ("pnzt-piezoceramic-aixacct", ["RMN_TRAP_1400V_1000V_CREEP.dat"], None),
}


def online_doc(name: str, tmp_path: Path) -> dict:
    folder, files, mapping = SETS[name]
    paths = [require_real_data() / folder / f for f in files]
    for p in paths:
        if not p.exists():
            pytest.skip(f"{p} not found")
    rec = tmp_path / f"{name}.h5"
    import_files(paths, rec, mapping=mapping)
    result = runner.invoke(app, ["online", str(rec), *FAST])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def check_bounded(doc: dict) -> None:
    """Every figure finite and bounded; a refused offline model says why; online worse than y(k-1)
    says why, in the JSON and in the text report."""
    assert doc["runs"]
    text = "\n".join(report_lines(doc))
    for r in doc["runs"]:
        on, per, off = r["online"], r["persistence"], r["offline"]
        for m in (on, per):
            assert m["re_n2_pct"] is not None and math.isfinite(m["re_n2_pct"]) and m["re_n2_pct"] > 0
            assert m["re_ninf_pct"] is not None and math.isfinite(m["re_ninf_pct"])
        # the prediction bound: never further off than the outputs' range allows (the stack reached
        # 3.4e8 um on main for a 39 um stroke)
        assert on["re_n2_pct"] < 200.0, r["run"]
        ident = r["identifier"]
        assert ident["nonfinite_skipped"] == 0 and all(math.isfinite(w) for w in r["weights_final"].values())
        assert r["poles_final"]["max_radius"] <= ident["pole_radius"] + 1e-9
        check = r["offline_check"]
        if check["status"] == "refused":
            assert off["re_n2_pct"] is None and check["reasons"], check
            assert f"{r['run']}: offline refused" in text
        else:
            assert off["re_n2_pct"] is not None and math.isfinite(off["re_n2_pct"])
            assert check["free_run_escape_spans"] <= 10.0 or check["status"] == "static-fallback"
        vs = r["online_vs_persistence"]
        if on["re_n2_pct"] <= per["re_n2_pct"]:
            assert vs["verdict"] == "better" and not vs["reasons"]
        else:
            assert vs["verdict"] == "worse" and vs["reasons"], r["run"]
            assert f"{r['run']}: online {on['re_n2_pct']:.4g} % is worse than y(k-1)" in text
            # derived from numbers, not a canned sentence: each reason quotes some
            assert all(any(ch.isdigit() for ch in reason) for reason in vs["reasons"])


def test_stack_online_offline_and_persistence(tmp_path: Path) -> None:
    doc = online_doc("stack", tmp_path)
    check_bounded(doc)
    (r,) = doc["runs"]
    # the 0 V rest (3.26 s) is neither trained on nor scored: on main it was all the training rows
    assert doc["left_out"] and "0-3.257 s" in doc["left_out"][0]
    assert r["offline_check"]["status"] == "ok"
    assert r["offline"]["re_n2_pct"] < 2.0  # measured 0.98 % (main: 6.7e9 %)
    assert r["online"]["re_n2_pct"] < r["persistence"]["re_n2_pct"]  # measured 0.385 vs 0.501 %
    assert r["identifier"]["divergence_resets"] == 0


@pytest.mark.parametrize("name", ["dspace20", "dspace100"])
def test_dspace_online_beats_persistence(name: str, tmp_path: Path) -> None:
    doc = online_doc(name, tmp_path)
    check_bounded(doc)
    (r,) = doc["runs"]
    # measured 0.123 vs 0.979 % (20 Hz; main: 5.2 % or inf) and 0.278 vs 4.90 % (100 Hz)
    assert r["online"]["re_n2_pct"] < r["persistence"]["re_n2_pct"]
    # the offline model is fitted on the staircase's first part (-90..-36 V) and scored up to +90 V
    assert any("fitted on inputs" in w for w in r["offline_check"].get("warnings", []))
    assert doc["front_end"]["input_range"][0] == pytest.approx(-90.0)


@pytest.mark.parametrize("name", ["pnzt-slow", "pnzt-creep"])
def test_pnzt_records_bounded(name: str, tmp_path: Path) -> None:
    doc = online_doc(name, tmp_path)
    check_bounded(doc)
    better = sum(r["online_vs_persistence"]["verdict"] == "better" for r in doc["runs"])
    if name == "pnzt-slow":
        assert len(doc["runs"]) == 10 and better >= 8  # measured 10 of 10
