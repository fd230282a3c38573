"""The ``hilbench`` application: the typer app, error handling, JSON output and progress bars.

The commands live in the modules beside this one, grouped by what they work on.

Conventions (DESIGN.md, "Command line"): every command that produces results takes ``--json`` and
then prints exactly one JSON document on stdout; progress goes to stderr; an error the user can fix
prints one line, ``error: <where>: <message> (hint: <hint>)``, on stderr and exits with status 2,
no traceback unless ``--debug``; with ``--json`` it also prints ``{"error", "hint", "exit"}`` on stdout.
Command-line usage errors (an unknown option, a value of the wrong type) take the same form: the
entry point :func:`run` runs the app outside click's standalone mode to print them so.
"""

from __future__ import annotations

import functools
import json
import sys
import traceback
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any, Optional, TypeVar

import typer

from hilbench import __version__
from hilbench import progress as _progress
from drivers.base import DeviceError
from hilbench.errors import RecordingWriterError, UserError, error_line
from hilbench.runners.faults import RunFault, summary

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
_state: dict[str, Any] = {"debug": False, "json": False}

F = TypeVar("F", bound=Callable[..., Any])


def report_error(message: str, hint: str | None = None, code: int = 2, *, as_json: bool | None = None) -> int:
    """Print an error: one line on stderr and, with --json, one JSON document on stdout."""
    if as_json if as_json is not None else _state["json"]:
        print_json({"error": " ".join(message.split()), "hint": hint, "exit": code})
    sys.stderr.write(error_line(message, hint) + "\n")
    sys.stderr.flush()
    return code


def fail(message: str, hint: str | None = None, code: int = 2) -> None:
    raise typer.Exit(report_error(message, hint, code))


def user_errors(func: F) -> F:
    """Turn :class:`UserError` (and a file the system refuses) into one line on stderr and exit status 2;
    with ``--json`` (``as_json``) also a JSON document ``{"error", "hint", "exit"}`` on stdout."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        _state["json"] = bool(kwargs.get("as_json", False))
        try:
            return func(*args, **kwargs)
        except UserError as exc:
            if _state["debug"]:
                traceback.print_exc()
            fail(exc.line(), exc.hint, code=getattr(exc, "exit_code", 2))
        except (DeviceError, RunFault, RecordingWriterError) as exc:
            # a device, an interlock or the recording's writer stopped a run: the runner made the actuator
            # safe and closed the recording as far as it could; one line naming the device (or the
            # writer), where the samples are, exit status 1
            if _state["debug"]:
                traceback.print_exc()
            recorded = getattr(exc, "hilbench_recorded", None)
            device = getattr(exc, "hilbench_device", "")
            line = summary(exc)
            fail(f"device {device!r}: {line}" if device and f"'{device}'" not in line else line,
                 f"recorded: {recorded}" if recorded else None, code=1)
        except OSError as exc:  # a path the system refuses: missing folder, permissions, full disk
            if exc.filename is None:
                raise
            if _state["debug"]:
                traceback.print_exc()
            fail(f"{exc.filename}: {exc.strerror or exc.__class__.__name__}",
                 "check the path and its permissions")
        except MemoryError:
            if _state["debug"]:
                traceback.print_exc()
            fail("out of memory", "use fewer operators or fewer samples, or raise --memory-limit")
        except KeyboardInterrupt:
            fail("interrupted", code=130)

    return wrapper  # type: ignore[return-value]


def show_progress(quiet: bool) -> Any:
    """A context in which long work shows progress on stderr (a terminal only, not with --quiet)."""
    return _progress.display(_progress.wanted(quiet))


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
    memory_limit: Optional[str] = typer.Option(
        None, "--memory-limit", metavar="SIZE",
        help="Largest memory a fit may need, e.g. 4GB, 512MB (default: $HILBENCH_MEMORY_LIMIT, else half the "
        "machine's memory); a model spec whose estimate exceeds it is refused before anything is allocated.",
    ),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
) -> None:
    _state["debug"] = debug
    from hilbench.models.spec import set_memory_limit

    try:
        set_memory_limit(memory_limit)
    except UserError as exc:
        fail(exc.line(), exc.hint)


class RunProgress:
    """A progress bar on stderr, one task per run."""

    def __init__(self, enabled: bool):
        self.enabled = _progress.wanted(not enabled)  # a terminal only, not with --quiet
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




def run(argv: list[str] | None = None) -> int:
    """The command line: run ``argv`` (default ``sys.argv[1:]``) and return the exit status.

    Usage errors (an unknown option, a value of the wrong type) are printed like every other error:
    one line on stderr, a JSON document on stdout when ``--json`` is among the arguments.
    """
    from typer._click import exceptions as click_exceptions  # typer's own copy of click

    args = list(sys.argv[1:] if argv is None else argv)
    command = typer.main.get_command(app)
    _state["json"] = "--json" in args
    try:
        status = command.main(args=args, prog_name="hilbench", standalone_mode=False)
    except click_exceptions.UsageError as exc:
        where = exc.ctx.command_path if exc.ctx is not None else "hilbench"
        return report_error(f"{where}: {exc.format_message()}", f"see '{where} --help'", 2, as_json=_state["json"])
    except click_exceptions.ClickException as exc:
        return report_error(exc.format_message(), None, exc.exit_code, as_json=_state["json"])
    except typer.Abort:
        return report_error("aborted", None, 130, as_json=_state["json"])
    return status if isinstance(status, int) else 0


def main() -> None:
    sys.exit(run())
