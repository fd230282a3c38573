"""hilbench: a hardware-in-the-loop bench for smart-material actuators.

The command line is ``hilbench``; the same verbs are functions here, for notebooks and scripts
(:mod:`hilbench.api`): :func:`open_recording`, :func:`fit`, :func:`diagnose`, :func:`online`,
:func:`open_rig`, :func:`track`, :func:`batch`. They are imported on first use, so ``import
hilbench`` stays light.
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"

_API = ("batch", "diagnose", "fit", "online", "open_recording", "open_rig", "track")
__all__ = ["__version__", *_API]


def __getattr__(name: str) -> Any:
    if name in _API:
        from hilbench import api

        return getattr(api, name)
    raise AttributeError(f"module 'hilbench' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_API])
