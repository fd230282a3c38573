"""Identification: separable least squares for the models, and the papers' linear-dynamics methods."""

from hilbench.identify.separable import FitReport, fit_model, solve_weights

__all__ = ["FitReport", "fit_model", "solve_weights"]
