"""hilbench demo: the whole loop on a simulated rig with hidden effects."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from hilbench.cli.app import (
    DEFAULT_RIG,
    RunProgress,
    app,
    print_json,
    show_progress,
    user_errors,
)
from hilbench.cli.summaries import diagnosis_summary_lines


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
    from hilbench.diagnosis.diagnose import diagnose as run_diagnosis
    from hilbench.excitation.plan import expand_runs
    from hilbench.recording.hdf5 import Recording
    from hilbench.report.diagnosis_report import write_report
    from hilbench.report.plotting import plot_runs
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig
    from hilbench.runners.sweep import run_plan

    rig_config = load_rig(rig)
    runs = expand_runs(rig_config.plan, file=rig_config.path)
    output_dir.mkdir(parents=True, exist_ok=True)
    h5 = output_dir / "demo.h5"
    h5.unlink(missing_ok=True)  # the demo starts afresh each time
    started = time.monotonic()
    with RunProgress(not quiet) as progress:
        result = run_plan(Rig(rig_config), runs, h5, experiment="demo", realtime=False, progress=progress)
    png = plot_runs(h5, output_dir / "demo.png")
    summary = Recording(h5).summary()
    if not quiet:
        typer.echo(f"diagnosing {model} on {h5} ...", err=True)
    with show_progress(quiet):
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
        print_json(document)
        return
    typer.echo(f"hilbench demo: rig {rig_config.name}: {rig_config.description}")
    typer.echo(f"  {len(result.runs)} runs recorded to {h5} ({result.status}), loops plotted to {png}")
    for r in summary["runs"]:
        typer.echo(f"  {r['name']:36s} {r['status']:9s} {r['n_samples']:>8d} samples")
    typer.echo("")
    for line in diagnosis_summary_lines(diagnosis.to_json()):
        typer.echo(line)
    typer.echo("")
    typer.echo(f"report: {report}")
    typer.echo(f"next: hilbench show {h5}   |   hilbench fit {h5} --model {diagnosis.spec} --plot fit.png")
