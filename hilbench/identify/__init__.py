"""Identification: separable least squares for the models, and the papers' linear-dynamics methods."""

from hilbench.identify.linear import fit_transfer_function, frequency_response, search_delay, step_response
from hilbench.identify.separable import FitReport, fit_model, solve_weights

__all__ = [
    "FitReport",
    "fit_model",
    "fit_transfer_function",
    "frequency_response",
    "search_delay",
    "solve_weights",
    "step_response",
]
