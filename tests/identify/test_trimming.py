"""Whole measured captures: the rest before the excitation is left out where the history is unknown,
said in the notes, overridable; run names from import are accepted in short forms."""

from __future__ import annotations

import numpy as np
import pytest

from hilbench.errors import DataError, UserError
from hilbench.identify.dataset import Dataset
from hilbench.identify.fitting import fit
from hilbench.identify.trimming import Trim, leading_rest, parse_window, unsettled_rest
from hilbench.recording.hdf5 import RecordingWriter

FS = 2000.0
UNITS = {"time": "s", "input": "V", "output": "um"}


def _pi(u: np.ndarray) -> np.ndarray:
    r = np.array([0.0, 10.0, 25.0, 40.0])
    w = np.array([0.05, 0.02, 0.015, 0.01])
    ops = np.zeros(r.size)
    out = np.empty(u.size)
    for k, x in enumerate(u):
        ops = np.maximum(x - r, np.minimum(x + r, ops))
        out[k] = ops @ w
    return out


def _capture(path, names=("20_hz_no_lp", "40_hz_no_lp"), rest_s=1.0, seed=0):
    """Imported-style captures: a rest at -90 V after a power-on step the input does not show, then sines."""
    rng = np.random.default_rng(seed)
    writer = RecordingWriter(path)
    for name, f in zip(names, (2.0, 4.0)):
        t = np.arange(0, rest_s + 3.0, 1 / FS)
        u = np.where(t < rest_s, -90.0, -90.0 * np.cos(2 * np.pi * f * (t - rest_s)))
        y = _pi(u)
        # the power-on step from 0 V: the output starts at 0 and settles to the rest level over 50 ms,
        # while the recorded input is -90 V from the first sample
        y = y + (0.0 - y[0]) * np.exp(-t / 0.02) * (t < rest_s)
        y = y + rng.normal(0, 0.01, t.size)
        writer.write_run(name, {"time": t, "input": u, "output": y}, UNITS, experiment="import", excitation="",
                         sample_rate_hz=FS)
    return path


def test_leading_rest_is_found_only_before_the_excitation():
    t = np.arange(0, 3.0, 1 / FS)
    u = np.where(t < 1.0, -90.0, -90.0 * np.cos(2 * np.pi * 2.0 * (t - 1.0)))
    k = leading_rest(u, FS)
    assert abs(k / FS - 1.0) < 0.02
    assert leading_rest(-90.0 * np.cos(2 * np.pi * 2.0 * t), FS) == 0  # moving from the first sample
    assert leading_rest(np.where(t < 0.05, 0.0, 1.0), FS) == 0  # a 50 ms pre-trigger is part of a step test


def test_the_rest_of_an_imported_capture_is_left_out_and_said(tmp_path):
    path = _capture(tmp_path / "whole.h5")
    data = Dataset.load(path)
    whole = fit(data, "pi", train=["20hz"], test=["40hz"])
    trimmed = fit(data.trimmed(Trim(auto=True)), "pi", train=["20hz"], test=["40hz"])
    assert any("left out 0-1" in n and "rests at -90" in n for n in trimmed.notes)
    # the power-on transient dominated the error of the whole capture; the excitation is what it is about
    assert trimmed.metrics["validation"]["rmse"] < 0.5 * whole.metrics["validation"]["rmse"]
    kept = fit(data.trimmed(Trim(auto=True, from_s=0.0)), "pi", train=["20hz"], test=["40hz"])
    assert kept.metrics["validation"]["rmse"] == pytest.approx(whole.metrics["validation"]["rmse"])


def test_user_windows_and_their_errors(tmp_path):
    path = _capture(tmp_path / "whole.h5")
    data = Dataset.load(path).trimmed(Trim(windows=[parse_window("20hz:0-1.2"), parse_window("2.5-end")]))
    result = fit(data, "pi", train=["20hz"], test=["40hz"])
    train_run = next(r for r in result.runs if r.key.endswith("20_hz_no_lp"))
    t = np.arange(len(train_run.data)) / FS
    assert not train_run.train[(t < 1.2) | (t >= 2.5)].any() and train_run.train[(t >= 1.2) & (t < 2.5)].all()
    for bad in ("abc", "2-1", "x:1"):
        with pytest.raises(UserError, match="--exclude"):
            parse_window(bad)


def test_short_run_names_and_a_clear_error_listing_the_runs(tmp_path):
    path = _capture(tmp_path / "whole.h5")
    result = fit(path, "pi", train=["20hz"], test=["40HZ"])
    assert [r.role for r in result.runs] == ["train", "validation"]
    with pytest.raises(DataError, match=r"no run '100hz'.*available runs: 0001-20_hz_no_lp, 0002-40_hz_no_lp"):
        fit(path, "pi", train=["100hz"])
    with pytest.raises(DataError, match="short for several runs"):
        fit(path, "pi", train=["0"])  # the start of both group names


def test_a_capture_that_starts_settled_keeps_its_rest(tmp_path):
    """A rest whose output does not move on its own is data like any other (a virgin actuator at rest)."""
    t = np.arange(0, 4.0, 1 / FS)
    u = np.where(t < 1.0, 0.0, 90.0 * np.sin(2 * np.pi * 2.0 * (t - 1.0)))
    y = _pi(u) + np.random.default_rng(5).normal(0, 0.01, t.size)
    path = tmp_path / "settled.h5"
    RecordingWriter(path).write_run("r", {"time": t, "input": u, "output": y}, UNITS, experiment="import",
                                    excitation="", sample_rate_hz=FS)
    data = Dataset.load(path).trimmed(Trim(auto=True))
    assert data.keep is not None and data.keep[0].all()
    assert not any("left out" in n for n in data.notes)


def _rest_with_channel(transient_um: float, follows_um: float, seed: int = 3) -> tuple[np.ndarray, np.ndarray, int]:
    """A 0.5 s rest then a sine; the output follows a recorded temperature by ``follows_um`` per
    degC and, when ``transient_um``, starts away from its rest level by a decaying power-on step."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, 2.0, 1 / FS)
    rest = int(0.5 * FS)
    u = np.where(t < 0.5, 0.0, 50.0 * np.sin(2 * np.pi * 2.0 * (t - 0.5)))
    temperature = 25.0 + 3.0 * np.sin(2 * np.pi * 2.0 * t) + rng.normal(0, 0.05, t.size)  # one cycle per rest
    y = _pi(u) + follows_um * (temperature - 25.0) + transient_um * np.exp(-t / 0.03) + rng.normal(0, 0.01, t.size)
    return y, temperature, rest


def test_a_rest_the_recorded_temperature_moves_is_data_not_an_unknown_history():
    """Decision 0073: the input holds still, but a cycling temperature moves the output; the channel
    explains that movement, so the rest is kept (without the channel it looks like a power-on step)."""
    y, temperature, rest = _rest_with_channel(transient_um=0.0, follows_um=0.05)
    assert unsettled_rest(y, rest)  # the output moves during the rest ...
    assert not unsettled_rest(y, rest, [temperature])  # ... as the recorded temperature makes it


def test_a_power_on_step_stays_unsettled_beside_a_moving_channel():
    y, temperature, rest = _rest_with_channel(transient_um=1.0, follows_um=0.05)
    assert unsettled_rest(y, rest, [temperature])  # the channel explains the cycle, not the decay
    noise_only = np.random.default_rng(4).normal(25.0, 0.05, y.size)
    y_step, _, _ = _rest_with_channel(transient_um=1.0, follows_um=0.0)
    assert unsettled_rest(y_step, rest, [noise_only])  # a channel that does not move explains nothing


def test_the_trim_reads_the_runs_channels(tmp_path):
    y, temperature, rest = _rest_with_channel(transient_um=0.0, follows_um=0.05)
    t = np.arange(y.size) / FS
    u = np.where(t < 0.5, 0.0, 50.0 * np.sin(2 * np.pi * 2.0 * (t - 0.5)))
    path = tmp_path / "temperature.h5"
    RecordingWriter(path).write_run("r", {"time": t, "input": u, "output": y, "temperature": temperature},
                                    {**UNITS, "temperature": "degC"}, experiment="import", excitation="",
                                    sample_rate_hz=FS)
    data = Dataset.load(path).trimmed(Trim(auto=True))
    assert data.keep is not None and data.keep[0].all()
    assert not any("left out" in n for n in data.notes)
