"""The ``hilbench`` command line.

Conventions (DESIGN.md, "Command line"): every command that produces results takes ``--json`` and
then prints exactly one JSON document on stdout; progress goes to stderr; an error the user can fix
prints one line (and a hint) on stderr and exits with status 2, no traceback unless ``--debug``.

Each module registers its commands on the one :data:`app`: recording_commands (sweep, show, watch, import,
plot, rigs), device_commands (devices, emulate, run), model_commands (fit, diagnose), online_commands (online), track_commands (track),
batch_commands (batch fit|diagnose|online), demo.
"""

from hilbench.cli import recording_commands, device_commands, demo, model_commands, identify_commands, online_commands, track_commands, batch_commands  # noqa: F401, I001  (registers the commands, in help order)
from hilbench.cli.app import app, main

__all__ = ["app", "main"]
