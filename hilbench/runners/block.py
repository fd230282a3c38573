"""Block mode: a run played whole on a device with a wave generator and data recorder (a Player).

Per-sample serial I/O cannot reach kHz rates, so a controller such as PI's plays the run itself:

1. the run's commands pass the rig's safety path as one block (:meth:`~hilbench.rig.rig.Rig.apply`:
   clamped, slew-limited; the plan was checked before anything moved);
2. the applied waveform goes to ``device.play(waveform, fs)``, in segments of the device's
   ``max_wave_points`` (its ``capabilities()``) when the run is longer than a wave table (the device
   holds the last value between segments while the next one is uploaded);
3. the channels it returns are recorded: trimmed to the segment, or resampled onto the plan's time
   grid when the device recorded at another rate (its ``time`` channel says so). ``input`` is what
   the device reports it applied (its ``input`` channel) when it reports it, else the applied
   waveform. Each configured sensor takes the device's channel ``source`` (default: its name),
   ``offset + scale * value``.

The sensor interlock applies to the recorded block: the first NaN or out-of-range sample fails the
run, and the samples before it are kept. When ``play`` itself fails, the device's position is
unknown to the rig, so the runner asks the device what it holds (its ``read()["input"]``) before
ramping to rest from there.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from hilbench.recording.hdf5 import RunWriter
from hilbench.rig.protocols import Player
from hilbench.rig.rig import Rig
from hilbench.runners.faults import DeviceFault, InterlockTripped, one_line


def can_play(rig: Rig) -> bool:
    """Block mode fits: the actuator is a Player and it measures every sensor channel itself."""
    if rig.lockstep is not None or not isinstance(rig.actuator_device, Player):
        return False
    return all((s.device or "") == rig.actuator_name for s in rig.config.sensors)


def _fit(series: np.ndarray, t_dev: np.ndarray | None, n: int, fs: float) -> np.ndarray:
    """``series`` on the plan's grid of ``n`` samples: trimmed, or resampled when the rates differ."""
    series = np.asarray(series, dtype=np.float64).ravel()
    if t_dev is not None and t_dev.size == series.size and series.size > 1:
        dt = float(np.median(np.diff(t_dev)))
        if dt > 0 and abs(dt * fs - 1.0) > 1e-6:
            t = np.arange(n) / fs + float(t_dev[0])
            t = t[t <= t_dev[-1] + 1e-12]
            return np.interp(t, t_dev, series)
    return series[:n]


def run_block(
    rig: Rig,
    excitation: Any,
    run: RunWriter,
    *,
    stop: Any,
    chunk_samples: int,
    on_chunk: Callable[[int], None] | None = None,
    law: Any = None,
) -> int:
    """Play one run on the rig's Player; returns the samples recorded. Raises on a fault.
    ``law.played(start, block, applied)``, when given, adds its channels to each recorded segment
    (e.g. the reference and error of a played feedforward tracking run); ``applied`` is the segment
    as it passed the rig's safety path."""
    fs = rig.sample_rate_hz
    player = rig.actuator_device
    name = rig.actuator_name
    driver = rig.config.actuator.driver
    commands = excitation.generate(fs)
    n_total = commands.shape[0]
    try:
        capacity = int(player.capabilities().get("max_wave_points") or n_total)
    except Exception as exc:
        raise DeviceFault(name, driver, "report its capabilities", exc) from exc
    capacity = max(2, capacity)
    done = 0
    for start in range(0, n_total, capacity):
        if stop:
            break
        segment = rig.apply(commands[start:start + capacity])
        n = segment.shape[0]
        try:
            got = player.play(segment, fs)  # type: ignore[union-attr]
        except Exception as exc:
            resync_from_device(rig)
            raise DeviceFault(name, driver, f"play samples {start}..{start + n - 1} of the run", exc) from exc
        t_dev = np.asarray(got["time"], dtype=np.float64) if "time" in got else None
        block: dict[str, np.ndarray] = {}
        reported = got.get("input")
        block["input"] = _fit(reported, t_dev, n, fs) if reported is not None else segment
        for s in rig.config.sensors:
            source = s.source or s.channel
            if source not in got:
                raise InterlockTripped(name, f"sensor {s.channel!r} of device {name!r} ({driver}): the device "
                                             f"recorded no channel {source!r} (it recorded {', '.join(got)})")
            block[s.channel] = s.offset + s.scale * _fit(got[source], t_dev, n, fs)
        m = min(len(v) for v in block.values())
        if law is not None:
            block.update(law.played(done, {c: v[:m] for c, v in block.items()}, segment[:m]))
        # interlock: the first NaN or out-of-range sample of any sensor
        first_bad, why = m, ""
        for s in rig.config.sensors:
            lo, hi = s.range if s.range is not None else (-math.inf, math.inf)
            v = block[s.channel][:m]
            bad = np.flatnonzero(~((v >= lo) & (v <= hi)))
            if bad.size and bad[0] < first_bad:
                first_bad = int(bad[0])
                value = v[first_bad]
                why = (f"sensor {s.channel!r} of device {name!r} ({driver}) at sample {done + first_bad}: " +
                       ("reading is NaN: over range, alarm or not valid as the device reports it"
                        if math.isnan(value) else
                        f"reading {value:.6g} {s.unit} is outside its range [{lo:g}, {hi:g}] {s.unit}"))
        keep = first_bad
        for k0 in range(0, keep, chunk_samples):
            k1 = min(keep, k0 + chunk_samples)
            run.append({"time": (done + np.arange(k0, k1)) / fs, **{c: v[k0:k1] for c, v in block.items()}})
            if on_chunk is not None:
                on_chunk(done + k1)
        done += keep
        if why:
            raise InterlockTripped(name, why)
        if m < n:
            raise InterlockTripped(name, f"device {name!r} ({driver}) returned {m} of the {n} samples it was "
                                         f"asked to play (samples {start}..{start + n - 1} of the run)")
    return done


def resync_from_device(rig: Rig) -> str:
    """After a failed play: continue the actuator path from the value the device says it holds."""
    device = rig.actuator_device
    read = getattr(device, "read", None)
    if read is None:
        return ""
    try:
        value = float(read().get("input", math.nan))
    except Exception as exc:  # noqa: BLE001 - the device is gone: nothing can be ramped anyway
        return f"could not ask the device what it holds: {one_line(exc)}"
    if math.isfinite(value):
        rig.resync(value)
    return ""
