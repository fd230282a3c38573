"""Tracking on a rig of real devices: the runner runs it, as every experiment on a real rig.

Two ways, chosen by what the devices can do (:func:`hilbench.runners.sweep.select_mode`):

* **per-sample devices** (an amplifier and sensors on Modbus, CAN, serial): the runner's fixed-rate
  loop (:mod:`hilbench.runners.fixed_rate`) with the compensator as its law (:class:`CompensatorLaw`):
  per sample the command for the reference, the safety path, the devices, the commit of what was
  applied and measured (model memory, feedback, identifier);
* **a controller that plays waveforms** (PI's wave generator and data recorder, block mode,
  :mod:`hilbench.runners.block`): the compensator's feedforward commands for the whole reference
  are computed before anything moves (:meth:`~hilbench.online.inverse.Compensator.feedforward`) and
  played as the run's waveform, the recorder reading the output back (:class:`PlayedFeedforward`
  records the reference, command and error beside it). Feedback and online adaptation need a
  measurement every sample inside the loop; per-sample serial I/O to such a controller cannot carry
  that at its rates, so they are refused on such a rig before anything moves, unless the device's
  own sample clock can pace a per-sample loop (a DAQ: :mod:`hilbench.runners.pacing`); then
  feedback and online adaptation run in the fixed-rate loop paced by that clock, and a feedforward
  alone is still played (:func:`plays_waveform`).

Either way the run has the interlocks, Ctrl-C and SIGTERM held off to a safe point (the run recorded
``aborted``, :class:`~hilbench.errors.RunStopped`), the recording closed with its status and the
actuator ramped to rest on any fault. Without ``output`` the run is recorded to a temporary file (a
run on hardware is always recorded while it runs), removed afterwards.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from hilbench.errors import RunStopped, UserError
from hilbench.online.inverse import Compensator
from hilbench.online.tracking import TrackResult, _finish_attrs, _result


class ReferenceSource:
    """A reference (um), or the commands played for it, as a run's source (an :class:`Excitation`'s interface)."""

    def __init__(self, values: np.ndarray, described: dict[str, Any]):
        self.values = np.ascontiguousarray(values, dtype=np.float64)
        self.described = described

    def n_samples(self, sample_rate_hz: float) -> int:
        return int(self.values.size)

    def generate(self, sample_rate_hz: float) -> np.ndarray:
        return self.values

    def chunks(self, sample_rate_hz: float, chunk: int) -> Any:
        for start in range(0, self.values.size, chunk):
            yield self.values[start:start + chunk]

    def describe(self) -> dict[str, Any]:
        return {"reference": self.described}


class CompensatorLaw:
    """The compensator as the fixed-rate loop's closed-loop law on a real rig
    (:class:`hilbench.runners.fixed_rate.LoopLaw`): per sample its command for the reference (with
    the aux channels measured at the sample before), then the commit of what was applied and
    measured (model memory, feedback, identifier). It keeps the run's reference, commands and output
    (preallocated) for the figures the recording gets when the run ends, whatever its status."""

    reads_reference = True

    def __init__(self, comp: Compensator, aux0: dict[str, float] | None, n: int,
                 on_finish: Any, targets: np.ndarray | None = None):
        from hilbench.runners.fixed_rate import tracking_channels

        self.channels = tracking_channels(comp.unit)
        self.comp = comp
        self.aux = dict(aux0) if aux0 else None
        self.k = 0
        self.ref, self.cmd, self.applied, self.y = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
        self._on_finish = on_finish
        self._step = comp.step
        self._update = comp.update
        self.targets = targets

    def command(self, reference: float) -> float:
        t = self.targets
        u = self._step(reference, self.aux, None if t is None else float(t[self.k]))
        self.cmd[self.k] = u
        return u

    def commit(self, reference: float, applied: float, row: dict[str, float]) -> None:
        aux = self.aux
        if aux is not None:
            for c in aux:
                aux[c] = row[c]
        y = row["output"]
        self._update(reference, applied, y, aux)
        k = self.k
        self.ref[k], self.applied[k], self.y[k] = reference, applied, y
        self.k = k + 1

    def take(self, n: int) -> dict[str, np.ndarray]:
        k = self.k
        ref = self.ref[k - n:k]
        return {"reference": ref, "command": self.cmd[k - n:k], "error": ref - self.y[k - n:k]}

    def finish_attrs(self, samples: int) -> dict[str, Any]:
        k = self.k
        return self._on_finish(self.ref[:k], self.cmd[:k], self.applied[:k], self.y[:k])


class PlayedFeedforward:
    """The compensator's feedforward commands played as one waveform (block mode): the run's source
    is the command sequence; the reference, the command and the error (reference - measured output)
    are recorded beside the rig's channels, segment by segment as the device returns them."""

    reads_reference = True  # the caller brought the rig to the first command; commands pass the safety path

    def __init__(self, reference: np.ndarray, commands: np.ndarray, unit: str, on_finish: Any = None):
        from hilbench.runners.fixed_rate import tracking_channels

        self.channels = tracking_channels(unit)
        self.reference = reference
        self.commands = commands
        #: the commands as they passed the rig's safety path (the device reports its own ``input``)
        self.applied = np.full(commands.shape, np.nan)
        self.y = np.full(commands.shape, np.nan)
        self.done = 0
        self._on_finish = on_finish

    def played(self, start: int, block: dict[str, np.ndarray], applied: np.ndarray) -> dict[str, np.ndarray]:
        """The law's channels for samples ``start..`` of the run, given what the device recorded and
        what passed the safety path."""
        y = block["output"]
        self.applied[start:start + y.size] = applied[:y.size]
        self.y[start:start + y.size] = y
        self.done = start + y.size
        ref = self.reference[start:start + y.size]
        return {"reference": ref, "command": self.commands[start:start + y.size], "error": ref - y}

    def finish_attrs(self, samples: int) -> dict[str, Any]:
        if self._on_finish is None:
            return {}
        k = min(samples, self.done)
        return self._on_finish(self.reference[:k], self.commands[:k], self.applied[:k], self.y[:k])


def track_on_devices(rig: Any, comp: Compensator, ref: np.ndarray, described: dict[str, Any],
                     clipped: dict[str, Any] | None, output: str | Path | None, label: str,
                     aux0: dict[str, float] | None, trips: dict[str, Any] | None = None,
                     targets: np.ndarray | None = None) -> TrackResult:
    """Run the tracking run on the rig's devices (see the module docstring) and read back its figures.
    The rig and the compensator's memory are at the first command already. ``targets``: the static
    part's previewed targets per sample (:meth:`Compensator.enable_preview`; None: the reference)."""
    from hilbench.excitation.plan import PlannedRun
    from hilbench.recording.hdf5 import Recording
    from hilbench.recording.lateness import loop_figures
    from hilbench.runners.sweep import run_plan

    approach_from = rig.last_applied
    attrs = {"compensator": json.dumps(comp.describe(), default=str),
             **({"round_trips": json.dumps(trips)} if trips else {})}
    def figures(r: np.ndarray, cmd: np.ndarray, applied: np.ndarray, y: np.ndarray) -> dict[str, Any]:
        return _finish_attrs(_result(rig, comp, r, cmd, applied, y, {}, described, clipped))

    targets = ref if targets is None else targets
    if plays_waveform(rig, comp):
        law: Any = _played_feedforward(rig, comp, ref, figures, targets)
        mode = "block"
        attrs["played"] = ("the compensator's feedforward commands, computed before the run, played by the "
                           "device's wave generator; its data recorder read the output back")
        source = ReferenceSource(law.commands, described)
    else:
        comp.warm_up(float(ref[0]) if np.isfinite(ref[0]) else 0.0, aux0)
        law = CompensatorLaw(comp, aux0, ref.size, figures, targets)
        mode = "fixed-rate"
        source = ReferenceSource(ref, described)
    temporary = tempfile.TemporaryDirectory(prefix="hilbench-track-") if output is None else None
    path = Path(output) if output is not None else Path(temporary.name) / "track.h5"  # type: ignore[union-attr]
    try:
        started = time.perf_counter()
        outcome = run_plan(rig, [PlannedRun(label, source)], path,  # type: ignore[arg-type]
                           experiment="track", mode=mode, law=law, pace=rig.pace, run_attrs=attrs)
        seconds = time.perf_counter() - started
        (done,) = outcome.runs
        if done.status == "aborted":
            raise RunStopped.of_run(done.reason, str(path) if output else None, done.group)
        run = Recording(path).run(done.group)
        data = run.data()
        aux = {c: data[c] for c in data if c not in ("time", "input", "output", "reference", "command", "error",
                                                      "lateness")}
        # what the compensator's commands became: the safety path's output (a played waveform's
        # ``input`` is what the device says it applied, within its DAC and servo)
        applied = law.applied[:data["output"].size] if mode == "block" else data["input"]
        result = _result(rig, comp, data["reference"], data["command"], applied, data["output"], aux,
                         described, clipped)
        result.limited = int(np.count_nonzero(result.command != result.input))
        result.seconds, result.approach_from = seconds, approach_from
        if mode == "fixed-rate":
            result.loop = loop_figures(run.attrs)
        else:
            result.compensator["played"] = attrs["played"]
        if output is not None:
            result.file, result.group = str(path), done.group
        return result
    finally:
        if temporary is not None:
            temporary.cleanup()


def plays_waveform(rig: Any, comp: Compensator) -> bool:
    """Whether the tracking run is played as one waveform (block mode): the rig's device plays
    waveforms, and either the compensator is a feedforward alone or no device sample clock can pace
    the per-sample loop its feedback or online adaptation needs."""
    from hilbench.runners.block import can_play
    from hilbench.runners.pacing import device_clock

    if not can_play(rig):
        return False
    return (comp.pid is None and comp.oiir is None) or device_clock(rig) is None


def refuse_per_sample_law_on_player(rig: Any, comp: Compensator) -> None:
    """Feedback or online adaptation on a rig whose controller plays waveforms and has no sample
    clock to pace a per-sample loop: refused (exit 2)."""
    if not plays_waveform(rig, comp) or (comp.pid is None and comp.oiir is None):
        return
    what = "feedback" if comp.pid is not None else "online adaptation"
    raise UserError(
        f"{what} needs the measured output inside the loop every sample, and rig {rig.config.name!r} drives "
        f"its actuator through a controller that plays waveforms ({rig.config.actuator.driver or 'its driver'}: "
        f"wave generator and data recorder); per-sample serial I/O to it cannot carry a loop at "
        f"{rig.sample_rate_hz:g} Hz", where=rig.config.path or rig.config.name,
        hint="track without --feedback/--online: the feedforward commands are played as one waveform")


def _played_feedforward(rig: Any, comp: Compensator, ref: np.ndarray, on_finish: Any,
                        targets: np.ndarray) -> PlayedFeedforward:
    if comp.channels:
        raise UserError(f"the model reads channel(s) {', '.join(comp.channels)} while the run plays, and rig "
                        f"{rig.config.name!r} plays a waveform computed before the run: it cannot follow them",
                        where=rig.config.path or rig.config.name)
    commands = comp.feedforward(ref, targets=targets)
    return PlayedFeedforward(ref, commands, comp.unit, on_finish)
