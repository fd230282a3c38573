"""Import measured data (CSV, MATLAB .mat, dSPACE ControlDesk captures) into a recording.

Every source becomes one run of a hilbench recording (see DESIGN "Recording format"): channels
``time`` (s), ``input`` (the actuator command, V or A), ``output`` (displacement, um by default) and
any auxiliary channels. Units come from the file (a CSV header cell ``name[unit]``), from a mapping
value (``output[um]``) or from :data:`hilbench.recording.hdf5.CANONICAL_CHANNELS`.

A mapping renames source columns to channels: ``{"displacement": "output[um]", "voltage": "input[V]"}``.
Sources are addressed by

- CSV: the header name, or the 0-based column index as a string (``"1"``), the only way for files
  without a header row;
- plain .mat: the variable name;
- dSPACE .mat: ``Y(n)`` (1-based, as in MATLAB) or the block name in ``Y(n).Name``
  (``"Måling"`` for ``"Model Root"/"Måling"/"In1"``); ``X.Data`` is always ``time``.

The target ``-`` drops a column. Every source is read and checked completely before the output
file is touched, so a bad source leaves no file behind and an existing recording unchanged.
Problems are raised as :class:`hilbench.errors.DataError`, one line naming file, line, column, value.

This module maps, checks and writes; a source's columns are read by
:mod:`hilbench.recording.source_columns`, text and unit spellings by :mod:`hilbench.recording.units`.
"""

from __future__ import annotations

import hashlib
import os
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hilbench import progress
from hilbench.errors import DataError
from hilbench.recording.hdf5 import CANONICAL_CHANNELS, RecordingWriter, check_recording
from hilbench.recording.source_columns import (
    CHANNEL_RE,
    SourceColumn,
    column_listing,
    csv_columns,
    mat_columns,
    parse_cells,
    resolve_column,
)
from hilbench.recording.units import TIME_UNITS_S, normalize_unit

TEXT_SUFFIXES = (".csv", ".tsv", ".txt")
MAT_SUFFIXES = (".mat",)
REQUIRED = ("input", "output")
DROP = "-"  # mapping target that drops a column

_TARGET_RE = re.compile(r"\s*([^\[\]]+?)\s*(?:\[\s*([^\[\]]*?)\s*\])?\s*")


@dataclass
class ImportedRun:
    """One source file read into memory, checked and ready to be written as a run.

    ``data`` holds float64 arrays of equal length (``time`` in s); ``units`` the unit per channel;
    ``sample_rate_hz`` in Hz.
    """

    source: Path
    label: str
    data: dict[str, np.ndarray]
    units: dict[str, str]
    descriptions: dict[str, str]
    sample_rate_hz: float
    sha256: str
    excitation: dict[str, Any] = field(default_factory=dict)

    @property
    def n_samples(self) -> int:
        return len(self.data["time"])


# -- names and units ------------------------------------------------------------------------


def _example_unit(channel: str) -> str:
    return {"input": "V", "output": "um", "time": "s"}.get(channel) or CANONICAL_CHANNELS.get(channel, ("",))[0] or "unit"


_RUN_NAME = re.compile(r"[A-Za-z0-9_.+=-][A-Za-z0-9_.+=@ -]*")
MAX_RUN_NAME = 100


def check_run_name(name: str, where: str = "--run") -> str:
    """A run label: letters, digits, ``_ . + = - @`` and spaces, 1-100 characters (it names an HDF5 group)."""
    if not isinstance(name, str) or not name.strip():
        raise DataError("empty run name", where=where, hint="e.g. --run 20hz")
    if len(name) > MAX_RUN_NAME or not _RUN_NAME.fullmatch(name):
        raise DataError(f"run name {name!r}: expected 1-{MAX_RUN_NAME} letters, digits, spaces or _ . + = - @ "
                        "(no '/', which would nest HDF5 groups)", where=where, hint="e.g. --run 20hz")
    return name


# -- mapping ---------------------------------------------------------------------------------


def parse_target(value: str, where: str = "--map") -> tuple[str, str | None]:
    """Split a mapping target ``"output"`` / ``"output[um]"`` into (channel, unit or None)."""
    if value.strip() == DROP:
        return DROP, None
    m = _TARGET_RE.fullmatch(value)
    if not m or not CHANNEL_RE.fullmatch(m.group(1)):
        raise DataError(
            f"{value!r} is not a channel name (expected NAME or NAME[unit], NAME of letters, digits, _ . + -)",
            where=where,
        )
    unit = m.group(2)
    if unit is not None and not unit.strip():
        raise DataError(f"{value!r}: empty unit in brackets", where=where, hint="e.g. output[um], input[V], time[s]")
    return m.group(1), normalize_unit(unit) if unit is not None else None


def parse_mapping(items: list[str]) -> dict[str, str]:
    """Turn ``--map`` strings ``"src=dst"`` / ``"src=dst[unit]"`` / ``"src=-"`` into ``{src: dst}``."""
    mapping: dict[str, str] = {}
    targets: dict[str, str] = {}
    for item in items:
        where = f"--map {item!r}"
        src, sep, dst = item.partition("=")
        src = src.strip()
        if not sep or not src or not dst.strip():
            raise DataError("expected SRC=CHANNEL or SRC=CHANNEL[unit], e.g. 2=output[um]", where=where)
        if src in mapping:
            raise DataError(f"{src!r} is mapped twice", where=where)
        name, unit = parse_target(dst, where)
        if name != DROP:
            if name in targets:
                raise DataError(f"{targets[name]!r} and {src!r} are both mapped to {name!r}", where=where)
            targets[name] = src
        mapping[src] = name if unit is None else f"{name}[{unit}]"
    return mapping


# -- reading sources -------------------------------------------------------------------------


def _sha256(raw: bytes) -> str:
    return hashlib.sha256(raw).hexdigest()


def _read_bytes(path: Path, where: str) -> bytes:
    if not path.exists():
        raise DataError("file not found", where=where)
    if path.is_dir():
        raise DataError("is a directory, expected a .csv or .mat file", where=where)
    suffix = path.suffix.lower()
    if suffix not in TEXT_SUFFIXES + MAT_SUFFIXES:
        raise DataError(
            f"unsupported file type {suffix or '(no extension)'!r} "
            f"(expected {', '.join(TEXT_SUFFIXES + MAT_SUFFIXES)}, or an aixACCT .dat export)",
            where=where,
        )
    try:
        return path.read_bytes()
    except OSError as exc:
        raise DataError(f"cannot read ({exc.strerror or exc.__class__.__name__})", where=where) from exc


def _sample_rate(time: np.ndarray, where: str) -> float:
    """Sample rate in Hz from a strictly increasing time vector in s.

    The mean step is used when it agrees with the median step within 1 % (it is exact for clocks that
    jitter by a least significant digit, as dSPACE and many loggers do); otherwise, with gaps, the median.
    """
    if len(time) < 2:
        raise DataError(f"need at least 2 samples to know the sample rate, got {len(time)}", where=where)
    median = float(np.median(np.diff(time)))
    mean = float(time[-1] - time[0]) / (len(time) - 1)
    return 1.0 / (mean if abs(mean / median - 1.0) < 0.01 else median)


@dataclass
class _Channels:
    """Channels picked from a source: float64 data, units, descriptions and the source key of each."""

    data: dict[str, np.ndarray] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    descriptions: dict[str, str] = field(default_factory=dict)
    sources: dict[str, str] = field(default_factory=dict)
    unitless: list[str] = field(default_factory=list)  # mapped columns with no unit in file or mapping


def _pick(
    columns: list[SourceColumn],
    mapping: dict[str, str],
    fmt: str,
    line_numbers: list[int],
    listing: str,
    path: Path,
    where: str,
) -> _Channels:
    """Apply the mapping, parse the chosen columns and give them units (time converted to s)."""
    targets: dict[int, tuple[str, str | None]] = {}  # id(column) -> (channel, unit override)
    for key, value in mapping.items():
        col = resolve_column(columns, key, where, listing)
        if id(col) in targets:
            raise DataError(f"--map: column {col.label} is mapped twice", where=where)
        targets[id(col)] = parse_target(value, f"--map {key}={value}")
    # In .mat files a mapping selects variables (they often hold many unrelated vectors); the time
    # base (dSPACE X.Data, a variable named `time`) stays unless a mapping gives another one.
    selecting = fmt != "csv" and bool(mapping)
    mapped_names = {name for name, _ in targets.values()}

    out = _Channels()
    for col in columns:
        mapped = id(col) in targets
        name, unit = targets.get(id(col), (col.name, None))
        if name == DROP or name is None:
            continue
        if selecting and not mapped and (name != "time" or "time" in mapped_names):
            continue
        if col.cells is not None and all(c == "" for c in col.cells):
            if mapped or name in ("time", *REQUIRED):
                raise DataError(f"column {col.label} ({name}) has no values", where=where)
            continue  # e.g. a pandas index column written without values
        if name in out.data:
            raise DataError(f"two columns give channel {name!r}: {out.sources[name]} and {col.label}", where=where)
        values = col.values if col.values is not None else parse_cells(col, name, line_numbers, where)
        if not np.all(np.isfinite(values)):  # only .mat data get here: CSV cells were checked one by one
            bad = int(np.flatnonzero(~np.isfinite(values))[0])
            raise DataError(f"{col.label} ({name}): {values[bad]} at element {bad + 1}, expected a finite number",
                            where=where)
        if unit is None and col.unit is None and mapped:
            out.unitless.append(f"{col.key}={name}")
        if unit is None:
            unit = col.unit if col.unit is not None else CANONICAL_CHANNELS.get(name, ("", ""))[0]
        description = f"imported from {path.name}, {col.label}"
        if name == "time" and unit != "s":
            if unit not in TIME_UNITS_S:
                raise DataError(f"time unit {unit!r} not understood (expected one of: {', '.join(TIME_UNITS_S)})",
                                where=where)
            values, description, unit = values * TIME_UNITS_S[unit], f"{description}, converted from {unit} to s", "s"
        out.data[name], out.units[name], out.descriptions[name], out.sources[name] = values, unit, description, col.key
    return out


def _add_time(ch: _Channels, rate_hz: float | None, line_numbers: list[int], where: str) -> float:
    """Check the time channel, or make one from ``rate_hz``; returns the sample rate in Hz."""
    n = len(ch.data["input"])
    if "time" not in ch.data:
        if rate_hz is None:
            raise DataError("no time column: give the sample rate (--rate HZ) or map a time column", where=where)
        ch.data["time"] = np.arange(n, dtype=np.float64) / rate_hz
        ch.units["time"] = "s"
        ch.descriptions["time"] = f"sample index / {rate_hz:g} Hz (the source has no time column)"
        ch.sources["time"] = f"rate {rate_hz:g} Hz"
        return float(rate_hz)
    time = ch.data["time"]
    steps = np.diff(time)
    if np.any(steps <= 0):
        i = int(np.flatnonzero(steps <= 0)[0]) + 1
        source = "X.Data" if ch.sources["time"] == "X" else ch.sources["time"]
        at = f"line {line_numbers[i]}" if line_numbers else f"{source}({i + 1})"
        raise DataError(f"time is not strictly increasing at {at} ({time[i]:.10g} after {time[i - 1]:.10g})",
                        where=where)
    rate = _sample_rate(time, where)
    if rate_hz is not None and abs(rate / rate_hz - 1.0) > 0.01:
        raise DataError(f"the time column gives {rate:.6g} Hz but the rate given is {rate_hz:.6g} Hz; drop one",
                        where=where)
    return rate


def load_source(
    source: str | os.PathLike[str],
    *,
    label: str | None = None,
    rate_hz: float | None = None,
    mapping: dict[str, str] | None = None,
) -> ImportedRun:
    """Read and check one source file completely; nothing is written.

    ``rate_hz`` (Hz) is needed when the source has no time column; with one, the rate comes from
    the time stamps (s) and a ``rate_hz`` that disagrees by more than 1 % is an error.
    """
    path = Path(source)
    where = str(source)
    if rate_hz is not None and not (np.isfinite(rate_hz) and rate_hz > 0):
        raise DataError(f"sample rate must be a positive number of Hz, got {rate_hz}", where="--rate")
    raw = _read_bytes(path, where)
    line_numbers: list[int] = []
    has_header = True
    if path.suffix.lower() in MAT_SUFFIXES:
        columns, fmt, info = mat_columns(raw, where)
    else:
        columns, line_numbers, has_header = csv_columns(raw, where)
        fmt, info = "csv", {}
    listing = column_listing(columns, has_header)
    ch = _pick(columns, dict(mapping or {}), fmt, line_numbers, listing, path, where)

    for required in REQUIRED:
        if required not in ch.data:
            raise DataError(
                f"missing column {required!r} (columns: {listing}); map one with --map SRC={required}", where=where
            )
    lengths = {name: len(v) for name, v in ch.data.items()}
    if len(set(lengths.values())) != 1:
        detail = ", ".join(f"{ch.sources[name]} ({name}) {k}" for name, k in lengths.items())
        raise DataError(f"channels differ in length: {detail}", where=where)
    if lengths["input"] == 0:
        raise DataError("no samples", where=where)
    rate = _add_time(ch, rate_hz, line_numbers, where)
    if ch.unitless:
        first = ch.unitless[0]
        raise DataError(
            f"--map {first}: the column has no unit in the file and the mapping gives none",
            where=where,
            hint=f"give the unit in the mapping, e.g. --map {first}[{_example_unit(first.split('=', 1)[1])}]",
        )

    order = ["time", "input", "output"] + [k for k in ch.data if k not in ("time", "input", "output")]
    digest = _sha256(raw)
    excitation = {"kind": "imported", "source": path.name, "sha256": digest, "format": fmt,
                  "channels": {k: ch.sources[k] for k in order}, **info}
    return ImportedRun(
        source=path,
        label=label if label is not None else path.stem,
        data={k: ch.data[k] for k in order},
        units={k: ch.units[k] for k in order},
        descriptions={k: ch.descriptions[k] for k in order},
        sample_rate_hz=rate,
        sha256=digest,
        excitation=excitation,
    )


def is_aixacct_export(path: Path) -> bool:
    """An aixACCT TF Analyzer text export: a ``.dat`` file with ``Table n`` data blocks."""
    if path.suffix.lower() != ".dat" or not path.is_file():
        return False
    with open(path, encoding="latin-1", errors="replace") as f:
        head = [f.readline() for _ in range(400)]
    return any(line.strip().startswith("Table ") and line.strip()[6:].strip().isdigit() for line in head)


def load_aixacct_runs(source: str | os.PathLike[str], *, label: str | None = None) -> list[ImportedRun]:
    """One run per ``Table n`` block of an aixACCT export: input the drive voltage ``V+`` (V), output the
    displacement ``D1`` (um), time from the block's start (s); every other column kept in its unit."""
    from hilbench.recording.aixacct import load_aixacct_dat

    path = Path(source)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataError(f"cannot read ({exc.strerror or exc.__class__.__name__})", where=str(source)) from exc
    digest = _sha256(raw)
    runs = []
    for block in load_aixacct_dat(path):
        t = np.asarray(block["time"], float)
        if t.size < 2:
            continue
        rate = (t.size - 1) / (t[-1] - t[0])
        name = f"{label or path.stem}-table{block['table']}"
        data = {"time": t - t[0], "input": np.asarray(block["voltage"], float),
                "output": np.asarray(block["displacement"], float)}
        runs.append(ImportedRun(
            source=path, label=name, data=data, units={"time": "s", "input": "V", "output": "um"},
            descriptions={"time": "time from the block's start", "input": "drive voltage V+",
                          "output": "displacement D1 (nm / 1000)"},
            sample_rate_hz=float(rate), sha256=digest,
            excitation={"kind": "imported", "source": path.name, "sha256": digest, "format": "aixacct-dat",
                        "table": block["table"], "header": block["header"]},
        ))
    if not runs:
        raise DataError("no data blocks (Table n) in the aixACCT export", where=str(source))
    return runs


# -- writing ---------------------------------------------------------------------------------


def _write(writer: RecordingWriter, run: ImportedRun, experiment: str) -> str:
    return writer.write_run(
        run.label,
        run.data,
        run.units,
        descriptions=run.descriptions,
        experiment=experiment,
        excitation=run.excitation,
        sample_rate_hz=run.sample_rate_hz,
        extra_attrs={"source": run.source.name, "source_sha256": run.sha256},
    )


def import_files(
    sources: list[str | Path],
    output: str | Path,
    *,
    run_names: list[str] | None = None,
    rate_hz: float | None = None,
    mapping: dict[str, str] | None = None,
    experiment: str = "import",
) -> list[str]:
    """Import each source as one run into the recording ``output`` (created, or appended to).

    ``rate_hz`` (Hz) is used for sources without a time column; ``mapping`` maps source columns to
    channels (see the module docstring). All sources are read and checked before ``output`` is
    touched; a new file is written under a temporary name and renamed when complete. Returns the
    run group names (``0003-label``).
    """
    if not sources:
        raise DataError("no files to import")
    if run_names is not None and len(run_names) != len(sources):
        raise DataError(f"got {len(run_names)} run names for {len(sources)} files; give one per file", where="--run")
    for name in run_names or []:
        check_run_name(name)
    out = Path(output)
    if out.suffix.lower() not in (".h5", ".hdf5", ".hdf", ".he5"):
        raise DataError(f"expected a recording file ending in .h5, got {out.name!r}", where=str(out),
                        hint="e.g. -o measured.h5")
    runs = []
    with progress.task(f"import {len(sources)} file(s)", total=2 * len(sources)) as advance:
        for i, src in enumerate(sources):
            advance(0, f"import: reading {Path(src).name}")
            label = None if run_names is None else run_names[i]
            if is_aixacct_export(Path(src)):
                runs.extend(load_aixacct_runs(src, label=label))
            else:
                runs.append(load_source(src, label=label, rate_hz=rate_hz, mapping=mapping))
            advance(1)
        advance(0, f"import: writing {out.name}")
        return _write_runs(runs, out, experiment, advance)


def _write_runs(runs: list[ImportedRun], out: Path, experiment: str, advance: Any) -> list[str]:
    if out.exists():
        if out.is_dir():
            raise DataError("is a directory, expected a recording file (.h5)", where=str(out))
        check_recording(out)
        writer = RecordingWriter(out)
        written = []
        for run in runs:
            written.append(_write(writer, run, experiment))
            advance(1)
        return written

    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    tmp.unlink()  # RecordingWriter creates the file itself
    try:
        writer = RecordingWriter(tmp)
        names = []
        for run in runs:
            names.append(_write(writer, run, experiment))
            advance(1)
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return names
