"""The results of a batch: one row per task, kept as they arrive, written as Parquet, CSV and JSON.

Every finished row is appended to ``rows.jsonl`` in the output folder and flushed to disk at once,
so an interrupt, a crash of the client or a lost cluster keeps every row that finished. A rerun
reads that file and skips every task whose key (content hash, run, command, options, version) has a
row; failed rows are kept too (a corrupt file stays corrupt) unless ``--retry-failed``. The table
files (``results.parquet``, ``results.csv``) and ``summary.json`` are rewritten from it at the end
of every batch, interrupted or not, with the rows of that batch's tasks in the order of its sources.
The columns are :data:`COLUMNS` (docs/archive.md explains each).
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from hilbench.errors import UserError

#: (column, type, meaning): the schema of results.parquet and results.csv, in order
COLUMNS: list[tuple[str, str, str]] = [
    ("file", "string", "the recording, absolute path"),
    ("name", "string", "its file name"),
    ("run", "string", "the run's group name, or * for every run of the file read as the single command reads it"),
    ("content_hash", "string", "SHA-256 of the recording's bytes"),
    ("command", "string", "fit, diagnose or online"),
    ("spec", "string", "the model spec or saved model given (--model)"),
    ("options", "string", "every option of the command, JSON"),
    ("key", "string", "the result's identity: content, run, command, options, hilbench version"),
    ("status", "string", "done or failed"),
    ("error", "string", "why it failed, one line (empty when done)"),
    ("recorded", "string", "when the recording was created (its 'created' attribute, ISO 8601 UTC)"),
    ("runs", "int64", "runs read"),
    ("samples", "int64", "samples read over those runs"),
    ("sample_rate_hz", "float64", "the first run's sample rate, Hz"),
    ("input_unit", "string", "the input channel's unit"),
    ("output_unit", "string", "the output channel's unit"),
    ("aux_means", "string", "mean of every auxiliary channel (temperature, load, ...) over the runs read, JSON"),
    ("final_spec", "string", "the model at the end: after diagnose's --add/--auto steps, online's offline model"),
    ("effects_found", "string", "diagnose: the significant effects of the final round, best first, ';'-separated"),
    ("effects_added", "string", "diagnose: the effects --add/--auto added, in order, ';'-separated"),
    ("train_rmse", "float64", "training rmse, output unit (online: the offline model's)"),
    ("validation_rmse", "float64", "validation rmse, output unit"),
    ("validation_erms_pct", "float64", "validation rms error, percent of the output's range"),
    ("validation_re_n2_pct", "float64", "validation relative 2-norm error, percent"),
    ("online_re_n2_pct", "float64", "online: one-step prediction re_N2, percent, mean over the runs"),
    ("offline_re_n2_pct", "float64", "online: the offline model's free-run re_N2, percent, mean over the runs"),
    ("persistence_re_n2_pct", "float64", "online: the naive y(k-1) predictor's re_N2, percent, mean over the runs"),
    ("metrics", "string", "every metric of the command's document, JSON"),
    ("parameters", "string", "the final model's parameters: [{name, value, unit}], JSON"),
    ("notes", "string", "the command's notes (left-out rows, incomplete runs), JSON"),
    ("read_s", "float64", "seconds reading the recording on the worker"),
    ("compute_s", "float64", "seconds of the command's computation on the worker"),
    ("task_s", "float64", "seconds the task took on the worker"),
    ("worker", "string", "host:pid of the worker process that ran it"),
    ("finished", "string", "when the task finished (ISO 8601 UTC)"),
    ("hilbench_version", "string", "the version that computed the row"),
]
COLUMN_NAMES = [name for name, _, _ in COLUMNS]
_NUMERIC = {name for name, kind, _ in COLUMNS if kind == "float64"}
_INTEGER = {name for name, kind, _ in COLUMNS if kind == "int64"}

ROWS_FILE = "rows.jsonl"
HASHES_FILE = "hashes.json"


def _normalised(row: dict[str, Any]) -> dict[str, Any]:
    """Every column present, with its type; NaN for a missing number, "" for a missing string."""
    out: dict[str, Any] = {}
    for name in COLUMN_NAMES:
        value = row.get(name)
        if name in _NUMERIC:
            try:
                value = float(value) if value is not None else math.nan
            except (TypeError, ValueError):
                value = math.nan
        elif name in _INTEGER:
            value = int(value) if isinstance(value, (int, float)) and math.isfinite(value) else None
        else:
            value = "" if value is None else str(value)
        out[name] = value
    return out


class ResultStore:
    """The output folder of a batch: the rows kept so far, appended to as tasks finish."""

    def __init__(self, folder: Path):
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.rows_file = folder / ROWS_FILE
        self.rows: dict[str, dict[str, Any]] = {}
        if self.rows_file.exists():
            self._read()
        self._append = open(self.rows_file, "a", encoding="utf-8")  # noqa: SIM115 - open for the batch
        try:  # two batches appending to one folder would each skip the other's work half done
            import fcntl

            fcntl.flock(self._append.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except ImportError:  # not on POSIX: no lock
            pass
        except OSError:
            self._append.close()
            raise UserError("another batch is writing to this folder", where=str(folder),
                            hint="wait for it, or give another --output folder") from None

    def _read(self) -> None:
        with open(self.rows_file, encoding="utf-8") as f:
            for line in f:
                try:
                    row = json.loads(line)
                except ValueError:
                    continue  # a line cut short by a crash: its task is simply run again
                if isinstance(row, dict) and "key" in row:
                    self.rows[row["key"]] = row

    def done(self, key: str, retry_failed: bool = False) -> bool:
        row = self.rows.get(key)
        return row is not None and not (retry_failed and row.get("status") != "done")

    def add(self, row: dict[str, Any]) -> None:
        """Keep a finished row: on disk before this returns."""
        row = _normalised(row)
        self.rows[row["key"]] = row
        self._append.write(json.dumps(row, allow_nan=True) + "\n")
        self._append.flush()
        os.fsync(self._append.fileno())

    def close(self) -> None:
        self._append.close()

    def table(self, keys: Iterable[str]) -> list[dict[str, Any]]:
        """The rows of these task keys that exist, in the keys' order."""
        return [_normalised(self.rows[k]) for k in keys if k in self.rows]

    def write_tables(self, rows: list[dict[str, Any]]) -> dict[str, Path]:
        """results.parquet and results.csv of these rows (written whole, then moved into place)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        types = {"string": pa.string(), "int64": pa.int64(), "float64": pa.float64()}
        schema = pa.schema([pa.field(name, types[kind]) for name, kind, _ in COLUMNS],
                           metadata={name: meaning for name, _, meaning in COLUMNS})
        arrays = [pa.array([r[name] for r in rows], type=types[kind]) for name, kind, _ in COLUMNS]
        parquet = self.folder / "results.parquet"
        tmp = parquet.with_suffix(".parquet.tmp")
        pq.write_table(pa.Table.from_arrays(arrays, schema=schema), tmp)
        os.replace(tmp, parquet)
        csv_path = self.folder / "results.csv"
        tmp = csv_path.with_suffix(".csv.tmp")
        with open(tmp, "w", newline="", encoding="utf-8") as f:
            writer = csv.DictWriter(f, fieldnames=COLUMN_NAMES)
            writer.writeheader()
            for row in rows:
                writer.writerow({k: ("" if isinstance(v, float) and math.isnan(v) else v) for k, v in row.items()})
        os.replace(tmp, csv_path)
        return {"parquet": parquet, "csv": csv_path}

    def write_summary(self, summary: dict[str, Any]) -> Path:
        path = self.folder / "summary.json"
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(summary, indent=2, default=str) + "\n", encoding="utf-8")
        os.replace(tmp, path)
        return path


def read_table(path: Path) -> list[dict[str, Any]]:
    """The rows of a results.parquet (a list of dicts, columns as :data:`COLUMNS`)."""
    import pyarrow.parquet as pq

    return pq.read_table(path).to_pylist()
