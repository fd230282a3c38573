"""Figures of a fit (``hilbench fit --plot``): measured vs model loops and the error over time.

One row per run (up to :data:`MAX_RUNS`): on the left the output-vs-input loop, measured (grey) and
model (red); on the right the error e = model - measured (output unit, usually um) against time (s),
training rows in blue, validation rows in orange on a shaded background. Long runs are decimated by
plain striding for drawing only.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hilbench.report.figures import save_figure, stride

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from hilbench.identify.fitting import FitResult, FitRun

MAX_RUNS = 6


def plot_fit(result: FitResult, png: str | os.PathLike[str], *, max_points: int = 8000) -> Path:
    """Draw the runs of ``result`` into the PNG ``png`` and return its path (matplotlib Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [r for r in result.runs if len(r.data)][:MAX_RUNS]
    n_rows = max(1, len(shown))
    fig, axes = plt.subplots(n_rows, 2, figsize=(12.0, 3.3 * n_rows), squeeze=False,
                             gridspec_kw={"width_ratios": [1.0, 1.6]})
    for row, run in zip(axes, shown):
        _draw(result, run, row[0], row[1], max_points)
    left_out = len([r for r in result.runs if len(r.data)]) - len(shown)
    note = f" (first {MAX_RUNS} runs of {MAX_RUNS + left_out})" if left_out > 0 else ""
    how = "fitted" if result.refitted else "loaded"
    val = result.metrics["validation"]
    trn = result.metrics["train"]
    fig.suptitle(f"{result.spec} ({how}): rmse train {trn['rmse']:.4g}, validation {val['rmse']:.4g} "
                 f"{result.output_unit}{note}", fontsize=11)
    fig.tight_layout()
    return save_figure(fig, png)


def _spans(mask: np.ndarray) -> list[tuple[int, int]]:
    """Index ranges [start, stop) where ``mask`` is True."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def _draw(result: FitResult, run: FitRun, ax_loop: Axes, ax_err: Axes, max_points: int) -> None:
    data = run.data
    n = len(data)
    step = stride(n, max_points)
    fs = data.sample_rate_hz if data.sample_rate_hz > 0 else 1.0
    t = np.arange(n) / fs
    y_model = run.simulated if run.simulated is not None else np.full(n, np.nan)
    error = y_model - data.output
    u_label = f"input [{result.input_unit}]" if result.input_unit else "input"
    y_unit = result.output_unit

    ax_loop.plot(data.input[::step], data.output[::step], color="0.55", lw=0.8, label="measured")
    ax_loop.plot(data.input[::step], y_model[::step], color="tab:red", lw=0.8, ls="--", label="model")
    ax_loop.set_xlabel(u_label)
    ax_loop.set_ylabel(f"output [{y_unit}]")
    ax_loop.set_title(f"{run.key} ({run.role})", fontsize=9)
    ax_loop.grid(True, alpha=0.3)
    ax_loop.legend(loc="upper left", fontsize=8)

    for start, stop in _spans(run.validation):
        ax_err.axvspan(t[start], t[stop - 1], color="tab:orange", alpha=0.12, lw=0)
    for role, color in (("train", "tab:blue"), ("validation", "tab:orange")):
        mask = getattr(run, role)
        e = np.where(mask, error, np.nan)[::step]
        if mask.any():
            m = run.metrics.get(role) or {}
            ax_err.plot(t[::step], e, color=color, lw=0.6,
                        label=f"{role}: rmse {m.get('rmse', float('nan')):.3g}, max |e| {m.get('max_abs_error', float('nan')):.3g}")
    unused = ~(run.train | run.validation)
    if unused.any():
        ax_err.plot(t[::step], np.where(unused, error, np.nan)[::step], color="0.6", lw=0.6, label="unused")
    ax_err.axhline(0.0, color="black", lw=0.5)
    ax_err.set_xlabel("time [s]")
    ax_err.set_ylabel(f"model - measured [{y_unit}]")
    drawn = f", 1 in {step} drawn" if step > 1 else ""
    ax_err.set_title(f"error over time ({n} samples, {data.sample_rate_hz:g} Hz{drawn}; validation shaded)",
                     fontsize=9)
    ax_err.grid(True, alpha=0.3)
    ax_err.legend(loc="upper right", fontsize=8)
