"""Errors the user can fix.

Every problem caused by input (a config, a plan, a data file, a command-line value) is raised as
:class:`UserError`. The CLI prints it as one line, ``error: <where>: <message> (hint: <hint>)``, and
exits with status 2; with ``--json`` it also prints ``{"error": ..., "hint": ..., "exit": 2}`` on
stdout; ``--debug`` shows the traceback. Everything else is a bug and keeps its traceback.
"""

from __future__ import annotations

from typing import Any


class UserError(Exception):
    """A problem with the user's input, reported as one line.

    ``where`` names the file (and key, line or value) at fault, ``message`` says what was expected.
    """

    def __init__(self, message: str, *, where: str | None = None, hint: str | None = None):
        self.message = message
        self.where = where
        self.hint = hint
        super().__init__(self.line())

    def __reduce__(self) -> tuple[Any, ...]:
        # raised in a worker process (diagnosis/workers.py), it is pickled to the caller whole
        return (_rebuild_user_error, (type(self), self.message, self.where, self.hint))

    def line(self) -> str:
        text = f"{self.where}: {self.message}" if self.where else self.message
        return " ".join(text.split())  # one line, whatever the parts contained


def _rebuild_user_error(cls: type[UserError], message: str, where: str | None, hint: str | None) -> UserError:
    return cls(message, where=where, hint=hint)


def error_line(message: str, hint: str | None = None) -> str:
    """The one line an error is printed as: ``error: <message> (hint: <hint>)``."""
    text = f"error: {message}" + (f" (hint: {hint})" if hint else "")
    return " ".join(text.split())


class RunStopped(UserError):
    """A run stopped by the user (Ctrl-C, SIGTERM) at a safe point: recorded ``aborted``, the
    actuator at rest. One line like any user error, exit status 130 (the shell's for SIGINT)."""

    exit_code = 130

    @classmethod
    def of_run(cls, reason: str, recording: str | None, group: str, what: str = "") -> RunStopped:
        """The error for a run closed ``aborted`` (``reason``: its recorded reason); ``recording``
        None when the run was not kept for the user (a temporary file)."""
        hint = None if recording is None else "the samples before the interrupt are recorded (status aborted)" + what
        return cls(reason.splitlines()[0], where=None if recording is None else f"{recording} run {group}", hint=hint)


class ConfigError(UserError):
    """A rig config or plan file is invalid."""


class PlanLimitError(UserError):
    """A plan would drive the actuator outside its range or slew limit."""


class DataError(UserError):
    """A data file (CSV, MAT, HDF5) cannot be read as asked."""


class RecordingWriterError(RuntimeError):
    """The recording's writer process failed (disk full, file removed) or stopped answering. Not the
    user's input, but not a bug either: the CLI reports it as one line with exit status 1."""
