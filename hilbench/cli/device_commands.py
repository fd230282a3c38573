"""Commands on devices and experiment scripts: devices, emulate, run.

* ``hilbench devices``: the registered drivers (entry-point group ``hilbench.drivers``) with their
  roles, transports, settings, and the serial ports present;
* ``hilbench emulate RIG.toml``: the emulators of a real-rig config's devices, backed by its
  ``[plant]``, listening on 127.0.0.1 (or a pty, or a python-can virtual bus) until Ctrl-C, so the
  config can be dry-run;
* ``hilbench run SCRIPT.py --rig RIG``: an experiment script with the scripting API of
  :mod:`hilbench.runners.script`.
"""

from __future__ import annotations

import importlib
import json
import sys
import time
import traceback
from datetime import datetime
from pathlib import Path
from typing import Any, Optional

import typer

from hilbench.cli.app import app, fail, print_json, user_errors
from hilbench.errors import UserError


def _debug() -> bool:
    state = getattr(importlib.import_module("hilbench.cli.app"), "_state", {})
    return bool(state.get("debug", False))


# -- devices -------------------------------------------------------------------------------------------


def _kind_name(kind: Any) -> str:
    return getattr(kind, "__name__", str(kind))


def _default(value: Any) -> Any:
    return value if value is None or isinstance(value, (str, int, float, bool)) else repr(value)


def driver_description(name: str) -> dict[str, Any]:
    """What ``hilbench devices`` says of one registered driver (a driver that fails to load says why)."""
    from hilbench.rig import registry

    entry_point = registry.entry_points()[name]
    info: dict[str, Any] = {"name": name, "entry_point": entry_point}
    try:
        driver = registry.get_driver(name)
    except UserError as exc:
        return {**info, "roles": [], "transports": [], "description": "", "emulator": False, "settings": [],
                "error": exc.message}
    settings = [
        {"name": s.name, "type": _kind_name(s.kind), "required": bool(s.required),
         "default": _default(s.default), "doc": s.doc}
        for s in getattr(driver, "settings", ()) or ()
    ]
    return {
        **info,
        "roles": list(driver.roles),
        "transports": list(getattr(driver, "transports", ()) or ()),
        "description": str(getattr(driver, "description", "") or ""),
        "emulator": getattr(driver, "emulator", None) is not None,
        "install": str(getattr(driver, "install_hint", "") or ""),
        "settings": settings,
    }


def serial_ports() -> tuple[list[dict[str, str]], str]:
    """The serial ports present (device, description, hwid) and a note when they cannot be listed."""
    try:
        from serial.tools import list_ports
    except ImportError:
        return [], "pyserial is not installed: serial ports cannot be listed"
    ports = []
    for port in sorted(list_ports.comports(), key=lambda p: p.device):
        ports.append({"device": str(port.device), "description": str(port.description or ""),
                      "hwid": str(port.hwid or "")})
    return ports, ""


@app.command()
@user_errors
def devices(as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout.")) -> None:
    """List the registered device drivers with their settings, and the serial ports present.

    Drivers register under the 'hilbench.drivers' entry-point group; a [devices.NAME] table of a rig
    config names one with driver = "NAME" and sets the keys listed here.
    """
    from hilbench.rig.registry import driver_names

    drivers = [driver_description(name) for name in driver_names()]
    ports, note = serial_ports()
    if as_json:
        print_json({"drivers": drivers, "serial_ports": ports, **({"note": note} if note else {})})
        return
    for d in drivers:
        typer.echo(f"{d['name']}  ({', '.join(d['roles']) or '?'})  {d['entry_point']}")
        if d.get("error"):
            typer.echo(f"    cannot be loaded: {d['error']}")
            continue
        if d["description"]:
            typer.echo(f"    {d['description']}")
        extras = []
        if d["transports"]:
            extras.append(f"transports: {', '.join(d['transports'])}")
        extras.append("emulator: yes" if d["emulator"] else "emulator: no")
        typer.echo(f"    {'; '.join(extras)}")
        if d["install"]:
            typer.echo(f"    needs an optional package: {d['install']}")
        for s in d["settings"]:
            if s["required"]:
                status = "required"
            elif s["default"] is not None:
                status = f"default {s['default']!r}"
            else:
                status = "optional"
            typer.echo(f"      {s['name']:22s} {s['type']:6s} {status:22s} {s['doc']}")
    typer.echo("serial ports: " + (", ".join(f"{p['device']} ({p['description']})" for p in ports) or (note or "none")))


# -- emulate -------------------------------------------------------------------------------------------


def _describe(emulated: Any, rig_config: Any) -> dict[str, Any]:
    """Per device: its driver and the settings that reach its emulator (url, interface, channel)."""
    if hasattr(emulated, "describe"):
        return dict(emulated.describe())
    settings = dict(getattr(emulated, "settings", {}) or {})
    return {"rig": rig_config.name, "sample_rate_hz": rig_config.sample_rate_hz,
            "devices": {name: {"driver": rig_config.devices[name]["driver"], **point}
                        for name, point in settings.items()}}


def _dry_run(emulated: Any, rig_config: Any, excitation: list[str], output: Optional[Path]) -> dict[str, Any]:
    """Play the config's plan (or ``excitation``) on the rig pointed at its emulators, in this process."""
    from hilbench.excitation.plan import expand_runs, plan_from_compact
    from hilbench.rig.rig import Rig
    from hilbench.runners.sweep import run_plan

    if excitation:
        runs = plan_from_compact(excitation)
    elif rig_config.plan:
        runs = expand_runs(rig_config.plan, file=rig_config.path)
    else:
        raise UserError("--dry-run: the rig config has no [[plan.runs]]", where=rig_config.path,
                        hint="give --excitation 'sine:amplitude=1,frequency_hz=1,cycles=3'")
    out = output or Path("recordings") / f"{rig_config.name}-emulated-{datetime.now().strftime('%Y%m%d-%H%M%S')}.h5"
    with Rig(emulated.config_for_emulators()) as rig:
        result = run_plan(rig, runs, out, experiment="emulated dry run")
    return {"file": str(out), "status": result.status,
            "runs": [{"name": r.group, "label": r.label, "status": r.status, "samples": r.samples} for r in result.runs]}


@app.command()
@user_errors
def emulate(
    config: str = typer.Argument(..., help="A real-rig config (TOML) with [devices.NAME] tables and a [plant]."),
    seconds: Optional[float] = typer.Option(
        None, "--seconds", min=0.0, max=86400.0,
        help="Stop after this many seconds (at most one day) instead of waiting for Ctrl-C.",
    ),
    dry_run: bool = typer.Option(
        False, "--dry-run", help="Play the config's plan (or --excitation) through the real drivers against the "
        "emulators in this process, record it, then stop (CANopen devices on a python-can virtual bus).",
    ),
    excitation: list[str] = typer.Option(
        [], "--excitation", "-e", metavar="KIND:KEY=VALUE,...", help="With --dry-run: runs in compact form. Repeatable.",
    ),
    output: Optional[Path] = typer.Option(None, "--output", "-o", help="With --dry-run: the recording (.h5)."),
    write_config: Optional[Path] = typer.Option(
        None, "--write-config", metavar="OUT.toml", help="Write the config with every device url pointed at the "
        "running emulators, to sweep or track it from another shell while this runs.",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout: per device its url, "
                                 "pty path and 127.0.0.1 TCP host:port."),
) -> None:
    """Start the emulators of a real-rig config's devices and print the settings that reach them.

    Each [devices.NAME] table gets its driver's emulator speaking the real protocol (a pty or a
    127.0.0.1 socket for serial, a Modbus server on 127.0.0.1, a python-can udp_multicast bus that
    stays on this machine), all backed by one simulated plant from the config's [plant]. Put the
    printed url (or interface/channel/port) in the device tables and dry-run the config with
    `hilbench sweep CONFIG` from another shell while this runs (until Ctrl-C or --seconds), or let
    --write-config OUT.toml write that config for you; --dry-run instead plays it in this process.
    """
    from hilbench.rig.config import load_rig

    rig_config = load_rig(config)
    if write_config is not None:
        _check_output_config(write_config, Path(rig_config.path))
    if not rig_config.devices:
        raise UserError("a simulated rig (driver = 'sim') has no devices to emulate", where=rig_config.path,
                        hint="emulate a real-rig config with [devices.NAME] tables, e.g. one of configs/templates/")
    if (excitation or output is not None) and not dry_run:
        raise UserError("--excitation and --output go with --dry-run", where="command line")
    from hilbench.rig.emulation import start_emulators

    emulated = start_emulators(rig_config, shared_can=not dry_run)
    try:
        document = {"config": rig_config.path, **_describe(emulated, rig_config), "host": "127.0.0.1"}
        if write_config is not None:
            document["written_config"] = str(emulated.write_config(write_config))
        if dry_run:
            document["dry_run"] = _dry_run(emulated, rig_config, excitation, output)
        if as_json:
            print_json(document)
        else:
            typer.echo(f"emulating {len(document['devices'])} device(s) of {rig_config.path}:")
            for name, point in document["devices"].items():
                settings = ", ".join(f"{k} = {v!r}" for k, v in point.items() if k != "driver")
                typer.echo(f"  [devices.{name}] driver = {point.get('driver', '?')!r}: {settings}")
            if write_config is not None:
                typer.echo(f"wrote {document['written_config']}: the config pointed at these emulators")
            if dry_run:
                d = document["dry_run"]
                typer.echo(f"dry run: {d['file']}: {len(d['runs'])} run(s), status {d['status']}")
        sys.stdout.flush()
        if dry_run:
            if document["dry_run"]["status"] != "complete":
                raise typer.Exit(1)
            return
        if not as_json:
            typer.echo("Ctrl-C stops the emulators" + (f" (or after {seconds:g} s)" if seconds is not None else ""),
                       err=True)
        deadline = None if seconds is None else time.monotonic() + seconds
        try:
            while deadline is None or time.monotonic() < deadline:
                time.sleep(0.1 if deadline is None else max(0.0, min(0.1, deadline - time.monotonic())))
        except KeyboardInterrupt:
            if not as_json:
                typer.echo("stopping the emulators", err=True)
    finally:
        emulated.close()


def _check_output_config(out: Path, source: Path) -> None:
    """Refuse, in one line naming the value, an --write-config path that cannot be written."""
    where = f"--write-config {out}"
    if out.suffix.lower() != ".toml":
        raise UserError("expected a .toml file name", where=where, hint="e.g. --write-config rig-emulated.toml")
    if out.exists() and out.resolve() == source.resolve():
        raise UserError("that is the config being emulated; it is never overwritten", where=where,
                        hint="give another file name")
    if not out.parent.is_dir():
        raise UserError(f"folder {str(out.parent)!r} does not exist", where=where)
    if out.is_dir():
        raise UserError("is a folder, expected a file", where=where)


# -- run -----------------------------------------------------------------------------------------------


@app.command(context_settings={"allow_extra_args": True})
@user_errors
def run(
    ctx: typer.Context,
    script: Path = typer.Argument(..., help="Experiment script (Python); it finds the bench as `bench`."),
    rig: Optional[str] = typer.Option(
        None, "--rig", "-r", help="Rig config path or built-in rig name (default: the script's RIG = \"...\").",
    ),
    output_dir: Optional[Path] = typer.Option(
        None, "--output-dir", "-o", help="Folder for the script's recordings (default: recordings/SCRIPT-STAMP/).",
    ),
    quick: bool = typer.Option(False, "--quick", help="Ask the script for shortened runs (bench.quick; also HILBENCH_QUICK=1)."),
    as_json: bool = typer.Option(
        False, "--json", help="Print one JSON document on stdout (recordings, reported results); the script's "
        "own printing goes to stderr.",
    ),
    allow_late: bool = typer.Option(False, "--allow-late", help="On real devices, sweep and track even when their "
                                    "measured round trip cannot hold the rig's rate (the overruns are recorded)."),
) -> None:
    """Run an experiment script on a rig with the scripting API (hilbench.runners.script).

    The rig is opened once and the script gets a `bench` (plan, sweep, fit, diagnose, track, rig,
    output_dir, log, report). Whatever happens, the rig is ramped to rest and closed at the end and
    every recording closed with its status. Arguments after `--` go to the script (sys.argv, bench.args).
    A script error prints one line naming the script's line and exits with status 1; a hilbench error
    (a plan outside the limits, a bad spec) prints its line and exits with status 2.
    """
    from hilbench.runners.script import ScriptFailed, quick_from_env, run_script

    args = list(ctx.args)  # what follows `--`
    if output_dir is None:
        stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
        output_dir = Path("recordings") / f"{script.stem}-{stamp}"
    started = time.monotonic()
    try:
        outcome = run_script(script, rig, output_dir, quick=quick or quick_from_env(), args=args,
                             script_stdout=sys.stderr if as_json else None, check_rate=not allow_late)
    except ScriptFailed as exc:
        if _debug():
            traceback.print_exception(exc.error)
        fail(exc.line(), "the rig was ramped to rest and closed; `hilbench --debug run ...` shows the traceback",
             code=1)
        return
    elapsed = time.monotonic() - started
    document = {**outcome.to_json(), "elapsed_s": round(elapsed, 3)}
    if as_json:
        print_json(document)
        return
    typer.echo(f"{script}: {outcome.status} on {outcome.rig} in {elapsed:.1f} s; recordings in {outcome.output_dir}")
    for rec in outcome.recordings:
        typer.echo(f"  {rec['file']}: {len(rec['runs'])} run(s), status {rec['status']}")
    for key, value in outcome.results.items():
        shown = value if isinstance(value, (str, int, float, bool)) or value is None else json.dumps(value, default=str)
        typer.echo(f"  {key} = {shown}")
