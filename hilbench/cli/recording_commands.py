"""Commands on rigs and recordings: sweep, show, watch, import, plot, rigs."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Optional

import typer

from hilbench.cli.app import (
    RunProgress,
    app,
    default_output,
    print_json,
    show_progress,
    user_errors,
)
from hilbench.errors import UserError


@app.command()
@user_errors
def sweep(
    config: str = typer.Argument(..., help="Rig config: a TOML path or a built-in rig name (see `hilbench rigs`)."),
    plan: Optional[str] = typer.Option(
        None, "--plan", "-p", metavar="FILE|NAME",
        help="Plan file (TOML with [[runs]] tables), or the short name of a packaged plan of the papers, "
        "e.g. 004-tracking (experiments/plans/paper-004-tracking.toml).",
    ),
    excitation: list[str] = typer.Option(
        [], "--excitation", "-e", metavar="KIND:KEY=VALUE,...",
        help="Run in compact form, e.g. 'sine:amplitude=3,frequency_hz=1,cycles=5'; '|' sweeps "
        "(amplitude=1|2|3), '/' makes lists. Repeatable.",
    ),
    output: Optional[Path] = typer.Option(None, "--output", "-o", help="Recording (.h5); appended when it exists."),
    realtime: Optional[bool] = typer.Option(
        None, "--realtime/--no-realtime", help="Pace a simulated rig at its sample rate (default: the config's)."
    ),
    check_only: bool = typer.Option(False, "--check", help="Check the plan against the limits and, on real devices, "
                                    "time their round trip against the rig's rate; then stop (exit 2 when either fails)."),
    allow_late: bool = typer.Option(False, "--allow-late", help="On real devices, run even when their measured round "
                                    "trip cannot hold the rig's rate (the overruns are recorded)."),
    log: Optional[Path] = typer.Option(None, "--log", help="Append a JSON line per event (run start, flush, end)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """Run a characterisation sweep on a rig and record it.

    The plan is the config's [[plan.runs]], a --plan file, or --excitation runs. The whole plan is
    checked against the actuator's range and slew limit before anything moves.
    """
    from hilbench.excitation.plan import (
        check_plan,
        expand_runs,
        load_plan_file,
        plan_from_compact,
    )
    from hilbench.rig.config import load_rig
    from hilbench.recording.lateness import loop_line
    from hilbench.rig.rig import Rig
    from hilbench.runners.sweep import run_plan

    rig_config = load_rig(config)
    if plan is not None and excitation:
        raise UserError("give either --plan or --excitation, not both")
    if plan is not None:
        runs = load_plan_file(plan)
    elif excitation:
        runs = plan_from_compact(excitation)
    elif rig_config.plan:
        runs = expand_runs(rig_config.plan, file=rig_config.path)
    else:
        raise UserError(
            "the rig config has no [[plan.runs]]", where=rig_config.path,
            hint="give --plan FILE or --excitation 'sine:amplitude=1,frequency_hz=1,cycles=3'",
        )
    totals = check_plan(runs, rig_config.actuator, rig_config.sample_rate_hz)
    if check_only:
        document = {"rig": rig_config.name, "plan_ok": True, **totals, "labels": [r.label for r in runs]}
        if not rig_config.simulated:
            document["round_trips"] = _timed_round_trips(rig_config, allow_late)
        if as_json:
            print_json(document)
        else:
            typer.echo(f"plan OK: {totals['runs']} runs, {totals['samples']} samples, {totals['duration_s']:.3f} s")
            if "round_trips" in document:
                rt = document["round_trips"]
                low, high = rt["max_rate_interval_hz"]
                typer.echo(f"devices OK at {rig_config.sample_rate_hz:g} Hz: round trip {rt['round_trip_p50_s'] * 1e3:.3g} ms "
                           f"(p50), {rt['round_trip_p99_s'] * 1e3:.3g} ms (p99); at most {rt['max_rate_hz']:.4g} Hz "
                           f"({low:.4g}-{high:.4g} Hz, 95 % confidence; {rt['advised_rate_hz']:g} Hz holds at either end)")
        return
    out = output or default_output(rig_config.name)
    rig = Rig(rig_config)
    log_file = open(log, "a", encoding="utf-8") if log is not None else None  # noqa: SIM115

    def on_event(event: dict[str, Any]) -> None:
        if log_file is not None:
            log_file.write(json.dumps({**event, "t": time.time()}) + "\n")
            log_file.flush()

    started = time.monotonic()
    try:
        with RunProgress(not quiet) as progress:
            result = run_plan(rig, runs, out, realtime=realtime, progress=progress, on_event=on_event,
                              check_rate=not allow_late)
    finally:
        if log_file is not None:
            log_file.close()
    elapsed = time.monotonic() - started
    document = {
        "file": str(out),
        "rig": rig_config.name,
        "status": result.status,
        "elapsed_s": round(elapsed, 3),
        "clamped_samples": rig.clamped_samples,
        "runs": [{"name": r.group, "label": r.label, "status": r.status, "samples": r.samples, "reason": r.reason}
                 for r in result.runs],
    }
    loops = _loop_figures(out, [r.group for r in result.runs])
    for entry in document["runs"]:
        if entry["name"] in loops:
            entry["loop"] = loops[entry["name"]]
    if as_json:
        print_json(document)
    else:
        typer.echo(f"{out}: {len(result.runs)} runs, status {result.status}, {elapsed:.1f} s")
        for r in result.runs:
            typer.echo(f"  {r.group:40s} {r.status:9s} {r.samples:>10d} samples")
            if r.group in loops:
                typer.echo(f"      {loop_line(loops[r.group])}")
    if result.status != "complete":
        raise typer.Exit(1)


def _timed_round_trips(rig_config: Any, allow_late: bool) -> dict[str, Any]:
    """``sweep --check`` on real devices: open them, time their round trip (the actuator held where it
    is), close them; refused (exit 2) when the rig's rate cannot be held, unless ``allow_late``."""
    from hilbench.rig.rig import Rig
    from hilbench.runners.rate_check import require_rate, time_round_trips
    from hilbench.runners.sweep import select_mode

    with Rig(rig_config) as rig:
        # a device that plays each run on its own clock (a PI wave generator) paces the run: its
        # round trip is reported, but it does not limit the rate (run_plan checks only fixed-rate runs)
        mode = select_mode(rig)
        trips = time_round_trips(rig) if allow_late or mode != "fixed-rate" else require_rate(rig)
    return {**trips.describe(), "mode": mode}


def _loop_figures(path: Path, groups: list[str]) -> dict[str, dict[str, Any]]:
    """The fixed-rate loop's timing figures of the given runs of a recording (none for other modes)."""
    from hilbench.recording.hdf5 import Recording
    from hilbench.recording.lateness import loop_figures

    if not groups or not Path(path).exists():
        return {}
    found = {}
    for run in Recording(path):
        if run.name in groups and run.attrs.get("loop") == "fixed-rate":
            found[run.name] = loop_figures(run.attrs)
    return found


@app.command()
@user_errors
def show(
    file: Path = typer.Argument(..., help="Recording (.h5)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
) -> None:
    """List the runs of a recording: status, sample rate, samples, channels and units."""
    from hilbench.recording.hdf5 import Recording
    from hilbench.recording.lateness import loop_line

    summary = Recording(file).summary()
    if as_json:
        print_json(summary)
        return
    typer.echo(f"{summary['file']}  ({summary['format']} v{summary['format_version']}, "
               f"hilbench {summary['hilbench_version']}, created {summary['created']})")
    for run in summary["runs"]:
        duration = f"{run['duration_s']:.3f} s" if run["duration_s"] is not None else "?"
        typer.echo(f"  {run['name']}: {run['status']}, {run['n_samples']} samples at {run['sample_rate_hz']:g} Hz "
                   f"({duration}), experiment {run['experiment']!r}")
        channels = ", ".join(f"{c['name']} [{c['units']}]" for c in run["channels"])
        typer.echo(f"      channels: {channels}")
        if "loop" in run:
            typer.echo(f"      {loop_line(run['loop'])}")
        if run["status"] not in ("complete",) and run["reason"]:
            typer.echo(f"      reason: {run['reason'].strip().splitlines()[-1]}")


@app.command("import")
@user_errors
def import_(
    sources: list[Path] = typer.Argument(..., help="CSV or MATLAB .mat files, one run each."),
    output: Path = typer.Option(..., "--output", "-o", help="Recording (.h5); appended when it exists."),
    run: list[str] = typer.Option([], "--run", metavar="NAME", help="Run name per source (default: the file name)."),
    rate: Optional[float] = typer.Option(None, "--rate", help="Sample rate, Hz, when there is no time column."),
    map_: list[str] = typer.Option(
        [], "--map", metavar="SRC=DST", help="Rename a column: SRC=DST or SRC=DST[unit]; SRC may be a 0-based column index or, "
        "for dSPACE exports, Y(1) or a signal name. Repeatable.",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar on stderr."),
) -> None:
    """Import measured data (CSV, MATLAB, dSPACE ControlDesk .mat) into a recording.

    Header units are normalised (µm, μm, um, micron -> um; °C, deg C -> degC; Ω, ohm -> Ohm), in
    UTF-8 or Latin-1 files alike; a column mapped with --map needs a unit, from the header or the
    mapping (SRC=output[um]).
    """
    from hilbench.recording.importers import import_files, parse_mapping

    mapping = parse_mapping(map_)
    with show_progress(quiet):
        names = import_files(sources, output, run_names=run or None, rate_hz=rate, mapping=mapping)
    if as_json:
        print_json({"file": str(output), "runs": names})
    else:
        typer.echo(f"{output}: imported {len(names)} run(s): {', '.join(names)}")


@app.command()
@user_errors
def plot(
    file: Path = typer.Argument(..., help="Recording (.h5)."),
    run: list[str] = typer.Option([], "--run", metavar="RUN", help="Run name, label or number (default: all). Repeatable."),
    output: Path = typer.Option(..., "--output", "-o", help="PNG to write."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
) -> None:
    """Plot time traces and input-output loops of a recording's runs."""
    from hilbench.report.plotting import plot_runs

    png = plot_runs(file, output, runs=run or None)
    if as_json:
        print_json({"file": str(file), "png": str(png)})
    else:
        typer.echo(f"wrote {png}")


@app.command()
@user_errors
def rigs(as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout.")) -> None:
    """List the built-in rig configs with the paper each follows."""
    from hilbench.rig.config import builtin_rigs, load_rig

    entries = []
    for name, path in sorted(builtin_rigs().items()):
        cfg = load_rig(path)
        entries.append({"name": name, "paper": cfg.paper, "description": cfg.description, "follows": cfg.follows,
                        "path": str(path)})
    if as_json:
        print_json(entries)
        return
    for e in entries:
        typer.echo(f"{e['name']:24s} paper {e['paper'] or '-':4s} {e['description']}")


@app.command()
@user_errors
def watch(
    file: Path = typer.Argument(..., help="Recording (.h5) being written (by sweep, track, online or run)."),
    text: bool = typer.Option(False, "--text", help="A line on the terminal twice a second instead of the page."),
    port: int = typer.Option(0, "--port", min=0, max=65535, help="Port of the page on 127.0.0.1 (0: a free one)."),
    window: float = typer.Option(10.0, "--window", min=0.1, max=3600.0, help="Seconds of the run shown."),
    linger: float = typer.Option(5.0, "--linger", min=0.0, max=600.0,
                                 help="After a run ends, seconds to wait for the sweep's next run."),
    wait: float = typer.Option(30.0, "--wait", min=0.0, max=3600.0,
                               help="Seconds to wait for the file, and its first run, to appear."),
) -> None:
    """Follow a recording while it is written: the running run's traces, its input-output loop and the
    loop's lateness, refreshed a few times a second, in a page on 127.0.0.1 (or --text). A reader in
    its own process: the run never waits for it. Ends by itself when the run does."""
    from hilbench.errors import DataError
    from hilbench.recording.hdf5 import check_recording
    from hilbench.report.live_view import Follower, serve, text_line

    deadline = time.monotonic() + wait
    while not file.exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    while True:
        try:
            check_recording(file)
            break
        except DataError as exc:
            # the writer has created the file and holds HDF5's lock until its SWMR mode starts (after
            # the root attributes): a lock is waited out like a file not there yet, anything else is not
            cause = exc.__cause__
            locked = isinstance(cause, BlockingIOError) or "lock" in str(cause)
            if not locked or time.monotonic() >= deadline:
                raise
            time.sleep(0.2)
    follower = Follower(file, window_s=window, linger_s=linger, wait_s=max(0.0, deadline - time.monotonic()))
    try:
        if text:
            while not follower.ended:
                typer.echo(text_line(follower.refresh()))
                time.sleep(0.5)
        else:
            server, _ = serve(follower, port)
            url = f"http://127.0.0.1:{server.server_address[1]}/"
            typer.echo(f"watching {file}: {url} (ends when the run does; Ctrl-C stops watching)")
            while not follower.ended:
                time.sleep(0.2)
            time.sleep(1.0)  # the page's last poll sees the end
            server.shutdown()
    except KeyboardInterrupt:
        typer.echo("stopped watching (the run goes on)")
        return
    typer.echo(f"watching ended: {follower.ended}")
