"""Tests for hilbench.report.plotting: time traces and loops of recorded runs as PNG."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from hilbench.errors import DataError  # noqa: E402
from hilbench.recording.importers import import_files, parse_mapping  # noqa: E402
from hilbench.report.plotting import make_figure, plot_runs  # noqa: E402
from tests.conftest import require_real_data
from hilbench.recording.hdf5 import RecordingWriter  # noqa: E402

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"




def _recording(path: Path, n_runs: int = 1, n: int = 1000, aux: bool = False, label: str = "loop") -> Path:
    writer = RecordingWriter(path)
    for k in range(n_runs):
        t = np.arange(n) / 1000.0
        u = 10 * np.sin(2 * np.pi * 5 * t)
        data = {"time": t, "input": u, "output": 0.5 * u + 0.1 * np.cos(2 * np.pi * 5 * t)}
        units = {"time": "s", "input": "V", "output": "um"}
        if aux:
            data["temperature"] = 25 + t
            units["temperature"] = "degC"
        writer.write_run(f"{label}{k}", data, units, experiment="test", excitation={"kind": "sine"}, sample_rate_hz=1000.0)
    return path


def _labels(fig: plt.Figure) -> set[str]:
    return {a.get_xlabel() for a in fig.axes} | {a.get_ylabel() for a in fig.axes}


def test_plot_writes_a_png(tmp_path: Path) -> None:
    rec = _recording(tmp_path / "rec.h5", n_runs=2)
    out = plot_runs(rec, tmp_path / "figs" / "rec.png")
    assert out == tmp_path / "figs" / "rec.png"
    assert out.read_bytes()[:8] == PNG_SIGNATURE
    assert out.stat().st_size > 5000


def test_figure_has_units_titles_and_one_row_per_run(tmp_path: Path) -> None:
    rec = _recording(tmp_path / "rec.h5", n_runs=2)
    fig = make_figure(rec)
    try:
        assert {"time [s]", "input [V]", "output [um]"} <= _labels(fig)
        titles = " ".join(a.get_title() for a in fig.axes)
        assert "0001-loop0" in titles and "0002-loop1" in titles
        # two runs x (trace + twin + loop) axes, no auxiliary panel
        assert len(fig.axes) == 6
    finally:
        plt.close(fig)


def test_aux_channels_get_their_panel(tmp_path: Path) -> None:
    fig = make_figure(_recording(tmp_path / "rec.h5", aux=True))
    try:
        legends = [t.get_text() for a in fig.axes if a.get_legend() for t in a.get_legend().get_texts()]
        assert "temperature [degC]" in legends
        assert "[degC]" in _labels(fig)
    finally:
        plt.close(fig)


def test_select_runs_by_label(tmp_path: Path) -> None:
    fig = make_figure(_recording(tmp_path / "rec.h5", n_runs=3), runs=["loop2"])
    try:
        titles = " ".join(a.get_title() for a in fig.axes)
        assert "loop2" in titles and "loop0" not in titles
        assert len(fig.axes) == 3
    finally:
        plt.close(fig)


def test_long_runs_are_decimated(tmp_path: Path) -> None:
    fig = make_figure(_recording(tmp_path / "rec.h5", n=10_000), max_points=1000)
    try:
        lengths = [len(line.get_xdata()) for a in fig.axes for line in a.get_lines()]
        assert lengths and max(lengths) <= 1000
        assert min(lengths) >= 900
        assert "1 in 10 drawn" in " ".join(a.get_title() for a in fig.axes)
    finally:
        plt.close(fig)


def test_at_most_twelve_runs_by_default(tmp_path: Path) -> None:
    fig = make_figure(_recording(tmp_path / "rec.h5", n_runs=13, n=50))
    try:
        assert len(fig.axes) == 12 * 3
        assert "first 12 of 13 runs" in fig.get_suptitle()
    finally:
        plt.close(fig)


def test_unknown_run_is_refused(tmp_path: Path) -> None:
    rec = _recording(tmp_path / "rec.h5")
    with pytest.raises(DataError) as exc:
        plot_runs(rec, tmp_path / "x.png", runs=["nope"])
    assert "no run 'nope'" in str(exc.value) and "0001-loop0" in str(exc.value)
    assert not (tmp_path / "x.png").exists()


def test_run_without_output_is_refused(tmp_path: Path) -> None:
    rec = tmp_path / "rec.h5"
    RecordingWriter(rec).write_run(
        "raw", {"time": np.arange(3.0), "input": np.ones(3), "load": np.zeros(3)}, {"time": "s", "input": "V", "load": "N"},
        experiment="test", excitation={}, sample_rate_hz=1.0,
    )
    with pytest.raises(DataError) as exc:
        plot_runs(rec, tmp_path / "x.png")
    message = str(exc.value)
    assert "0001-raw" in message and "'output'" in message and "time, input, load" in message
    assert not (tmp_path / "x.png").exists()


def test_missing_recording_is_refused(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="file not found"):
        plot_runs(tmp_path / "none.h5", tmp_path / "x.png")


def test_real_data_plots(tmp_path: Path) -> None:
    real = require_real_data()
    rec = tmp_path / "real.h5"
    import_files([real / "piezo-stack-150V-1Hz" / "hysteresis_v_150_1hz.csv"], rec,
                 mapping=parse_mapping(["1=time[s]", "2=output[um]", "3=input[V]"]))
    import_files([real / "piezo-dspace-preisach" / "20_hz_no_lp.mat"], rec,
                 mapping=parse_mapping(["Y(3)=input[V]", "Y(1)=output[um]"]))
    out = plot_runs(rec, tmp_path / "real.png")
    assert out.read_bytes()[:8] == PNG_SIGNATURE
    assert out.stat().st_size > 20_000
