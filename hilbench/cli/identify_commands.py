"""hilbench linear: the papers' identification methods for the linear dynamics, on one recorded run."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import numpy as np
import typer

from hilbench.cli.app import app, print_json, user_errors
from hilbench.errors import UserError

METHODS = ("step", "frequency", "transfer-function")


def _step_size(u: np.ndarray) -> float:
    """The largest departure of the input from its first value, signed (input unit)."""
    up, down = float(np.max(u) - u[0]), float(np.min(u) - u[0])
    return up if abs(up) >= abs(down) else down


@app.command("linear")
@user_errors
def linear(
    data: Path = typer.Argument(..., metavar="DATA", help="Recording (.h5)."),
    run: str = typer.Option(..., "--run", metavar="RUN", help="The run to analyse (name, label or number)."),
    method: str = typer.Option(
        "step", "--method", help="step: K, zeta, fn from a small step (002 eq. 9-10); frequency: H1 estimate with "
        "coherence and 3-sigma band (000 Fig. 2d); transfer-function: discrete G(z) of 000 eq. 15.",
    ),
    step_size: Optional[float] = typer.Option(None, "--step-size", help="Input step, A or V (default: from the input)."),
    nb: int = typer.Option(2, "--nb", help="transfer-function: numerator order (1-20)."),
    na: int = typer.Option(2, "--na", help="transfer-function: denominator order (1-20)."),
    max_delay: int = typer.Option(10, "--max-delay", help="transfer-function: delays tried, samples (0-1000)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON document on stdout."),
) -> None:
    """Identify the linear dynamics after the hysteresis from one run: a step, a broadband or a swept run.

    The step method prints the spec part that fixes the dynamics for a fit, e.g.
    'dynamics(natural_frequency_hz=3180,zeta=0.281)' (paper 002: identify the linear part first).
    """
    from hilbench.identify.dataset import load_runs
    from hilbench.identify.frequency_response import frequency_response
    from hilbench.identify.step_response import step_response
    from hilbench.identify.transfer_function import search_delay

    if method not in METHODS:
        raise UserError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}", where="--method")
    for name, value, hi in (("--nb", nb, 20), ("--na", na, 20), ("--max-delay", max_delay, 1000)):
        if not (0 if name == "--max-delay" else 1) <= value <= hi:
            raise UserError(f"{value} is outside the allowed range up to {hi}", where=name)
    (r,) = load_runs(data, [run])
    u, y, fs = np.asarray(r.input, float), np.asarray(r.output, float), r.sample_rate_hz
    document: dict[str, Any] = {"file": str(data), "run": r.name, "method": method, "sample_rate_hz": fs}
    lines: list[str] = []
    if method == "step":
        size = step_size if step_size is not None else _step_size(u)
        if size == 0:
            raise UserError(f"run {r.name} holds its input constant: no step to identify", where=str(data))
        ident = step_response(np.arange(u.size) / fs, y, u_step=size, u=u)
        spec = f"dynamics(natural_frequency_hz={ident.natural_frequency_hz:.6g},zeta={ident.zeta:.6g})"
        document.update(ident.to_dict(), spec_part=spec)
        lines = [f"step of {size:g} at t = {ident.t_step_s:.6g} s: K {ident.gain:.5g} per input unit, "
                 f"zeta {ident.zeta:.4g}, fn {ident.natural_frequency_hz:.5g} Hz ({ident.used})",
                 f"overshoot {ident.overshoot_pct:.3g} %, peak time {ident.peak_time_s:.4g} s, "
                 f"settling time {ident.settling_time_s:.4g} s, noise {ident.noise_std:.3g}",
                 f"fix it in a fit: --model 'pi+{spec}'"]
    elif method == "frequency":
        frf = frequency_response(u, y, fs)
        peak = frf.resonant_frequency_hz()
        document.update(frf.to_dict(), resonant_frequency_hz=peak)
        lines = [f"H1 estimate over {frf.n_segments} segments of {frf.nperseg} samples, "
                 f"{frf.frequency_hz[0]:.4g}-{frf.frequency_hz[-1]:.4g} Hz",
                 f"first resonance: {peak:.5g} Hz" if np.isfinite(peak) else "no resonance with enough coherence"]
    else:
        tf = search_delay(u, y, fs, nb=nb, na=na, max_delay=max_delay)
        document.update(tf.to_dict())
        fn = ", ".join(f"{f:.4g}" for f in tf.natural_frequencies_hz()) or "none"
        lines = [f"G(z) with nb={nb}, na={na}, delay {tf.delay} samples: dc gain {tf.dc_gain:.5g}, "
                 f"rmse {tf.rmse:.4g}, stable {tf.stable}", f"natural frequencies: {fn} Hz",
                 f"b = {np.array2string(tf.b, precision=6)}", f"a = {np.array2string(tf.a, precision=6)}"]
    if as_json:
        print_json(document)
        return
    for line in lines:
        typer.echo(line)
