"""HDF5 recordings, format_version 1 (see README "Recording format").

One file per sweep or experiment, one group ``/runs/<NNNN>-<label>`` per run, one resizable float64
dataset per channel. The writer streams: samples are appended in chunks, the file is in SWMR mode
while a run streams and is flushed at least once a second, and ``status`` is written last, after
the data are complete. A process killed mid-run leaves ``status = "running"`` and every sample that
was flushed before the kill.

Readable with plain h5py, pandas, MATLAB ``h5read``; no pickles, only numbers and text.
"""

from __future__ import annotations

import json
import os
import re
import socket
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from hilbench import __version__
from hilbench.errors import DataError, UserError
from hilbench.recording.lateness import loop_figures
from hilbench.recording.recover import clear_stale_write_flags, write_flags

FORMAT = "hilbench-recording"
FORMAT_VERSION = 1
STATUSES = ("running", "complete", "aborted", "failed")

#: Units and descriptions of the canonical channels; auxiliary channels bring their own.
CANONICAL_CHANNELS: dict[str, tuple[str, str]] = {
    "time": ("s", "time since the start of the run"),
    "input": ("", "actuator command actually applied (after clamping and slew limiting)"),
    "output": ("um", "actuator displacement"),
    "reference": ("um", "reference displacement"),
    "temperature": ("degC", "temperature"),
    "load": ("N", "external load on the actuator"),
    "current": ("A", "actuator current"),
    "lateness": ("s", "how late each sample of a fixed-rate loop was taken"),
}

_CHUNK = 8192  # samples per HDF5 chunk: 64 KiB of float64, a good size for appends and reads


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def run_group_name(index: int, label: str) -> str:
    safe = re.sub(r"[^A-Za-z0-9_.+=-]+", "_", label).strip("_") or "run"
    return f"{index:04d}-{safe}"


@dataclass
class ChannelSpec:
    name: str
    units: str
    description: str = ""


class RunWriter:
    """Streams one run's channels into a recording.

    Use through :meth:`RecordingWriter.run` as a context manager, which writes the final status.
    """

    def __init__(
        self,
        path: Path,
        group_name: str,
        channels: list[ChannelSpec],
        flush_interval_s: float = 0.5,
    ):
        self.path = path
        self.group_name = group_name
        self.channels = channels
        self.flush_interval_s = flush_interval_s
        self.n_samples = 0
        self.n_flushed = 0
        self.last_flush = time.monotonic()
        self._file: h5py.File | None = None
        self._datasets: dict[str, h5py.Dataset] = {}

    # -- streaming -------------------------------------------------------------------------
    def open(self) -> None:
        """Open the file for streaming, in SWMR mode (the first append does it too)."""
        if self._file is not None:
            return
        self._file = h5py.File(self.path, "a", libver="latest")
        group = self._file[f"runs/{self.group_name}"]
        self._datasets = {c.name: group[c.name] for c in self.channels}
        self._file.swmr_mode = True

    def close(self) -> int:
        """Flush and close the streaming file (attributes are written by :meth:`finish`); the samples written."""
        if self._file is not None:
            self.flush()
            self._file.close()
            self._file = None
        return self.n_samples

    def append(self, data: Mapping[str, np.ndarray]) -> None:
        """Append a block of samples; every channel of the run must be given, all of one length."""
        self.open()
        lengths = {len(np.asarray(data[c.name])) for c in self.channels}
        if len(lengths) != 1:
            raise ValueError(f"channels of one block differ in length: {sorted(lengths)}")
        n = lengths.pop()
        if n == 0:
            return
        new_size = self.n_samples + n
        for c in self.channels:
            ds = self._datasets[c.name]
            ds.resize((new_size,))
            ds[self.n_samples : new_size] = np.asarray(data[c.name], dtype=np.float64)
        self.n_samples = new_size
        if time.monotonic() - self.last_flush >= self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        if self._file is None:
            return
        for ds in self._datasets.values():
            ds.flush()
        self._file.flush()
        self.n_flushed = self.n_samples
        self.last_flush = time.monotonic()

    def finish(self, status: str, reason: str = "", extra_attrs: Mapping[str, Any] | None = None) -> None:
        """Flush, leave SWMR mode and write ``ended``, ``reason`` and, last, ``status``."""
        if status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}, got {status!r}")
        self.close()
        # Attributes are written outside SWMR mode (SWMR does not cover attribute changes).
        with h5py.File(self.path, "a", libver="latest") as f:
            group = f[f"runs/{self.group_name}"]
            for key, value in (extra_attrs or {}).items():
                group.attrs[key] = value
            group.attrs["ended"] = utc_now()
            group.attrs["reason"] = reason
            group.attrs["n_samples"] = self.n_samples
            f.attrs["writer"] = ""
            f.flush()
            group.attrs["status"] = status
            f.flush()


class RecordingWriter:
    """Creates or appends to a recording file."""

    def __init__(self, path: str | os.PathLike[str], flush_interval_s: float = 0.5):
        self.path = Path(path)
        self.flush_interval_s = flush_interval_s
        #: other processes writing this file's runs (a writer process), kept with this one's pid
        self.helper_pids: list[int] = []
        if self.path.exists():
            self._recover_if_stale()
            check_recording(self.path)
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with h5py.File(self.path, "w", libver="latest") as f:
                f.attrs["format"] = FORMAT
                f.attrs["format_version"] = FORMAT_VERSION
                f.attrs["created"] = utc_now()
                f.attrs["hilbench_version"] = __version__
                f.create_group("runs")

    def _recover_if_stale(self) -> None:
        """A writer killed in SWMR mode leaves its write flags set; clear them if it is dead.

        A SWMR writer releases HDF5's file lock, so the writer's pid and host (root attr
        ``writer``, set while a run streams) tell whether it still lives.
        """
        if write_flags(self.path) in (0, -1):
            return
        try:
            with h5py.File(self.path, "r", swmr=True) as f:
                writer = json.loads(_text(f.attrs.get("writer", "")) or "{}")
        except (OSError, ValueError):
            writer = {}
        pids = [int(writer.get("pid", -1)), *(int(p) for p in writer.get("helpers", []))]
        alive = [p for p in pids if _pid_alive(p)]
        if writer.get("host") == socket.gethostname() and alive:
            raise DataError(
                f"the recording is being written by process {alive[0]}; wait for it or give another file",
                where=str(self.path),
            )
        clear_stale_write_flags(self.path)

    def next_index(self) -> int:
        with h5py.File(self.path, "r") as f:
            names = list(f["runs"].keys())
        indices = [int(n.split("-", 1)[0]) for n in names if n[:4].isdigit()]
        return max(indices, default=0) + 1

    def begin_run(
        self,
        label: str,
        channels: list[ChannelSpec],
        *,
        experiment: str,
        excitation: Any,
        sample_rate_hz: float,
        rig_toml: str = "",
        devices: Any = None,
        extra_attrs: Mapping[str, Any] | None = None,
    ) -> RunWriter:
        """Create the run group with ``status = "running"`` and its empty channels."""
        group_name = run_group_name(self.next_index(), label)
        with h5py.File(self.path, "a", libver="latest") as f:
            f.attrs["writer"] = json.dumps({"pid": os.getpid(), "helpers": self.helper_pids,
                                            "host": socket.gethostname()})
            group = f["runs"].create_group(group_name)
            group.attrs["experiment"] = experiment
            group.attrs["excitation"] = excitation if isinstance(excitation, str) else json.dumps(excitation)
            group.attrs["sample_rate_hz"] = float(sample_rate_hz)
            group.attrs["started"] = utc_now()
            group.attrs["ended"] = ""
            group.attrs["status"] = "running"
            group.attrs["reason"] = ""
            group.attrs["rig"] = rig_toml
            group.attrs["devices"] = json.dumps(devices if devices is not None else [])
            group.attrs["channels"] = json.dumps([c.name for c in channels])  # the intended order
            for key, value in (extra_attrs or {}).items():
                group.attrs[key] = value
            for c in channels:
                ds = group.create_dataset(
                    c.name, shape=(0,), maxshape=(None,), chunks=(_CHUNK,), dtype="f8"
                )
                ds.attrs["units"] = c.units
                ds.attrs["description"] = c.description
        return RunWriter(self.path, group_name, channels, self.flush_interval_s)

    def write_run(
        self,
        label: str,
        data: Mapping[str, np.ndarray],
        units: Mapping[str, str],
        *,
        descriptions: Mapping[str, str] | None = None,
        status: str = "complete",
        reason: str = "",
        **attrs: Any,
    ) -> str:
        """Write a whole run at once (imports, derived data)."""
        descriptions = descriptions or {}
        channels = [
            ChannelSpec(name, units.get(name, ""), descriptions.get(name, CANONICAL_CHANNELS.get(name, ("", ""))[1]))
            for name in data
        ]
        writer = self.begin_run(label, channels, **attrs)
        writer.append(data)
        writer.finish(status, reason)
        return writer.group_name


# -- reading --------------------------------------------------------------------------------


def _text(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.generic):
        return value.item()
    return value


def check_recording(path: Path) -> None:
    """Refuse a file that is not a hilbench recording, with a one-line reason."""
    if not path.exists():
        raise DataError("file not found", where=str(path))
    try:
        # Opened without SWMR first: a damaged file (cut short by a copy, a full disk) fails here at
        # once, where a SWMR reader retries its metadata reads for minutes. A file being written by
        # a SWMR writer, or left with its flags by a crashed one, refuses this open; only then is
        # it opened as a SWMR reader, which is what reads it.
        with h5py.File(path, "r"):
            pass
    except OSError as exc:
        text = " ".join(str(exc).split())
        if "truncated" in text:
            raise DataError(f"not a readable HDF5 file: it is cut short ({text.split('(')[-1].rstrip(')')})",
                            where=str(path), hint="the copy or the write that made it did not finish") from exc
        if "already open for write" not in text and "lock" not in text:
            raise DataError(f"not a readable HDF5 file ({exc.__class__.__name__}: {text[:160]})",
                            where=str(path)) from exc
    try:
        with h5py.File(path, "r", swmr=True) as f:
            fmt = _text(f.attrs.get("format", ""))
            version = _text(f.attrs.get("format_version", -1))
    except OSError as exc:
        raise DataError(f"not a readable HDF5 file ({exc.__class__.__name__})", where=str(path)) from exc
    if fmt != FORMAT:
        raise DataError(f"not a hilbench recording (root attr format={fmt!r}, expected {FORMAT!r})", where=str(path))
    if version != FORMAT_VERSION:
        raise DataError(f"format_version {version} is not supported (expected {FORMAT_VERSION})", where=str(path))


@dataclass
class Run:
    """One run of a recording, read fully into memory on :meth:`channel` access."""

    path: Path
    name: str
    attrs: dict[str, Any] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    descriptions: dict[str, str] = field(default_factory=dict)
    lengths: dict[str, int] = field(default_factory=dict)

    @property
    def channels(self) -> list[str]:
        return list(self.units)

    @property
    def status(self) -> str:
        return str(self.attrs.get("status", ""))

    @property
    def sample_rate_hz(self) -> float:
        return float(self.attrs.get("sample_rate_hz", float("nan")))

    @property
    def n_samples(self) -> int:
        return min(self.lengths.values(), default=0)

    @property
    def label(self) -> str:
        return self.name.split("-", 1)[1] if "-" in self.name else self.name

    @property
    def excitation(self) -> Any:
        text = self.attrs.get("excitation", "")
        try:
            return json.loads(text) if text else None
        except json.JSONDecodeError:
            return text

    def channel(self, name: str) -> np.ndarray:
        if name not in self.units:
            raise DataError(
                f"run has no channel {name!r}; available: {', '.join(self.channels)}",
                where=f"{self.path}:{self.name}",
            )
        with h5py.File(self.path, "r", swmr=True) as f:
            return np.asarray(f[f"runs/{self.name}/{name}"][: self.n_samples], dtype=np.float64)

    def data(self) -> dict[str, np.ndarray]:
        with h5py.File(self.path, "r", swmr=True) as f:
            group = f[f"runs/{self.name}"]
            return {c: np.asarray(group[c][: self.n_samples], dtype=np.float64) for c in self.channels}

    def to_dataframe(self) -> Any:
        """Every channel as a pandas DataFrame, one column per channel (units in ``.attrs["units"]``).
        pandas is not a dependency of hilbench: install it for this (``pip install pandas``)."""
        try:
            import pandas as pd
        except ImportError:
            raise UserError("pandas is not installed; Run.data() gives the same channels as numpy arrays",
                            hint="pip install pandas") from None
        frame = pd.DataFrame(self.data())
        frame.attrs["units"] = dict(self.units)
        frame.attrs["run"] = self.name
        return frame

    def __repr__(self) -> str:
        return (f"Run({self.name!r}, {self.status}, {self.n_samples} samples at {self.sample_rate_hz:g} Hz, "
                f"channels {', '.join(f'{c} [{u}]' for c, u in self.units.items())})")


class Recording:
    """Read access to a recording: runs, channels with units, attributes."""

    def __init__(self, path: str | os.PathLike[str]):
        self.path = Path(path)
        check_recording(self.path)
        with h5py.File(self.path, "r", swmr=True) as f:
            self.attrs = {k: _text(v) for k, v in f.attrs.items()}
            self.runs: list[Run] = []
            for name in sorted(f["runs"].keys()):
                group = f["runs"][name]
                run = Run(self.path, name, {k: _text(v) for k, v in group.attrs.items()})
                order = json.loads(run.attrs.get("channels", "[]") or "[]")
                names = [c for c in order if c in group] + sorted(c for c in group if c not in order)
                for cname in names:
                    ds = group[cname]
                    if isinstance(ds, h5py.Dataset):
                        run.units[cname] = str(_text(ds.attrs.get("units", "")))
                        run.descriptions[cname] = str(_text(ds.attrs.get("description", "")))
                        run.lengths[cname] = int(ds.shape[0])
                self.runs.append(run)

    def __iter__(self) -> Iterator[Run]:
        return iter(self.runs)

    def __repr__(self) -> str:
        return f"Recording({str(self.path)!r}, {len(self.runs)} runs: {', '.join(r.name for r in self.runs)})"

    def __len__(self) -> int:
        return len(self.runs)

    def run(self, name: str) -> Run:
        """A run by full group name (``0001-sine``), label (``sine``) or 1-based index."""
        for run in self.runs:
            if name in (run.name, run.label) or (name.isdigit() and int(name) == int(run.name[:4])):
                return run
        available = ", ".join(r.name for r in self.runs) or "none"
        raise DataError(f"no run {name!r}; available: {available}", where=str(self.path))

    def summary(self) -> dict[str, Any]:
        """What ``hilbench show --json`` prints."""
        return {
            "file": str(self.path),
            "format": self.attrs.get("format"),
            "format_version": self.attrs.get("format_version"),
            "created": self.attrs.get("created"),
            "hilbench_version": self.attrs.get("hilbench_version"),
            "runs": [
                {
                    "name": r.name,
                    "experiment": r.attrs.get("experiment", ""),
                    "status": r.status,
                    "reason": r.attrs.get("reason", ""),
                    "started": r.attrs.get("started", ""),
                    "ended": r.attrs.get("ended", ""),
                    "sample_rate_hz": r.sample_rate_hz,
                    "n_samples": r.n_samples,
                    "duration_s": r.n_samples / r.sample_rate_hz if r.sample_rate_hz > 0 else None,
                    "excitation": r.excitation,
                    **({"loop": loop_figures(r.attrs)} if r.attrs.get("loop") == "fixed-rate" else {}),
                    "channels": [
                        {"name": c, "units": r.units[c], "description": r.descriptions[c], "n_samples": r.lengths[c]}
                        for c in r.channels
                    ],
                }
                for r in self.runs
            ],
        }
