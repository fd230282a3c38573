"""The fixed-rate loop: one run on per-sample devices, paced by the wall clock.

Each sample ``k`` of a run is due at the absolute deadline ``t0 + k / fs`` (``time.perf_counter_ns``;
absolute, so a late sample does not push the later ones back: the loop catches up). The loop sleeps
until ``spin_s`` before the deadline, then spins to it (``time.sleep`` overshoots by tens of
microseconds on Linux; spinning is exact but burns the core). Then, holding the rig's I/O lock, the
command goes through the rig's one safety path (:meth:`~hilbench.rig.rig.Rig.apply_value`: clamp,
slew limit), is written to the actuator, and every sensor device is read once.

Recorded per sample besides ``input`` (the value applied) and the sensor channels: ``time`` (s),
when the sample was taken, measured from the first deadline (the schedule, ``k / fs``, is in the
run's ``schedule`` attribute; a fit or a plot of a late run sees the rates that happened), and
``lateness`` (s): how long after its deadline the sample was taken. A sample later than one period
is an overrun; the run's attrs keep ``overruns``, ``overrun_pct``, ``late`` (more than
``LATE_OVERRUN_PCT`` % overran), ``lateness_p50_s``, ``lateness_p99_s`` (from a log-spaced
histogram, 5 % bins) and ``lateness_max_s``. With ``pace=False`` (emulated rigs in tests,
whose plant advances one sample per write whatever the time) the loop runs as fast as the devices
answer and ``lateness`` is NaN: there is no schedule to be late for.

Interlocks, checked on every sample (any of them stops the run; the runner makes the actuator safe
and closes the run ``failed`` with the reason, keeping every sample before):

* a sensor value that is NaN (drivers report over range, alarm and not-valid status that way) or
  outside its channel's ``range`` -> :class:`~hilbench.runners.faults.InterlockTripped`;
* a device call that raises (timeouts after the driver's retries, error replies, garbage, a lost
  transport or heartbeat) -> :class:`~hilbench.runners.faults.DeviceFault` naming the device;
* the watchdog: a thread that sees no sample for ``watchdog_periods`` periods makes the actuator safe
  itself (``rig.stop(False)`` through :class:`~hilbench.runners.faults.SafeStop`), then the loop ends
  with :class:`~hilbench.runners.faults.LoopStalled` when it gets control back.

A law (:class:`LoopLaw`) runs in the same loop, per sample: it turns the run's source value into the
command (``law.command(r)``) before the safety path, then learns what was applied and measured
(``law.commit(r, applied, row)``, ``row`` the sample's calibrated channels), and the channels it
declares (``law.channels``) are recorded beside the rig's, taken from it at every append
(``law.take(n)``). A closed loop (:class:`hilbench.online.tracking.CompensatorLaw`) reads a reference
and records ``reference``, ``command`` and ``error``; the live identifier
(:class:`hilbench.online.live.IdentifierLaw`) passes the excitation through and records its
prediction and weights.

The cyclic garbage collector is frozen for the loop (``gc.freeze``): the objects alive before the run
are not scanned again, so collections stay short.
"""

from __future__ import annotations

import gc
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from hilbench.recording.hdf5 import CANONICAL_CHANNELS, LATE_OVERRUN_PCT, ChannelSpec, RunWriter
from hilbench.rig.rig import Rig
from hilbench.runners.faults import DeviceFault, InterlockTripped, LoopStalled, SafeStop

#: default watchdog time: longer than one retried timeout of the drivers' defaults
DEFAULT_WATCHDOG_S = 2.0
#: sleep until this long before a deadline, then spin
DEFAULT_SPIN_S = 200e-6

# lateness histogram: 1 ns .. 100 s, 20 bins per decade (p50/p99 to within ~12 %)
_EDGES = np.concatenate([[-np.inf, 0.0], np.logspace(-9, 2, 11 * 20 + 1), [np.inf]])


def lateness_channel() -> ChannelSpec:
    return ChannelSpec("lateness", "s", CANONICAL_CHANNELS["lateness"][1])


def tracking_channels(unit: str) -> list[ChannelSpec]:
    """The channels a tracking run records besides the rig's (``unit``: the actuator's)."""
    return [ChannelSpec("reference", "um", CANONICAL_CHANNELS["reference"][1]),
            ChannelSpec("command", unit, "compensator command before the safety path"),
            ChannelSpec("error", "um", "tracking error: reference - output")]


class LoopLaw(Protocol):
    """What a law adds to the fixed-rate loop (see the module docstring)."""

    #: True: the run's source is a reference (um), not commands (the plan check does not apply)
    reads_reference: bool
    #: the channels it records besides the rig's
    channels: list[ChannelSpec]

    def command(self, source: float) -> float:
        """The command for this sample's source value, before the rig's safety path."""

    def commit(self, source: float, applied: float, row: dict[str, float]) -> None:
        """What was applied and measured (``row``: channel -> calibrated value) this sample."""

    def take(self, n: int) -> dict[str, np.ndarray]:
        """Its channels' values of the last ``n`` committed samples (the loop appends them)."""


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


class Watchdog:
    """Trips when the loop's heartbeat (``last_ns``) is older than ``timeout_s``; calls ``on_trip`` once."""

    def __init__(self, timeout_s: float, on_trip: Callable[[float, int], None]):
        self.timeout_ns = int(timeout_s * 1e9)
        self.on_trip = on_trip
        self.last_ns = time.perf_counter_ns()
        self.sample = 0
        self.tripped = False
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="hilbench-watchdog", daemon=True)
        self.error: BaseException | None = None

    def start(self) -> Watchdog:
        self.last_ns = time.perf_counter_ns()
        self._thread.start()
        return self

    def _run(self) -> None:
        check_s = max(0.001, self.timeout_ns / 1e9 / 8)
        while not self._done.wait(check_s):
            silent_ns = time.perf_counter_ns() - self.last_ns
            if silent_ns > self.timeout_ns:
                self.tripped = True
                try:
                    self.on_trip(silent_ns / 1e9, self.sample)
                except BaseException as exc:  # noqa: BLE001 - kept for the runner: never silent
                    self.error = exc
                return

    def stop(self) -> None:
        self._done.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(5.0)


def run_fixed_rate(
    rig: Rig,
    excitation: Any,
    run: RunWriter,
    *,
    safe: SafeStop,
    stop: Any,
    chunk_samples: int,
    pace: bool = True,
    watchdog_periods: int | None = None,
    spin_s: float = DEFAULT_SPIN_S,
    on_chunk: Callable[[int], None] | None = None,
    law: LoopLaw | None = None,
) -> tuple[int, LoopStats]:
    """Play one run sample by sample; returns (samples recorded, stats). Raises on a fault.
    With ``law``, the run's source is a reference and the law computes each command (closed loop).

    ``safe.io_lock`` is held around each sample's device I/O, so the watchdog's ``rig.stop`` never
    talks to a device at the same time as the loop. ``stop`` is the deferred-interrupt flag, checked
    between chunks; ``on_chunk(samples_done)`` runs after each chunk is appended.
    """
    fs = rig.sample_rate_hz
    period_s = 1.0 / fs
    period_ns = 1e9 / fs
    spin_ns = int(spin_s * 1e9)
    stats = LoopStats(period_s, pace)
    lock = safe.io_lock
    assert lock is not None
    periods = watchdog_periods if watchdog_periods is not None else max(50, math.ceil(DEFAULT_WATCHDOG_S * fs))
    timeout_s = periods * period_s

    def on_trip(silent_s: float, sample: int) -> None:
        why = (f"watchdog: the fixed-rate loop produced no sample for {silent_s * 1000:.0f} ms "
               f"(limit {periods} periods = {timeout_s * 1000:.0f} ms) after sample {sample}")
        safe.make_safe(why, lock_timeout_s=timeout_s)

    write = rig.actuator_device.write  # type: ignore[union-attr]
    apply_value = rig.apply_value
    act_name = rig.actuator_name
    act_driver = rig.config.actuator.driver
    reads = []
    for name, device, sensors in rig.sensor_reads:
        driver = rig.config.devices.get(name, {}).get("driver", "sim")
        plan = []
        for s in sensors:
            lo, hi = (s.range if s.range is not None else (-math.inf, math.inf))
            plan.append((s.channel, s.source or s.channel, s.offset, s.scale, float(lo), float(hi)))
        reads.append((name, driver, device.read, plan))
    channels = [c for _, _, _, plan in reads for c, *_ in plan]
    row: dict[str, float] = dict.fromkeys(channels, math.nan)  # this sample's values, for the law
    law_command = law.command if law is not None else None
    law_commit = law.commit if law is not None else None
    perf = time.perf_counter_ns
    sleep = time.sleep
    nan = math.nan

    done = 0
    watchdog = Watchdog(timeout_s, on_trip)
    frozen = False
    if gc.isenabled():
        gc.collect()
        gc.freeze()
        frozen = True
    t0 = perf() + int(2 * period_ns)  # the first deadline: two periods from now
    watchdog.start()
    try:
        for commands in excitation.chunks(fs, chunk_samples):
            if stop:
                break
            m = commands.shape[0]
            u = np.empty(m)
            late = np.full(m, nan)
            taken = np.empty(m)  # when each sample was taken, s from the first deadline
            buf = {c: np.empty(m) for c in channels}
            cols = [[buf[c] for c, *_ in plan] for _, _, _, plan in reads]
            j = 0
            try:
                for j in range(m):
                    k = done + j
                    if pace:
                        deadline = t0 + int(k * period_ns)
                        wait = deadline - perf() - spin_ns
                        if wait > 0:
                            sleep(wait * 1e-9)
                        now = perf()
                        while now < deadline:
                            now = perf()
                        late[j] = (now - deadline) * 1e-9
                        taken[j] = (now - t0) * 1e-9
                    else:
                        now = perf()
                        taken[j] = k / fs  # unpaced: no schedule to keep, the sample index is the time
                    with lock:
                        if watchdog.tripped:
                            raise LoopStalled(act_name, f"{safe.note or 'watchdog tripped'} (loop resumed at "
                                                        f"sample {k})")
                        r = float(commands[j])
                        value = apply_value(law_command(r) if law_command is not None else r)
                        try:
                            write(value)
                        except Exception as exc:
                            raise DeviceFault(act_name, act_driver, f"write {value:.6g} "
                                              f"{rig.actuator.unit} at sample {k}", exc) from exc
                        u[j] = value
                        for (name, driver, read, plan), col in zip(reads, cols):
                            try:
                                values = read()
                            except Exception as exc:
                                raise DeviceFault(name, driver, f"read at sample {k}", exc) from exc
                            for (channel, source, offset, scale, lo, hi), out in zip(plan, col):
                                raw = values.get(source, nan)
                                v = offset + scale * raw
                                if not lo <= v <= hi:
                                    raise InterlockTripped(name, _interlock_text(
                                        name, driver, channel, source, values, v, lo, hi, rig, k))
                                out[j] = v
                                row[channel] = v
                        if law_commit is not None:
                            law_commit(r, value, row)
                    watchdog.last_ns = now
                    watchdog.sample = k
                j = m
            finally:
                # every sample before a fault is kept
                if j:
                    data = {"time": taken[:j], "input": u[:j], "lateness": late[:j], **{c: buf[c][:j] for c in channels}}
                    if law is not None:
                        data.update(law.take(j))
                    run.append(data)
                    stats.add(late[:j])
                    done += j
            if on_chunk is not None:
                on_chunk(done)
            watchdog.last_ns = perf()  # appending and flushing are the loop's work too
    finally:
        watchdog.stop()
        if frozen:
            gc.unfreeze()
    if watchdog.error is not None:
        raise watchdog.error
    if watchdog.tripped:
        raise LoopStalled(act_name, safe.note or "watchdog tripped")
    return done, stats


def _interlock_text(name: str, driver: str, channel: str, source: str, values: Any, v: float, lo: float,
                    hi: float, rig: Rig, k: int) -> str:
    unit = next((s.unit for s in rig.config.sensors if s.channel == channel), "")
    where = f"sensor {channel!r} of device {name!r} ({driver}) at sample {k}"
    if source not in values:
        return f"{where}: the device returned no channel {source!r} (it returned {', '.join(values) or 'none'})"
    if math.isnan(v):
        status = getattr(rig.devices_by_name.get(name), "last_status", "")
        detail = f" ({status})" if status and status != "ok" else ""
        return f"{where}: reading is NaN{detail}: over range, alarm or not valid as the driver reports it"
    return f"{where}: reading {v:.6g} {unit} is outside its range [{lo:g}, {hi:g}] {unit}"
