"""The ``hilbench`` application: the typer app, error handling, JSON output and progress bars.

The commands live in the modules beside this one, grouped by what they work on.

Conventions (DESIGN.md, "Command line"): every command that produces results takes ``--json`` and
then prints exactly one JSON document on stdout; progress goes to stderr; an error the user can fix
prints one line (and a hint) on stderr and exits with status 2, no traceback unless ``--debug``.
"""

from __future__ import annotations

import functools
import json
import sys
import traceback
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any, TypeVar

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


def fail(message: str, hint: str | None = None, code: int = 2) -> None:
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
            fail(exc.line(), exc.hint)
        except KeyboardInterrupt:
            fail("interrupted", code=130)

    return wrapper  # type: ignore[return-value]


def print_json(document: Any) -> None:
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


class RunProgress:
    """A progress bar on stderr, one task per run."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self._bar: Any = None
        self._task: Any = None
        self._run = 0

    def __enter__(self) -> RunProgress:
        if self.enabled:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                Progress,
                TextColumn,
                TimeRemainingColumn,
            )

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


def default_output(rig_name: str) -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("recordings") / f"{rig_name}-{stamp}.h5"




def main() -> None:
    app()
