"""hilbench online, end to end on the simulated gmm-fpmpi rig (paper 000): rig mode (sweep, then
replay), replay of the recording, the saved online run, the plot, one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from hilbench.cli import app
from hilbench.identify.metrics import metrics
from hilbench.recording.hdf5 import Recording

runner = CliRunner()
TRAIN = "ramped-sine:amplitude_start=0.15,amplitude_end=1.5,offset=1.5,phase_deg=-90,frequency_hz=0.5,cycles=6"
DRIVES = "sine:amplitude=1,offset=1,phase_deg=-90,cycles=3,frequency_hz=1|5"
FAST = ["--global-starts", "4", "-q"]


def run_ok(*args: str) -> dict:
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)  # exactly one JSON document on stdout


def run_error(*args: str) -> str:
    result = runner.invoke(app, list(args))
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    lines = result.stderr.strip().splitlines()
    assert lines[0].startswith("error: ") and len(lines) <= 2, lines
    return lines[0]


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("online")
    rec, out, png = tmp / "rec.h5", tmp / "online.h5", tmp / "online.png"
    doc = run_ok("online", "gmm-fpmpi", "-e", TRAIN, "-e", DRIVES, "--train", "ramped-sine", "--record", str(rec),
                 "-o", str(out), "--plot", str(png), "--no-realtime", *FAST)
    return doc, rec, out, png


def test_rig_mode_sweeps_then_compares_online_with_offline(live):
    doc, rec, _, png = live
    assert doc["mode"] == "rig" and doc["rig"] == "gmm-fpmpi" and doc["files"] == [str(rec)]
    assert doc["offline"]["spec"] == "fpmpi+delay+dynamics"
    assert doc["online"]["M"] == 3 and doc["online"]["N"] == 5 and doc["online"]["lambda"] == 1.0
    assert doc["online"]["delta"] == 1e5 and len(doc["online"]["weights"]) == 9
    runs = doc["runs"]
    assert [r["run"] for r in runs] == ["0002-sine-frequency_hz=1", "0003-sine-frequency_hz=5"]
    for r in runs:
        assert r["evaluated_from_s"] == pytest.approx(0.5) and r["evaluated_samples"] == r["samples"] - 500
        for kind in ("online", "offline", "persistence"):
            assert set(r[kind]) >= {"re_n2_pct", "re_ninf_pct"} and r[kind]["re_n2_pct"] > 0
        assert r["online"]["re_n2_pct"] < r["offline"]["re_n2_pct"]  # 000 Table 4, rate rows
        assert r["identifier"]["covariance_resets"] == 0 and len(r["weights_final"]) == 9
        # the checks of decisions 0082-0083: a sound offline model is scored as is; the verdict on
        # y(k-1) agrees with the figures and carries reasons only when online loses
        assert r["offline_check"]["status"] == "ok" and r["offline_check"]["reasons"] == []
        assert r["identifier"]["divergence_resets"] == 0 and r["poles_final"]["max_radius"] <= 0.999
        vs = r["online_vs_persistence"]
        assert vs["verdict"] == ("better" if r["online"]["re_n2_pct"] <= r["persistence"]["re_n2_pct"] else "worse")
        assert bool(vs["reasons"]) == (vs["verdict"] == "worse")
    assert doc["offline"]["status"] == "ok" and doc["left_out"] == []  # simulated runs: history known
    assert runs[1]["online"]["re_n2_pct"] < runs[1]["persistence"]["re_n2_pct"]  # 5 Hz: more than the lags
    assert png.stat().st_size > 10_000


def test_saved_run_holds_online_output_and_weights(live):
    doc, _, out, _ = live
    recording = Recording(out)
    assert [r.name for r in recording] == doc["output_runs"] == ["0001-online-sine-frequency_hz=1",
                                                                 "0002-online-sine-frequency_hz=5"]
    for saved, r in zip(recording, doc["runs"]):
        assert saved.status == "complete" and saved.attrs["source_run"] == r["run"]
        names = [f"weight_p{i}" for i in range(4)] + [f"weight_q{j}" for j in range(1, 6)]
        assert set(names + ["time", "input", "output", "online_output", "offline_output", "u_r"]) <= set(saved.channels)
        data = saved.data()
        assert data["output"].size == r["samples"]
        np.testing.assert_array_equal([data[n][-1] for n in names], [r["weights_final"][n[7:]] for n in names])
        spans = json.loads(saved.attrs["scored_rows"])
        rows = np.zeros(r["samples"], bool)
        for a, b in zip(spans[::2], spans[1::2]):
            rows[a:b] = True
        for channel, kind in (("online_output", "online"), ("offline_output", "offline")):
            got = metrics(data["output"][rows], data[channel][rows])["re_n2_pct"]
            assert got == pytest.approx(r[kind]["re_n2_pct"], rel=1e-12)


def test_replay_of_the_recording_gives_the_same_comparison(live):
    doc, rec, _, _ = live
    again = run_ok("online", str(rec), "--train", "ramped-sine", *FAST)
    assert again["mode"] == "recording"
    for a, b in zip(doc["runs"], again["runs"]):
        assert a["online"] == b["online"] and a["offline"] == b["offline"] and a["persistence"] == b["persistence"]
    # other orders and forgetting: the same held offline model, another identifier
    other = run_ok("online", str(rec), "--train", "ramped-sine", "--orders", "2,3", "--forgetting", "0.999",
                   "--delta", "1e3", *FAST)
    assert other["online"]["weights"] == ["p0", "p1", "p2", "q1", "q2", "q3"]
    for a, b in zip(doc["runs"], other["runs"]):
        assert a["offline"] == b["offline"] and a["online"] != b["online"]


def test_text_report_and_errors(live):
    _, rec, _, _ = live
    result = runner.invoke(app, ["online", str(rec), "--train", "ramped-sine", *FAST])
    assert result.exit_code == 0, result.output
    assert "re_N2 %" in result.stdout and "y(k-1)" in result.stdout and "0003-sine-frequency_hz=5" in result.stdout
    assert "--orders" in run_error("online", str(rec), "--orders", "3")
    assert "--forgetting" in run_error("online", str(rec), "--forgetting", "1.5")
    assert "no run 'nope'" in run_error("online", str(rec), "--train", "nope")
    assert "no run is left" in run_error("online", str(rec), "--train", "1", "--train", "2", "--train", "3")
