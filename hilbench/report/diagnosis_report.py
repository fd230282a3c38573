"""A self-contained HTML page of a :class:`hilbench.diagnosis.diagnose.Diagnosis` (:func:`write_report`).

The page ``out_dir/report.html`` has no external files, scripts or styles: CSS is inline and every
figure is a base64 PNG data URI (matplotlib Agg). It shows

* the spec(s) and the data files;
* the metrics of the final model (training and validation, every key of
  :data:`hilbench.identify.metrics.METRIC_KEYS`) and, with several rounds, of the first model side by side;
* where the squared validation error lies (kind, range, share %, share of rows %);
* the ranked candidate effects (significant, expected gain %, explanation, key evidence) and the
  untestable effects with the reason;
* the steps of ``add`` / ``auto`` (spec, added effect, training and validation rmse);
* figures of the final model and, when ``rounds`` has more than one entry, of the first model
  ("before / after"): measured vs model loops, error over time (validation shaded), error against
  input coloured by direction, against |input rate| and against every auxiliary channel, the
  error's amplitude spectrum and the input-to-error frequency response magnitude.

Long runs are decimated by plain striding for drawing; spectra use Welch segments. Units: input in
the command unit (V or A), output and errors in the output unit (usually um), times in s,
frequencies in Hz, rates in input units per s.
"""

from __future__ import annotations

import base64
import html
import io
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hilbench.errors import UserError
from hilbench.identify.metrics import METRIC_KEYS
from hilbench.report.figures import stride

if TYPE_CHECKING:
    from hilbench.diagnosis.diagnose import Diagnosis
    from hilbench.identify.fitting import FitResult, FitRun

#: runs drawn per figure
MAX_RUNS = 4
#: points drawn per line / scatter
MAX_POINTS = 6000
#: samples per Welch segment (at most)
NPERSEG = 8192
REPORT_NAME = "report.html"

_CSS = """
body{font-family:-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;margin:1.5em auto;max-width:1300px;
color:#222;line-height:1.35;padding:0 1em}
h1{font-size:1.5em;margin-bottom:.2em}h2{font-size:1.2em;border-bottom:1px solid #ccc;margin-top:1.6em}
h3{font-size:1.05em;margin-bottom:.3em}
table{border-collapse:collapse;margin:.5em 0;font-size:.88em}
th,td{border:1px solid #ccc;padding:3px 7px;text-align:left;vertical-align:top}
th{background:#f0f0f0}td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
tr.yes td{background:#eaf7ea}tr.final td{font-weight:bold}
.meta{color:#555;font-size:.9em}.ev{font-size:.85em;color:#333}
.fail{color:#b00}.pass{color:#070}
figure{margin:.8em 0}figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:.85em;color:#555}
.pair{display:flex;gap:1em;flex-wrap:wrap}.pair>div{flex:1 1 600px;min-width:0}
"""


# -- formatting ---------------------------------------------------------------------------------


def _e(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _num(x: Any, digits: int = 4) -> str:
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if math.isnan(v):
        return "–"
    if math.isinf(v):
        return "∞" if v > 0 else "-∞"
    return f"{v:.{digits}g}"


def _value(x: Any) -> str:
    """A compact text of an evidence value (numbers, lists, dicts), not escaped."""
    if isinstance(x, dict):
        return ", ".join(f"{k} {_value(v)}" for k, v in x.items())
    if isinstance(x, (list, tuple)):
        return "[" + ", ".join(_value(v) for v in x) + "]"
    if isinstance(x, (int, float, np.integer, np.floating, bool)):
        return _num(x, 3)
    return str(x)


def _range(kind: str, rng: Any) -> str:
    if kind == "time" and isinstance(rng, (list, tuple)) and len(rng) == 3:
        return f"{rng[0]}: {_num(rng[1], 4)}–{_num(rng[2], 4)} s"
    if isinstance(rng, (list, tuple)) and len(rng) == 2:
        return f"{_num(rng[0], 4)} … {_num(rng[1], 4)}"
    return str(rng)


def _table(head: list[str], rows: list[list[tuple[str, str]]], classes: list[str] | None = None) -> str:
    """``rows`` of (already escaped html, css class) cells."""
    out = ["<table><thead><tr>", *(f"<th>{_e(h)}</th>" for h in head), "</tr></thead><tbody>"]
    for i, row in enumerate(rows):
        cls = classes[i] if classes and classes[i] else ""
        out.append(f'<tr class="{cls}">' if cls else "<tr>")
        out += [f'<td class="{c}">{v}</td>' if c else f"<td>{v}</td>" for v, c in row]
        out.append("</tr>")
    out.append("</tbody></table>")
    return "".join(out)


# -- figures ------------------------------------------------------------------------------------


def _png(fig: Any) -> str:
    """The figure as a base64 PNG data URI; the figure is closed."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=90)
    finally:
        plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _shown(result: FitResult) -> list[FitRun]:
    return [r for r in result.runs if len(r.data) and r.simulated is not None and r.simulated.size][:MAX_RUNS]


def _error(run: FitRun) -> np.ndarray:
    return np.asarray(run.simulated, float) - np.asarray(run.data.output, float)


def _used(run: FitRun) -> np.ndarray:
    m = run.train | run.validation
    return m if m.any() else np.ones(len(run.data), bool)


def _direction(u: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """Input rate (input unit / s) and direction: +1 rising, -1 falling, 0 still."""
    if u.size < 2:
        return np.zeros(u.size), np.zeros(u.size)
    du = np.gradient(u) * fs
    span = max(float(np.ptp(u)), 1e-12)
    still = np.abs(du) / fs <= 1e-6 * span
    return du, np.where(still, 0.0, np.sign(du))


def _spans(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def _filled(x: np.ndarray) -> np.ndarray:
    """NaNs replaced by linear interpolation (for spectra)."""
    ok = np.isfinite(x)
    if ok.all() or not ok.any():
        return np.nan_to_num(x)
    idx = np.arange(x.size)
    return np.interp(idx, idx[ok], x[ok])


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _labels(result: FitResult) -> tuple[str, str]:
    u = f"input [{result.input_unit}]" if result.input_unit else "input"
    return u, result.output_unit or ""


def fig_loops(result: FitResult) -> str:
    """Measured vs model loops (output vs input), one panel per run."""
    plt = _plt()
    runs = _shown(result)
    n = max(1, len(runs))
    cols = min(n, 2)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6.2 * cols, 4.2 * rows), squeeze=False)
    u_label, y_unit = _labels(result)
    for ax, run in zip(axes.flat, runs):
        step = stride(len(run.data), MAX_POINTS)
        u, y, s = run.data.input[::step], run.data.output[::step], run.simulated[::step]
        ax.plot(u, y, color="0.5", lw=0.9, label="measured")
        ax.plot(u, s, color="tab:red", lw=0.9, ls="--", label="model")
        ax.set_xlabel(u_label)
        ax.set_ylabel(f"output [{y_unit}]")
        ax.set_title(f"{run.key} ({run.role})", fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
    for ax in list(axes.flat)[len(runs):]:
        ax.axis("off")
    if not runs:
        axes.flat[0].text(0.5, 0.5, "no simulated runs", ha="center", va="center")
    fig.suptitle(f"{result.spec}: measured vs model loops", fontsize=11)
    fig.tight_layout()
    return _png(fig)


def fig_time(result: FitResult) -> str:
    """Error over time, one row per run, validation rows shaded."""
    plt = _plt()
    runs = _shown(result)
    fig, axes = plt.subplots(max(1, len(runs)), 1, figsize=(12.4, 2.8 * max(1, len(runs))), squeeze=False)
    _, y_unit = _labels(result)
    for ax, run in zip(axes[:, 0], runs):
        n = len(run.data)
        fs = run.data.sample_rate_hz if run.data.sample_rate_hz > 0 else 1.0
        step = stride(n, MAX_POINTS)
        t = np.arange(n) / fs
        e = _error(run)
        for a, b in _spans(run.validation):
            ax.axvspan(t[a], t[b - 1], color="tab:orange", alpha=0.15, lw=0)
        for role, color in (("train", "tab:blue"), ("validation", "tab:orange")):
            m = getattr(run, role)
            if m.any():
                ax.plot(t[::step], np.where(m, e, np.nan)[::step], color=color, lw=0.7, label=role)
        rest = ~(run.train | run.validation)
        if rest.any():
            ax.plot(t[::step], np.where(rest, e, np.nan)[::step], color="0.6", lw=0.7, label="unused")
        ax.axhline(0.0, color="black", lw=0.5)
        ax.set_ylabel(f"model - measured [{y_unit}]")
        drawn = f", 1 in {step} drawn" if step > 1 else ""
        ax.set_title(f"{run.key}: error over time ({n} samples{drawn}; validation shaded)", fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(f"{result.spec}: error over time", fontsize=11)
    fig.tight_layout()
    return _png(fig)


def _pooled(result: FitResult) -> dict[str, Any]:
    """Used rows of the shown runs, decimated, pooled: e, u, |rate|, direction, aux, validation."""
    runs = _shown(result)
    total = sum(int(_used(r).sum()) for r in runs) or 1
    step = stride(total, MAX_POINTS)
    common: set[str] | None = None
    for r in runs:
        common = set(r.data.aux) if common is None else common & set(r.data.aux)
    parts: dict[str, list[np.ndarray]] = {"e": [], "u": [], "rate": [], "dir": [], "val": []}
    aux: dict[str, list[np.ndarray]] = {c: [] for c in sorted(common or ())}
    for r in runs:
        fs = r.data.sample_rate_hz if r.data.sample_rate_hz > 0 else 1.0
        du, d = _direction(np.asarray(r.data.input, float), fs)
        idx = np.flatnonzero(_used(r))[::step]
        parts["e"].append(_error(r)[idx])
        parts["u"].append(r.data.input[idx])
        parts["rate"].append(np.abs(du[idx]))
        parts["dir"].append(d[idx])
        parts["val"].append(r.validation[idx])
        for c in aux:
            aux[c].append(np.asarray(r.data.aux[c], float)[idx])
    out: dict[str, Any] = {k: np.concatenate(v) if v else np.zeros(0) for k, v in parts.items()}
    out["aux"] = {c: np.concatenate(v) for c, v in aux.items()}
    out["step"] = step
    return out


def fig_location(result: FitResult) -> str:
    """Error against input (by direction), against |input rate| and against every aux channel."""
    plt = _plt()
    p = _pooled(result)
    aux = p["aux"]
    n = 2 + len(aux)
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.8 * rows), squeeze=False)
    flat = list(axes.flat)
    u_label, y_unit = _labels(result)
    unit = result.input_unit or "input unit"
    e_label = f"model - measured [{y_unit}]"
    ax = flat[0]
    for d, name, color in ((1.0, "rising", "tab:red"), (-1.0, "falling", "tab:blue"), (0.0, "still", "0.5")):
        m = p["dir"] == d
        if m.any():
            ax.scatter(p["u"][m], p["e"][m], s=2, color=color, alpha=0.5, lw=0, label=f"{name} ({m.mean():.0%})")
    ax.set_xlabel(u_label)
    ax.set_title("error vs input, by direction", fontsize=9)
    ax.legend(loc="best", fontsize=8, markerscale=4)
    ax = flat[1]
    val = p["val"].astype(bool)
    ax.scatter(p["rate"][~val], p["e"][~val], s=2, color="tab:blue", alpha=0.4, lw=0, label="train")
    ax.scatter(p["rate"][val], p["e"][val], s=2, color="tab:orange", alpha=0.5, lw=0, label="validation")
    ax.set_xlabel(f"|input rate| [{unit}/s]")
    ax.set_title("error vs |input rate|", fontsize=9)
    ax.legend(loc="best", fontsize=8, markerscale=4)
    for ax, (c, a) in zip(flat[2:], aux.items()):
        ax.scatter(a[~val], p["e"][~val], s=2, color="tab:blue", alpha=0.4, lw=0, label="train")
        ax.scatter(a[val], p["e"][val], s=2, color="tab:orange", alpha=0.5, lw=0, label="validation")
        ax.set_xlabel(c)
        ax.set_title(f"error vs {c}", fontsize=9)
        ax.legend(loc="best", fontsize=8, markerscale=4)
    for ax in flat[:n]:
        ax.axhline(0.0, color="black", lw=0.5)
        ax.set_ylabel(e_label)
        ax.grid(True, alpha=0.3)
    for ax in flat[n:]:
        ax.axis("off")
    note = "" if aux else "; no auxiliary channels"
    drawn = f", 1 in {p['step']} drawn" if p["step"] > 1 else ""
    fig.suptitle(f"{result.spec}: where the error is (training and validation rows{drawn}{note})", fontsize=11)
    fig.tight_layout()
    return _png(fig)


def spectra(run: FitRun) -> dict[str, np.ndarray]:
    """Error amplitude spectrum and input-to-error frequency response of one run's used rows.

    ``amplitude`` (output unit) is the peak amplitude of a sinusoid in each Welch bin
    (sqrt(2 * power spectrum)); ``gain`` (output unit per input unit) is |P_ue / P_uu|;
    ``excited`` marks bins whose input power is at least 1e-4 of the largest (where the gain means
    something).
    """
    from scipy import signal

    m = _used(run)
    idx = np.flatnonzero(m)
    e = _filled(_error(run)[idx])
    u = np.asarray(run.data.input, float)[idx]
    fs = run.data.sample_rate_hz if run.data.sample_rate_hz > 0 else 1.0
    nper = int(min(e.size, NPERSEG))
    if nper < 8:
        z = np.zeros(0)
        return {"f": z, "amplitude": z, "gain": z, "excited": z.astype(bool)}
    f, pee = signal.welch(e, fs=fs, nperseg=nper, scaling="spectrum", detrend="constant")
    _, puu = signal.welch(u, fs=fs, nperseg=nper, detrend="constant")
    _, pue = signal.csd(u, e, fs=fs, nperseg=nper, detrend="constant")
    gain = np.abs(pue) / np.maximum(puu, 1e-300)
    excited = puu >= 1e-4 * max(float(puu.max()), 1e-300)
    return {"f": f, "amplitude": np.sqrt(2.0 * pee), "gain": gain, "excited": excited}


def fig_frequency(result: FitResult) -> str:
    """Error amplitude spectrum and input-to-error |H(f)|, one line per run."""
    plt = _plt()
    fig, (ax_a, ax_h) = plt.subplots(1, 2, figsize=(12.4, 4.0))
    u_unit = result.input_unit or "input unit"
    y_unit = result.output_unit or ""
    gains: list[np.ndarray] = []
    for k, run in enumerate(_shown(result)):
        s = spectra(run)
        f = s["f"]
        if f.size < 2:
            continue
        color = f"C{k}"
        ax_a.loglog(f[1:], np.maximum(s["amplitude"][1:], 1e-30), color=color, lw=0.8, label=run.key)
        ax_h.loglog(f[1:], np.maximum(s["gain"][1:], 1e-30), color=color, lw=0.5, alpha=0.35)
        ex = s["excited"].copy()
        ex[0] = False
        if ex.any():
            ax_h.loglog(f[ex], s["gain"][ex], "o", color=color, ms=3, label=f"{run.key} (input excited)")
            gains.append(s["gain"][ex])
    g = np.concatenate(gains) if gains else np.zeros(0)
    g = g[np.isfinite(g) & (g > 0)]
    if g.size:  # unexcited bins divide by ~0: keep the axis on the excited ones
        ax_h.set_ylim(float(g.min()) / 30.0, float(g.max()) * 30.0)
    ax_a.set_xlabel("frequency [Hz]")
    ax_a.set_ylabel(f"error amplitude [{y_unit}]")
    ax_a.set_title("error amplitude spectrum (Welch, peak amplitude per bin)", fontsize=9)
    ax_h.set_xlabel("frequency [Hz]")
    ax_h.set_ylabel(f"|H| [{y_unit}/{u_unit}]")
    ax_h.set_title("input-to-error frequency response |P_ue / P_uu| (dots: input excited)", fontsize=9)
    for ax in (ax_a, ax_h):
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize=8)
    fig.suptitle(f"{result.spec}: error in frequency", fontsize=11)
    fig.tight_layout()
    return _png(fig)


FIGURES = (
    ("loops", "Measured vs model loops (output vs input)", fig_loops),
    ("time", "Error over time (validation rows shaded)", fig_time),
    ("location", "Error against input (coloured by direction), |input rate| and auxiliary channels", fig_location),
    ("frequency", "Error amplitude spectrum and input-to-error frequency response", fig_frequency),
)


def figures(result: FitResult) -> list[tuple[str, str, str]]:
    """(name, caption, data URI) of every figure of ``result``."""
    return [(name, caption, make(result)) for name, caption, make in FIGURES]


# -- sections -----------------------------------------------------------------------------------


def _files(result: FitResult) -> list[str]:
    out: list[str] = []
    for r in result.runs:
        f = str(r.data.source.get("file", "")) if isinstance(r.data.source, dict) else ""
        if f and f not in out:
            out.append(f)
    return out


def _metrics_section(d: Diagnosis) -> str:
    models = [("", d.result)]
    first = d.rounds[0].result if len(d.rounds) > 1 else None
    if first is not None:
        models = [("before", first), ("after", d.result)]
    head = ["metric"]
    for tag, res in models:
        for role in ("train", "validation"):
            head.append(f"{tag} {role} ({res.spec})".strip() if tag else role)
    rows = []
    for key in (*METRIC_KEYS, "n"):
        row = [(_e(key), "")]
        for _, res in models:
            for role in ("train", "validation"):
                row.append((_e(_num((res.metrics.get(role) or {}).get(key, float("nan")))), "num"))
        rows.append(row)
    unit = _e(d.result.output_unit)
    return (f"<h2>Metrics</h2><p class='meta'>e = model - measured; rmse, mse, max_abs_error, mean_abs_error in {unit} "
            f"(mse in {unit}²), *_pct in %. Split: {_e(d.result.split)}</p>" + _table(head, rows))


def _where_section(d: Diagnosis) -> str:
    rows = []
    for w in d.where:
        share = float(w.get("share", float("nan")))
        frac = float(w.get("fraction_of_rows", float("nan")))
        rows.append([(_e(w.get("kind", "")), ""), (_e(_range(str(w.get("kind", "")), w.get("range"))), ""),
                     (_e(_num(100 * share, 3)), "num"), (_e(_num(100 * frac, 3)), "num")])
    body = _table(["kind", "range", "share %", "rows %"], rows) if rows else "<p>no validation rows</p>"
    return ("<h2>Where the error is</h2><p class='meta'>Share of the summed squared validation error; "
            "a share well above the bin's share of rows marks where the model fails. Input ranges in "
            f"{_e(d.result.input_unit or 'input units')}, rates in input units/s.</p>" + body)


_KEY_EVIDENCE = ("p_value", "validation_rmse", "train_rmse", "train_gain", "blocks_improved", "noise_floor")


def evidence_cell(ev: dict[str, Any]) -> str:
    parts = []
    for k in _KEY_EVIDENCE:
        if k in ev:
            parts.append(f"<b>{_e(k)}</b> {_e(_value(ev[k]))}")
    for k, v in ev.items():
        if k in _KEY_EVIDENCE or k in ("checks", "spec", "failed_checks"):
            continue
        parts.append(f"{_e(k)} {_e(_value(v))}")
    checks = ev.get("checks")
    if isinstance(checks, dict):
        marks = [f"<span class='{'pass' if ok else 'fail'}'>{'✓' if ok else '✗'} {_e(name)}</span>"
                 for name, ok in checks.items()]
        parts.append("checks: " + " ".join(marks))
    for f in ev.get("failed_checks") or []:  # why not: measured vs required, in words
        parts.append(f"<span class='fail'>✗ {_e(f.get('check', ''))}: {_e(f.get('text', ''))}</span>")
    return "<span class='ev'>" + "; ".join(parts) + "</span>"


def _effects_section(d: Diagnosis) -> str:
    rows, classes = [], []
    for i, c in enumerate(d.effects, 1):
        doc = c.to_json()  # the explanation with its reason, the evidence with the failed checks
        rows.append([(str(i), "num"), (_e(c.effect), ""), (_e(c.spec), ""),
                     ("<b>yes</b>" if c.significant else "no", ""), (_e(_num(100 * c.expected_gain, 3)), "num"),
                     (_e(doc["explanation"]), ""), (evidence_cell(doc["evidence"]), "")])
        classes.append("yes" if c.significant else "")
    out = [f"<h2>Candidate effects of {_e(d.spec)}</h2>",
           "<p class='meta'>Ranked: significant first, then by the measured drop of validation rmse "
           "(expected gain). rmse pairs are [current, with the effect].</p>"]
    out.append(_table(["rank", "effect", "spec tried", "significant", "expected gain %", "explanation",
                       "key evidence"], rows, classes) if rows else "<p>no effect could be tested</p>")
    out.append("<h3>Untestable effects</h3>")
    if d.untestable:
        out.append("<ul>" + "".join(f"<li><b>{_e(u.get('effect', ''))}</b>: {_e(u.get('reason', ''))}</li>"
                                    for u in d.untestable) + "</ul>")
    else:
        out.append("<p>none</p>")
    return "".join(out)


def _steps_section(d: Diagnosis) -> str:
    if not d.steps:
        return ""
    rows, classes = [], []
    for i, s in enumerate(d.steps):
        val = s.get("validation") or {}
        trn = s.get("train") or {}
        added = s.get("added") or "(start)"
        reach = s.get("within_reach")
        if reach:  # judged on the validation rows within training's input reach (decision 0071)
            before, after = reach["validation_rmse"]
            added += (f" (judged within training's input reach, {reach['left_out']} of "
                      f"{reach['validation_rows']} rows left out: {_num(before)} → {_num(after)})")
        rows.append([(str(i), "num"), (_e(s.get("spec", "")), ""),
                     (_e(added), ""),
                     (_e(_num(val.get("rmse", float("nan")))), "num"),
                     (_e(_num(trn.get("rmse", float("nan")))), "num")])
        classes.append("final" if i == len(d.steps) - 1 else "")
    return ("<h2>Steps (before → after)</h2>"
            f"<p class='meta'>rmse in {_e(d.result.output_unit)}.</p>"
            + _table(["step", "spec", "added", "validation rmse", "train rmse"], rows, classes))


def _figures_section(d: Diagnosis) -> str:
    final = figures(d.result)
    first = figures(d.rounds[0].result) if len(d.rounds) > 1 else None
    out = ["<h2>Figures</h2>"]
    for k, (name, caption, uri) in enumerate(final):
        out.append(f"<h3>{_e(caption)}</h3>")
        if first is None:
            out.append(f"<figure><img alt='{_e(name)}' src='{uri}'><figcaption>{_e(d.result.spec)}"
                       "</figcaption></figure>")
        else:
            before = first[k][2]
            out.append(
                "<div class='pair'>"
                f"<div><figure><img alt='{_e(name)} before' src='{before}'><figcaption>before: "
                f"{_e(d.rounds[0].result.spec)}</figcaption></figure></div>"
                f"<div><figure><img alt='{_e(name)} after' src='{uri}'><figcaption>after: "
                f"{_e(d.result.spec)}</figcaption></figure></div></div>")
    return "".join(out)


def render(diagnosis: Diagnosis) -> str:
    """The report page as one HTML string."""
    d = diagnosis
    start = d.steps[0]["spec"] if d.steps else (d.rounds[0].spec if d.rounds else d.spec)
    title = f"Diagnosis of {start}" + (f" → {d.spec}" if start != d.spec else "")
    files = _files(d.result)
    head = (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{_e(title)}</title>"
            f"<style>{_CSS}</style></head><body>")
    meta = [f"<h1>{_e(title)}</h1>",
            "<p class='meta'>Data: " + (", ".join(f"<code>{_e(f)}</code>" for f in files) or "–") + "<br>",
            f"Final model <code>{_e(d.spec)}</code> ({'fitted' if d.result.refitted else 'loaded'}); "
            f"noise floor {_e(_num(d.noise, 3))} {_e(d.result.output_unit)}; {_e(d.result.date)}</p>"]
    for note in d.result.notes:
        meta.append(f"<p class='meta'>{_e(note)}</p>")
    body = [_metrics_section(d), _where_section(d), _effects_section(d), _steps_section(d), _figures_section(d)]
    return head + "".join(meta) + "".join(body) + "</body></html>\n"


def write_report(diagnosis: Diagnosis, out_dir: str | os.PathLike[str]) -> Path:
    """Write ``out_dir/report.html`` (folders created) and return its path."""
    out = Path(out_dir)
    page = render(diagnosis)  # before touching the disk: a failure here leaves nothing half-written
    try:
        out.mkdir(parents=True, exist_ok=True)
        path = out / REPORT_NAME
        path.write_text(page, encoding="utf-8")
    except OSError as exc:
        raise UserError(f"cannot write the report ({exc.strerror or exc}); expected a folder path",
                        where=str(out)) from None
    return path


__all__ = ["FIGURES", "figures", "render", "spectra", "write_report"]
