"""Identification: separable least squares for the models, and the papers' linear-dynamics methods
(step response, frequency response, discrete transfer function)."""

from hilbench.identify.frequency_response import frequency_response
from hilbench.identify.separable import FitReport, fit_model, solve_weights
from hilbench.identify.step_response import step_response
from hilbench.identify.transfer_function import fit_transfer_function, search_delay

__all__ = [
    "FitReport",
    "fit_model",
    "fit_transfer_function",
    "frequency_response",
    "search_delay",
    "solve_weights",
    "step_response",
]
