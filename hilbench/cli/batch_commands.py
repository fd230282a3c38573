"""``hilbench batch fit|diagnose|online SOURCE...``: a single command over a lab's archive, on Dask.

Each subcommand takes the options of its single command (same names, same defaults) and the
batch's own: where the rows go (``-o``), where the work runs (``--scheduler``, ``--workers``),
whether each run of a file is its own row (``--each run``) and whether failed rows are retried.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from hilbench.cli.app import app, print_json, show_progress, user_errors
from hilbench.errors import RunStopped, UserError

batch_app = typer.Typer(
    help="Run fit, diagnose or online over many recordings (a folder, a glob, a list file) on a Dask cluster: "
    "one row per recording in a Parquet/CSV table, resumable, a report across the archive.",
    no_args_is_help=True, rich_markup_mode=None,
)
app.add_typer(batch_app, name="batch")

SOURCES = typer.Argument(..., metavar="SOURCE...", help="Folders (every .h5 below), recordings, glob patterns in "
                         "quotes ('archive/**/*.h5') or list files (.txt, one path per line).")
OUTPUT = typer.Option(None, "--output", "-o", metavar="DIR", help="Folder of the results (default batch-COMMAND): "
                      "rows.jsonl as rows arrive, results.parquet, results.csv, summary.json, report.html. A rerun "
                      "into the same folder skips every row already there.")
SCHEDULER = typer.Option(None, "--scheduler", metavar="tcp://HOST:PORT", help="An existing Dask scheduler "
                         "(default $DASK_SCHEDULER_ADDRESS, else a local cluster). Its workers need hilbench (same "
                         "version) and the recordings at the same paths.")
WORKERS = typer.Option(None, "--workers", "-w", metavar="N", help="Worker processes of the local cluster "
                       "(default one per core).")
EACH = typer.Option("file", "--each", metavar="file|run", help="file: a row per recording, all its runs read as "
                    "the single command reads them; run: a row per run, each read alone.")
RETRY = typer.Option(False, "--retry-failed", help="Run again the tasks whose row failed (by default a rerun keeps them).")
NO_REPORT = typer.Option(False, "--no-report", help="Skip report.html.")
JSON = typer.Option(False, "--json", help="Print the summary (summary.json) on stdout.")
QUIET = typer.Option(False, "--quiet", "-q", help="No progress on stderr.")
TRAIN = typer.Option([], "--train", metavar="RUN", help="As in the single command: a run that trains entirely. Repeatable.")
TEST = typer.Option([], "--test", metavar="RUN", help="As in the single command: a run that validates entirely. Repeatable.")


def _batch(command: str, sources: list[str], options: dict[str, Any], output: Optional[Path], scheduler: Optional[str],
           workers: Optional[int], each: str, retry_failed: bool, no_report: bool, as_json: bool, quiet: bool) -> None:
    from hilbench.archive.batch import run_batch
    from hilbench.archive.sources import content_hash
    from hilbench.archive.tasks import default_options

    options = default_options(command, options)  # the keys the Python API's batch writes: the same rows
    out = output or Path(f"batch-{command}")
    for key in ("model", "online_model"):  # a saved model keys the rows by its content, as the recordings do
        value = options.get(key)
        if value and Path(value).is_file():
            options[f"{key}_sha256"] = content_hash(Path(value))

    def note(message: str) -> None:
        if not quiet and not as_json:
            typer.echo(message, err=True)

    try:
        with show_progress(quiet):
            summary = run_batch(command, sources, options, out, scheduler=scheduler, workers=workers, each=each,
                                retry_failed=retry_failed, report=not no_report, note=note)
    except KeyboardInterrupt:
        raise RunStopped("interrupted", where=str(out), hint="every finished row is in the table; run the same "
                         "command again to do the rest") from None
    document = summary.to_json()
    if as_json:
        print_json(document)
        return
    typer.echo(f"{out}: {document['rows']} rows of {document['tasks']} tasks: {document['done']} done, "
               f"{document['failed']} failed; {document['computed']} computed, {document['skipped_already_done']} "
               f"already there; {document['wall_s']:.1f} s")
    if document["task_s"]:
        t = document["task_s"]
        typer.echo(f"  per task: median {t['median']:.2f} s, max {t['max']:.2f} s, {t['sum']:.1f} s in all")
    for failure in document["failures"][:10]:
        run = "" if failure["run"] == "*" else f" run {failure['run']}"
        typer.echo(f"  failed{run}: {failure['error']}")
    if len(document["failures"]) > 10:
        typer.echo(f"  ... {len(document['failures']) - 10} more failures in {document['files'].get('csv')}")
    typer.echo("  wrote " + ", ".join(Path(p).name for p in document["files"].values()))


def _check_fraction(value: Optional[float], option: str = "--train-fraction") -> None:
    if value is not None and not 0.0 < value <= 1.0:
        raise UserError(f"{value:g}: expected 0 < fraction <= 1", where=option)


@batch_app.command("fit")
@user_errors
def batch_fit(
    sources: list[str] = SOURCES,
    model: str = typer.Option(..., "--model", "-m", metavar="SPEC|FIT.json", help="As in `hilbench fit`: a model "
                              "spec to fit on every recording, or a saved model to score on each."),
    train: list[str] = TRAIN, test: list[str] = TEST,
    train_fraction: Optional[float] = typer.Option(None, "--train-fraction", help="As in `hilbench fit` (default 0.7)."),
    output: Optional[Path] = OUTPUT, scheduler: Optional[str] = SCHEDULER, workers: Optional[int] = WORKERS,
    each: str = EACH, retry_failed: bool = RETRY, no_report: bool = NO_REPORT, as_json: bool = JSON, quiet: bool = QUIET,
) -> None:
    """Fit (or score) a model on every recording: errors and parameters with units, a row each."""
    from hilbench.cli.model_commands import check_spec_early

    check_spec_early(model)
    _check_fraction(train_fraction)
    options = {"model": _model_option(model), "train": train, "test": test, "train_fraction": train_fraction}
    _batch("fit", sources, options, output, scheduler, workers, each, retry_failed, no_report, as_json, quiet)


@batch_app.command("diagnose")
@user_errors
def batch_diagnose(
    sources: list[str] = SOURCES,
    model: str = typer.Option(..., "--model", "-m", metavar="SPEC|FIT.json", help="As in `hilbench diagnose`."),
    add: Optional[str] = typer.Option(None, "--add", metavar="EFFECT", help="Add this effect and refit, on every recording."),
    auto: bool = typer.Option(False, "--auto", help="Add the best significant effect while one remains, on every recording."),
    train: list[str] = TRAIN, test: list[str] = TEST,
    train_fraction: float = typer.Option(0.7, "--train-fraction", help="As in `hilbench diagnose`."),
    from_s: Optional[float] = typer.Option(None, "--from", metavar="SECONDS", help="As in `hilbench diagnose`."),
    to_s: Optional[float] = typer.Option(None, "--to", metavar="SECONDS", help="As in `hilbench diagnose`."),
    exclude: list[str] = typer.Option([], "--exclude", metavar="[RUN:]T0-T1", help="As in `hilbench diagnose`. Repeatable."),
    output: Optional[Path] = OUTPUT, scheduler: Optional[str] = SCHEDULER, workers: Optional[int] = WORKERS,
    each: str = EACH, retry_failed: bool = RETRY, no_report: bool = NO_REPORT, as_json: bool = JSON, quiet: bool = QUIET,
) -> None:
    """Diagnose every recording: the effects found (and added with --auto), errors and parameters, a row each."""
    from hilbench.cli.model_commands import check_spec_early
    from hilbench.identify.trimming import parse_window

    check_spec_early(model)
    if add is not None:
        from hilbench.diagnosis.refit import spec_with

        check_spec_early(spec_with("linear", add), option="--add")
    _check_fraction(train_fraction)
    for window in exclude:
        parse_window(window)
    options = {"model": _model_option(model), "add": add, "auto": auto, "train": train, "test": test,
               "train_fraction": train_fraction, "from_s": from_s, "to_s": to_s, "exclude": exclude}
    _batch("diagnose", sources, options, output, scheduler, workers, each, retry_failed, no_report, as_json, quiet)


@batch_app.command("online")
@user_errors
def batch_online(
    sources: list[str] = SOURCES,
    train: list[str] = TRAIN,
    train_fraction: float = typer.Option(0.3, "--train-fraction", help="As in `hilbench online`."),
    orders: str = typer.Option("3,5", "--orders", metavar="M,N", help="As in `hilbench online`."),
    forgetting: float = typer.Option(1.0, "--forgetting", help="As in `hilbench online`."),
    forgetting_kind: str = typer.Option("directional", "--forgetting-kind", help="As in `hilbench online`."),
    delta: float = typer.Option(1.0e5, "--delta", help="As in `hilbench online`."),
    model: Optional[Path] = typer.Option(None, "--model", metavar="FIT.json", help="As in `hilbench online`."),
    settle: float = typer.Option(0.5, "--settle", help="As in `hilbench online`."),
    global_starts: int = typer.Option(16, "--global-starts", help="As in `hilbench online`."),
    output: Optional[Path] = OUTPUT, scheduler: Optional[str] = SCHEDULER, workers: Optional[int] = WORKERS,
    each: str = EACH, retry_failed: bool = RETRY, no_report: bool = NO_REPORT, as_json: bool = JSON, quiet: bool = QUIET,
) -> None:
    """Identify every recording online (paper 000's RLS) against its offline model, a row each."""
    from hilbench.cli.online_commands import check_online_settings, parse_orders

    parse_orders(orders)
    check_online_settings(forgetting, forgetting_kind, delta, settle, global_starts)
    _check_fraction(train_fraction)
    if model is not None and not model.is_file():
        raise UserError("no such file", where=str(model), hint="a fitted fpmpi model from `hilbench fit -o`")
    options = {"train": train, "train_fraction": train_fraction, "orders": orders, "forgetting": forgetting,
               "forgetting_kind": forgetting_kind, "delta": delta,
               "online_model": str(model.resolve()) if model is not None else None,
               "settle": settle, "global_starts": global_starts}
    _batch("online", sources, options, output, scheduler, workers, each, retry_failed, no_report, as_json, quiet)


def _model_option(model: str) -> str:
    """A saved model is named by its absolute path (the workers may run elsewhere); a spec as given."""
    from hilbench.identify.fitting import is_model_file

    return str(Path(model).resolve()) if is_model_file(model) else model


@batch_app.command("example")
@user_errors
def batch_example(
    folder: Path = typer.Argument(..., metavar="DIR", help="Folder to write the recordings into (created)."),
    recordings: int = typer.Option(50, "--recordings", "-n", help="Simulated days, one recording each."),
    seconds: float = typer.Option(4.0, "--seconds", help="Length of each recording, s (1 kHz: 1000 samples a second)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the days' temperatures and the sensors' noise."),
    as_json: bool = JSON,
) -> None:
    """Write a simulated archive to try the batch on: a piezo stack ageing over days, some warm, some loaded."""
    from hilbench.archive.example import write_example_archive

    if not 1 <= recordings <= 10000:
        raise UserError(f"{recordings}: expected 1-10000 recordings", where="--recordings")
    if not 1.0 <= seconds <= 3600.0:
        raise UserError(f"{seconds:g} s: expected 1-3600 s", where="--seconds")
    paths = write_example_archive(folder, recordings, seconds, seed)
    if as_json:
        print_json({"folder": str(folder), "recordings": [str(p) for p in paths]})
        return
    typer.echo(f"{folder}: {len(paths)} recordings ({paths[0].name} ... {paths[-1].name}), {seconds:g} s each")
