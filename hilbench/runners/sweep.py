"""The experiment runner: plays a checked plan on a rig into a recording, safely.

* The whole plan is checked against the actuator's limits before anything moves.
* Runs stream to disk chunk by chunk (memory stays bounded however long a run is); the writer
  flushes at least once a second.
* Ctrl-C and SIGTERM are held off: the handler only sets a flag, the runner finishes the chunk,
  makes the actuator safe, flushes and writes ``status = "aborted"`` (QCoDeS-style deferral).
* Any exception makes the actuator safe and closes the run with ``status = "failed"`` and the
  traceback in ``reason`` before it propagates.
"""

from __future__ import annotations

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
from hilbench.rig.rig import Rig

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
) -> SweepResult:
    """Check the plan, then play each run on the rig into ``output`` (appended when it exists).

    ``on_event`` receives ``{"event": "run-started" | "flushed" | "run-ended", "run": group, ...}``;
    a ``flushed`` event says how many samples of the run are on disk.
    """
    def emit(event: str, group: str, **fields: Any) -> None:
        if on_event is not None:
            on_event({"event": event, "run": group, **fields})

    check_plan(runs, rig.actuator, rig.sample_rate_hz)
    realtime = rig.config.realtime if realtime is None else realtime
    if chunk_samples is None:
        # Real time: 50 ms chunks keep the pacing smooth and the flushes frequent.
        chunk_samples = max(1, int(rig.sample_rate_hz * 0.05)) if realtime else 65536
    writer = RecordingWriter(output)
    result = SweepResult(str(output))
    channels = rig.channels()
    sweep_id = uuid.uuid4().hex
    previous_group = ""
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
                extra_attrs={"sweep": sweep_id, "previous_run": previous_group, "approach_from": rig.last_applied},
            )
            previous_group = run.group_name
            n_total = exc.n_samples(rig.sample_rate_hz)
            done = 0
            emit("run-started", run.group_name, samples=n_total)
            try:
                first = next(exc.chunks(rig.sample_rate_hz, 1))
                rig.start_run(float(first[0]))
                t0 = time.monotonic()
                for chunk in exc.chunks(rig.sample_rate_hz, chunk_samples):
                    if stop:
                        break
                    applied = rig.apply(chunk)
                    measured = rig.measure(applied)
                    t = (done + np.arange(chunk.shape[0])) / rig.sample_rate_hz
                    flushed_before = run.n_flushed
                    run.append({"time": t, "input": applied, **measured})
                    done += chunk.shape[0]
                    if run.n_flushed != flushed_before:
                        emit("flushed", run.group_name, samples=run.n_flushed)
                    if progress is not None:
                        progress(index, planned.label, done, n_total)
                    if realtime:
                        lag = t0 + done / rig.sample_rate_hz - time.monotonic()
                        if lag > 0:
                            time.sleep(lag)
                if stop:
                    rig.stop(False)
                    reason = f"interrupted by {stop.signal_name} after {done} of {n_total} samples; actuator ramped to rest"
                    run.finish("aborted", reason)
                    emit("run-ended", run.group_name, status="aborted", samples=done)
                    result.runs.append(RunResult(planned.label, run.group_name, "aborted", done, reason))
                    break
                run.finish("complete")
                emit("run-ended", run.group_name, status="complete", samples=done)
                result.runs.append(RunResult(planned.label, run.group_name, "complete", done))
            except BaseException as error:
                try:
                    rig.stop(False)
                finally:
                    reason = "".join(traceback.format_exception(error))
                    run.finish("failed", reason)
                    emit("run-ended", run.group_name, status="failed", samples=done)
                    result.runs.append(RunResult(planned.label, run.group_name, "failed", done, reason))
                raise
        rig.stop(True)
    return result
