"""``hilbench track``: track a reference on a rig with an inverse-model compensator."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from hilbench.cli.app import app, default_output, print_json, user_errors
from hilbench.errors import UserError


@app.command()
@user_errors
def track(
    rig: str = typer.Argument(..., metavar="RIG", help="Rig config: a TOML path or a built-in rig name."),
    model: Path = typer.Option(..., "--model", "-m", metavar="FIT.json", help="Fitted model (hilbench fit -o)."),
    reference: str = typer.Option(
        ..., "--reference", "-r", metavar="SPEC",
        help="Reference in the OUTPUT unit (um): the compact form of `sweep --excitation`, e.g. "
        "'sine:amplitude=50,offset=50,frequency_hz=1,phase_deg=-90,cycles=5', attenuated-triangle, multitone, "
        "step; or FILE.h5:RUN (that run's output channel).",
    ),
    feedback: bool = typer.Option(False, "--feedback", help="Add PID feedback around the inverse, in the output "
                                  "domain (um of error in, um added to the reference out). Without --kp/--ki/--kd "
                                  "the gains are designed from the identified loop (6 dB, 45 deg over the rig's "
                                  "local gain range); the margins are reported."),
    kp: Optional[float] = typer.Option(None, "--kp", help="PID proportional gain (um/um), with --feedback; given "
                                       "gains are checked on the identified loop and refused when unstable."),
    ki: Optional[float] = typer.Option(None, "--ki", help="PID integral gain (um/um per s = 1/s), with --feedback."),
    kd: Optional[float] = typer.Option(None, "--kd", help="PID derivative gain (um/um times s = s, on the "
                                       "measurement), with --feedback."),
    online: bool = typer.Option(False, "--online", help="Adapt the inverse online with the OIIR identifier "
                                "(paper 000; needs an fpmpi model)."),
    method: str = typer.Option("auto", "--method", help="Inverse: auto, pi, mpi, im (004 eq. 13), fpmpi, general."),
    output: Optional[Path] = typer.Option(None, "--output", "-o", metavar="FILE.h5",
                                          help="Recording (appended when it exists); default recordings/RIG-track-*.h5."),
    plot_png: Optional[Path] = typer.Option(None, "--plot", metavar="PNG",
                                            help="Figure: tracking, error, desired vs actual."),
    label: str = typer.Option("track", "--label", help="Run label in the recording."),
    allow_clip: bool = typer.Option(False, "--allow-clip", help="Run a reference that leaves the reachable output "
                                    "range clipped to it (recorded in the run), or one a planned path cannot "
                                    "follow, instead of refusing it."),
    allow_late: bool = typer.Option(False, "--allow-late", help="On real devices, run even when their measured "
                                    "round trip cannot hold the rig's rate (timed before anything moves; the "
                                    "overruns are recorded)."),
    strict: bool = typer.Option(False, "--strict", help="Exit with status 3 when the run is degraded (health: "
                                "samples at a limit or slew-limited > 1 %, or the error well above the model's own)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
) -> None:
    """Track a reference with the inverse of a fitted model, optionally with feedback or online
    adaptation; record it and report the tracking error (um; *_pct in percent of the reference).

    A configuration that cannot be stable (004 eq. 16 violated with no gain, PID gains that
    destabilise the identified loop), a model that cannot be inverted over its operating range and a reference
    outside the reachable output range (unless --allow-clip) are refused before anything moves. Where the
    model's loop turns over in its fitted range (a figure eight), a reference beyond its monotone part
    runs on a command path planned over the whole reference (reversing early so the overshoot lands on
    each extremum; decision 0118), refused when the model itself cannot follow it
    (exit 2). The run's health (samples at a limit, slew-limited, error against the model's own) is
    reported; --strict makes a degraded run exit with status 3.
    """
    from hilbench.online.health import DEGRADED_EXIT, health_line
    from hilbench.online.pid import PID
    from hilbench.online.tracking import plot_tracking, track as run_track
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig

    given = (kp, ki, kd) != (None, None, None)
    if given and not feedback:
        raise UserError("--kp/--ki/--kd are the feedback's gains", hint="add --feedback")
    # gains given: those (a missing one is 0), checked on the identified loop; none: designed on it
    pid = PID(kp or 0.0, ki or 0.0, kd or 0.0) if given else (True if feedback else None)
    config = load_rig(rig)
    out = output or default_output(f"{config.name}-track")
    with Rig(config) as opened:
        result = run_track(opened, model, reference, feedback=pid,
                           online=True if online else None, output=out, label=label, method=method,
                           allow_clip=allow_clip, check_rate=not allow_late)
        try:
            opened.stop(True)
        except Exception:  # noqa: BLE001  (the run is recorded; a failing stop is reported, not fatal)
            typer.echo("warning: the rig did not stop cleanly", err=True)
    if plot_png is not None:
        plot_tracking(result, plot_png, title=config.name)
    document = {"rig": config.name, **result.to_json()}
    if plot_png is not None:
        document["png"] = str(plot_png)
    if as_json:
        print_json(document)
        _exit_if_degraded(strict, result.health, DEGRADED_EXIT)
        return
    m = result.metrics
    typer.echo(f"{result.file} run {result.group}: {result.compensator['method']} inverse of {result.compensator['model']}"
               + (" + PID" if feedback else "") + (" + online" if online else ""))
    typer.echo("  " + ", ".join(f"{k} {v:.4g}" for k, v in m.items()))
    typer.echo("  " + health_line(result.health))
    if result.loop:
        from hilbench.recording.lateness import loop_line

        typer.echo("  " + loop_line(result.loop))
    if result.compensator.get("played"):
        typer.echo(f"  played: {result.compensator['played']} (feedforward: a controller that plays waveforms "
                   "cannot carry feedback through per-sample serial I/O at this rate)")
    if result.reference_clipped:
        c = result.reference_clipped
        typer.echo(f"  reference clipped: {c['samples']} samples ({c['share_pct']:.3g} %) to the reachable "
                   f"[{c['reachable_um'][0]:.4g}, {c['reachable_um'][1]:.4g}] um")
    fb = result.compensator.get("feedback")
    if fb and fb.get("margins") and fb["kp"] == 0.0 and fb["ki_per_s"] == 0.0 and fb["kd_s"] == 0.0:
        typer.echo("  feedback (designed): left open, ki 0 (see the note)")
    elif fb and fb.get("margins"):
        mg, lp = fb["margins"], fb["loop"]
        typer.echo(f"  feedback ({'designed' if fb['designed'] else 'given'}, um/um): kp {fb['kp']:.4g}, "
                   f"ki {fb['ki_per_s']:.4g} 1/s, kd {fb['kd_s']:.4g} s; gain margin {mg['gain_margin_db']:.3g} dB, "
                   f"phase margin {mg['phase_margin_deg']:.3g} deg, crossover {mg['crossover_hz']:.3g} Hz over local "
                   f"gains {lp['local_gain_range'][0]:.3g}-{lp['local_gain_range'][1]:.3g}")
    for note in result.compensator.get("notes", []):
        typer.echo(f"  note: {note}")
    if plot_png is not None:
        typer.echo(f"  figure: {plot_png}")
    _exit_if_degraded(strict, result.health, DEGRADED_EXIT)


def _exit_if_degraded(strict: bool, health: dict, code: int) -> None:
    """--strict: a degraded run (recorded, reported) ends with its own exit status."""
    if strict and health.get("degraded"):
        typer.echo("error: the run is degraded: " + "; ".join(health.get("reasons", [])), err=True)
        raise typer.Exit(code)
