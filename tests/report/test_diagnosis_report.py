"""The HTML report of a diagnosis (hilbench.report.diagnosis_report)."""

from __future__ import annotations

import dataclasses
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from hilbench.cli import app
from hilbench.diagnosis.diagnose import diagnose
from hilbench.diagnosis.verdict import Candidate
from hilbench.report.diagnosis_report import render, spectra, write_report
from hilbench.identify.metrics import METRIC_KEYS
from tests.browser import chromium

SINE = "sine:amplitude=5,offset=5,phase_deg=-90,frequency_hz=1,cycles=4"
HEADINGS = ("Metrics", "Where the error is", "Candidate effects", "Untestable effects", "Steps", "Figures",
            "Measured vs model loops", "Error over time", "Error against input", "Error amplitude spectrum",
            "share %", "expected gain %", "validation rmse", "p_value")


@pytest.fixture(scope="module")
def diagnosis(tmp_path_factory: pytest.TempPathFactory):
    folder = tmp_path_factory.mktemp("report")
    h5 = folder / "sine.h5"
    out = CliRunner().invoke(app, ["sweep", "piezo-pmpi", "-e", SINE, "-o", str(h5)])
    assert out.exit_code == 0, out.output
    return diagnose(h5, "linear", auto=True)


@pytest.fixture(scope="module")
def report(diagnosis, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_report(diagnosis, tmp_path_factory.mktemp("out") / "nested")


def test_report_is_one_self_contained_html_file(report: Path) -> None:
    assert report.name == "report.html" and report.is_file()
    assert [p.name for p in report.parent.iterdir()] == ["report.html"]
    text = report.read_text(encoding="utf-8")
    assert text.startswith("<!DOCTYPE html>") and text.rstrip().endswith("</html>")
    assert "<script" not in text.lower()
    assert "<style>" in text and "<link" not in text.lower()
    # every src is an embedded PNG: no external file or URL
    srcs = re.findall(r"src=['\"]([^'\"]*)", text)
    assert srcs and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert text.count("data:image/png;base64,") >= 5


def test_report_content(report: Path, diagnosis) -> None:
    text = report.read_text(encoding="utf-8")
    assert len(diagnosis.rounds) > 1 and diagnosis.steps  # auto added effects: before/after figures
    for step in diagnosis.steps:
        assert f"<td>{step['spec']}</td>" in text
    for heading in HEADINGS:
        assert heading in text, heading
    for key in METRIC_KEYS:
        assert f"<td>{key}</td>" in text
    assert "before train (linear)" in text and f"after validation ({diagnosis.spec})" in text
    assert diagnosis.result.runs[0].data.source["file"] in text  # the data file
    for u in diagnosis.untestable:
        assert u["effect"] in text
    for c in diagnosis.effects:
        assert c.effect in text
    # 4 figures of the first model and 4 of the final one
    assert text.count("data:image/png;base64,") == 8


def test_single_round_has_no_before_after(diagnosis, tmp_path: Path) -> None:
    one = dataclasses.replace(diagnosis, rounds=[diagnosis], steps=[])
    text = write_report(one, tmp_path).read_text(encoding="utf-8")
    assert text.count("data:image/png;base64,") == 4
    assert "before:" not in text and "before train" not in text and "Steps (before" not in text


def test_text_is_escaped(diagnosis) -> None:
    evil = Candidate("<script>alert(1)</script>", "pi&co", False, 0.5, "a < b & <b>c</b>",
                     {"p_value": 0.5, "note": "<img src=x onerror=1>"})
    bad = dataclasses.replace(diagnosis, effects=[evil], rounds=[diagnosis], steps=[],
                              untestable=[{"effect": "<i>", "reason": "\"quoted\" & <tag>"}])
    text = render(bad)
    assert "<script" not in text and "<img src=x" not in text and "<i>" not in text
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in text and "a &lt; b &amp; &lt;b&gt;c&lt;/b&gt;" in text


def test_spectra_find_the_error_frequency(diagnosis) -> None:
    run = diagnosis.rounds[0].result.runs[0]  # linear: the error is mostly at the 1 Hz drive
    s = spectra(run)
    assert s["f"].size > 10 and np.all(np.isfinite(s["amplitude"]))
    peak = s["f"][1:][np.argmax(s["amplitude"][1:])]
    assert 0.3 <= peak <= 3.0
    assert s["excited"].any() and np.all(s["gain"][s["excited"]] > 0)


def test_report_renders_in_chromium(report: Path, tmp_path: Path) -> None:
    browser = chromium()
    if browser is None:
        pytest.skip("chromium is not installed")
    png = tmp_path / "report.png"
    cmd = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--disable-component-update", "--disable-sync", "--no-first-run", f"--user-data-dir={tmp_path / 'profile'}",
           f"--screenshot={png}", "--window-size=1400,4000", report.resolve().as_uri()]
    try:
        subprocess.run(cmd, capture_output=True, timeout=120, check=False)
    except subprocess.TimeoutExpired:
        pytest.skip("chromium did not finish in 120 s")
    assert png.is_file() and png.stat().st_size > 50_000
    image = pytest.importorskip("PIL.Image")
    with image.open(png) as im:
        assert im.size == (1400, 4000)
        # the page is not blank: many distinct colours (tables, figures)
        colours = im.convert("RGB").resize((350, 1000)).getcolors(maxcolors=1 << 20)
        assert colours is not None and len(colours) > 200
