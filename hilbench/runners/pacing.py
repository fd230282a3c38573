"""What paces the fixed-rate loop: the PC's clock, or a device's hardware sample clock.

The loop (:mod:`hilbench.runners.fixed_rate`) asks its clock once per sample to wait for sample
``k`` (:meth:`wait`), which returns when the sample was taken, s from the run's first sample, and
how late, s. Two clocks:

* :class:`PcClock`: absolute deadlines ``t0 + k / fs`` on ``time.perf_counter_ns``; it sleeps until
  ``spin_s`` before a deadline, then spins to it. Lateness = wake time - deadline.
* :class:`DeviceClock`: a DAQ whose sample clock runs the I/O (a :class:`SampleClock` device:
  NI-DAQmx hardware-timed single point with Wait For Next Sample Clock, or a hardware-timed AI
  acquisition read one sample a period). The device's wait returns at its clock's tick and says
  whether the DAQ saw the tick go by before the wait began (late). The PC cannot read the DAQ's
  clock, so the loop estimates the tick times: the phase is the earliest wake seen (a wake cannot
  precede its tick), drifting forward by ``DRIFT_PPM`` of a period per sample so that a DAQ clock
  slower than the PC's is followed too (crystals differ by up to ~50 ppm). Lateness = wake time -
  the estimated tick: the driver's and transport's latency above their fastest, or, for a sample
  the DAQ reported late, how long after its tick the loop came. The DAQ skips the ticks the loop
  missed (it waits for the next one), so the estimate does too. The DAQ's own count of late samples
  is kept beside (:attr:`DeviceClock.reported_late`) and goes into the run's attributes.

A device clock paces only a run whose devices share it: the rig's sample rate must be the DAQ's
(refused otherwise, one line naming both).
"""

from __future__ import annotations

import math
import time
from typing import Any

from hilbench.errors import UserError
from hilbench.rig.protocols import SampleClock

#: how fast (parts per million of a period, per sample) the estimated tick phase drifts forward
DRIFT_PPM = 100.0


class PcClock:
    """Absolute deadlines on the PC's clock (see the module docstring)."""

    kind = "pc"

    def __init__(self, sample_rate_hz: float, spin_s: float):
        self.period_ns = 1e9 / sample_rate_hz
        self.spin_ns = int(spin_s * 1e9)
        self.t0 = 0

    def describe(self) -> str:
        return "the PC's clock (absolute deadlines)"

    def start(self) -> None:
        """The first deadline one period from now (everything for the first chunk is ready)."""
        self.t0 = time.perf_counter_ns() + int(self.period_ns)

    def wait(self, k: int) -> tuple[float, float, int]:
        """Wait for sample ``k``'s deadline: (taken s since the first deadline, late s, wake ns)."""
        perf = time.perf_counter_ns
        deadline = self.t0 + int(k * self.period_ns)
        wait = deadline - perf() - self.spin_ns
        if wait > 0:
            time.sleep(wait * 1e-9)
        now = perf()
        while now < deadline:
            now = perf()
        return (now - self.t0) * 1e-9, (now - deadline) * 1e-9, now

    def attrs(self) -> dict[str, Any]:
        return {"clock": "pc"}


class DeviceClock:
    """The sample clock of device ``name`` paces the loop (see the module docstring)."""

    kind = "device"

    def __init__(self, name: str, device: SampleClock, sample_rate_hz: float):
        self.name = name
        self.device = device
        self.period_ns = 1e9 / sample_rate_hz
        self._drift_ns = self.period_ns * DRIFT_PPM * 1e-6
        self._wait = device.wait_for_next_sample_clock
        self.first = 0  # wake time of the run's first sample, ns
        self.phase = 0.0  # estimated time of tick 0, ns
        self.tick = 0  # the tick the last sample was taken at
        self.reported_late = 0  # samples the DAQ reported late in this run
        self.samples = 0

    def describe(self) -> str:
        return f"the sample clock of device {self.name!r} ({self.device.sample_clock()})"

    def start(self) -> None:
        self.first, self.reported_late, self.samples = 0, 0, 0

    def wait(self, k: int) -> tuple[float, float, int]:
        """Wait for the device's next tick: (taken s since the first sample, late s, wake ns).
        The device's exceptions propagate (the loop names the device)."""
        late = self._wait()
        now = time.perf_counter_ns()
        self.samples += 1
        if not self.first:  # the run starts at whatever tick comes: its first sample is not late
            self.first, self.phase, self.tick = now, float(now), 0
            return 0.0, 0.0, now
        period = self.period_ns
        self.phase += self._drift_ns
        wanted = self.tick + 1
        due = self.phase + wanted * period
        if late:
            self.reported_late += 1
            # the DAQ waited for the tick after the ones that went by: catch up as it did
            self.tick = max(wanted, math.floor((now - self.phase) / period))
            lateness = max(0.0, now - due)
        else:
            self.tick = wanted
            if now < due:  # woke before the estimated tick: the tick was earlier than thought
                self.phase -= due - now
                due = now
            lateness = now - due
        return (now - self.first) * 1e-9, lateness * 1e-9, now

    def attrs(self) -> dict[str, Any]:
        return {"clock": f"device {self.name}: {self.device.sample_clock()}",
                "clock_late_samples": int(self.reported_late)}


def device_clock(rig: Any) -> tuple[str, SampleClock] | None:
    """The rig's device whose sample clock paces its I/O (the actuator's device first), or None.
    Refused when that clock's rate is not the rig's sample rate."""
    names = [rig.actuator_name] + [name for name, _, _ in rig.sensor_reads]
    for name in dict.fromkeys(names):
        device = rig.devices_by_name.get(name)
        if not isinstance(device, SampleClock):
            continue
        rate = device.sample_clock_hz()
        if rate is None:
            continue
        if not math.isclose(rate, rig.sample_rate_hz, rel_tol=1e-9):
            raise UserError(f"device {name!r} runs its sample clock at {rate:g} Hz and the rig's "
                            f"sample_rate_hz is {rig.sample_rate_hz:g}: one clock paces the loop",
                            where=rig.config.path or rig.config.name,
                            hint="set the device's sample_rate_hz and the rig's to the same rate")
        return name, device
    return None


def clock_for(rig: Any, pace: bool, spin_s: float) -> PcClock | DeviceClock | None:
    """The clock of a fixed-rate run on ``rig``: its device's sample clock when one paces its I/O,
    else the PC's; None when unpaced (emulated rigs in tests)."""
    if not pace:
        return None
    found = device_clock(rig)
    if found is not None:
        return DeviceClock(found[0], found[1], rig.sample_rate_hz)
    return PcClock(rig.sample_rate_hz, spin_s)
