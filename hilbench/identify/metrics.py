"""Error metrics with the keys used everywhere (JSON, reports, fits); see DESIGN.md.

=============  =====================================================================  ==========
key            definition (e = model - measured, y = measured)                        paper
=============  =====================================================================  ==========
rmse           sqrt(mean(e^2))                                                          004
mse            mean(e^2)                                                                001 eq. 32
mae            max |e|                                                                  004 eq. 21
mad            mean |e|                                                                 004 eq. 21
mre_pct        100 mae / max |y|                                                        004 eq. 21
e_rel_pct      100 mae / (max y - min y)                                                001 eq. 34, 003 emax
erms_pct       100 rmse / (max y - min y)                                               003 eq. 17
re_n2_pct      100 ||e||_2 / ||y||_2                                                    000 eq. 18
re_ninf_pct    100 ||e||_inf / ||y||_inf                                                000 eq. 18
=============  =====================================================================  ==========
"""

from __future__ import annotations

import numpy as np

METRIC_KEYS = ("rmse", "mse", "mae", "mad", "mre_pct", "e_rel_pct", "erms_pct", "re_n2_pct", "re_ninf_pct")


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
    mae = float(np.max(np.abs(e)))
    span = float(np.ptp(y))
    peak = float(np.max(np.abs(y)))
    norm2 = float(np.linalg.norm(y))

    def pct(value: float, scale: float) -> float:
        return 100.0 * value / scale if scale > 0 else float("nan")

    return {
        "rmse": rmse,
        "mse": rmse**2,
        "mae": mae,
        "mad": float(np.mean(np.abs(e))),
        "mre_pct": pct(mae, peak),
        "e_rel_pct": pct(mae, span),
        "erms_pct": pct(rmse, span),
        "re_n2_pct": pct(float(np.linalg.norm(e)), norm2),
        "re_ninf_pct": pct(mae, peak),
        "n": int(y.size),
    }
