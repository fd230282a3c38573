"""The HTML report of a batch: the archive at a glance, one self-contained page (figures inline).

Three views a bench engineer asks of an archive: how well the model holds on each recording (the
validation error per recording, failures marked), how the fitted parameters move over the archive
(against the recordings' dates and against every auxiliary channel's mean, which is how an actuator
ageing or drifting with temperature or load shows), and the table of every row with its status and
reason. The parameters shown are those present in every successful row whose relative spread over
the archive is largest (at most :data:`MAX_PARAMETERS`): the ones that moved.
"""

from __future__ import annotations

import json
import math
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from hilbench.report.diagnosis_report import _CSS, _e, _num, _plt, _png, _table

MAX_PARAMETERS = 6
#: the column shown as "the error" of each command
ERROR_COLUMN = {"fit": "validation_erms_pct", "diagnose": "validation_erms_pct", "online": "online_re_n2_pct"}


def _when(text: str) -> float:
    try:
        return datetime.fromisoformat(str(text).replace("Z", "+00:00")).timestamp()
    except ValueError:
        return math.nan


def _parameter_table(rows: list[dict[str, Any]]) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """name -> value per row (NaN where a row lacks it), name -> unit; only names every row has."""
    per_row = [{p["name"]: p for p in json.loads(r["parameters"] or "[]")} for r in rows]
    common = set(per_row[0]) if per_row else set()
    for entry in per_row[1:]:
        common &= set(entry)
    values = {n: np.array([float(e[n]["value"]) for e in per_row]) for n in sorted(common)}
    units = {n: str(per_row[0][n].get("unit", "")) for n in common}
    return values, units


def _moving(values: dict[str, np.ndarray]) -> list[str]:
    """The parameters with the largest spread relative to their size, largest first."""
    spread = {}
    for name, v in values.items():
        v = v[np.isfinite(v)]
        if v.size < 2:
            continue
        scale = max(float(np.median(np.abs(v))), 1e-12)
        spread[name] = float(np.std(v)) / scale
    return [n for n, s in sorted(spread.items(), key=lambda kv: -kv[1]) if s > 0][:MAX_PARAMETERS]


def _axes(rows: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """The x axes parameters are drawn against: the date when dates differ, every auxiliary mean."""
    axes: dict[str, np.ndarray] = {}
    when = np.array([_when(r["recorded"]) for r in rows])
    if np.isfinite(when).sum() >= 2 and np.nanmax(when) - np.nanmin(when) > 0:
        axes["recorded (days from the first)"] = (when - np.nanmin(when)) / 86400.0
    means = [json.loads(r["aux_means"] or "{}") for r in rows]
    for name in sorted({k for m in means for k in m}):
        axes[f"mean {name}"] = np.array([float(m.get(name, math.nan)) for m in means])
    return axes


def _fig_errors(rows: list[dict[str, Any]], column: str) -> str:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 3.2))
    x = np.arange(len(rows))
    y = np.array([float(r[column]) if r["status"] == "done" else math.nan for r in rows])
    ax.bar(x, np.nan_to_num(y), color="#4477aa")
    failed = [i for i, r in enumerate(rows) if r["status"] != "done"]
    if failed:
        top = float(np.nanmax(y)) if np.isfinite(y).any() else 1.0
        ax.plot(failed, [top * 0.05] * len(failed), "x", color="#b00", label="failed")
        ax.legend(loc="upper right")
    ax.set_xlabel("recording (table order)")
    ax.set_ylabel(column.replace("_", " "))
    ax.set_xlim(-1, max(len(rows), 1))
    fig.tight_layout()
    return _png(fig)


def _fig_parameters(values: dict[str, np.ndarray], units: dict[str, str], names: list[str], x: np.ndarray,
                    xlabel: str) -> str:
    plt = _plt()
    cols = min(3, len(names))
    nrows = math.ceil(len(names) / cols)
    fig, axs = plt.subplots(nrows, cols, figsize=(3.4 * cols, 2.6 * nrows), squeeze=False)
    for ax, name in zip(axs.flat, names):
        ax.plot(x, values[name], "o", ms=3.5, color="#228833")
        ax.set_title(f"{name} ({units[name]})" if units[name] else name, fontsize=9)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in list(axs.flat)[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    return _png(fig)


def render(rows: list[dict[str, Any]], command: str) -> str:
    done = [r for r in rows if r["status"] == "done"]
    column = ERROR_COLUMN.get(command, "validation_erms_pct")
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>hilbench batch {_e(command)}</title>"
             f"<style>{_CSS}</style></head><body>",
             f"<h1>hilbench batch {_e(command)}: {len(rows)} rows</h1>",
             f"<p class='meta'>{len(done)} done, {len(rows) - len(done)} failed. Each row is one recording (or one "
             "run with --each run), computed by the library call of the single command on a Dask worker.</p>"]
    if rows:
        parts.append(f"<h2>Error per recording</h2><figure><img alt='errors' src='{_fig_errors(rows, column)}'>"
                     f"<figcaption>{_e(column)} of every row; a cross marks a failed row</figcaption></figure>")
    if len(done) >= 2:
        values, units = _parameter_table(done)
        names = _moving(values)
        if names:
            parts.append("<h2>Parameters over the archive</h2><p class='meta'>The parameters every successful row "
                         f"has that moved the most over the archive (std / |median|), at most {MAX_PARAMETERS}.</p>")
            for label, x in _axes(done).items():
                if np.isfinite(x).sum() >= 2:
                    parts.append(f"<figure><img alt='{_e(label)}' src='"
                                 f"{_fig_parameters(values, units, names, x, label)}'><figcaption>against "
                                 f"{_e(label)}</figcaption></figure>")
    head = ["file", "run", "status", "model", column, "effects added", "task s", "error"]
    body = [[(_e(r["name"]), ""), (_e(r["run"]), ""), (_e(r["status"]), "pass" if r["status"] == "done" else "fail"),
             (_e(r["final_spec"] or r["spec"]), ""), (_e(_num(r[column], 4)), ""), (_e(r["effects_added"]), ""),
             (_e(_num(r["task_s"], 3)), ""), (_e(r["error"]), "fail" if r["error"] else "")] for r in rows]
    parts.append("<h2>Rows</h2>" + _table(head, body))
    parts.append("</body></html>\n")
    return "".join(parts)


def write_archive_report(rows: list[dict[str, Any]], path: Path, command: str) -> Path:
    """Write the page (rendered whole before the file is touched) and return its path."""
    page = render(rows, command)
    tmp = path.with_suffix(".html.tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(path)
    return path
