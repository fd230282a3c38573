"""Reader for aixACCT TF Analyzer text exports (``.dat``: latin-1, tab separated).

A file holds a summary table, then blocks that start with a line ``Table n``, a header of
``key: value`` lines (Waveform, SampleName, Hysteresis Frequency [Hz], ...) and a data table whose
first line names the columns (``Time [s]``, ``V+ [V]``, ..., ``D1 [nm]``, ...).

:func:`load_aixacct_dat` returns one dict per block: ``time`` (s), ``voltage`` (V, column ``V+``),
``displacement`` (um, column ``D1`` in nm divided by 1000), ``columns`` (every column by its
header name, source units), ``header`` (the block's ``key: value`` fields, values as text) and
``table`` (the block number).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from hilbench.errors import DataError

_TABLE = re.compile(r"^Table\s+(\d+)\s*$")


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return float("nan")


def load_aixacct_dat(path: str | Path) -> list[dict[str, Any]]:
    """One dict per ``Table n`` data block of the aixACCT export ``path`` (see the module docstring)."""
    p = Path(path)
    lines = p.read_text(encoding="latin-1").splitlines()
    blocks: list[dict[str, Any]] = []
    i = 0
    n = len(lines)
    while i < n:
        m = _TABLE.match(lines[i].strip())
        if not m:
            i += 1
            continue
        table = int(m.group(1))
        header: dict[str, str] = {}
        j = i + 1
        # header lines up to the column line ("Time [s] ..."); the summary table has no such line
        while j < n and not lines[j].startswith("Time [s]") and not _TABLE.match(lines[j].strip()):
            if ":" in lines[j] and "\t" not in lines[j]:
                key, _, value = lines[j].partition(":")
                header[key.strip()] = value.strip()
            j += 1
        if j >= n or not lines[j].startswith("Time [s]"):
            i = j  # a summary table, not a data block
            continue
        names = [c.strip() for c in lines[j].split("\t") if c.strip()]
        rows: list[list[float]] = []
        j += 1
        while j < n and lines[j].strip() and not _TABLE.match(lines[j].strip()):
            cells = [c for c in lines[j].split("\t") if c.strip()]
            rows.append([_float(c) for c in cells[: len(names)]] + [float("nan")] * (len(names) - len(cells)))
            j += 1
        data = np.asarray(rows, dtype=float).reshape(-1, len(names))
        columns = {name: data[:, k] for k, name in enumerate(names)}
        for needed in ("Time [s]", "V+ [V]", "D1 [nm]"):
            if needed not in columns:
                raise DataError(f"table {table} has no column {needed!r}", where=str(p))
        blocks.append({
            "table": table,
            "header": header,
            "time": columns["Time [s]"],
            "voltage": columns["V+ [V]"],
            "displacement": columns["D1 [nm]"] / 1000.0,
            "columns": columns,
        })
        i = j
    if not blocks:
        raise DataError("no 'Table n' data blocks found", where=str(p))
    return blocks


__all__ = ["load_aixacct_dat"]
