"""Which rows of a measured capture a model is scored on: rests before the excitation, user windows.

Measured captures are whole: they start with the actuator at rest or at a bias voltage, often after
a power-on step, and only then comes the excitation (the dSPACE captures of
``shared/data/real/piezo-dspace-preisach`` rest 1.5 s at -90 V). Before the input first moves the
model's memory is unknown (the actuator's history before the capture was not recorded) and a power-on
transient is not explained by the recorded input at all, so such a leading rest says nothing about
the model yet can hold most of the error. :func:`leading_rest` finds it and :func:`unsettled_rest`
tells whether the output shows such a history (it moves on its own during the rest); :class:`Trim`
applies it and the user's ``--from/--to/--exclude`` windows. Trimmed rows are still simulated (the model's
memory runs through them); they are only left out of training and scoring.

Units: times in s from the start of each run, inputs in the command unit (V or A).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from hilbench.errors import UserError
from hilbench.identify.statistics import aux_variation, difference_noise_std

#: A leading rest counts when the input holds still at least this long before it first moves (s):
#: shorter stills are part of an excitation (a staircase's first level, a step's pre-trigger).
MIN_REST_S = 0.2
#: The input "holds still" while it stays within this many of its own noise stds of the first value
#: (a recorded voltage carries noise; a digital command has none).
REST_NOISE_SIGMAS = 5.0
#: ... and within this fraction of its range, whatever the noise estimate says.
REST_SPAN_FRACTION = 0.002
#: The output shows the capture began mid-history when, early in the rest, it sits this many noise
#: stds (and this fraction of its range) away from where the rest settles: a power-on step or the
#: creep of an earlier move. A capture that starts settled at rest is data like any other.
TRANSIENT_NOISE_SIGMAS = 10.0
TRANSIENT_SPAN_FRACTION = 0.01
#: ... and has mostly decayed: its early departure exceeds the drift over the rest's last half this many
#: times (a power-on step settles; the dSPACE captures: 3.5 um early, 0.02 um late).
TRANSIENT_DECAY_RATIO = 5.0
#: An auxiliary channel explains the output's movement during a rest only where it moves itself: its
#: smoothed range over its noise (:func:`hilbench.identify.statistics.aux_variation`) at least this
#: (the diagnosis tries a channel from the same ratio, AUX_MIN_VARIATION); a fit on a channel's noise
#: alone would take part of a power-on transient away by chance.
CHANNEL_MIN_VARIATION = 3.0


def leading_rest(u: np.ndarray, sample_rate_hz: float) -> int:
    """Samples at the start of a run during which the input rests before the excitation (0: none)."""
    n = u.shape[0]
    if n < 16:
        return 0
    finite = np.isfinite(u)
    if not finite.all():
        return 0
    span = float(np.ptp(u))
    if span == 0.0:
        return 0  # the whole run rests: nothing follows to score instead
    noise = difference_noise_std(np.diff(u, 4), order=4) if n > 8 else 0.0
    band = max(REST_NOISE_SIGMAS * noise, REST_SPAN_FRACTION * span)
    moved = np.flatnonzero(np.abs(u - u[0]) > band)
    if moved.size == 0:
        return 0
    k = int(moved[0])
    return k if k >= MIN_REST_S * sample_rate_hz and k < n - 16 else 0


def unsettled_rest(y: np.ndarray, rest: int, channels: Sequence[np.ndarray] = ()) -> bool:
    """Whether the output moves on its own during the first quarter of a leading rest of ``rest``
    samples (a power-on transient, creep of an earlier move), compared with where the rest settles.

    ``channels``: the run's recorded auxiliary channels (temperature, load). The input holds still,
    but these are inputs too: what they explain of the output's movement during the rest (a least-
    squares fit on them over the rest, :func:`_unexplained`) is a response to a recorded cause, the
    data a model with that channel is identified on, not an unknown history (for example, a
    cycling temperature moved the output 0.5 um during a 0.38 s rest; trimmed, the temperature
    model that fits the whole run at the noise validated 84x worse; decision 0073)."""
    if rest < 32:
        return False
    finite = y[np.isfinite(y)]
    span = float(np.ptp(finite)) if finite.size else 0.0  # of the whole run, as the thresholds are
    # the sensor's noise, from the output itself (a fit on a noisy channel would move it)
    quiet = y[rest // 2:rest]
    noise = difference_noise_std(np.diff(quiet[np.isfinite(quiet)], 4), order=4)
    y = _unexplained(np.asarray(y[:rest], dtype=float), [np.asarray(a[:rest], dtype=float) for a in channels])
    settled_part = y[rest // 2:rest]
    settled_part = settled_part[np.isfinite(settled_part)]
    early = y[:max(rest // 4, 8)]
    early = early[np.isfinite(early)]
    if settled_part.size < 16 or early.size < 4:
        return False
    settled = float(np.median(settled_part))
    departure = float(np.percentile(np.abs(early - settled), 95))
    # a transient decays: most of the movement is over early; a steady drift through the whole rest
    # (a temperature ramp the model reads from its channel) is data, not an unknown history
    late = y[rest // 2:rest]
    half = late.size // 2
    late_drift = abs(float(np.nanmedian(late[half:])) - float(np.nanmedian(late[:half])))
    return (departure > max(TRANSIENT_NOISE_SIGMAS * noise, TRANSIENT_SPAN_FRACTION * span)
            and departure > TRANSIENT_DECAY_RATIO * late_drift)


_WINDOW = re.compile(r"^\s*(?:(?P<run>[^:]+):)?\s*(?P<t0>[0-9.eE+-]+)\s*-\s*(?P<t1>[0-9.eE+-]+|end)\s*$")


def _unexplained(y: np.ndarray, channels: Sequence[np.ndarray]) -> np.ndarray:
    """``y`` less its least-squares fit on ``channels`` (and a constant), the channels that are finite
    and move beyond their noise over these rows (CHANNEL_MIN_VARIATION); ``y`` itself when none does.
    Rows where ``y`` is not finite stay NaN."""
    moving = [a for a in channels if a.shape == y.shape and np.isfinite(a).all()
              and aux_variation([a]) >= CHANNEL_MIN_VARIATION]
    ok = np.isfinite(y)
    if not moving or ok.sum() <= len(moving) + 1:
        return y
    # each channel centred and scaled, so the solve is well conditioned whatever its unit
    x = np.column_stack([np.ones(y.size)] + [(a - a.mean()) / np.ptp(a) for a in moving])
    coef, *_ = np.linalg.lstsq(x[ok], y[ok], rcond=None)
    out = np.full(y.shape, np.nan)
    out[ok] = y[ok] - x[ok, 1:] @ coef[1:]
    return out


def parse_window(text: str) -> tuple[str | None, float, float]:
    """``RUN:T0-T1`` or ``T0-T1`` (s; ``end`` for the run's end) -> (run selector or None, t0, t1)."""
    m = _WINDOW.match(text)
    if not m:
        raise UserError(f"cannot read {text!r}; expected T0-T1 or RUN:T0-T1 in seconds (e.g. 0-1.5, 20hz:0-1.5, "
                        "2.5-end)", where="--exclude")
    try:
        t0 = float(m.group("t0"))
        t1 = math.inf if m.group("t1") == "end" else float(m.group("t1"))
    except ValueError:
        raise UserError(f"cannot read the times in {text!r}; expected numbers in seconds", where="--exclude") from None
    if not (math.isfinite(t0) and t0 >= 0 and t1 > t0):
        raise UserError(f"{text!r}: expected 0 <= T0 < T1", where="--exclude")
    return m.group("run"), t0, t1


@dataclass
class Trim:
    """Rows left out of training and scoring. ``auto`` leaves out each run's leading rest."""

    auto: bool = False
    from_s: float | None = None
    to_s: float | None = None
    windows: list[tuple[str | None, float, float]] = field(default_factory=list)

    def __post_init__(self) -> None:
        for name, value in (("--from", self.from_s), ("--to", self.to_s)):
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise UserError(f"expected a time >= 0 in seconds, got {value!r}", where=name)
        if self.from_s is not None and self.to_s is not None and self.to_s <= self.from_s:
            raise UserError(f"--to {self.to_s:g} s must come after --from {self.from_s:g} s")

    @property
    def active(self) -> bool:
        return self.auto or self.from_s is not None or self.to_s is not None or bool(self.windows)

    def keep(self, u: np.ndarray, y: np.ndarray, sample_rate_hz: float, matches: Callable[[str], bool], name: str,
             *, history_known: bool = False, channels: Sequence[np.ndarray] = ()) -> tuple[np.ndarray, list[str]]:
        """Rows to keep of one run, and one note per reason rows were left out. ``history_known``: the
        run follows a recorded one or starts from the rig's rest, so its leading rest is data.
        ``channels``: the run's auxiliary channels, whose effect on the output is no unknown history
        (:func:`unsettled_rest`)."""
        n = u.shape[0]
        t = np.arange(n) / sample_rate_hz
        keep = np.ones(n, bool)
        notes: list[str] = []
        if self.auto and self.from_s is None and not history_known:
            k = leading_rest(u, sample_rate_hz)
            if k and unsettled_rest(y, k, channels):
                keep[:k] = False
                notes.append(f"run {name}: left out 0-{k / sample_rate_hz:.4g} s, where the input rests at "
                             f"{u[0]:.4g} before the excitation starts (the model's memory there is unknown and a "
                             "power-on transient is not explained by the input; --from 0 keeps it)")
        if self.from_s is not None and self.from_s > 0:
            keep &= t >= self.from_s
            notes.append(f"run {name}: left out 0-{self.from_s:.4g} s (--from)")
        if self.to_s is not None:
            keep &= t < self.to_s
            notes.append(f"run {name}: left out {self.to_s:.4g} s to the end (--to)")
        for run, t0, t1 in self.windows:
            if run is None or matches(run):
                keep &= ~((t >= t0) & (t < t1))
                notes.append(f"run {name}: left out {t0:.4g}-{t1:.4g} s (--exclude)")
        return keep, notes
