"""The columns of one source file before any mapping: a CSV file's text cells (split by its
delimiter, with or without a header of ``name[unit]`` cells), a plain .mat file's variables, or a
dSPACE ControlDesk capture's ``X`` and ``Y(n)`` signals; and how a mapping key finds its column.

Problems are raised as :class:`hilbench.errors.DataError` naming file, line, column and value.
"""

from __future__ import annotations

import csv
import io
import re
import unicodedata
from dataclasses import dataclass
from typing import Any

import numpy as np

from hilbench.errors import DataError
from hilbench.recording.units import decode_text, normalize_unit

CHANNEL_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_.+-]*")
_HEADER_RE = re.compile(r"\s*(.*?)\s*(?:\[\s*([^\[\]]*?)\s*\]|\(\s*([^()]*?)\s*\))?\s*")
_Y_INDEX_RE = re.compile(r"[Yy]\((\d+)\)")


@dataclass
class SourceColumn:
    """A source column before mapping: ``key`` addresses it in a mapping, ``label`` names it in messages."""

    key: str
    label: str
    name: str | None  # channel name it gets when not mapped (None: ignored unless mapped)
    unit: str | None
    values: np.ndarray | None = None  # float64, None until parsed
    cells: list[str] | None = None  # CSV text cells, parsed lazily
    aliases: tuple[str, ...] = ()  # other keys that address it (header text with unit, dSPACE names)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _sniff_delimiter(line: str) -> str:
    counts = {d: line.count(d) for d in (",", ";", "\t")}
    best = max(counts, key=lambda d: counts[d])
    return best if counts[best] > counts[","] else ","


def csv_columns(raw: bytes, where: str) -> tuple[list[SourceColumn], list[int], bool]:
    """Split a delimited text file into columns of text cells; returns (columns, line numbers, has header)."""
    text = decode_text(raw)
    lines = text.splitlines()
    first = next((ln for ln in lines if ln.strip() and not ln.lstrip().startswith("#")), None)
    if first is None:
        raise DataError("no data (the file is empty)", where=where)
    reader = csv.reader(io.StringIO(text), delimiter=_sniff_delimiter(first))
    rows: list[list[str]] = []
    line_numbers: list[int] = []
    for row in reader:
        if all(not c.strip() for c in row) or row[0].lstrip().startswith("#"):
            continue  # blank lines and # comments
        rows.append([c.strip() for c in row])
        line_numbers.append(reader.line_num)
    header_cells = rows[0]
    has_header = not all(c == "" or _is_number(c) for c in header_cells)
    width = len(header_cells)
    header_line = line_numbers[0]
    if has_header:
        rows, line_numbers = rows[1:], line_numbers[1:]
    for row, ln in zip(rows, line_numbers):
        if len(row) != width:
            what = f"the header (line {header_line})" if has_header else "the first row"
            raise DataError(f"line {ln}: {len(row)} cells, expected {width} as in {what}", where=where)
    if not rows:
        raise DataError("no data rows", where=where)

    columns: list[SourceColumn] = []
    for j in range(width):
        cells = [row[j] for row in rows]
        if has_header:
            m = _HEADER_RE.fullmatch(header_cells[j])
            assert m is not None  # the pattern matches any text
            raw_name, unit = m.group(1), m.group(2) if m.group(2) is not None else m.group(3)
            unit = normalize_unit(unit) if unit is not None else None
            name = re.sub(r"[^A-Za-z0-9_.+-]+", "_", raw_name).strip("_") or None
            if name is not None and not CHANNEL_RE.fullmatch(name):
                name = f"c_{name}"
            key = raw_name if raw_name else str(j)
            label = f"{raw_name!r}" if raw_name else f"{j}"
            aliases = tuple({header_cells[j], str(j)} - {key})
            columns.append(SourceColumn(key, label, name, unit, cells=cells, aliases=aliases))
        else:
            columns.append(SourceColumn(str(j), str(j), None, None, cells=cells))
    return columns, line_numbers, has_header


def parse_cells(col: SourceColumn, target: str, line_numbers: list[int], where: str) -> np.ndarray:
    """Convert a CSV column's text cells to float64, naming line, column and value on failure."""
    assert col.cells is not None
    label = col.label if target == col.key else f"{col.label} (mapped to {target!r})"
    try:
        values = np.array(col.cells, dtype=np.float64)
    except ValueError:
        values = None
    if values is None or not np.all(np.isfinite(values)):
        for cell, ln in zip(col.cells, line_numbers):
            if cell == "":
                raise DataError(f"line {ln}, column {label}: empty cell, expected a number", where=where)
            try:
                number = float(cell)
            except ValueError:
                raise DataError(f"line {ln}, column {label}: {cell!r} is not a number", where=where) from None
            if not np.isfinite(number):
                raise DataError(f"line {ln}, column {label}: {cell!r} is not a finite number", where=where)
    assert values is not None
    return values


def _display(name: str) -> str:
    """A dSPACE block name for messages: control characters (a lost 'å') shown as '?'."""
    return "".join("?" if unicodedata.category(ch).startswith("C") else ch for ch in name)


def _fold(name: str) -> str:
    """Compare names ignoring case and non-ASCII letters, which dSPACE exports often mangle to '\\x1a'."""
    name = unicodedata.normalize("NFC", name).casefold()
    return re.sub(r"(?:[^\x20-\x7e]|\?)+", "?", name)


def _dspace_names(full_name: str) -> list[str]:
    """Path components of ``"Model Root"/"Måling"/"In1"`` without quotes: ['Model Root', 'Måling', 'In1']."""
    return [part.strip().strip('"').strip() for part in str(full_name).split("/") if part.strip()]


def _as_1d(value: Any) -> np.ndarray | None:
    """A real numeric 1-D (or 1xN) array as float64, else None."""
    if not isinstance(value, np.ndarray) or value.dtype.kind not in "iufb":
        return None
    array = np.squeeze(value)
    return array.astype(np.float64) if array.ndim == 1 else None


def mat_columns(raw: bytes, where: str) -> tuple[list[SourceColumn], str, dict[str, Any]]:
    """Columns of a .mat file; returns (columns, format name, extra excitation info)."""
    import scipy.io  # imported late: scipy.io is slow to import and only needed here

    try:
        contents = scipy.io.loadmat(io.BytesIO(raw), squeeze_me=True, struct_as_record=False)
    except NotImplementedError as exc:  # v7.3 files are HDF5
        raise DataError(f"MATLAB v7.3 (HDF5) files are not supported; save with -v7 ({exc})", where=where) from exc
    except Exception as exc:  # scipy raises ValueError, TypeError, MatReadError... for a corrupt file
        raise DataError(f"not a readable MATLAB .mat file ({exc})", where=where) from exc
    variables = {k: v for k, v in contents.items() if not k.startswith("__")}
    captures = {
        k: v
        for k, v in variables.items()
        if hasattr(v, "_fieldnames") and {"X", "Y"} <= set(v._fieldnames)
    }
    if len(captures) > 1:
        names = ", ".join(captures)
        raise DataError(f"{len(captures)} dSPACE captures ({names}); one per file is supported", where=where)
    if captures:
        return _dspace_columns(*next(iter(captures.items())), where=where)
    columns = []
    for name, value in variables.items():
        array = _as_1d(value)
        if array is not None:
            label = f"variable {name!r}"
            ok = CHANNEL_RE.fullmatch(name) is not None
            columns.append(SourceColumn(name, label, name if ok else None, None, values=array))
    return columns, "mat", {}


def _dspace_columns(var: str, capture: Any, where: str) -> tuple[list[SourceColumn], str, dict[str, Any]]:
    x = capture.X
    if isinstance(x, np.ndarray):
        if x.size != 1:
            raise DataError(f"capture {var!r} has {x.size} time bases X; one is supported", where=where)
        x = x.item()
    time = _as_1d(getattr(x, "Data", None))
    if time is None:
        raise DataError(f"capture {var!r}: X.Data is not a numeric vector", where=where)
    columns = [SourceColumn("X", "X.Data", "time", "s", values=time)]
    ys = capture.Y if isinstance(capture.Y, np.ndarray) else np.array([capture.Y], dtype=object)
    for i, y in enumerate(np.atleast_1d(ys), start=1):
        parts = _dspace_names(getattr(y, "Name", ""))
        block = parts[-2] if len(parts) >= 3 else (parts[-1] if parts else "")
        label = f"Y({i}) {_display(block)!r}" if block else f"Y({i})"
        data = _as_1d(getattr(y, "Data", None))
        if data is None:
            raise DataError(f"capture {var!r}: Y({i}).Data is not a numeric vector", where=where)
        unit = getattr(y, "Unit", "")
        unit = normalize_unit(unit) if isinstance(unit, str) and unit.strip() else None
        # Addressable by any trailing path (Måling/In1, In1) or the block name alone.
        trailing = {"/".join(parts[k:]) for k in range(len(parts))}
        without_port = {"/".join(parts[k:-1]) for k in range(len(parts) - 1)}
        aliases = tuple(trailing | without_port)
        columns.append(SourceColumn(f"Y({i})", label, None, unit, values=data, aliases=aliases))
    info: dict[str, Any] = {"capture": var}
    date = getattr(getattr(capture, "Capture", None), "DateTime", None)
    if isinstance(date, str) and date:
        info["captured"] = date
    return columns, "dspace-mat", info


def resolve_column(columns: list[SourceColumn], key: str, where: str, listing: str) -> SourceColumn:
    """The column a mapping key addresses: by key, then alias (case- and umlaut-insensitive), then index."""
    exact = [c for c in columns if key == c.key or key in c.aliases]
    if len(exact) == 1:
        return exact[0]
    folded = [c for c in columns if _fold(key) in {_fold(a) for a in (c.key, *c.aliases)}]
    if len(folded) == 1:
        return folded[0]
    if len(folded) > 1:
        names = ", ".join(c.key for c in folded)
        raise DataError(f"--map key {key!r} matches several columns ({names}); use one of those", where=where)
    m = _Y_INDEX_RE.fullmatch(key)
    if m and any(c.key.startswith("Y(") for c in columns):
        n = sum(c.key.startswith("Y(") for c in columns)
        raise DataError(f"--map key {key!r}: the capture has only Y(1)..Y({n})", where=where)
    raise DataError(f"--map key {key!r} matches no column (columns: {listing})", where=where)


def column_listing(columns: list[SourceColumn], has_header: bool = True) -> str:
    parts = []
    for c in columns:
        if c.cells is not None and not has_header:
            first = c.cells[0] if c.cells else ""
            parts.append(f"{c.key} ({first or 'empty'})")
        else:
            parts.append(c.label.replace("variable ", ""))
    return ", ".join(parts) or "none"
