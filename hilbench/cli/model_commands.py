"""Commands on models: fit and diagnose, with their text summaries."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from hilbench.cli.app import (
    app,
    print_json,
    show_progress,
    user_errors,
)
from hilbench.cli.summaries import diagnosis_lines, diagnosis_summary_lines, fit_report_lines
from hilbench.errors import UserError


def check_spec_early(spec: str, option: str = "--model") -> None:
    """Refuse a malformed spec before any data is read (aux channels are checked against the data later)."""
    from hilbench.identify.fitting import is_model_file
    from hilbench.models.spec import SpecError, build_components

    if option == "--model" and is_model_file(spec):
        return
    try:
        build_components(spec)
    except SpecError as exc:
        raise SpecError(exc.message, where=option, hint=exc.hint) from None


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
    train_fraction: Optional[float] = typer.Option(
        None, "--train-fraction", help="Without --train/--test: the first part of every run that trains (0-1]; the "
        "rest validates (default 0.7). A saved model (--model FIT.json) is scored on whole runs unless this is given.",
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
    give whole runs roles instead. A saved model (--model FIT.json) is not refitted: it is scored on
    every run, whole (or on the --test runs), as one figure. Runs of one file are chained: the model's memory carries over
    from one run to the next, as the actuator's did. Errors are free-run simulation errors, in the
    output unit (um), mse in its square, the *_pct keys in percent.
    """
    from hilbench.identify.fitting import fit_or_evaluate, is_model_file

    check_spec_early(model)
    if output is not None and is_model_file(model):
        raise UserError("-o writes a fitted model, but --model names a saved one, which is evaluated, not refitted",
                        where="-o", hint="use --json to keep the evaluation, or give a spec to refit")
    if train and is_model_file(model):
        raise UserError("a saved model is scored, not trained: there is nothing for --train runs to do", where="--train",
                        hint="--test RUN scores the named runs only; without it every run is scored")
    if train_fraction is None and not is_model_file(model):
        train_fraction = 0.7

    def note(message: str) -> None:
        if not quiet:
            typer.echo(message, err=True)

    with show_progress(quiet):
        result = fit_or_evaluate(data, model, train=train or None, test=test or None,
                                 train_fraction=train_fraction, progress=note)
    for line in result.notes:
        note(f"note: {line}")
    if output is not None:
        note(f"wrote {result.save(output)}")
    if plot_png is not None:
        from hilbench.report.fit_figures import plot_fit

        note(f"wrote {plot_fit(result, plot_png)}")
    if as_json:
        document = result.to_json()
        document["files"] = [str(p) for p in data]
        if output is not None:
            document["output"] = str(output)
        if plot_png is not None:
            document["png"] = str(plot_png)
        print_json(document)
        return
    for line in fit_report_lines(result):
        typer.echo(line)


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
    from_s: Optional[float] = typer.Option(
        None, "--from", metavar="SECONDS", help="Leave out each run's rows before this time (s). Default: the rest "
        "at the start of an imported capture, before its excitation, is left out and the notes say so; --from 0 keeps it.",
    ),
    to_s: Optional[float] = typer.Option(None, "--to", metavar="SECONDS", help="Leave out each run's rows from this time (s)."),
    exclude: list[str] = typer.Option([], "--exclude", metavar="[RUN:]T0-T1",
                                      help="Leave out a time window (s; 'end' for the run's end), of one run or all. Repeatable."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
    report: Optional[Path] = typer.Option(None, "--report", metavar="DIR",
                                          help="Write a self-contained HTML report (DIR/report.html)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar on stderr."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Every candidate's explanation and failed checks "
                                 "in full, and more of where the error lies (the compact view fits one screen)."),
    jobs: Optional[int] = typer.Option(None, "--jobs", "-j", metavar="N",
                                       help="Worker processes for the refits of each round (default: one per core, "
                                       "at most 8; the result does not depend on it)."),
) -> None:
    """Compare a model with measurements: where it fails, which physical effect is missing.

    Every effect the data can test is added in turn and refitted on the same split; an effect is
    significant when it lowers the validation error by more than 10 %, agrees between training and
    validation, passes a block-wise signed-rank test (p < 0.01) and the error is above the noise.
    """
    from hilbench.diagnosis.diagnose import diagnose as run_diagnosis

    check_spec_early(model)
    if add is not None:
        from hilbench.diagnosis.refit import spec_with  # 'hysteresis' replaces a linear base

        check_spec_early(spec_with("linear", add), option="--add")
    from hilbench.identify.trimming import Trim, parse_window

    with show_progress(quiet):
        trim = Trim(auto=True, from_s=from_s, to_s=to_s, windows=[parse_window(w) for w in exclude])
        result = run_diagnosis(data, model, train=train or None, test=test or None, add=add, auto=auto,
                               train_fraction=train_fraction, trim=trim, jobs=jobs)
    document = result.to_json()
    page = None
    if report is not None:
        from hilbench.report.diagnosis_report import write_report

        page = write_report(result, report)
    if as_json:
        print_json(document)
        if page is not None:
            typer.echo(f"report: {page}", err=True)
        return
    for line in (diagnosis_lines if verbose else diagnosis_summary_lines)(document):
        typer.echo(line)
    if page is not None:
        typer.echo(f"report: {page}")
