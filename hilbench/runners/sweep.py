"""The experiment runner: plays a checked plan on a rig into a recording, safely.

One entry point, :func:`run_plan`; the rig chooses how samples are produced (``mode``):

* ``lockstep`` - a simulated rig: chunks of commands through the plant in blocks (optionally paced
  to real time with ``realtime``);
* ``fixed-rate`` - per-sample devices: a loop paced by the PC's clock with absolute deadlines, or
  by a DAQ's sample clock when one times the devices' I/O (:mod:`hilbench.runners.pacing`),
  lateness recorded per sample, a watchdog, sensor interlocks (:mod:`hilbench.runners.fixed_rate`);
* ``block`` - a device with a wave generator and data recorder plays each run whole
  (:mod:`hilbench.runners.block`).

Whatever the mode:

* The whole plan is checked against the actuator's limits before anything moves.
* Runs stream to disk chunk by chunk (memory stays bounded however long a run is); the writer
  flushes at least once a second.
* Ctrl-C and SIGTERM are held off: the handler only sets a flag, the runner finishes the chunk,
  makes the actuator safe, flushes and writes ``status = "aborted"`` (QCoDeS-style deferral).
* Any exception (a device fault, an interlock, a stalled loop) makes the actuator safe and closes
  the run with ``status = "failed"``; its ``reason`` starts with one line naming the device and
  why and what was done about the actuator, then the traceback. The exception then propagates.
"""

from __future__ import annotations

import json
import signal
import threading
import time
import traceback
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hilbench.excitation.plan import PlannedRun, check_plan
from hilbench.recording.hdf5 import RecordingWriter
from hilbench.recording.writer_process import WriterProcess
from hilbench.rig.rig import Rig
from hilbench.runners.block import can_play, run_block
from hilbench.runners.faults import DeviceFault, SafeStop, summary
from hilbench.runners.fixed_rate import DEFAULT_SPIN_S, LoopLaw, lateness_channel, run_fixed_rate
from hilbench.runners.loop_tuning import LoopTuning, apply_tuning, spin_for
from hilbench.runners.pacing import clock_for

#: progress(run_index, run_label, samples_done_in_run, samples_in_run)
Progress = Callable[[int, str, int, int], None]


@dataclass
class RunResult:
    label: str
    group: str
    status: str
    samples: int
    reason: str = ""


@dataclass
class SweepResult:
    file: str
    runs: list[RunResult] = field(default_factory=list)

    @property
    def status(self) -> str:
        statuses = {r.status for r in self.runs}
        for s in ("failed", "aborted"):
            if s in statuses:
                return s
        return "complete"


class _StopRequest:
    def __init__(self) -> None:
        self.signal_name: str | None = None

    def __bool__(self) -> bool:
        return self.signal_name is not None


@contextmanager
def deferred_interrupts() -> Iterator[_StopRequest]:
    """Turn SIGINT/SIGTERM into a flag for the duration; restores the old handlers after."""
    request = _StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return

    def handler(signum: int, _frame: Any) -> None:
        request.signal_name = signal.Signals(signum).name

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield request
    finally:
        for s, h in old.items():
            signal.signal(s, h)


MODES = ("lockstep", "fixed-rate", "block")


def select_mode(rig: Rig) -> str:
    """``lockstep`` for a simulated plant, ``block`` for a Player measuring every channel, else ``fixed-rate``."""
    if rig.lockstep is not None:
        return "lockstep"
    return "block" if can_play(rig) else "fixed-rate"


def run_plan(
    rig: Rig,
    runs: list[PlannedRun],
    output: str | Path,
    *,
    experiment: str = "sweep",
    realtime: bool | None = None,
    progress: Progress | None = None,
    chunk_samples: int | None = None,
    on_event: Callable[[dict[str, Any]], None] | None = None,
    mode: str | None = None,
    pace: bool = True,
    watchdog_periods: int | None = None,
    law: LoopLaw | None = None,
    run_attrs: dict[str, Any] | None = None,
    check_rate: bool = False,
) -> SweepResult:
    """Check the plan, then play each run on the rig into ``output`` (appended when it exists).

    ``on_event`` receives ``{"event": "run-started" | "flushed" | "run-ended", "run": group, ...}``;
    a ``flushed`` event says how many samples of the run are on disk. ``mode`` overrides
    :func:`select_mode`. ``realtime`` paces the lock-step mode only. ``pace=False`` lets the
    fixed-rate loop (and the rig's unrecorded ramps) run as fast as the devices answer: for emulated
    rigs in tests only, never for hardware. ``watchdog_periods``: the fixed-rate loop's watchdog
    trips after this many periods without a sample (default: 2 s worth).

    ``law``: a per-sample law in the loop (fixed-rate mode only, :class:`LoopLaw`). One that reads a
    reference (a closed loop) gets each run's excitation as the reference (um) it turns into
    commands, so that is not checked against the actuator's limits (its commands go through the
    safety path), and the caller has brought the rig (and the law's memory) to the first command; ``law.finish_attrs(samples)``, when the law has it, adds to the run's
    attributes whatever its status. ``run_attrs`` go into every run's attributes.

    ``check_rate``: a paced fixed-rate run first times the devices' round trips (the actuator held
    still) and is refused before anything moves when they cannot hold the rig's rate
    (:func:`hilbench.runners.rate_check.require_rate`); the command line does this unless
    ``--allow-late``.
    """
    def emit(event: str, group: str, **fields: Any) -> None:
        if on_event is not None:
            on_event({"event": event, "run": group, **fields})

    mode = select_mode(rig) if mode is None else mode
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if mode == "lockstep" and rig.lockstep is None:
        raise ValueError("lockstep mode needs a simulated rig (a LockstepPlant backend)")
    if mode == "block" and not can_play(rig):
        raise ValueError("block mode needs an actuator device with play() that measures every sensor channel")
    if mode == "fixed-rate" and rig.lockstep is not None:
        raise ValueError("fixed-rate mode needs per-sample devices; open a simulated rig with Rig(config, "
                         "lockstep=False) to step it sample by sample")
    if law is not None and not (mode == "fixed-rate" or (mode == "block" and hasattr(law, "played"))):
        raise ValueError(f"a law runs in fixed-rate mode (or, when it has played(), in block mode), not {mode}")
    reads_reference = law is not None and law.reads_reference
    if not reads_reference:
        check_plan(runs, rig.actuator, rig.sample_rate_hz)
    realtime = rig.config.realtime if realtime is None else realtime
    if mode == "fixed-rate" and pace:
        from hilbench.runners.pacing import device_clock

        device_clock(rig)  # a DAQ clock at another rate than the rig's is refused before anything moves
    if check_rate and mode == "fixed-rate" and pace:
        from hilbench.runners.rate_check import require_rate

        run_attrs = {**(run_attrs or {}), "round_trips": json.dumps(require_rate(rig).describe())}
    if chunk_samples is None:
        if mode == "lockstep":
            # Real time: 50 ms chunks keep the pacing smooth and the flushes frequent.
            chunk_samples = max(1, int(rig.sample_rate_hz * 0.05)) if realtime else 65536
        else:
            # 0.2 s: appends to the file are the loop's largest pauses; fewer of them, same flushing
            chunk_samples = max(1, int(rig.sample_rate_hz * 0.2))
    writer = RecordingWriter(output)
    result = SweepResult(str(output))
    channels = rig.channels() + ([lateness_channel()] if mode == "fixed-rate" else [])
    if law is not None:
        channels += law.channels
    # the fixed-rate loop's recording is written by a process of its own (no HDF5 in the loop's process)
    stream = WriterProcess(len(channels), chunk_samples) if mode == "fixed-rate" else None
    if stream is not None:
        writer.helper_pids = [stream.pid]
    finish_attrs = getattr(law, "finish_attrs", None)

    def law_attrs(done: int) -> dict[str, Any]:
        if finish_attrs is None:
            return {}
        try:
            return dict(finish_attrs(done))
        except Exception as error:  # noqa: BLE001 - the run is closed with its status whatever the law says
            return {"law_attrs_error": summary(error)}
    sweep_id = uuid.uuid4().hex
    previous_group = ""
    paced_before = rig.pace
    rig.pace = pace
    try:
        with deferred_interrupts() as stop:
            for index, planned in enumerate(runs, start=1):
                if stop:
                    break
                exc = planned.excitation
                # Which run this one follows on the same actuator, and from which command the rig
                # approached its first value: what a model needs to carry the actuator's memory over.
                run = writer.begin_run(
                    planned.label, channels, experiment=experiment, excitation=exc.describe(),
                    sample_rate_hz=rig.sample_rate_hz, rig_toml=rig.config.text, devices=rig.devices(),
                    extra_attrs={"sweep": sweep_id, "previous_run": previous_group,
                                 "approach_from": rig.last_applied, "mode": mode, **(run_attrs or {})},
                )
                previous_group = run.group_name
                if stream is not None:
                    run = stream.open_run(run, period_s=1.0 / rig.sample_rate_hz, paced=pace)
                if law is not None and hasattr(law, "start_run"):
                    law.start_run()  # e.g. a fresh identifier per run
                n_total = exc.n_samples(rig.sample_rate_hz)
                emit("run-started", run.group_name, samples=n_total)
                safe = SafeStop(rig, threading.Lock())
                stats_attrs: dict[str, Any] = {}
                flushed = {"n": 0}

                def on_chunk(done: int, run: Any = run, index: int = index, planned: PlannedRun = planned,
                             n_total: int = n_total, flushed: dict[str, int] = flushed) -> None:
                    if run.n_flushed != flushed["n"]:
                        flushed["n"] = run.n_flushed
                        emit("flushed", run.group_name, samples=run.n_flushed)
                    if progress is not None:
                        progress(index, planned.label, done, n_total)

                try:
                    # a closed loop starts from where its caller brought the rig
                    first = rig.last_applied if reads_reference else float(next(exc.chunks(rig.sample_rate_hz, 1))[0])
                    try:
                        rig.start_run(first)
                    except Exception as error:
                        if rig.lockstep is not None:
                            raise
                        raise DeviceFault(rig.actuator_name, rig.config.actuator.driver,
                                          f"approach the run's first value {first:g} "
                                          f"{rig.actuator.unit}", error) from error
                    if mode == "fixed-rate":
                        # the lateness figures go into the run's attributes from the writer process
                        tuning = LoopTuning(rig.config.lock_memory, rig.config.loop_priority, rig.config.loop_cpu)
                        restore = apply_tuning(tuning) if pace else None
                        stats_attrs["loop_tuning"] = tuning.summary() if pace else "none (unpaced)"
                        clock = clock_for(rig, pace, spin_for(1.0 / rig.sample_rate_hz, DEFAULT_SPIN_S,
                                                              tuning.realtime))
                        try:
                            done = run_fixed_rate(
                                rig, exc, run, safe=safe, stop=stop, chunk_samples=chunk_samples, clock=clock,
                                watchdog_periods=watchdog_periods, on_chunk=on_chunk, law=law)
                        finally:
                            if restore is not None:
                                restore()
                            if clock is not None:
                                stats_attrs.update(_clock_attrs(clock, run.n_samples))
                    elif mode == "block":
                        done = run_block(rig, exc, run, stop=stop, chunk_samples=chunk_samples, on_chunk=on_chunk,
                                         law=law)
                    else:
                        done = _run_lockstep(rig, exc, run, stop=stop, chunk_samples=chunk_samples,
                                             realtime=realtime, on_chunk=on_chunk)
                    stats_attrs.update(law_attrs(done))
                    if stop:
                        note = safe.make_safe()
                        if not safe.ok:
                            raise RuntimeError(note)
                        reason = f"interrupted by {stop.signal_name} after {done} of {n_total} samples; {note}"
                        run.finish("aborted", reason, extra_attrs=stats_attrs)
                        emit("run-ended", run.group_name, status="aborted", samples=done)
                        result.runs.append(RunResult(planned.label, run.group_name, "aborted", done, reason))
                        break
                    run.finish("complete", extra_attrs=stats_attrs)
                    emit("run-ended", run.group_name, status="complete", samples=done)
                    result.runs.append(RunResult(planned.label, run.group_name, "complete", done))
                except BaseException as error:
                    try:
                        note = safe.make_safe()
                    finally:
                        done = run.n_samples
                        stats_attrs.update(law_attrs(done))
                        reason = f"{summary(error)}; {note if safe.done else 'actuator not made safe'}\n\n" + \
                            "".join(traceback.format_exception(error))
                        run.finish("failed", reason, extra_attrs={**stats_attrs, "made_safe": bool(safe.ok)})
                        emit("run-ended", run.group_name, status="failed", samples=done)
                        result.runs.append(RunResult(planned.label, run.group_name, "failed", done, reason))
                    # the command line names the run that keeps the samples (hilbench.cli.app.user_errors)
                    recorded = f"{output} run {run.group_name} (failed; {note if safe.done else 'actuator not made safe'})"
                    if isinstance(error, DeviceFault):
                        # the caller sees the driver's own exception (DeviceLost, DeviceTimeout, ...);
                        # the recording's reason says which of the rig's devices it was
                        _tell_recorded(error.error, recorded, device=error.device)
                        raise error.error from None
                    _tell_recorded(error, recorded)
                    raise
            rig.stop(True)
    finally:
        rig.pace = paced_before
        if stream is not None:
            stream.close()
    return result


def _clock_attrs(clock: Any, samples: int) -> dict[str, Any]:
    """Which clock paced a fixed-rate run; a DAQ's late reports above LATE_OVERRUN_PCT % mark it late."""
    from hilbench.recording.lateness import LATE_OVERRUN_PCT

    attrs = clock.attrs()
    reported = int(attrs.get("clock_late_samples", 0))
    if samples and 100.0 * reported / samples > LATE_OVERRUN_PCT:
        attrs["late"] = True
    return attrs


def _tell_recorded(error: BaseException, recorded: str, device: str = "") -> None:
    """What the command line says besides the error: where the samples are and (a driver's own
    exception) which of the rig's devices raised it."""
    try:
        error.hilbench_recorded = recorded  # type: ignore[attr-defined]
        if device:
            error.hilbench_device = device  # type: ignore[attr-defined]
    except (AttributeError, TypeError):  # an exception type with __slots__
        pass


def _run_lockstep(rig: Rig, exc: Any, run: Any, *, stop: Any, chunk_samples: int, realtime: bool,
                  on_chunk: Callable[[int], None]) -> int:
    """The simulated rig: chunks of commands through the plant in blocks."""
    done = 0
    t0 = time.monotonic()
    for chunk in exc.chunks(rig.sample_rate_hz, chunk_samples):
        if stop:
            break
        applied = rig.apply(chunk)
        measured = rig.measure(applied)
        t = (done + np.arange(chunk.shape[0])) / rig.sample_rate_hz
        run.append({"time": t, "input": applied, **measured})
        done += chunk.shape[0]
        on_chunk(done)
        if realtime:
            lag = t0 + done / rig.sample_rate_hz - time.monotonic()
            if lag > 0:
                time.sleep(lag)
    return done
