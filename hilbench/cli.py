"""The ``hilbench`` command line.

Conventions (DESIGN.md, "Command line"): every command that produces results takes ``--json`` and
then prints exactly one JSON document on stdout; progress goes to stderr; an error the user can fix
prints one line (and a hint) on stderr and exits with status 2, no traceback unless ``--debug``.
"""

from __future__ import annotations

import functools
import json
import sys
import time
import traceback
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any, Optional, TypeVar

import typer

from hilbench import __version__
from hilbench.errors import UserError

app = typer.Typer(
    name="hilbench",
    help="Hardware-in-the-loop bench for smart-material actuators: sweep simulated or real rigs, "
    "record crash-safe HDF5, import measured data, plot loops, fit hysteresis models.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)

DEFAULT_RIG = "piezo-demo"
_state = {"debug": False}

F = TypeVar("F", bound=Callable[..., Any])


def _fail(message: str, hint: str | None = None, code: int = 2) -> None:
    typer.echo(f"error: {message}", err=True)
    if hint:
        typer.echo(f"hint: {hint}", err=True)
    raise typer.Exit(code)


def user_errors(func: F) -> F:
    """Turn :class:`UserError` into one line on stderr and exit status 2."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except UserError as exc:
            if _state["debug"]:
                traceback.print_exc()
            _fail(exc.line(), exc.hint)
        except KeyboardInterrupt:
            _fail("interrupted", code=130)

    return wrapper  # type: ignore[return-value]


def _print_json(document: Any) -> None:
    sys.stdout.write(json.dumps(document, indent=2, default=str) + "\n")
    sys.stdout.flush()


def _version(value: bool) -> None:
    if value:
        typer.echo(f"hilbench {__version__}")
        raise typer.Exit()


@app.callback()
def main_options(
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks for errors."),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
) -> None:
    _state["debug"] = debug


class _Progress:
    """A progress bar on stderr, one task per run."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self._bar: Any = None
        self._task: Any = None
        self._run = 0

    def __enter__(self) -> _Progress:
        if self.enabled:
            from rich.console import Console
            from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

            self._bar = Progress(
                TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
                TimeRemainingColumn(), console=Console(stderr=True), transient=False,
            )
            self._bar.__enter__()
        return self

    def __call__(self, index: int, label: str, done: int, total: int) -> None:
        if self._bar is None:
            return
        if index != self._run:
            self._run = index
            self._task = self._bar.add_task(f"run {index} {label}", total=total)
        self._bar.update(self._task, completed=done)

    def __exit__(self, *exc: Any) -> None:
        if self._bar is not None:
            self._bar.__exit__(*exc)


def _default_output(rig_name: str) -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("recordings") / f"{rig_name}-{stamp}.h5"


@app.command()
@user_errors
def sweep(
    config: str = typer.Argument(..., help="Rig config: a TOML path or a built-in rig name (see `hilbench rigs`)."),
    plan: Optional[Path] = typer.Option(None, "--plan", "-p", help="Plan file (TOML with [[runs]] tables)."),
    excitation: list[str] = typer.Option(
        [], "--excitation", "-e", metavar="KIND:KEY=VALUE,...",
        help="Run in compact form, e.g. 'sine:amplitude=3,frequency_hz=1,cycles=5'; '|' sweeps "
        "(amplitude=1|2|3), '/' makes lists. Repeatable.",
    ),
    output: Optional[Path] = typer.Option(None, "--output", "-o", help="Recording (.h5); appended when it exists."),
    realtime: Optional[bool] = typer.Option(
        None, "--realtime/--no-realtime", help="Pace a simulated rig at its sample rate (default: the config's)."
    ),
    check_only: bool = typer.Option(False, "--check", help="Check the plan against the limits and stop."),
    log: Optional[Path] = typer.Option(None, "--log", help="Append a JSON line per event (run start, flush, end)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """Run a characterisation sweep on a rig and record it.

    The plan is the config's [[plan.runs]], a --plan file, or --excitation runs. The whole plan is
    checked against the actuator's range and slew limit before anything moves.
    """
    from hilbench.config import load_rig
    from hilbench.plan import check_plan, expand_runs, load_plan_file, plan_from_compact
    from hilbench.rig import Rig
    from hilbench.runner import run_plan

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
        if as_json:
            _print_json(document)
        else:
            typer.echo(f"plan OK: {totals['runs']} runs, {totals['samples']} samples, {totals['duration_s']:.3f} s")
        return
    out = output or _default_output(rig_config.name)
    rig = Rig(rig_config)
    log_file = open(log, "a", encoding="utf-8") if log is not None else None  # noqa: SIM115

    def on_event(event: dict[str, Any]) -> None:
        if log_file is not None:
            log_file.write(json.dumps({**event, "t": time.time()}) + "\n")
            log_file.flush()

    started = time.monotonic()
    try:
        with _Progress(not quiet) as progress:
            result = run_plan(rig, runs, out, realtime=realtime, progress=progress, on_event=on_event)
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
    if as_json:
        _print_json(document)
    else:
        typer.echo(f"{out}: {len(result.runs)} runs, status {result.status}, {elapsed:.1f} s")
        for r in result.runs:
            typer.echo(f"  {r.group:40s} {r.status:9s} {r.samples:>10d} samples")
    if result.status != "complete":
        raise typer.Exit(1)


@app.command()
@user_errors
def show(
    file: Path = typer.Argument(..., help="Recording (.h5)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
) -> None:
    """List the runs of a recording: status, sample rate, samples, channels and units."""
    from hilbench.recording import Recording

    summary = Recording(file).summary()
    if as_json:
        _print_json(summary)
        return
    typer.echo(f"{summary['file']}  ({summary['format']} v{summary['format_version']}, "
               f"hilbench {summary['hilbench_version']}, created {summary['created']})")
    for run in summary["runs"]:
        duration = f"{run['duration_s']:.3f} s" if run["duration_s"] is not None else "?"
        typer.echo(f"  {run['name']}: {run['status']}, {run['n_samples']} samples at {run['sample_rate_hz']:g} Hz "
                   f"({duration}), experiment {run['experiment']!r}")
        channels = ", ".join(f"{c['name']} [{c['units']}]" for c in run["channels"])
        typer.echo(f"      channels: {channels}")
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
) -> None:
    """Import measured data (CSV, MATLAB, dSPACE ControlDesk .mat) into a recording."""
    from hilbench.importers import import_files, parse_mapping

    names = import_files(sources, output, run_names=run or None, rate_hz=rate, mapping=parse_mapping(map_))
    if as_json:
        _print_json({"file": str(output), "runs": names})
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
    from hilbench.plotting import plot_runs

    png = plot_runs(file, output, runs=run or None)
    if as_json:
        _print_json({"file": str(file), "png": str(png)})
    else:
        typer.echo(f"wrote {png}")


@app.command()
@user_errors
def rigs(as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout.")) -> None:
    """List the built-in rig configs with the paper each follows."""
    from hilbench.config import builtin_rigs, load_rig

    entries = []
    for name, path in sorted(builtin_rigs().items()):
        cfg = load_rig(path)
        entries.append({"name": name, "paper": cfg.paper, "description": cfg.description, "follows": cfg.follows,
                        "path": str(path)})
    if as_json:
        _print_json(entries)
        return
    for e in entries:
        typer.echo(f"{e['name']:24s} paper {e['paper'] or '-':4s} {e['description']}")


@app.command()
@user_errors
def demo(
    output_dir: Path = typer.Option(Path("recordings"), "--output-dir", help="Where demo.h5, demo.png and the report go."),
    rig: str = typer.Option(DEFAULT_RIG, "--rig", help="Built-in rig name or config path."),
    model: str = typer.Option("pi", "--model", "-m", metavar="SPEC", help="The model the diagnosis starts from."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """The whole loop on a simulated rig with hidden effects: sweep, fit, diagnose, add, report.

    Sweeps the rig into demo.h5 and plots its loops (demo.png), fits the starting model, lets the
    diagnosis find and add the missing effects while they lower the validation error significantly,
    prints the falling-error table and writes an HTML report (demo-report/report.html).
    """
    from hilbench.config import load_rig
    from hilbench.diagnosis import diagnose as run_diagnosis
    from hilbench.diagnosis_report import write_report
    from hilbench.plan import expand_runs
    from hilbench.plotting import plot_runs
    from hilbench.recording import Recording
    from hilbench.rig import Rig
    from hilbench.runner import run_plan

    rig_config = load_rig(rig)
    runs = expand_runs(rig_config.plan, file=rig_config.path)
    output_dir.mkdir(parents=True, exist_ok=True)
    h5 = output_dir / "demo.h5"
    h5.unlink(missing_ok=True)  # the demo starts afresh each time
    started = time.monotonic()
    with _Progress(not quiet) as progress:
        result = run_plan(Rig(rig_config), runs, h5, experiment="demo", realtime=False, progress=progress)
    png = plot_runs(h5, output_dir / "demo.png")
    summary = Recording(h5).summary()
    if not quiet:
        typer.echo(f"diagnosing {model} on {h5} ...", err=True)
    diagnosis = run_diagnosis(h5, model, auto=True)
    report = write_report(diagnosis, output_dir / "demo-report")
    document = {
        "rig": rig_config.name,
        "paper": rig_config.paper,
        "file": str(h5),
        "png": str(png),
        "report": str(report),
        "status": result.status,
        "elapsed_s": round(time.monotonic() - started, 3),
        "runs": [{"name": r["name"], "status": r["status"], "n_samples": r["n_samples"]} for r in summary["runs"]],
        "diagnosis": diagnosis.to_json(),
    }
    if as_json:
        _print_json(document)
        return
    typer.echo(f"hilbench demo: rig {rig_config.name}: {rig_config.description}")
    typer.echo(f"  {len(result.runs)} runs recorded to {h5} ({result.status}), loops plotted to {png}")
    for r in summary["runs"]:
        typer.echo(f"  {r['name']:36s} {r['status']:9s} {r['n_samples']:>8d} samples")
    typer.echo("")
    for line in _diagnosis_lines(diagnosis.to_json()):
        typer.echo(line)
    typer.echo("")
    typer.echo(f"report: {report}")
    typer.echo(f"next: hilbench show {h5}   |   hilbench fit {h5} --model {diagnosis.spec} --plot fit.png")


@app.command("fit")
@user_errors
def fit_(
    data: list[Path] = typer.Argument(..., metavar="DATA", help="Recording(s) (.h5); all runs are read, in order."),
    model: str = typer.Option(
        ..., "--model", "-m", metavar="SPEC|FIT.json",
        help="Model spec: a base and effects joined by '+', e.g. 'pi', 'pmpi+dynamics', 'pi+creep+temperature', "
        "'pi(n=16)'; or a fitted model (.json) to evaluate on the data without refitting.",
    ),
    train: list[str] = typer.Option(
        [], "--train", metavar="RUN", help="Run that trains entirely (name, label or number; FILE-STEM:RUN with "
        "several files). Repeatable. Without --test, the other runs validate.",
    ),
    test: list[str] = typer.Option(
        [], "--test", metavar="RUN", help="Run that validates entirely. Repeatable. Without --train, the other runs train.",
    ),
    train_fraction: float = typer.Option(
        0.7, "--train-fraction", help="Without --train/--test: the first part of every run that trains (0-1]; the rest validates.",
    ),
    output: Optional[Path] = typer.Option(
        None, "--output", "-o", metavar="FIT.json", help="Write the fitted model (spec, parameters with units, "
        "the runs it was fitted on, metrics) as JSON.",
    ),
    plot_png: Optional[Path] = typer.Option(
        None, "--plot", metavar="PNG", help="Plot measured vs model loops and the error over time, per run (up to 6).",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress notes on stderr."),
) -> None:
    """Fit a model to recordings and report its error on training and validation data.

    By default the first 70 % of every run trains and the last 30 % validates; --train/--test
    give whole runs roles instead. Runs of one file are chained: the model's memory carries over
    from one run to the next, as the actuator's did. Errors are free-run simulation errors, in the
    output unit (um), mse in its square, the *_pct keys in percent.
    """
    from hilbench.fitting import fit_or_evaluate, is_model_file

    if output is not None and is_model_file(model):
        raise UserError("-o writes a fitted model, but --model names a saved one, which is evaluated, not refitted",
                        where="-o", hint="use --json to keep the evaluation, or give a spec to refit")

    def note(message: str) -> None:
        if not quiet:
            typer.echo(message, err=True)

    result = fit_or_evaluate(data, model, train=train or None, test=test or None,
                             train_fraction=train_fraction, progress=note)
    for line in result.notes:
        note(f"note: {line}")
    if output is not None:
        note(f"wrote {result.save(output)}")
    if plot_png is not None:
        from hilbench.fitplots import plot_fit

        note(f"wrote {plot_fit(result, plot_png)}")
    if as_json:
        document = result.to_json()
        document["files"] = [str(p) for p in data]
        if output is not None:
            document["output"] = str(output)
        if plot_png is not None:
            document["png"] = str(plot_png)
        _print_json(document)
        return
    for line in _fit_report_lines(result):
        typer.echo(line)


def _fit_report_lines(result: Any) -> list[str]:
    """Human summary of a :class:`hilbench.fitting.FitResult`: spec, parameters, metric table, time."""
    from hilbench.metrics import METRIC_KEYS

    model_dict = result.model.to_dict()
    how = "fitted" if result.refitted else f"loaded from {result.loaded_from}, not refitted"
    lines = [f"model: {result.spec} ({how})", f"split: {result.split}"]
    shape = model_dict["parameters"]["shape"]
    if shape:
        lines.append("shape parameters:")
        for p in shape:
            unit = f" {p['unit']}" if p["unit"] else ""
            lines.append(f"  {p['component']:>16s}  {p['name']:<22s} {p['value']:12.6g}{unit}")
    else:
        lines.append("shape parameters: none (weights only)")
    weights = model_dict["parameters"]["weights"]
    y_unit = result.output_unit
    if len(weights) <= 16:
        lines.append(f"weights [{y_unit}]: " + ", ".join(f"{w['name']}={w['value']:.4g}" for w in weights))
    else:
        lines.append(f"weights: {len(weights)} (see -o FIT.json or --json)")
    units = {"rmse": y_unit, "mse": f"{y_unit}^2", "mae": y_unit, "mad": y_unit}
    lines.append(f"{'metric':<18s}{'train':>14s}{'validation':>14s}")
    for key in METRIC_KEYS:
        label = f"{key} [{units.get(key, '%')}]"
        cells = [result.metrics[role][key] for role in ("train", "validation")]
        lines.append(f"{label:<18s}" + "".join(f"{c:>14.5g}" if c == c else f"{'-':>14s}" for c in cells))
    lines.append(f"{'samples':<18s}" + "".join(f"{result.metrics[r]['n']:>14d}" for r in ("train", "validation")))
    lines.append("runs:")
    for r in result.runs:
        rmse = "  ".join(f"{role} rmse {m['rmse']:.4g}" for role, m in r.metrics.items() if m)
        lines.append(f"  {r.key:<36s} {r.role:<17s} {rmse}")
    info = result.fit_info()
    if result.refitted:
        n_eval = info["evaluations"]
        lines.append(f"fit: {info['seconds']:.2f} s, {n_eval} evaluation{'' if n_eval == 1 else 's'} of the weights")
    elif info.get("seconds") is not None:
        lines.append(f"fit: loaded; the original fit took {info['seconds']:.2f} s")
    return lines


@app.command()
@user_errors
def diagnose(
    data: list[Path] = typer.Argument(..., metavar="DATA", help="Recording(s) (.h5); all runs are read, in order."),
    model: str = typer.Option(..., "--model", "-m", metavar="SPEC|FIT.json",
                              help="Model spec to fit (e.g. 'pi', 'linear') or a fitted model (.json)."),
    add: Optional[str] = typer.Option(None, "--add", metavar="EFFECT",
                                      help="Add this effect, refit, and show before and after."),
    auto: bool = typer.Option(False, "--auto", help="Add the best significant effect while one remains."),
    train: list[str] = typer.Option([], "--train", metavar="RUN", help="Run that trains entirely. Repeatable."),
    test: list[str] = typer.Option([], "--test", metavar="RUN", help="Run that validates entirely. Repeatable."),
    train_fraction: float = typer.Option(0.7, "--train-fraction", help="Without --train/--test: the part of every run that trains."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
    report: Optional[Path] = typer.Option(None, "--report", metavar="DIR",
                                          help="Write a self-contained HTML report (DIR/report.html)."),
) -> None:
    """Compare a model with measurements: where it fails, which physical effect is missing.

    Every effect the data can test is added in turn and refitted on the same split; an effect is
    significant when it lowers the validation error by more than 10 %, agrees between training and
    validation, passes a block-wise signed-rank test (p < 0.01) and the error is above the noise.
    """
    from hilbench.diagnosis import diagnose as run_diagnosis

    result = run_diagnosis(data, model, train=train or None, test=test or None, add=add, auto=auto,
                           train_fraction=train_fraction)
    document = result.to_json()
    page = None
    if report is not None:
        from hilbench.diagnosis_report import write_report

        page = write_report(result, report)
    if as_json:
        _print_json(document)
        if page is not None:
            typer.echo(f"report: {page}", err=True)
        return
    for line in _diagnosis_lines(document):
        typer.echo(line)
    if page is not None:
        typer.echo(f"report: {page}")


def _range_text(value: Any) -> str:
    """A where-range for people: numbers to 4 significant digits, a time window as ``run t0-t1 s``."""
    if isinstance(value, list):
        if len(value) == 3 and isinstance(value[0], str):
            return f"{value[0]} {value[1]:.4g}-{value[2]:.4g} s"
        return "[" + ", ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in value) + "]"
    return str(value)


def _diagnosis_lines(d: dict[str, Any]) -> list[str]:
    """Human summary of a diagnosis document (the --json one)."""
    val = d["metrics"]["validation"]
    trn = d["metrics"]["train"]
    lines = [f"model: {d['spec']}   rmse train {trn['rmse']:.4g}, validation {val['rmse']:.4g} "
             f"(erms {val['erms_pct']:.3g} % of range)"]
    lines.append("where the validation error is (share of the squared error):")
    for entry in sorted(d["where"], key=lambda e: -e["share"])[:8]:
        lines.append(f"  {entry['kind']:<18s} {_range_text(entry['range']):<42s} {100 * entry['share']:6.1f} %"
                     f"  (of {100 * entry.get('fraction_of_rows', float('nan')):.3g} % of rows)")
    lines.append("effects (best first):")
    for e in d["effects"]:
        mark = "significant" if e["significant"] else "not significant"
        lines.append(f"  {e['effect']:<16s} {mark:<16s} expected gain {100 * e['expected_gain']:6.1f} %  {e['explanation']}")
    if not d["effects"]:
        lines.append("  none testable")
    for u in d["untestable"]:
        lines.append(f"  {u['effect']:<16s} untestable: {u['reason']}")
    if d.get("steps"):
        lines.append("step  spec                                   added             validation rmse")
        for k, s in enumerate(d["steps"]):
            lines.append(f"{k:>4d}  {s['spec']:<38s} {str(s['added'] or '-'):<17s} {s['validation']['rmse']:.4g}")
    return lines


def main() -> None:
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
