"""The Python API: the command line's verbs as functions, for notebooks and scripts.

Each function is the library call its command makes, so a notebook and `hilbench COMMAND` give the
same numbers. ``import hilbench`` exposes them lazily (nothing heavy is imported until one is used)::

    import hilbench

    with hilbench.open_rig("piezo-demo", output_dir="work") as bench:       # a simulated rig
        sweep = bench.sweep(bench.plan("sine:amplitude=40,offset=50,frequency_hz=1,cycles=4"), "sweep.h5")
    recording = hilbench.open_recording("work/sweep.h5")
    arrays = recording.runs[0].data()             # {"time": ..., "input": ..., "output": ...} numpy arrays
    fit = hilbench.fit("work/sweep.h5", "pi")     # FitResult: .metrics, .model, .to_json(), .save(path)
    found = hilbench.diagnose("work/sweep.h5", "pi", auto=True)   # Diagnosis: .spec, .effects, .to_json()

Results print as one readable line and have ``.to_json()`` (the document the command prints with
``--json``). Errors you can fix raise :class:`hilbench.errors.UserError` with the same one-line
message the command line prints.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from hilbench.archive.batch import BatchSummary
    from hilbench.diagnosis.diagnose import Diagnosis
    from hilbench.identify.fitting import FitResult
    from hilbench.online.tracking import TrackResult
    from hilbench.recording.hdf5 import Recording
    from hilbench.runners.script import Bench

PathLike = str | os.PathLike[str]


def open_recording(path: PathLike) -> Recording:
    """A recording's runs (``.runs``; ``run.data()`` gives every channel as numpy arrays, ``run.units``
    their units, ``run.to_dataframe()`` a pandas DataFrame when pandas is installed)."""
    from hilbench.recording.hdf5 import Recording

    return Recording(path)


def fit(data: PathLike | Sequence[PathLike], spec: str, **options: Any) -> FitResult:
    """`hilbench fit`: fit ``spec`` (``"pi"``, ``"pmpi+dynamics"``, ...) to the recordings, or score a
    saved model (``spec`` a FIT.json). Options as the command's: ``train``, ``test`` (run names),
    ``train_fraction`` (default 0.7 for a fit; a saved model is scored whole unless given)."""
    from hilbench.identify.fitting import fit_or_evaluate, is_model_file

    if "train_fraction" not in options and not is_model_file(spec):
        options["train_fraction"] = 0.7
    return fit_or_evaluate(data, spec, **options)


def diagnose(data: PathLike | Sequence[PathLike], spec: str, **options: Any) -> Diagnosis:
    """`hilbench diagnose`: where ``spec`` fails on the recordings and which effect is missing.
    Options as the command's: ``add``, ``auto``, ``train``, ``test``, ``train_fraction``, ``trim``, ``jobs``."""
    from hilbench.diagnosis.diagnose import diagnose as run

    return run(data, spec, **options)


def online(data: PathLike | Sequence[PathLike], *, train: Sequence[str] = (), train_fraction: float = 0.3,
           orders: str = "3,5", forgetting: float = 1.0, forgetting_kind: str = "directional", delta: float = 1.0e5,
           model: PathLike | None = None, settle: float = 0.5, global_starts: int = 16) -> dict[str, Any]:
    """`hilbench online` on recordings: paper 000's identifier run over every evaluated run against the
    offline model; the document the command prints with ``--json``."""
    from hilbench.cli.online_commands import (
        check_online_settings,
        online_on_recordings,
        parse_orders,
    )

    M, N = parse_orders(orders)
    check_online_settings(forgetting, forgetting_kind, delta, settle, global_starts)
    paths = [Path(data)] if isinstance(data, (str, os.PathLike)) else [Path(p) for p in data]
    doc, _, _ = online_on_recordings(paths, train=list(train), train_fraction=train_fraction, M=M, N=N,
                                     forgetting=forgetting, forgetting_kind=forgetting_kind, delta=delta,
                                     model=Path(model) if model is not None else None, settle=settle,
                                     global_starts=global_starts, note=lambda _: None)
    return doc


def open_rig(name_or_path: PathLike, output_dir: PathLike = ".", *, check_rate: bool = True) -> Bench:
    """A rig to drive (a built-in name or a config), as `hilbench run` scripts get it: ``bench.plan``,
    ``bench.sweep``, ``bench.fit``, ``bench.track``... Use it in a ``with`` block: on leaving, the
    actuator ramps to rest and the devices close, whatever happened."""
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig
    from hilbench.runners.script import Bench

    return Bench(Rig(load_rig(name_or_path)), output_dir, experiment="api", check_rate=check_rate)


def track(rig: PathLike | Bench, model: Any, reference: Any, **options: Any) -> TrackResult:
    """`hilbench track`: track ``reference`` (a compact excitation or an array at the rig's rate, um)
    with the inverse of ``model`` (a fitted Model or FIT.json); options as
    :func:`hilbench.online.tracking.track` (``feedback``, ``online``, ``output``, ...)."""
    from hilbench.online.tracking import track as run
    from hilbench.runners.script import Bench

    if isinstance(rig, Bench):
        return rig.track(reference, model, **options)
    return run(rig, model, reference, **options)


def batch(command: str, sources: Sequence[str] | str, output: PathLike, *, scheduler: str | None = None,
          workers: int | None = None, each: str = "file", retry_failed: bool = False,
          **options: Any) -> BatchSummary:
    """`hilbench batch COMMAND`: ``command`` (fit, diagnose, online) over every recording of ``sources``
    on Dask; rows in ``output`` (results.parquet, .csv, summary.json, report.html). ``options`` as the
    single command's (``model="pi"``, ``auto=True``, ...). Call it under ``if __name__ == "__main__":``
    in a script: the local cluster's workers are started as fresh Python processes."""
    from hilbench.archive.batch import run_batch
    from hilbench.archive.tasks import default_options

    return run_batch(command, [sources] if isinstance(sources, str) else list(sources),
                     default_options(command, options), Path(output), scheduler=scheduler, workers=workers,
                     each=each, retry_failed=retry_failed)


__all__ = ["batch", "diagnose", "fit", "online", "open_recording", "open_rig", "track"]
