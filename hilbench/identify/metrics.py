"""Error metrics with the keys used everywhere (JSON, reports, model files).

The table of keys, definitions and the papers' names is in the README, section "Metrics"
(README.md#metrics); e = model - measured, y = measured, errors in the output unit (um):

=================  ===================================================  ===========================
key                definition                                           papers' name
=================  ===================================================  ===========================
rmse               sqrt(mean(e^2)), um                                  RMSE (004)
mse                mean(e^2), um^2                                      MSE (001 eq. 32)
max_abs_error      max |e|, um                                          MAE (004 eq. 21), Emax (001)
mean_abs_error     mean |e|, um                                         MAD (004 eq. 21)
mre_pct            100 max |e| / max |y|, %                             MRE (004 eq. 21)
e_rel_pct          100 max |e| / (max y - min y), %                     Erelative (001 eq. 34), emax (003)
erms_pct           100 rmse / (max y - min y), %                        erms (003 eq. 17)
re_n2_pct          100 ||e||_2 / ||y||_2, %                             re_N2 (000 eq. 18)
re_ninf_pct        100 ||e||_inf / ||y||_inf, %                         re_Ninf (000 eq. 18)
=================  ===================================================  ===========================

The papers' "MAE" is the *maximum* absolute error, not the mean of scikit-learn and MATLAB, hence
the explicit names. Model files written before the rename (keys ``mae``, ``mad``) are read with the keys renamed
(:func:`hilbench.models.model.upgrade_model_document`).
"""

from __future__ import annotations


import numpy as np

METRIC_KEYS = ("rmse", "mse", "max_abs_error", "mean_abs_error", "mre_pct", "e_rel_pct", "erms_pct", "re_n2_pct",
               "re_ninf_pct")
#: the unit of each key, with y_unit the output's unit (um)
METRIC_UNITS = {"rmse": "{y}", "mse": "{y}^2", "max_abs_error": "{y}", "mean_abs_error": "{y}", "mre_pct": "%",
                "e_rel_pct": "%", "erms_pct": "%", "re_n2_pct": "%", "re_ninf_pct": "%"}


def metric_unit(key: str, y_unit: str = "um") -> str:
    return METRIC_UNITS.get(key, "").format(y=y_unit)


def metrics(measured: np.ndarray, model: np.ndarray) -> dict[str, float]:
    """All metric keys for one stretch of data; NaN samples (sensor out of range) are left out."""
    y = np.asarray(measured, dtype=float)
    m = np.asarray(model, dtype=float)
    keep = np.isfinite(y) & np.isfinite(m)
    y, m = y[keep], m[keep]
    if y.size == 0:
        return {k: float("nan") for k in METRIC_KEYS} | {"n": 0}
    e = m - y
    rmse = float(np.sqrt(np.mean(e**2)))
    max_abs = float(np.max(np.abs(e)))
    span = float(np.ptp(y))
    peak = float(np.max(np.abs(y)))
    norm2 = float(np.linalg.norm(y))

    def pct(value: float, scale: float) -> float:
        return 100.0 * value / scale if scale > 0 else float("nan")

    return {
        "rmse": rmse,
        "mse": rmse**2,
        "max_abs_error": max_abs,
        "mean_abs_error": float(np.mean(np.abs(e))),
        "mre_pct": pct(max_abs, peak),
        "e_rel_pct": pct(max_abs, span),
        "erms_pct": pct(rmse, span),
        "re_n2_pct": pct(float(np.linalg.norm(e)), norm2),
        "re_ninf_pct": pct(max_abs, peak),
        "n": int(y.size),
    }
