"""The fixed-rate loop: one run on per-sample devices, paced by a clock.

The clock (:mod:`hilbench.runners.pacing`) is the PC's or a DAQ's. On the PC's, each sample ``k``
of a run is due at the absolute deadline ``t0 + k / fs`` (``time.perf_counter_ns``; absolute, so a
late sample does not push the later ones back: the loop catches up); the loop sleeps until ``spin_s``
before the deadline, then spins to it (``time.sleep`` overshoots by tens of microseconds on Linux;
spinning is exact but burns the core). On a DAQ whose sample clock times the rig's I/O (hardware-timed
single point), the loop waits for the DAQ's next tick instead, through the driver, and the DAQ's own
reports of late samples are counted. Then, holding the rig's I/O lock, the
command goes through the rig's one safety path (:meth:`~hilbench.rig.rig.Rig.apply_value`: clamp,
slew limit), is written to the actuator, and every sensor device is read once.

Recorded per sample besides ``input`` (the value applied) and the sensor channels: ``time`` (s),
when the sample was taken, measured from the first deadline (the schedule, ``k / fs``, is in the
run's ``schedule`` attribute; a fit or a plot of a late run sees the rates that happened), and
``lateness`` (s): how long after its deadline the sample was taken. A sample later than one period
is an overrun; the run's attrs keep ``overruns``, ``overrun_pct``, ``late`` (more than
``LATE_OVERRUN_PCT`` % overran), ``lateness_p50_s``, ``lateness_p99_s`` and ``lateness_max_s``
(:mod:`hilbench.recording.lateness`, accumulated by the writer process, not the loop), and which clock
paced it (``clock``; with a DAQ's, ``clock_late_samples`` too). Without a clock (``pace=False``:
emulated rigs in tests, whose plant advances one sample per write whatever the time) the loop runs as
fast as the devices answer and ``lateness`` is NaN: there is no schedule to be late for.

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

The samples go straight into a slot of the writer process's shared ring
(:mod:`hilbench.recording.writer_process`); at the end of a chunk the slot is handed over and the
writer process appends and flushes it, so no HDF5 call happens in the loop's process while it runs.

The cyclic garbage collector is held off for the run (``gc.disable`` after a full collection and
``gc.freeze``): a collection would pause the loop at an arbitrary sample, and the loop creates no
reference cycles, so nothing accumulates that a collection would free. It runs again after the run.
"""

from __future__ import annotations

import gc
import math
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from drivers.base import DEFAULT_BACKOFF_S, retry_budget_s
from hilbench.recording.hdf5 import CANONICAL_CHANNELS, ChannelSpec
from hilbench.recording.writer_process import StreamedRun
from hilbench.rig.rig import Rig
from hilbench.runners.faults import DeviceFault, InterlockTripped, LoopStalled, SafeStop
from hilbench.runners.pacing import DeviceClock, PcClock

#: shortest watchdog time: longer than one retried timeout of the drivers' defaults
DEFAULT_WATCHDOG_S = 2.0
#: the watchdog waits this much longer than the most patient device's retries (see :func:`watchdog_s`)
WATCHDOG_MARGIN = 1.25
#: sleep until this long before a deadline, then spin
DEFAULT_SPIN_S = 200e-6


def device_patience_s(rig: Rig) -> float:
    """The longest one request may take before a device's driver gives up (s): ``attempts`` tries of
    ``timeout_s`` each plus the back-off between them, the largest over the rig's devices (their config
    tables, driver defaults filled in). 0 for a simulated rig."""
    from hilbench.rig.registry import get_driver

    worst = 0.0
    for name, table in rig.config.devices.items():
        full = get_driver(str(table["driver"]), where=f"{rig.config.path}: [devices.{name}]").complete(table)
        worst = max(worst, retry_budget_s(full.get("attempts", 1), full.get("timeout_s", 0.0),
                                          full.get("backoff_s", DEFAULT_BACKOFF_S)))
    return worst


def watchdog_s(rig: Rig) -> float:
    """How long the loop may produce no sample before the watchdog makes the actuator safe (s).

    At least :data:`DEFAULT_WATCHDOG_S`, and longer than any one device's retried request: a device
    configured patient (a slow gateway, ``timeout_s = 1`` on a DAQ) then fails in its own words, naming
    itself, instead of the watchdog cutting its retries short with a vaguer "no sample" trip.
    """
    return max(DEFAULT_WATCHDOG_S, WATCHDOG_MARGIN * device_patience_s(rig))


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
    run: StreamedRun,
    *,
    safe: SafeStop,
    stop: Any,
    chunk_samples: int,
    clock: PcClock | DeviceClock | None = None,
    watchdog_periods: int | None = None,
    on_chunk: Callable[[int], None] | None = None,
    law: LoopLaw | None = None,
) -> int:
    """Play one run sample by sample; returns the samples recorded. Raises on a fault.
    ``clock`` paces it (:mod:`hilbench.runners.pacing`; None: unpaced). With ``law``, the run's
    source is a reference and the law computes each command (closed loop).

    ``safe.io_lock`` is held around each sample's device I/O, so the watchdog's ``rig.stop`` never
    talks to a device at the same time as the loop. ``stop`` is the deferred-interrupt flag, checked
    between chunks; ``on_chunk(samples_done)`` runs after each chunk is appended.
    """
    fs = rig.sample_rate_hz
    period_s = 1.0 / fs
    pace = clock is not None
    wait = clock.wait if clock is not None else None
    clock_name = getattr(clock, "name", "")
    lock = safe.io_lock
    assert lock is not None
    periods = watchdog_periods if watchdog_periods is not None else max(50, math.ceil(watchdog_s(rig) * fs))
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
    rows = run.rows
    row_input, row_lateness, row_time = rows["input"], rows["lateness"], rows["time"]
    law_command = law.command if law is not None else None
    law_commit = law.commit if law is not None else None
    perf = time.perf_counter_ns
    nan = math.nan

    done = 0
    watchdog = Watchdog(timeout_s, on_trip)
    collecting = gc.isenabled()
    if collecting:  # held off for the run: a collection is a pause of milliseconds at any sample
        gc.collect()
        gc.freeze()
        gc.disable()
    started = False
    watchdog.start()
    try:
        for commands in excitation.chunks(fs, chunk_samples):
            if stop:
                break
            m = commands.shape[0]
            block = run.slot()  # the writer process's shared slot: the loop stores straight into it
            u, late, taken = block[row_input], block[row_lateness], block[row_time]
            if not pace:
                late[:m] = nan
            cols = [[block[rows[c]] for c, *_ in plan] for _, _, _, plan in reads]
            if not started and clock is not None:  # everything for the first chunk is ready
                clock.start()
                started = True
            j = 0
            try:
                for j in range(m):
                    k = done + j
                    if wait is not None:
                        try:
                            taken[j], late[j], now = wait(k)
                        except Exception as exc:  # a DAQ's clock wait is a device call
                            raise DeviceFault(clock_name, rig.config.devices.get(clock_name, {}).get("driver", ""),
                                              f"wait for its sample clock at sample {k}", exc) from exc
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
                if j and law is not None:
                    for name, values in law.take(j).items():
                        block[rows[name], :j] = values
                run.commit(j)
                done += j
            if on_chunk is not None:
                on_chunk(done)
            watchdog.last_ns = perf()  # appending and flushing are the loop's work too
    finally:
        watchdog.stop()
        if collecting:
            gc.unfreeze()
            gc.enable()
    if watchdog.error is not None:
        raise watchdog.error
    if watchdog.tripped:
        raise LoopStalled(act_name, safe.note or "watchdog tripped")
    return done


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
