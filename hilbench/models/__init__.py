"""The papers' hysteresis models as one composable library (see :mod:`hilbench.models.model`)."""

from hilbench.models.model import Model, RunData, SpecError, available_names

__all__ = ["Model", "RunData", "SpecError", "available_names"]
