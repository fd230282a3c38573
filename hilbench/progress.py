"""Progress of long work: reported by library code, shown by the command line.

Library code (fits, the diagnosis, imports) opens a task and advances it::

    with progress.task("diagnose pi: effects", total=len(effects)) as advance:
        for effect in effects:
            ...
            advance(1, f"diagnose pi: {effect}")

Nothing is shown unless a display is installed (:func:`display`), which the CLI does when stderr is
a terminal and ``--quiet`` is not given: a rich progress bar on stderr, one line per open task
(tasks close themselves, so nested fits inside a diagnosis appear and disappear under it). Without a
display a task costs one function call.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, Protocol


class _Display(Protocol):
    def add(self, description: str, total: float | None) -> Any: ...
    def advance(self, task_id: Any, amount: float, description: str | None) -> None: ...
    def remove(self, task_id: Any) -> None: ...


_display: _Display | None = None

Advance = Callable[..., None]


def _noop(amount: float = 1, description: str | None = None) -> None:
    return None


@contextmanager
def task(description: str, total: float | None = None) -> Iterator[Advance]:
    """A unit of long work; yields ``advance(amount=1, description=None)``."""
    shown = _display
    if shown is None:
        yield _noop
        return
    task_id = shown.add(description, total)

    def advance(amount: float = 1, description: str | None = None) -> None:
        shown.advance(task_id, amount, description)

    try:
        yield advance
    finally:
        shown.remove(task_id)


def wanted(quiet: bool, stream: Any = None) -> bool:
    """Progress is shown on a terminal only: not with --quiet, not when stderr is a pipe or file."""
    stream = sys.stderr if stream is None else stream
    try:
        tty = bool(stream.isatty())
    except (AttributeError, ValueError):
        tty = False
    return not quiet and tty and os.environ.get("TERM", "") != "dumb"


class _RichDisplay:
    def __init__(self) -> None:
        from rich.console import Console
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            SpinnerColumn,
            TextColumn,
            TimeElapsedColumn,
        )

        self.bar = Progress(
            SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
            TimeElapsedColumn(), console=Console(stderr=True), transient=True, refresh_per_second=8,
        )

    def add(self, description: str, total: float | None) -> Any:
        task_id = self.bar.add_task(description, total=total)
        self.bar.refresh()
        return task_id

    def advance(self, task_id: Any, amount: float, description: str | None) -> None:
        if description is None:
            self.bar.advance(task_id, amount)
        else:
            self.bar.update(task_id, advance=amount, description=description)

    def remove(self, task_id: Any) -> None:
        self.bar.remove_task(task_id)


@contextmanager
def display(enabled: bool) -> Iterator[None]:
    """Show the tasks opened meanwhile on stderr (when ``enabled``)."""
    global _display
    if not enabled or _display is not None:
        yield
        return
    shown = _RichDisplay()
    _display = shown
    shown.bar.start()
    try:
        yield
    finally:
        _display = None
        shown.bar.stop()
