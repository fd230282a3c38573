"""Figure helpers shared by the plots and reports: thinning long runs, saving and releasing figures."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any


def stride(n: int, max_points: int) -> int:
    """Sample step that keeps at most ``max_points`` points of a run of ``n`` samples."""
    return max(1, math.ceil(n / max(1, max_points)))


def save_figure(fig: Any, output_png: str | Path) -> Path:
    """Write a figure to PNG (folders created) and release it."""
    import matplotlib.pyplot as plt

    out = Path(output_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        fig.savefig(out, dpi=100)
    finally:
        plt.close(fig)
    return out
