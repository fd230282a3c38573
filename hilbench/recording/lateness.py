"""A fixed-rate run's timing: how late its samples were taken, kept in the run's attributes.

:class:`LoopStats` accumulates the ``lateness`` channel chunk by chunk (the recording's writer process
does it, so the loop never does): overruns (samples later than one period), the largest lateness and
a log-spaced histogram (1 ns .. 100 s, 20 bins per decade) for p50 and p99 to within ~12 % without
keeping the samples. :func:`loop_figures` and :func:`loop_line` read them back for ``show``,
``sweep`` and ``track``. A run paced by a DAQ's sample clock (:mod:`hilbench.runners.pacing`) also
keeps ``clock`` (which device) and ``clock_late_samples`` (the samples the DAQ itself reported late).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: a fixed-rate run with more overruns than this (percent of its samples) is marked ``late``
LATE_OVERRUN_PCT = 1.0
#: what a fixed-rate loop's run keeps about its timing (``loop_tuning``: hilbench.runners.loop_tuning)
LOOP_KEYS = ("paced", "overruns", "overrun_pct", "late", "lateness_p50_s", "lateness_p99_s", "lateness_max_s",
             "loop_tuning", "clock", "clock_late_samples")

_EDGES = np.concatenate([[-np.inf, 0.0], np.logspace(-9, 2, 11 * 20 + 1), [np.inf]])


@dataclass
class LoopStats:
    period_s: float
    paced: bool
    samples: int = 0
    overruns: int = 0
    max_s: float = float("nan")
    hist: np.ndarray = field(default_factory=lambda: np.zeros(_EDGES.size - 1, dtype=np.int64))

    def add(self, lateness: np.ndarray) -> None:
        if not self.paced or lateness.size == 0:
            return
        self.samples += lateness.size
        self.overruns += int(np.count_nonzero(lateness > self.period_s))
        top = float(lateness.max())
        self.max_s = top if not self.max_s >= top else self.max_s
        self.hist += np.histogram(lateness, _EDGES)[0]

    def quantile(self, q: float) -> float:
        if self.samples == 0:
            return float("nan")
        k = int(np.searchsorted(np.cumsum(self.hist), q * self.samples, side="left"))
        hi = _EDGES[min(k + 1, _EDGES.size - 1)]
        return float(min(hi, self.max_s))  # the bin's upper edge, never above the largest seen

    def attrs(self) -> dict[str, Any]:
        share = 100.0 * self.overruns / self.samples if self.samples else 0.0
        return {"loop": "fixed-rate", "paced": self.paced, "overruns": self.overruns, "overrun_pct": share,
                "late": bool(share > LATE_OVERRUN_PCT),
                "time": "measured" if self.paced else "schedule",
                "schedule": f"sample k due at k / {1.0 / self.period_s:g} Hz from the first deadline",
                "lateness_p50_s": self.quantile(0.5), "lateness_p99_s": self.quantile(0.99),
                "lateness_max_s": self.max_s}


def loop_figures(attrs: Any) -> dict[str, Any]:
    """A fixed-rate run's timing figures from its attributes (numpy scalars as Python values)."""
    out: dict[str, Any] = {}
    for key in LOOP_KEYS:
        if key in attrs:
            value = attrs[key]
            out[key] = value.item() if hasattr(value, "item") else value
    return out


def loop_line(figures: dict[str, Any]) -> str:
    """One line of a fixed-rate run's timing: lateness p50/p99/max, overruns, and whether it was late."""
    if not figures.get("paced", True):
        return "loop: unpaced (as fast as the devices answered; no schedule)"

    def t(s: Any) -> str:
        s = float(s)
        if s != s:
            return "n/a"
        return f"{s * 1e6:.3g} us" if s < 1e-3 else f"{s * 1e3:.3g} ms" if s < 1.0 else f"{s:.3g} s"

    text = (f"loop: lateness p50 {t(figures.get('lateness_p50_s', float('nan')))}, p99 "
            f"{t(figures.get('lateness_p99_s', float('nan')))}, max {t(figures.get('lateness_max_s', float('nan')))}; "
            f"{int(figures.get('overruns', 0))} overruns ({float(figures.get('overrun_pct', 0.0)):.3g} %)")
    if "clock_late_samples" in figures:
        text += f"; the DAQ reported {int(figures['clock_late_samples'])} samples late"
    if figures.get("late"):
        text += (f": LATE, the devices did not keep the rate (more than {LATE_OVERRUN_PCT:g} % of samples a period "
                 "late, or reported late by the DAQ)")
    if str(figures.get("clock", "pc")) != "pc":
        text += f"; paced by {figures['clock']}"
    if figures.get("loop_tuning"):
        text += f"; os: {figures['loop_tuning']}"
    return text
