"""Quick-look plots of recorded runs: time traces and the input-output loop, one row per run.

Axis labels carry the units stored in the recording (``time`` in s, ``input`` in V or A, ``output``
usually in um). Long runs are decimated by plain striding for drawing only.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hilbench.errors import DataError
from hilbench.recording.hdf5 import Recording, Run
from hilbench.report.figures import save_figure, stride

if TYPE_CHECKING:
    from matplotlib.figure import Figure

MAX_RUNS = 12
#: Channels drawn in the trace panel already; everything else goes to the auxiliary panel.
_MAIN = ("time", "input", "output", "reference")


def _label(name: str, unit: str) -> str:
    return f"{name} [{unit}]" if unit else name


def _select(recording: Recording, runs: list[str] | None) -> tuple[list[Run], str]:
    """Runs to draw and a note for the title when some were left out."""
    if not recording.runs:
        raise DataError("the recording has no runs", where=str(recording.path))
    if runs:
        if len(runs) > MAX_RUNS:
            raise DataError(f"at most {MAX_RUNS} runs fit in one figure, {len(runs)} were asked for", where="--run")
        return [recording.run(name) for name in runs], ""
    chosen = recording.runs[:MAX_RUNS]
    note = f" (first {MAX_RUNS} of {len(recording.runs)} runs)" if len(recording.runs) > MAX_RUNS else ""
    return chosen, note


def _check(run: Run) -> None:
    missing = [c for c in ("input", "output") if c not in run.units]
    if missing:
        raise DataError(
            f"run {run.name} has no {' or '.join(repr(m) for m in missing)} channel to plot "
            f"(channels: {', '.join(run.channels) or 'none'})",
            where=str(run.path),
        )


def plot_runs(
    path: str | os.PathLike[str],
    output_png: str | os.PathLike[str],
    *,
    runs: list[str] | None = None,
    max_points: int = 20000,
) -> Path:
    """Draw the runs of the recording ``path`` into the PNG ``output_png`` and return its path.

    Each run gets a row: input and output against time (s) on twin y axes, auxiliary channels
    against time when the recording has any, and the loop output against input. ``runs`` selects
    runs by name, label or 1-based index (default: all, at most 12); runs longer than
    ``max_points`` samples are drawn with every k-th sample.
    """
    return save_figure(make_figure(path, runs=runs, max_points=max_points), output_png)


def make_figure(
    path: str | os.PathLike[str], *, runs: list[str] | None = None, max_points: int = 20000
) -> Figure:
    """The figure :func:`plot_runs` saves (Agg backend); close it with ``plt.close(fig)``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recording = Recording(path)
    selected, note = _select(recording, runs)
    for run in selected:
        _check(run)
    has_aux = any(c not in _MAIN for run in selected for c in run.channels)
    n_cols = 3 if has_aux else 2
    widths = [2.2, 1.6, 1.2] if has_aux else [2.4, 1.2]
    fig, axes = plt.subplots(
        len(selected), n_cols, figsize=(5.2 * n_cols, 3.4 * len(selected)),
        gridspec_kw={"width_ratios": widths}, squeeze=False,
    )
    for row, run in zip(axes, selected):
        _draw_run(run, row, has_aux, max_points)
    fig.suptitle(f"{recording.path.name}{note}", fontsize=12)
    fig.tight_layout()
    return fig


def _draw_run(run: Run, row: np.ndarray, has_aux: bool, max_points: int) -> None:
    data = run.data()
    n = run.n_samples
    step = stride(n, max_points)
    rate = run.sample_rate_hz
    if "time" in data:
        t, t_label = data["time"], _label("time", run.units["time"])
    else:
        t = np.arange(n) / rate if rate > 0 else np.arange(n, dtype=float)
        t_label = "time [s]" if rate > 0 else "sample"
    t = t[::step]
    title = f"{run.name}  ({n} samples, {rate:g} Hz{f', 1 in {step} drawn' if step > 1 else ''})"

    ax_in = row[0]
    ax_out = ax_in.twinx()
    u, y = data["input"][::step], data["output"][::step]
    ax_in.plot(t, u, color="tab:blue", lw=0.8, label="input")
    ax_out.plot(t, y, color="tab:red", lw=0.8, label="output")
    if "reference" in data and run.units.get("reference") == run.units["output"]:
        ax_out.plot(t, data["reference"][::step], color="black", lw=0.8, ls="--", label="reference")
    ax_in.set_xlabel(t_label)
    ax_in.set_ylabel(_label("input", run.units["input"]), color="tab:blue")
    ax_out.set_ylabel(_label("output", run.units["output"]), color="tab:red")
    ax_in.tick_params(axis="y", colors="tab:blue")
    ax_out.tick_params(axis="y", colors="tab:red")
    ax_in.set_title(title, fontsize=9)
    ax_in.grid(True, alpha=0.3)
    handles = ax_in.get_legend_handles_labels()[0] + ax_out.get_legend_handles_labels()[0]
    ax_in.legend(handles, [h.get_label() for h in handles], loc="upper left", fontsize=8)

    if has_aux:
        ax_aux = row[1]
        aux = [c for c in run.channels if c not in _MAIN]
        for name in aux:
            ax_aux.plot(t, data[name][::step], lw=0.8, label=_label(name, run.units[name]))
        if aux:
            units = {run.units[c] for c in aux}
            ax_aux.set_ylabel(f"[{units.pop()}]" if len(units) == 1 and "" not in units else "auxiliary")
            ax_aux.legend(loc="best", fontsize=8)
        else:
            ax_aux.text(0.5, 0.5, "no auxiliary channels", ha="center", va="center", transform=ax_aux.transAxes)
        ax_aux.set_xlabel(t_label)
        ax_aux.set_title(f"{run.label}: auxiliary channels", fontsize=9)
        ax_aux.grid(True, alpha=0.3)

    ax_loop = row[-1]
    ax_loop.plot(u, y, color="tab:purple", lw=0.6)
    ax_loop.set_xlabel(_label("input", run.units["input"]))
    ax_loop.set_ylabel(_label("output", run.units["output"]))
    ax_loop.set_title(f"{run.label}: output vs input", fontsize=9)
    ax_loop.grid(True, alpha=0.3)
    if n == 0:
        for ax in row:
            ax.text(0.5, 0.5, "no samples", ha="center", va="center", transform=ax.transAxes)
