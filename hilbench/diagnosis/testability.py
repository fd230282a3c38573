"""What the data can test: each effect of the registry against the data's excitation.

Each effect of :data:`hilbench.effects.EFFECTS` names its requirements; :data:`REQUIREMENTS` says
for each how it is checked and, when the data fall short, why the effect cannot be tested. Rate
effects are judged on the training rows, where their parameters are learned: several drive
frequencies there for rate-dependence, several frequencies or steps for dynamics and delay. With
one training rate, dynamics and delay are calibrated across the validation rates when those allow
it (:mod:`hilbench.diagnosis.rate_calibration`); rate-dependence is then untestable, unless the
one frequency comes at several amplitudes: those are several rates for its damping (decision 0064).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hilbench import effects as E
from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.input_motion import LOOP_HALF_CYCLES, LOOP_MIN_SPAN, excitation_summary
from hilbench.diagnosis.rate_calibration import RatePlan, rate_plan
from hilbench.identify.fitting import FitResult
from hilbench.identify.statistics import aux_variation
from hilbench.models.model import split_spec


def excitation(result: FitResult, role: str = "all") -> dict[str, Any]:
    """:func:`excitation_summary` of the rows that train (``role="train"``) or train or validate."""
    active = [r for r in result.runs if len(r.data) and (r.train.any() or r.validation.any())]
    span = max(float(np.ptp(np.concatenate([r.data.input for r in active]))), 1e-12)
    us = [r.data.input[r.train if role == "train" else (r.train | r.validation)] for r in active]
    return excitation_summary(us, active[0].data.sample_rate_hz, span)


def frequencies_text(ex: dict[str, Any]) -> str:
    return (f"{ex['frequencies_hz'][0]:.3g}-{ex['frequencies_hz'][1]:.3g} Hz, spread {ex['frequency_spread']:.2f}"
            if ex["frequencies_hz"] else "no input reversals")


def channel_reach(result: FitResult, channel: str) -> float:
    """How many times further a recorded channel moves on the validation rows than on the training
    rows: the rms deviation from the training rows' mean on each (1 when the channel does not move
    beyond its noise in training, AUX_MIN_VARIATION: a coefficient learned from noise has no reach)."""
    train = [r.data.aux[channel][r.train] for r in result.runs if channel in r.data.aux and r.train.any()]
    validation = [r.data.aux[channel][r.validation] for r in result.runs if channel in r.data.aux and r.validation.any()]
    if not train or not validation or aux_variation(train) < T.AUX_MIN_VARIATION:
        return 1.0
    a_t, a_v = np.concatenate(train), np.concatenate(validation)
    a_t, a_v = a_t[np.isfinite(a_t)], a_v[np.isfinite(a_v)]
    if not a_t.size or not a_v.size:
        return 1.0
    centre = float(np.mean(a_t))
    spread_t = float(np.sqrt(np.mean((a_t - centre) ** 2)))
    spread_v = float(np.sqrt(np.mean((a_v - centre) ** 2)))
    return max(1.0, spread_v / spread_t) if spread_t > 0 else 1.0


@dataclass
class Testability:
    """What the diagnosis tries: effects refitted on the split as is, effects whose shape is
    calibrated across drive rates, and the untestable ones with the reason."""

    tries: list[str]
    untestable: list[dict[str, str]]
    plan: RatePlan | None = None  # for the effects in ``calibrated``
    calibrated: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # what the training rows cannot identify, for the user


def _spread_rates(ex: dict[str, Any]) -> bool:
    """Several drive rates for a damping: loops whose rates spread (decision 0064), or a step that moves
    faster than any part of the loops (:func:`hilbench.diagnosis.input_motion.step_rate_ratio`): there
    the damping's term sgn(v')|v'/Q|^m is a pulse that no rate-independent loop makes (decision 0074)."""
    return ex["rate_spread"] >= T.SEVERAL_RATES_SPREAD or ex.get("step_rate_ratio", 1.0) >= T.SEVERAL_RATES_SPREAD


@dataclass
class DataContext:
    """What the requirements look at: the base model and the excitation of all and of training rows."""

    base: str
    result: FitResult
    ex: dict[str, Any]
    ex_train: dict[str, Any]
    plan: RatePlan | None
    no_plan: str

    @property
    def multi(self) -> bool:
        return self.ex["frequency_spread"] >= T.SEVERAL_RATES_SPREAD

    @property
    def multi_train(self) -> bool:
        return self.ex_train["frequency_spread"] >= T.SEVERAL_RATES_SPREAD

    @property
    def several_rates(self) -> bool:
        """Several drive rates: several frequencies, or one frequency at several amplitudes (what a
        velocity damping is a function of, :func:`hilbench.diagnosis.input_motion.rate_spread`)."""
        return self.multi or _spread_rates(self.ex)

    @property
    def several_rates_train(self) -> bool:
        return self.multi_train or _spread_rates(self.ex_train)

    @property
    def broadband(self) -> bool:
        return self.multi or self.ex["steps"] > 0

    @property
    def broadband_train(self) -> bool:
        return self.multi_train or self.ex_train["steps"] > 0

    @property
    def single(self) -> str:
        return f"single drive frequency ({frequencies_text(self.ex)})"

    @property
    def single_train(self) -> str:
        return (f"the training rows hold a single drive frequency ({frequencies_text(self.ex_train)}) while the "
                f"validation rows reach {frequencies_text(self.ex)}")


#: A requirement's verdict: None (testable), "calibrate" (testable across drive rates), or the reason.
Verdict = str | None
CALIBRATE = "calibrate"


def _memoryless_base(name: str, ctx: DataContext) -> Verdict:
    if ctx.base != "linear":
        return f"the base {ctx.base!r} already has memory"
    return None


def _several_rates(name: str, ctx: DataContext) -> Verdict:
    """Rate-dependence needs several drive rates, in training too: several frequencies for its
    frequency polynomials, or one frequency at several amplitudes for its damping, whose gain and
    power law act on the rate itself (one gain on the loop since decision 0018, not a weight per
    operator that one rate cannot fix). At one rate a damping's loop is a hysteresis loop
    (decision 0064), unless a step moves faster than the loops (decision 0074)."""
    if not ctx.several_rates:
        return f"{ctx.single} at one amplitude, and no step faster than its loops: {name} cannot be separated from hysteresis"
    if not ctx.several_rates_train:
        return (f"{ctx.single_train}, at one amplitude and no step faster than its loops: {name} cannot be separated "
                "from hysteresis in training (train on two or more rates, or with steps, to test it)")
    return None


def _rings(ex_train: dict[str, Any], top_hz: float) -> bool:
    """Whether the training input's own content reaches HARMONIC_REACH x its drive frequency and the
    highest drive frequency to be predicted (triangle corners: the dynamics show at one rate).

    Training rows without a reversal (a step and holds) have no drive frequency: all their content is
    the step's edges, which ring the dynamics whatever the step's slew. They ring them up to the rates to be
    predicted when that content reaches HARMONIC_REACH x the highest drive frequency of all rows.
    Counted in samples, a step slewed over several samples at a high sample rate is no step at all
    (a resonance near the drive: a 1.2 V step over 7 samples at 5 kHz, content to 476 Hz, and a
    4.8-9.8 Hz test run whose resonance validated 5x lower with dynamics; decision 0072)."""
    need = _ring_need(ex_train, top_hz)
    return need > 0 and ex_train["excited_hz"] >= need


def _ring_need(ex_train: dict[str, Any], top_hz: float) -> float:
    """The content (Hz) :func:`_rings` asks of the training input (0: nothing to predict)."""
    f = ex_train["frequencies_hz"]
    return max(T.HARMONIC_REACH * f[1], top_hz) if f else T.HARMONIC_REACH * top_hz


def _reach(ex_train: dict[str, Any], top_hz: float) -> str:
    return (f"the training input's content reaches {ex_train['excited_hz']:.3g} Hz, under the "
            f"{_ring_need(ex_train, top_hz):.3g} Hz that would ring the dynamics at the rates to predict")


def _broadband(name: str, ctx: DataContext) -> Verdict:
    top = ctx.ex["frequencies_hz"][1] if ctx.ex["frequencies_hz"] else 0.0
    if not ctx.broadband:
        if _rings(ctx.ex_train, top):
            return None  # one rate, but its corners ring the dynamics: learned and judged as they are
        return f"{ctx.single} and no steps ({_reach(ctx.ex_train, top)}): a {name} phase lag at one frequency looks like loop width"
    if not ctx.broadband_train:
        if ctx.plan is not None:
            return CALIBRATE
        if _rings(ctx.ex_train, top):
            return None  # the training input's harmonics reach the validation's rates
        return f"{ctx.single_train} and no steps ({_reach(ctx.ex_train, top)}), and {ctx.no_plan}"
    return None


def _holds(name: str, ctx: DataContext) -> Verdict:
    if ctx.ex["longest_hold_s"] < T.CREEP_MIN_HOLD_S:
        return (f"the input never holds still (longest hold {ctx.ex['longest_hold_s']:.3g} s): "
                "slow drift cannot be told from hysteresis")
    return None


def _varying_channel(name: str, ctx: DataContext) -> Verdict:
    ratio = aux_variation([r.data.aux[name] for r in ctx.result.runs if len(r.data)])
    if ratio < T.AUX_MIN_VARIATION:
        return (f"{name} barely varies (its smoothed range is {ratio:.3g}x its noise, below "
                f"{T.AUX_MIN_VARIATION:g})")
    return None


#: requirement name (hilbench.effects) -> check(effect name, context)
REQUIREMENTS: dict[str, Callable[[str, DataContext], Verdict]] = {
    E.MEMORYLESS_BASE: _memoryless_base,
    E.SEVERAL_RATES: _several_rates,
    E.BROADBAND: _broadband,
    E.HOLDS: _holds,
    E.VARYING_CHANNEL: _varying_channel,
}

#: What a base that already contains an effect contains, for the reason text.
_CONTAINED = {"asymmetry": "the polynomial (asymmetric) terms", "saturation": "the fractional (saturating) terms"}


def _verdict(effect: E.Effect, name: str, ctx: DataContext) -> Verdict:
    if ctx.base in effect.built_into:
        return f"the base {ctx.base!r} already has {_CONTAINED.get(name, name)}"
    calibrate = False
    for requirement in effect.requires:
        verdict = REQUIREMENTS[requirement](name, ctx)
        if verdict == CALIBRATE:
            calibrate = True
        elif verdict is not None:
            return verdict
    return CALIBRATE if calibrate else None


def _few_training_loops(ctx: DataContext) -> str | None:
    """A note when a base with memory trains on fewer than two full loops while the other rows draw
    more: its loops are identified from the training rows, so the validation error then says more
    about the training data than about a missing effect (a training run that only steps and holds)."""
    k = LOOP_HALF_CYCLES
    if ctx.base == "linear" or ctx.ex_train["loops"] >= k or ctx.ex["loops"] < ctx.ex_train["loops"] + k:
        return None
    return (f"the training rows draw {ctx.ex_train['loops']} half cycles over {100 * LOOP_MIN_SPAN:g} % of the input span "
            f"(all rows {ctx.ex['loops']}): the base {ctx.base!r} learns its loops from them, so its validation "
            "error reflects the training data more than a missing effect; train on a run with loops (--train)")


def _shared_channels(result: FitResult) -> list[str] | None:
    """The auxiliary channels every run with data records (None: no run has data)."""
    channels = None
    for r in result.runs:
        if len(r.data):
            channels = list(r.data.aux) if channels is None else [c for c in channels if c in r.data.aux]
    return channels


def testable(spec: str, result: FitResult) -> Testability:
    """Effects to try (not in ``spec``) and the untestable ones with the reason."""
    parts = split_spec(spec)
    have = {name for name, _ in parts}
    structure = result.model.structure
    if structure is not None:
        # one state equation (restoring-force): its mechanics are the dynamics, and nothing is added to it
        names = [e.name for e in E.EFFECTS.values()] + [c for c in _shared_channels(result) or []]
        return Testability([], [{"effect": name, "reason": f"{spec!r} is a whole model ({structure.name}), which "
                                 "takes no other effect"} for name in names if name not in have])
    ex = excitation(result)
    ex_train = excitation(result, "train")
    ctx = DataContext(parts[0][0], result, ex, ex_train, None, "")
    if not ctx.broadband_train and ctx.broadband:
        ctx.plan, ctx.no_plan = rate_plan(result)
    out = Testability([], [], ctx.plan)
    note = _few_training_loops(ctx)
    if note:
        out.notes.append(note)
    channels = _shared_channels(result)
    candidates = [(e.name, e) for e in E.EFFECTS.values()] + [(c, E.AUX_CHANNEL) for c in channels or []]
    for name, effect in candidates:
        if name in have:
            continue
        verdict = _verdict(effect, name, ctx)
        if verdict is not None and verdict != CALIBRATE:
            out.untestable.append({"effect": name, "reason": verdict})
            continue
        if verdict == CALIBRATE:
            out.calibrated.append(name)
        out.tries.append(name)
    return out
