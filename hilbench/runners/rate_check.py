"""Can the devices keep the rig's rate? Timed before anything moves.

The fixed-rate loop writes the actuator and reads every sensor device once per sample; when that
round trip takes longer than a period, samples overrun and the run falls behind its schedule.
:func:`time_round_trips` holds the actuator where it is (it writes the value last applied, so nothing
moves) and times a few hundred unpaced round trips, each device's call on its own; :func:`require_rate`
refuses (:class:`~hilbench.errors.UserError`, exit 2) a rate above what the measured round trips allow,
naming the slowest device, the measured times and the highest rate they can hold.

The rate they can hold is ``HEADROOM / p99`` of the round trip: the loop's own work (the safety path,
a compensator, appending to the recording) comes on top of the devices' time, and a p99 at the period
would already overrun about 1 % of the samples.

A p99 from a few hundred round trips is itself uncertain: two checks in a row on the same emulated
Modbus + Keyence rig said 320 and 305 Hz, so the rate the first one advised was refused by the
second. The check therefore uses the distribution-free interval of the p99 (order statistics, the
binomial law of how many round trips fall below it; ``P99_CONFIDENCE``): it refuses a rate above
what even the interval's short end allows, and advises one that its long end allows. A rate
advised is then refused again only when the devices really got slower.

When a DAQ's sample clock paces the loop (:func:`hilbench.runners.pacing.device_clock`), each timed
round trip starts at the clock's tick, as in the run: the wait for the tick is not timed (it is the
period, not the devices' work), the write and the reads after it are, and the rule is the same.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hilbench.errors import UserError

#: share of a period the devices' round trip (p99) may take
HEADROOM = 0.8
#: round trips timed: enough for the p99's interval to end below the slowest one
DEFAULT_SAMPLES = 1000
#: two-sided confidence of the interval on the p99 that the refusal and the advice use
P99_CONFIDENCE = 0.95


def quantile_interval(values: np.ndarray, q: float, confidence: float = P99_CONFIDENCE) -> tuple[float, float]:
    """Distribution-free ``confidence`` interval of the ``q`` quantile of the law ``values`` were drawn
    from: the order statistics X(r) <= quantile <= X(s) whose ranks the binomial law of the count of
    values below the quantile, Bin(n, q), gives. An end beyond the sample is its extreme value."""
    from scipy.stats import binom

    x = np.sort(np.asarray(values, dtype=float))
    n = x.size
    tail = 0.5 * (1.0 - confidence)
    # P(X(r) <= xi_q) = P(B >= r) >= 1 - tail for r = ppf(tail); P(X(s) >= xi_q) = P(B <= s - 1)
    r = int(binom.ppf(tail, n, q))
    s = int(binom.ppf(1.0 - tail, n, q)) + 1
    return float(x[min(max(r, 1), n) - 1]), float(x[min(max(s, 1), n) - 1])


@dataclass
class RoundTrips:
    """Measured round trips, seconds: the whole sample and each device's call."""

    samples: int
    total_s: np.ndarray
    per_device_s: dict[str, np.ndarray] = field(default_factory=dict)
    #: the device whose sample clock paced the round trips ('' = none: back to back)
    clock: str = ""

    def p(self, q: float, values: np.ndarray | None = None) -> float:
        return float(np.quantile(self.total_s if values is None else values, q))

    @property
    def max_rate_hz(self) -> float:
        """The highest sample rate the devices can hold (see the module docstring)."""
        return HEADROOM / self.p(0.99)

    def rate_interval_hz(self) -> tuple[float, float]:
        """The rate they can hold at the long and at the short end of the p99's interval, Hz."""
        lo, hi = quantile_interval(self.total_s, 0.99)
        return HEADROOM / hi, HEADROOM / lo

    @property
    def advised_rate_hz(self) -> float:
        """A round rate they hold even at the long end of the p99's interval: what the check advises."""
        return _round_down(self.rate_interval_hz()[0])

    @property
    def slowest(self) -> str:
        return max(self.per_device_s, key=lambda d: float(np.median(self.per_device_s[d])))

    def describe(self) -> dict[str, Any]:
        low, high = self.rate_interval_hz()
        return {"samples": self.samples, "round_trip_p50_s": self.p(0.5), "round_trip_p99_s": self.p(0.99),
                "max_rate_hz": self.max_rate_hz, "max_rate_interval_hz": [low, high],
                "advised_rate_hz": self.advised_rate_hz,
                "devices": {d: {"p50_s": self.p(0.5, v), "p99_s": self.p(0.99, v)} for d, v in self.per_device_s.items()},
                "paced_by": f"device {self.clock}: each round trip from its sample clock's tick" if self.clock
                else "none: back to back"}

    def line(self) -> str:
        def ms(s: float) -> str:
            return f"{s * 1e3:.3g} ms"

        parts = ", ".join(f"{d} {ms(self.p(0.5, v))}" for d, v in self.per_device_s.items())
        low, high = self.rate_interval_hz()
        return (f"the devices' round trip takes {ms(self.p(0.5))} (p50), {ms(self.p(0.99))} (p99) "
                f"[{parts}]: they can hold at most {self.max_rate_hz:.4g} Hz ({low:.4g}-{high:.4g} Hz, "
                f"{P99_CONFIDENCE:.0%} confidence)")


def time_round_trips(rig: Any, samples: int = DEFAULT_SAMPLES) -> RoundTrips:
    """Time ``samples`` round trips of a rig of per-sample devices, holding the actuator still."""
    from hilbench.runners.pacing import device_clock

    write = rig.actuator_device.write
    value = rig.last_applied
    reads = [(name, device.read) for name, device, _ in rig.sensor_reads]
    act = rig.actuator_name
    clock = device_clock(rig)
    tick = clock[1].wait_for_next_sample_clock if clock is not None else None
    total = np.empty(samples)
    each = {act: np.empty(samples), **{name: np.empty(samples) for name, _ in reads}}
    perf = time.perf_counter_ns
    for k in range(samples):
        if tick is not None:
            tick()
        t0 = perf()
        write(value)
        t1 = perf()
        each[act][k] = (t1 - t0) * 1e-9
        for name, read in reads:
            ta = perf()
            read()
            each[name][k] = (perf() - ta) * 1e-9
        total[k] = (perf() - t0) * 1e-9
    return RoundTrips(samples, total, each, clock[0] if clock is not None else "")


def require_rate(rig: Any, samples: int = DEFAULT_SAMPLES) -> RoundTrips:
    """The measured round trips; refused (exit 2) when the rig's rate is above what they can hold at
    the short end of the p99's interval (see the module docstring)."""
    trips = time_round_trips(rig, samples)
    fs = rig.sample_rate_hz
    if fs > trips.rate_interval_hz()[1]:
        where = rig.config.path or rig.config.name
        raise UserError(f"sample_rate_hz = {fs:g} cannot be held: {trips.line()} (slowest: {trips.slowest})",
                        where=where, hint=f"set sample_rate_hz <= {trips.advised_rate_hz:g} in the rig "
                        "config, or --allow-late to run anyway (its overruns are recorded)")
    return trips


def _round_down(rate_hz: float) -> float:
    """A round rate at or below ``rate_hz`` (two significant digits)."""
    if rate_hz <= 0 or not np.isfinite(rate_hz):
        return 0.0
    scale = 10.0 ** (int(np.floor(np.log10(rate_hz))) - 1)
    return float(np.floor(rate_hz / scale) * scale)
