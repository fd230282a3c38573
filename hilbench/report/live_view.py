"""Watching a recording while it is written: snapshots read in SWMR mode, a page, a terminal line.

:func:`snapshot` opens the file read-only in SWMR mode without HDF5's file lock (``locking=False``,
so the run's own writes, attributes included, never wait for a viewer), reads the newest run's
attributes and the last ``window_s`` of its channels (thinned to ``max_points``), and closes it
again: a viewer holds nothing between refreshes. The channels of a run are appended one after the
other, so a snapshot takes the samples every channel has. A read that meets the writer mid-update
fails now and then; the viewer keeps its last snapshot and tries again at the next refresh.

:class:`Follower` decides what to show and when to stop: the newest run of the file; when it leaves
``running`` it waits ``linger_s`` for the next run of the same sweep (the rig ramps between runs)
and ends otherwise, or at once when the process that writes the file is gone (a run killed with
SIGKILL stays ``running`` forever).

:func:`serve` serves the page (one HTML file with its script, no external resources) and the
snapshot as ``/data.json`` on 127.0.0.1; the page polls it a few times a second and draws the traces,
the input-output loop and the lateness.
"""

from __future__ import annotations

import json
import math
import socket
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from hilbench.recording.hdf5 import _pid_alive, _text

#: channels a snapshot never draws as traces (time is the axis; lateness has its own panel)
_NOT_TRACES = ("time", "lateness")


def _finite(values: np.ndarray) -> list[float | None]:
    return [float(v) if math.isfinite(v) else None for v in values]


def snapshot(path: str | Path, window_s: float = 10.0, max_points: int = 2000) -> dict[str, Any]:
    """The newest run of ``path`` as the viewer shows it (see the module docstring)."""
    with h5py.File(path, "r", swmr=True, locking=False) as f:
        writer = json.loads(_text(f.attrs.get("writer", "")) or "{}")
        runs = sorted(f["runs"].keys()) if "runs" in f else []
        if not runs:
            return {"file": str(path), "run": None, "status": "none", "writer": writer, "runs": 0}
        name = runs[-1]
        group = f["runs"][name]
        attrs = {k: _text(v) for k, v in group.attrs.items()}
        order = json.loads(attrs.get("channels", "[]") or "[]")
        datasets = {c: group[c] for c in order if c in group and isinstance(group[c], h5py.Dataset)}
        for ds in datasets.values():
            ds.refresh()
        n = min((ds.shape[0] for ds in datasets.values()), default=0)
        fs = float(attrs.get("sample_rate_hz", float("nan")))
        span = int(window_s * fs) if fs > 0 else n
        start = max(0, n - max(span, 1))
        step = max(1, math.ceil((n - start) / max_points))
        part = {c: np.asarray(ds[start:n:step], dtype=np.float64) for c, ds in datasets.items()}
        late = np.asarray(datasets["lateness"][start:n], dtype=np.float64) if "lateness" in datasets else None
        units = {c: str(_text(ds.attrs.get("units", ""))) for c, ds in datasets.items()}
    out: dict[str, Any] = {
        "file": str(path), "run": name, "runs": len(runs), "status": attrs.get("status", ""),
        "reason": str(attrs.get("reason", "")).strip().split("\n", 1)[0], "experiment": attrs.get("experiment", ""),
        "sample_rate_hz": fs, "n_samples": n, "duration_s": n / fs if fs > 0 else None, "writer": writer,
        "window": {"first": start, "step": step},
        "time": _finite(part.get("time", (start + np.arange(0, n - start, step)) / fs if fs > 0 else np.zeros(0))),
        "traces": {c: _finite(v) for c, v in part.items() if c not in _NOT_TRACES},
        "units": units,
    }
    if late is not None and late.size and np.isfinite(late).any():
        late = late[np.isfinite(late)]
        period = 1.0 / fs if fs > 0 else math.inf
        out["lateness"] = {"p50_us": float(np.percentile(late, 50)) * 1e6,
                           "p99_us": float(np.percentile(late, 99)) * 1e6, "max_us": float(late.max()) * 1e6,
                           "overruns": int(np.count_nonzero(late > period)), "samples": int(late.size),
                           "of_last_s": late.size / fs if fs > 0 else None}
    if out["status"] != "running":
        for key in ("overruns", "overrun_pct", "late", "lateness_p99_s"):
            if key in attrs:
                out.setdefault("run_figures", {})[key] = attrs[key]
    return out


def _writer_alive(writer: dict[str, Any]) -> bool | None:
    """Whether the process writing the file lives (None: not on this host or not said)."""
    if not writer or writer.get("host") != socket.gethostname():
        return None
    pids = [int(writer.get("pid", -1)), *(int(p) for p in writer.get("helpers", []))]
    return any(_pid_alive(p) for p in pids)


@dataclass
class Follower:
    """Refreshes snapshots of a recording and says when watching is over."""

    path: Path
    window_s: float = 10.0
    linger_s: float = 5.0
    #: how long a file with no run yet is waited for (a sweep creates the file, then ramps, then begins)
    wait_s: float = 30.0
    last: dict[str, Any] = field(default_factory=dict)
    ended: str = ""
    _ended_at: float | None = None
    _ended_run: str | None = None
    _started: float = field(default_factory=time.monotonic)

    def refresh(self) -> dict[str, Any]:
        try:
            snap = snapshot(self.path, self.window_s)
        except (OSError, KeyError, ValueError):  # met the writer mid-update: keep the last one
            return self.last
        self.last = snap
        status, run = snap.get("status"), snap.get("run")
        if status == "running":
            if _writer_alive(snap.get("writer", {})) is False:
                self.ended = (f"run {run} stays running: the process writing {self.path} is gone "
                              "(killed?); every flushed sample is in the file")
            else:
                self._ended_at = self._ended_run = None
            return snap
        now = time.monotonic()
        if run is None:
            if now - self._started >= self.wait_s:
                self.ended = f"no run began in {self.path} within {self.wait_s:g} s"
            return snap
        if self._ended_run != run:
            self._ended_run, self._ended_at = run, now
        if now - (self._ended_at or now) >= self.linger_s:
            self.ended = f"run {run} ended {status}" + (f": {snap['reason']}" if snap.get("reason") else "")
        return snap


def text_line(snap: dict[str, Any]) -> str:
    """One line for the terminal (``watch --text``)."""
    if not snap.get("run"):
        return f"{snap.get('file')}: no run yet"
    parts = [f"{snap['run']} {snap['status']}: {snap['n_samples']} samples"]
    if snap.get("duration_s") is not None:
        parts[0] += f" ({snap['duration_s']:.2f} s)"
    for channel, values in snap.get("traces", {}).items():
        latest = next((v for v in reversed(values) if v is not None), None)
        if latest is not None:
            parts.append(f"{channel} {latest:.4g} {snap['units'].get(channel, '')}".rstrip())
    late = snap.get("lateness")
    if late:
        parts.append(f"lateness p99 {late['p99_us']:.3g} us, max {late['max_us']:.3g} us, {late['overruns']} overruns "
                     f"(last {late['of_last_s']:.3g} s)")
    return ", ".join(parts)


def serve(follower: Follower, port: int = 0, refresh_s: float = 0.25) -> tuple[ThreadingHTTPServer, threading.Thread]:
    """Serve the page and ``/data.json`` on 127.0.0.1:``port`` (0: a free one) in a thread; a thread of
    its own refreshes the snapshot every ``refresh_s`` so that requests never read the file."""
    state = {"snap": follower.refresh(), "lock": threading.Lock()}
    page = _PAGE.replace("__REFRESH_MS__", str(int(refresh_s * 1000)))

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - http.server's name
            if self.path.split("?")[0] == "/data.json":
                with state["lock"]:
                    snap = dict(state["snap"], ended=follower.ended)
                body, kind = json.dumps(snap).encode(), "application/json"
            elif self.path.split("?")[0] in ("/", "/index.html"):
                body, kind = page.encode(), "text/html; charset=utf-8"
            else:
                self.send_error(404)
                return
            self.send_response(200)
            self.send_header("Content-Type", kind)
            self.send_header("Cache-Control", "no-store")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: Any) -> None:  # quiet: the terminal is the user's
            return

    server = ThreadingHTTPServer(("127.0.0.1", port), Handler)
    server.daemon_threads = True

    def refresher() -> None:
        while not follower.ended:
            time.sleep(refresh_s)
            snap = follower.refresh()
            with state["lock"]:
                state["snap"] = snap

    thread = threading.Thread(target=refresher, name="hilbench-watch-refresh", daemon=True)
    thread.start()
    threading.Thread(target=server.serve_forever, name="hilbench-watch-http", daemon=True).start()
    return server, thread


_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>hilbench watch</title>
<style>
 body { font: 14px system-ui, sans-serif; margin: 16px; color: #222; }
 h1 { font-size: 18px; margin: 0 0 8px; }
 .row { display: flex; gap: 16px; flex-wrap: wrap; }
 canvas { border: 1px solid #ccc; background: #fff; }
 #status.running { color: #06702f; } #status.ended { color: #8a1c1c; }
 .figure { font-size: 12px; color: #555; }
 .legend span { margin-right: 12px; }
</style></head>
<body>
<h1>hilbench watch: <span id="file"></span></h1>
<div>run <b id="run">-</b>, <b id="status">-</b>: <b id="samples">0</b> samples (<span id="seconds">0</span> s)
 at <span id="rate"></span> Hz; <span id="lateness">no lateness recorded</span></div>
<div id="ended"></div>
<div class="row">
 <div><canvas id="traces" width="760" height="360"></canvas>
  <div class="figure legend" id="legend"></div>
  <div class="figure">the last seconds of every channel, each scaled to its own range</div></div>
 <div><canvas id="loop" width="360" height="360"></canvas>
  <div class="figure">output against input (the hysteresis loop), same window</div></div>
</div>
<script>
const colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf"];
function range(v) { let lo = Infinity, hi = -Infinity;
  for (const x of v) if (x !== null) { if (x < lo) lo = x; if (x > hi) hi = x; }
  if (!(hi > lo)) { hi = (isFinite(lo) ? lo : 0) + 1; lo = hi - 2; } return [lo, hi]; }
function line(ctx, xs, ys, xr, yr, w, h, colour) {
  ctx.strokeStyle = colour; ctx.lineWidth = 1.2; ctx.beginPath(); let pen = false;
  for (let i = 0; i < xs.length; i++) { const x = xs[i], y = ys[i];
    if (x === null || y === null) { pen = false; continue; }
    const px = 40 + (x - xr[0]) / (xr[1] - xr[0]) * (w - 50), py = h - 20 - (y - yr[0]) / (yr[1] - yr[0]) * (h - 30);
    if (pen) ctx.lineTo(px, py); else ctx.moveTo(px, py); pen = true; }
  ctx.stroke(); }
function axes(ctx, w, h, xlabel) { ctx.clearRect(0, 0, w, h); ctx.strokeStyle = "#999"; ctx.strokeRect(40, 10, w - 50, h - 30);
  ctx.fillStyle = "#555"; ctx.font = "11px sans-serif"; ctx.fillText(xlabel, w / 2, h - 4); }
function draw(d) {
  document.getElementById("file").textContent = d.file;
  document.getElementById("run").textContent = d.run || "-";
  const st = document.getElementById("status"); st.textContent = d.status; st.className = d.status === "running" ? "running" : "ended";
  document.getElementById("samples").textContent = d.n_samples || 0;
  document.getElementById("seconds").textContent = d.duration_s ? d.duration_s.toFixed(2) : "0";
  document.getElementById("rate").textContent = d.sample_rate_hz;
  if (d.lateness) document.getElementById("lateness").textContent = "lateness p50 " + d.lateness.p50_us.toFixed(1) +
    " us, p99 " + d.lateness.p99_us.toFixed(1) + " us, max " + d.lateness.max_us.toFixed(1) + " us, " +
    d.lateness.overruns + " overruns in the last " + (d.lateness.of_last_s || 0).toFixed(1) + " s";
  document.getElementById("ended").textContent = d.ended ? "watching ended: " + d.ended : "";
  const t = d.time || [], tr = d.traces || {};
  const c = document.getElementById("traces"), ctx = c.getContext("2d"); axes(ctx, c.width, c.height, "time (s)");
  const xr = range(t); let k = 0, legend = [];
  for (const [name, v] of Object.entries(tr)) { const colour = colours[k++ % colours.length];
    line(ctx, t, v, xr, range(v), c.width, c.height, colour);
    legend.push('<span style="color:' + colour + '">' + name + " [" + (d.units[name] || "") + "]</span>"); }
  document.getElementById("legend").innerHTML = legend.join("");
  const l = document.getElementById("loop"), lc = l.getContext("2d"); axes(lc, l.width, l.height, "input");
  if (tr.input && tr.output) line(lc, tr.input, tr.output, range(tr.input), range(tr.output), l.width, l.height, colours[1]);
}
async function tick() {
  let ended = false;
  try { const r = await fetch("/data.json", {cache: "no-store"}); const d = await r.json(); draw(d); ended = !!d.ended; }
  catch (e) { document.getElementById("ended").textContent = "viewer not reachable: " + e; }
  if (!ended) setTimeout(tick, __REFRESH_MS__);
}
tick();
</script></body></html>
"""
