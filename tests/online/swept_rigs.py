"""A rig written from TOML text, swept with its own plan and fitted: the start of every tracking test
on a generated rig."""

from __future__ import annotations

from pathlib import Path


def sweep_and_fit(folder: Path, text: str, spec: str) -> tuple[Path, object]:
    """Write ``text`` as ``folder/rig.toml``, play its plan into ``folder/sweep.h5`` and fit ``spec``
    there: (the rig file, the fitted model)."""
    from hilbench.excitation.plan import expand_runs
    from hilbench.identify.fitting import fit
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig
    from hilbench.runners.sweep import run_plan

    rig = folder / "rig.toml"
    rig.write_text(text, encoding="utf-8")
    config = load_rig(rig)
    with Rig(config) as opened:
        run_plan(opened, expand_runs(config.plan, file=config.path), folder / "sweep.h5")
    return rig, fit(folder / "sweep.h5", spec).model
