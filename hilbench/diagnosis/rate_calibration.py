"""Rate effects when the training runs hold one drive rate (``hilbench diagnose --train``).

A delay or a dynamic lag adds phase lag proportional to the drive frequency. At one drive
frequency that lag is indistinguishable from loop width, so a fit on one rate learns it as
hysteresis and mispredicts every other rate (piezo-dspace-preisach: ``pi`` trained at 20 Hz,
validated at 40 and 100 Hz). When the validation runs hold two or more other drive rates, the
effect's shape (delay in s, corner or natural frequency) is *calibrated* on the training runs plus
the validation runs at the nearer rates, then fixed, and the model is refitted on the training runs
alone; the validation runs at the farthest rate, which no fit saw, *confirm* it. The fixed shape is
written into the spec (``pi+delay(seconds=0.000176)``), so the result is reproducible and
``--add``/``--auto`` carry it on. See docs/decisions/0006-rate-effects-from-one-training-rate.md.

When validation holds only one other rate, a power-on step at the start of a training run (the
command at its first level from the first sample, the output moving to it with the actuator's own
transient: :mod:`hilbench.identify.power_on`) is a step response recorded at no drive rate at all:
its dead time and ringing calibrate ``delay`` and ``dynamics``, and every validation run confirms
(decision 0015).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hilbench.diagnosis.input_motion import half_cycle_frequencies, motion
from hilbench.identify.power_on import PowerOnStep, power_on_step
from hilbench.identify.trimming import leading_rest, unsettled_rest

if TYPE_CHECKING:
    from hilbench.identify.fitting import FitResult, FitRun

#: drive frequencies closer than this ratio count as one rate
RATE_RATIO = 1.5
#: the effects whose shape is calibrated this way: all their shape is a few rate parameters
CALIBRATED_EFFECTS = ("dynamics", "delay")


@dataclass
class RatePlan:
    """Which runs calibrate and which confirm a rate effect; drive frequencies in Hz."""

    train: list[str]
    calibrate: list[str]
    confirm: list[str]
    training_hz: float
    calibrate_hz: list[float]
    confirm_hz: list[float]
    #: calibration from a power-on step response instead of calibrating runs (``calibrate`` is empty)
    step: PowerOnStep | None = None
    step_run: str = ""

    @property
    def calibrated_by(self) -> str:
        """Where the shape comes from, for the verdict's sentence."""
        if self.step is not None:
            s = self.step
            return (f"the power-on step of {self.step_run} (dead time {1e3 * s.dead_time_s:.3g} ms from the record "
                    f"start, ringing {s.natural_frequency_hz:.3g} Hz, zeta {s.zeta:.2g}, R^2 {s.r2:.4f})")
        return f"{'/'.join(f'{f:.3g}' for f in self.calibrate_hz)} Hz"

    def describe(self) -> str:
        def hz(values: Sequence[float]) -> str:
            return "/".join(f"{v:.3g}" for v in values) + " Hz"

        source = f"{', '.join(self.calibrate)} ({hz(self.calibrate_hz)})" if self.step is None else self.calibrated_by
        return f"calibrated on {source}, confirmed on {', '.join(self.confirm)} ({hz(self.confirm_hz)})"

    def to_json(self) -> dict[str, Any]:
        out = {"training_hz": self.training_hz, "calibrated_on": self.calibrate, "calibrate_hz": self.calibrate_hz,
               "confirmed_on": self.confirm, "confirm_hz": self.confirm_hz}
        if self.step is not None:
            out["power_on_step"] = {"run": self.step_run, **self.step.to_json()}
        return out


def _drive_hz(runs: Sequence[FitRun], span: float) -> float:
    """Median half-cycle drive frequency over the runs (Hz); NaN without reversals."""
    f = [half_cycle_frequencies(motion(r.data.input, r.data.sample_rate_hz, span)["flips"], r.data.sample_rate_hz)
         for r in runs]
    cat = np.concatenate(f) if f else np.zeros(0)
    return float(np.median(cat)) if cat.size else float("nan")


def _ratio(a: float, b: float) -> float:
    return max(a / b, b / a)


def rate_plan(result: FitResult) -> tuple[RatePlan | None, str]:
    """The calibrate/confirm split of the validation runs, or None and the reason there is none."""
    runs = [r for r in result.runs if len(r.data) and (r.train.any() or r.validation.any())]
    if any(r.train.any() and r.validation.any() for r in runs):
        return None, "runs are split in time, so validation holds the training's rates"
    span = max(float(np.ptp(np.concatenate([r.data.input for r in runs]))), 1e-12)
    train = [r for r in runs if r.train.any()]
    f_train = _drive_hz(train, span)
    if not np.isfinite(f_train):
        return None, "the training runs have no input reversals"
    other = []
    for r in runs:
        if r.validation.any():
            f = _drive_hz([r], span)
            if np.isfinite(f) and _ratio(f, f_train) >= RATE_RATIO:
                other.append((f, r.key))
    # group the other rates: sorted, a new group where the frequency jumps by RATE_RATIO or more
    other.sort()
    groups: list[list[tuple[float, str]]] = []
    for f, key in other:
        if groups and f / groups[-1][-1][0] < RATE_RATIO:
            groups[-1].append((f, key))
        else:
            groups.append([(f, key)])
    if len(groups) < 2:
        step_plan = _power_on_plan(train, runs, f_train, span)
        if step_plan is not None:
            return step_plan, ""
        seen = ", ".join(f"{f:.3g} Hz" for f, _ in other) or "none"
        return None, (f"validation holds fewer than two other drive rates (training {f_train:.3g} Hz, other rates: "
                      f"{seen}) and no training run starts with a power-on step, so a rate effect cannot be "
                      "calibrated on one and confirmed on another")
    far = max(groups, key=lambda g: _ratio(float(np.median([f for f, _ in g])), f_train))
    near = [item for g in groups if g is not far for item in g]
    return RatePlan(train=[r.key for r in train], calibrate=[k for _, k in near], confirm=[k for _, k in far],
                    training_hz=f_train, calibrate_hz=[f for f, _ in near], confirm_hz=[f for f, _ in far]), ""


def _power_on_plan(train: Sequence[FitRun], runs: Sequence[FitRun], f_train: float, span: float) -> RatePlan | None:
    """A plan calibrated on the cleanest power-on step among the training runs, confirmed on every
    validation run; None without one."""
    best: tuple[PowerOnStep, str] | None = None
    for r in train:
        fs = r.data.sample_rate_hz
        rest = leading_rest(r.data.input, fs)
        if not rest or not unsettled_rest(r.data.output, rest, list(r.data.aux.values())):
            continue
        step = power_on_step(r.data.output, fs, rest)
        if step is not None and (best is None or step.r2 > best[0].r2):
            best = (step, r.key)
    if best is None:
        return None
    confirm = [r for r in runs if r.validation.any()]
    confirm_hz = [_drive_hz([r], span) for r in confirm]
    return RatePlan(train=[r.key for r in train], calibrate=[], confirm=[r.key for r in confirm], training_hz=f_train,
                    calibrate_hz=[], confirm_hz=[f for f in confirm_hz if np.isfinite(f)], step=best[0],
                    step_run=best[1])


def calibrated_spec(paths: Any, base_spec: str, effect: str, plan: RatePlan) -> tuple[str, FitResult | None]:
    """``base_spec`` plus ``effect`` with its shape fitted on training + calibration runs and fixed
    (every shape parameter written as an option), and that calibration fit; with a power-on step,
    the shape read off the step (no calibration fit)."""
    from hilbench.identify.fitting import fit

    name = effect.split("(", 1)[0].strip()
    if plan.step is not None:
        s = plan.step
        if name == "delay":
            return f"{base_spec}+delay(seconds={s.dead_time_s:.6g})", None
        return (f"{base_spec}+dynamics(kind=second-order,natural_frequency_hz={s.natural_frequency_hz:.6g},"
                f"zeta={s.zeta:.6g})"), None

    probe = fit(paths, f"{base_spec}+{effect}", train=plan.train + plan.calibrate, test=plan.confirm)
    component = probe.model.effect(name)
    assert component is not None, (effect, probe.spec)
    options = {**{k: v for k, v in component.options.items()}, **{p.name: f"{p.value:.6g}" for p in component.params}}
    fixed = f"{name}({','.join(f'{k}={v}' for k, v in options.items())})"
    return f"{base_spec}+{fixed}", probe


__all__ = ["CALIBRATED_EFFECTS", "RATE_RATIO", "RatePlan", "calibrated_spec", "rate_plan"]
