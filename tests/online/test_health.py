"""A run's health figures and verdict (:mod:`hilbench.online.health`) on constructed runs."""

from __future__ import annotations

import numpy as np
import pytest

from hilbench.online.health import DEGRADED_EXIT, health_line, run_health


class _Model:
    def __init__(self, validation: float | None, train: float | None = None, rmse_um: float | None = None):
        metrics = {}
        if validation is not None:
            metrics["validation"] = {"erms_pct": validation} | ({"rmse": rmse_um} if rmse_um is not None else {})
        if train is not None:
            metrics["train"] = {"erms_pct": train}
        self.info = {"metrics": metrics} if metrics else {}


def test_limits_and_slew_are_counted_apart() -> None:
    n = 1000
    command = np.linspace(0.0, 5.0, n)
    command[:30] = -1.0  # at the low end of the command range: 3 %
    applied = np.clip(command, -1.0, 10.0)
    applied[500:505] -= 0.01  # the slew limiter held these back: 0.5 %
    h = run_health(command, applied, (-1.0, 10.0), (-1.0, 10.0), 0.1, _Model(0.05))
    assert h["at_limit_samples"] == 30 and h["slew_limited_samples"] == 5
    assert h["at_limit_pct"] == pytest.approx(3.0) and h["slew_limited_pct"] == pytest.approx(0.5)
    assert h["degraded"] and len(h["reasons"]) == 1 and "limit" in h["reasons"][0]
    assert "DEGRADED" in health_line(h)


def test_the_error_threshold_is_twice_the_model_or_three_tenths_more() -> None:
    u = np.linspace(0.0, 1.0, 100)
    ok = run_health(u, u, (-1.0, 2.0), (-1.0, 2.0), 0.34, _Model(0.05))
    assert ok["erms_allowed_pct"] == pytest.approx(0.35) and not ok["degraded"]
    bad = run_health(u, u, (-1.0, 2.0), (-1.0, 2.0), 2.1, _Model(1.0))
    assert bad["erms_allowed_pct"] == pytest.approx(2.0) and bad["degraded"] and "erms" in bad["reasons"][0]
    train = run_health(u, u, (-1.0, 2.0), (-1.0, 2.0), 0.1, _Model(None, 0.02))
    assert train["model_erms_split"] == "train" and not train["degraded"]
    unknown = run_health(u, u, (-1.0, 2.0), (-1.0, 2.0), 50.0, _Model(None))
    assert unknown["model_erms_pct"] is None and not unknown["degraded"]
    assert "unknown" in health_line(unknown) and health_line(unknown).endswith("- ok")
    assert DEGRADED_EXIT == 3


def test_the_model_error_is_put_on_the_reference_span_before_it_is_compared() -> None:
    # a model scored at 0.5 um rms over a 100 um recorded range (0.5 %); a reference over 40 um of it
    # tracked at the same 0.5 um rms is 1.25 % of its span: the model's own error on that span
    u = np.linspace(0.0, 1.0, 100)
    model = _Model(0.5, rmse_um=0.5)
    same = run_health(u, u, (-1.0, 2.0), (-1.0, 2.0), 1.25, model, reference_span_um=40.0)
    assert same["model_erms_on_reference_pct"] == pytest.approx(1.25)
    assert same["erms_allowed_pct"] == pytest.approx(2.5) and not same["degraded"]
    assert "0.5 um" in health_line(same) and "1.25 % of the reference's span" in health_line(same)
    # three times the model's error in um is degraded whatever the span
    worse = run_health(u, u, (-1.0, 2.0), (-1.0, 2.0), 3.75, model, reference_span_um=40.0)
    assert worse["degraded"] and "rmse 0.5 um" in worse["reasons"][0]
    # on the compared span the model's erms_pct alone would have flagged the first run (1.25 > 1.0)
    assert run_health(u, u, (-1.0, 2.0), (-1.0, 2.0), 1.25, _Model(0.5))["degraded"]
