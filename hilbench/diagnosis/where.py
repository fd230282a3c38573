"""Where the validation error is: shares of the squared error by run, time, input, rate and channel."""

from __future__ import annotations

from typing import Any

import numpy as np

from hilbench.diagnosis.rows import ResidualRows


def _shares(total: float, labels: list[tuple[str, Any]], masks: list[np.ndarray], e2: np.ndarray,
            top: int) -> list[dict[str, Any]]:
    out = []
    for (kind, rng), m in zip(labels, masks):
        if m.any():
            out.append({"kind": kind, "range": rng, "share": float(e2[m].sum() / total),
                        "fraction_of_rows": float(m.mean())})
    out.sort(key=lambda d: -d["share"])
    return out[:top]


def _quantile_bins(x: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    edges = np.unique(np.quantile(x, np.linspace(0, 1, n + 1)))
    if edges.size < 2:
        edges = np.array([x.min(), x.max() + 1e-12])
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    return edges, idx


def where(rows: ResidualRows, top: int = 5) -> list[dict[str, Any]]:
    """Shares of the summed squared validation error: top entries per kind, largest first.

    Kinds: ``run`` (range = run name), ``time`` (range = [run, t0 s, t1 s], 10 windows per run),
    ``input:<direction>`` (range = [lo, hi] input unit, quantile bins), ``rate`` (|input rate|
    bins, input unit/s), ``aux:<channel>`` (channel bins). ``fraction_of_rows`` is each bin's share
    of rows, so a share well above it marks where the model fails.
    """
    e2 = rows.e**2
    total = float(e2.sum()) or 1.0
    out: list[dict[str, Any]] = []
    runs = np.unique(rows.run)
    out += _shares(total, [("run", rows.keys[k]) for k in runs], [rows.run == k for k in runs], e2, top)
    labels, masks = [], []
    for k in runs:
        idx = np.flatnonzero(rows.run == k)
        for chunk in np.array_split(idx, min(10, idx.size)):
            labels.append(("time", [rows.keys[k], float(rows.t[chunk[0]]), float(rows.t[chunk[-1]])]))
            m = np.zeros(e2.size, bool)
            m[chunk] = True
            masks.append(m)
    out += _shares(total, labels, masks, e2, top)
    edges, idx = _quantile_bins(rows.u, 5)
    labels, masks = [], []
    for b in range(edges.size - 1):
        for d in ("rising", "falling", "turning", "hold"):
            labels.append((f"input:{d}", [float(edges[b]), float(edges[b + 1])]))
            masks.append((idx == b) & (rows.direction == d))
    out += _shares(total, labels, masks, e2, top)
    rate = np.abs(rows.du)
    edges, idx = _quantile_bins(rate, 5)
    out += _shares(total, [("rate", [float(edges[b]), float(edges[b + 1])]) for b in range(edges.size - 1)],
                   [idx == b for b in range(edges.size - 1)], e2, top)
    for c, a in rows.aux.items():
        ok = np.isfinite(a)
        if not ok.any():
            continue
        edges, idx = _quantile_bins(np.where(ok, a, np.nanmean(a)), 5)
        out += _shares(total, [(f"aux:{c}", [float(edges[b]), float(edges[b + 1])]) for b in range(edges.size - 1)],
                       [(idx == b) & ok for b in range(edges.size - 1)], e2, top)
    return out
