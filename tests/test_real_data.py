"""Validation on third-party measured data (``../shared/data/real``); skipped when it is absent.

The files are imported into temporary recordings with :func:`hilbench.recording.importers.import_files`
(never copied into the project) and fitted as the issue asks:

* ``piezo-stack-150V-1Hz``: one 10 s record at 5 kHz. The command is 0 V until 3.257 s (the
  output rests at -1.68 um), then a 150 V, 1 Hz sine starts mid-phase (a step to -87 V followed by
  ~0.05 s of ringing at ~875 Hz). Trained on the first 70 % of the samples, validated on the last
  30 % (t >= 7.0 s, three full cycles the fit never sees), in two ways:

  - the whole record with :func:`hilbench.identify.fitting.fit`'s default split: the idle rows are 46 % of
    the training rows and pin the model's offset to the resting value, so a plain 16-operator PI
    validates at ~2.0 % with a constant -0.78 um error;
  - the idle part excluded from training (the model still runs through it): a plain PI validates at
    ~0.32 %, the best spec at ~0.14 %.

* ``piezo-dspace-preisach``: the 20, 40 and 100 Hz identification captures (10 kHz), one run each.
  The command reads -90 V from the first sample and rests there for 1.5 s; the output starts at
  +0.12 um and rings at ~730 Hz for ~0.05 s: the rig stepped 0 V -> -90 V at t = 0. Training is
  the active part (t >= 1.5 s) of the 20 Hz run, validation the active parts of the 40 Hz and
  100 Hz runs; the rest and the start-up are neither trained on nor scored (the model still runs
  through them). The only other use of data: the lag of the best spec is read off the first
  0.02 s of the 20 Hz run (the power-on step), see :func:`_startup_delay_s`.

Figures (erms_pct = rms error / measured range, in %) are in the closing note of the change and in
the README table; the thresholds below leave a margin over the measured values.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hilbench.identify.fitting import fit, load_runs
from hilbench.identify import fit_model
from hilbench.recording.importers import import_files
from hilbench.identify.metrics import metrics
from hilbench.models import Model, RunData
from tests.conftest import require_real_data

STACK_CSV = ("piezo-stack-150V-1Hz", "hysteresis_v_150_1hz.csv")
STACK_MAP = {"1": "time[s]", "2": "output[um]", "3": "input[V]"}
DSPACE_DIR = "piezo-dspace-preisach"
DSPACE_FILES = ("20_hz_no_lp.mat", "40_hz_no_lp.mat", "100_hz_no_lp.mat")
DSPACE_MAP = {"Y(3)": "input[V]", "Y(1)": "output[um]"}

#: best specs found (see the module docstring and the closing note for the full tables)
STACK_BEST = "pmpi+rate-dependence(form=damping)"
DSPACE_BEST = "pi(n=16)+asymmetry+creep(n=1)+delay(seconds={delay_s:.3g})"

DSPACE_FS_HZ = 10_000.0
DSPACE_ACTIVE_S = 1.5  # the excitation (cycles from -90 V up to rising maxima) starts here in all three


def _source(*parts: str) -> Path:
    path = require_real_data().joinpath(*parts)
    if not path.exists():
        pytest.skip(f"{path} not found")
    return path


@pytest.fixture(scope="module")
def stack_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    csv = _source(*STACK_CSV)
    out = tmp_path_factory.mktemp("real") / "piezo-stack.h5"
    import_files([csv], out, mapping=STACK_MAP)
    return out


@pytest.fixture(scope="module")
def dspace_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    files = [_source(DSPACE_DIR, name) for name in DSPACE_FILES]
    out = tmp_path_factory.mktemp("real") / "piezo-dspace.h5"
    import_files(files, out, mapping=DSPACE_MAP, run_names=["20hz", "40hz", "100hz"])
    return out


def _fit_masked(spec: str, fit_runs: list[RunData], train: list[np.ndarray]) -> Model:
    model = Model(spec)
    fit_model(model, fit_runs, train)
    return model


def _erms(model: Model, run: RunData, rows: np.ndarray) -> float:
    """erms_pct of the free-run simulation of the whole run, scored on ``rows``."""
    return metrics(run.output[rows], model.simulate(run)[rows])["erms_pct"]


# -- piezo-stack-150V-1Hz --------------------------------------------------------------------------


def test_stack_import_shape(stack_recording: Path) -> None:
    (run,) = load_runs(stack_recording)
    assert len(run) == 50_001
    assert run.sample_rate_hz == pytest.approx(5000.0)
    assert np.ptp(run.input) == pytest.approx(300.0)
    # the idle part the notes describe: 0 V until ~3.257 s
    first_active = int(np.flatnonzero(run.input != 0.0)[0])
    assert first_active / run.sample_rate_hz == pytest.approx(3.257, abs=0.002)


def test_stack_whole_record_default_split(stack_recording: Path) -> None:
    """The issue's protocol taken literally: ``fit`` with its default 70/30 split of the record."""
    plain = fit(stack_recording, "pi(n=16)")
    best = fit(stack_recording, STACK_BEST)
    plain_val = plain.metrics["validation"]["erms_pct"]
    best_val = best.metrics["validation"]["erms_pct"]
    assert 1.5 < plain_val < 2.5  # measured 2.02 %
    assert best_val < 1.0  # measured 0.15 %
    assert best_val < plain_val / 3
    # what the plain PI gets wrong is the offset: the idle rows pin it (measured -0.78 um)
    run = plain.runs[0]
    mean_error = float(np.mean(run.simulated[run.validation] - run.data.output[run.validation]))
    assert mean_error < -0.5


def test_stack_idle_excluded_from_training(stack_recording: Path) -> None:
    """Idle part (0 V) not trained on; the model still runs through it. Same validation rows."""
    (run,) = load_runs(stack_recording)
    rows = np.arange(len(run))
    cut = int(np.floor(0.7 * len(run)))
    first_active = int(np.flatnonzero(run.input != 0.0)[0])
    train = (rows >= first_active) & (rows < cut)
    validation = rows >= cut
    plain = _erms(_fit_masked("pi(n=16)", [run], [train]), run, validation)
    best = _erms(_fit_masked(STACK_BEST, [run], [train]), run, validation)
    assert plain < 0.6  # measured 0.32 %: without the idle rows a plain PI is already good
    assert best < 1.0  # measured 0.14 %
    assert best < 0.7 * plain


# -- piezo-dspace-preisach ------------------------------------------------------------------------


def _dspace_runs(path: Path) -> list[RunData]:
    runs = load_runs(path)
    assert [r.name for r in runs] == ["0001-20hz", "0002-40hz", "0003-100hz"]
    assert not any(r.chain for r in runs)  # imported runs start afresh
    return runs


def _after(run: RunData, seconds: float) -> np.ndarray:
    return np.arange(len(run)) >= int(round(seconds * run.sample_rate_hz))


def test_dspace_import_shape(dspace_recording: Path) -> None:
    runs = _dspace_runs(dspace_recording)
    assert [len(r) for r in runs] == [40_001, 27_501, 20_001]
    for r in runs:
        assert r.sample_rate_hz == pytest.approx(DSPACE_FS_HZ, rel=1e-5)
        rest = ~_after(r, DSPACE_ACTIVE_S)
        assert np.all(r.input[rest] == -90.0)  # the rest the notes describe
        assert np.ptp(r.input) == pytest.approx(180.0)
        # the capture starts at the 0-V position: the step to -90 V happens at t = 0
        assert abs(r.output[0]) < 0.5 and r.output[_after(r, 1.0)][0] < -3.0


def test_dspace_pi_shows_the_rate_effect(dspace_recording: Path) -> None:
    """``pi`` on the 20 Hz active part, as imported: worse at 40 Hz and worse still at 100 Hz."""
    runs = _dspace_runs(dspace_recording)
    active = [_after(r, DSPACE_ACTIVE_S) for r in runs]
    model = _fit_masked("pi", [runs[0]], [active[0]])
    train, at40, at100 = (_erms(model, r, m) for r, m in zip(runs, active))
    assert train < at40 < at100  # measured 1.12 / 1.26 / 1.68 %
    assert at100 > 1.2 * at40
    assert at100 > 1.0


def _startup_delay_s(run: RunData) -> float:
    """The actuator's lag (s) read off the power-on step at the start of a capture.

    The command steps 0 V -> -90 V at the first sample and the output rings (~730 Hz, second order,
    lightly damped) about its settled level; the first extreme of a second-order step response
    comes half a ringing period after the response starts, so lag = t(first extreme) - half period.
    """
    fs = run.sample_rate_hz
    y = run.output
    settled = float(np.median(y[int(0.1 * fs):int(DSPACE_ACTIVE_S * fs)]))
    e = y[: int(0.02 * fs)] - settled  # the first ~15 periods of the ringing
    k = np.flatnonzero(np.sign(e[:-1]) != np.sign(e[1:]))
    crossings = (k + e[k] / (e[k] - e[k + 1])) / fs  # interpolated, s
    half_period = (crossings[-1] - crossings[0]) / (len(crossings) - 1)
    i = k[0] + 1 + int(np.argmax(np.abs(e[k[0] + 1 : k[1] + 1])))
    a, b, c = np.abs(e[i - 1 : i + 2])
    first_extreme = (i + 0.5 * (a - c) / (a - 2 * b + c)) / fs
    return first_extreme - half_period


def test_dspace_best_spec_at_100_hz(dspace_recording: Path) -> None:
    """Best spec trained on the 20 Hz active part only, validated on the 40 and 100 Hz active parts.

    The lag that matters at 100 Hz (~0.12 ms, 0.015 rad of phase at 20 Hz) is not identifiable
    from the 20 Hz loops: searched freely, ``delay`` ends at 0.33 ms and the model validates at
    2.7 % at 100 Hz. It is read instead off the training run's own power-on step (its first
    0.02 s, not otherwise used) and fixed with ``delay(seconds=...)``.
    """
    runs = _dspace_runs(dspace_recording)
    active = [_after(r, DSPACE_ACTIVE_S) for r in runs]
    delay_s = _startup_delay_s(runs[0])
    assert 0.08e-3 < delay_s < 0.18e-3  # measured 0.116 ms (a joint fit of all three runs: 0.136 ms)
    best = _fit_masked(DSPACE_BEST.format(delay_s=delay_s), [runs[0]], [active[0]])
    at40, at100 = (_erms(best, r, m) for r, m in zip(runs[1:], active[1:]))
    assert at40 < 1.0  # measured 0.31 %
    assert at100 < 1.0  # measured 0.44 %
    # the rate effect matters at 100 Hz: the same model without the delay
    no_delay = _fit_masked(DSPACE_BEST.split("+delay")[0], [runs[0]], [active[0]])
    assert _erms(no_delay, runs[2], active[2]) > 2 * at100  # measured 1.57 %
    # and plain pi, same protocol
    plain = _fit_masked("pi", [runs[0]], [active[0]])
    assert _erms(plain, runs[2], active[2]) > 2 * at100  # measured 1.68 %
