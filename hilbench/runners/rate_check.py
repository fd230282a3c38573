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
#: round trips timed
DEFAULT_SAMPLES = 300


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

    @property
    def slowest(self) -> str:
        return max(self.per_device_s, key=lambda d: float(np.median(self.per_device_s[d])))

    def describe(self) -> dict[str, Any]:
        return {"samples": self.samples, "round_trip_p50_s": self.p(0.5), "round_trip_p99_s": self.p(0.99),
                "max_rate_hz": self.max_rate_hz,
                "devices": {d: {"p50_s": self.p(0.5, v), "p99_s": self.p(0.99, v)} for d, v in self.per_device_s.items()},
                "paced_by": f"device {self.clock}: each round trip from its sample clock's tick" if self.clock
                else "none: back to back"}

    def line(self) -> str:
        def ms(s: float) -> str:
            return f"{s * 1e3:.3g} ms"

        parts = ", ".join(f"{d} {ms(self.p(0.5, v))}" for d, v in self.per_device_s.items())
        return (f"the devices' round trip takes {ms(self.p(0.5))} (p50), {ms(self.p(0.99))} (p99) "
                f"[{parts}]: they can hold at most {self.max_rate_hz:.4g} Hz")


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
    """The measured round trips; refused (exit 2) when the rig's rate is above what they can hold."""
    trips = time_round_trips(rig, samples)
    fs = rig.sample_rate_hz
    if fs > trips.max_rate_hz:
        where = rig.config.path or rig.config.name
        raise UserError(f"sample_rate_hz = {fs:g} cannot be held: {trips.line()} (slowest: {trips.slowest})",
                        where=where, hint=f"set sample_rate_hz <= {_round_down(trips.max_rate_hz):g} in the rig "
                        "config, or --allow-late to run anyway (its overruns are recorded)")
    return trips


def _round_down(rate_hz: float) -> float:
    """A round rate at or below ``rate_hz`` (two significant digits)."""
    if rate_hz <= 0 or not np.isfinite(rate_hz):
        return 0.0
    scale = 10.0 ** (int(np.floor(np.log10(rate_hz))) - 1)
    return float(np.floor(rate_hz / scale) * scale)
