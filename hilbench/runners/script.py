"""Experiment scripts: a user's Python procedure run on a rig with ``hilbench run SCRIPT.py --rig RIG``.

A script is plain Python. It finds a :class:`Bench` named ``bench`` among its globals (or calls
:func:`current_bench`), already holding the rig opened once; whatever the script does, the rig is
made safe (ramped to rest through its safety path) and closed when the script ends, and a sweep
interrupted or broken mid-run leaves its recording closed with ``status = "aborted"`` or
``"failed"``::

    # experiments/my-loops.py         run with: hilbench run experiments/my-loops.py --rig piezo-demo
    plan = bench.plan("sine:amplitude=20|40,offset=50,frequency_hz=1,cycles=3")
    sweep = bench.sweep(plan, "loops.h5", label="loops")
    result = bench.fit(sweep, "pi+asymmetry")
    bench.log(f"validation rmse {result.metrics['validation']['rmse']:.3f} um")
    bench.report(rmse_um=result.metrics["validation"]["rmse"])

The API (units: the actuator's command unit A or V, the output unit um, times s, frequencies Hz):

``bench.plan(*runs)``
    A checked list of runs from compact strings (``"sine:amplitude=1|2,frequency_hz=1,cycles=3"``,
    the ``--excitation`` form), run tables (``{"kind": "step", "levels": [0, 1], "hold_s": 0.1}``, with
    ``label`` and ``sweep`` as in a plan file), plan-file paths (``Path("plans/x.toml")``) or runs
    of earlier plans, in any mix.
``bench.sweep(plan, output, label=None, **options)``
    Plays the plan on the rig into ``output`` (a ``.h5`` relative to ``bench.output_dir``; appended
    when it exists) through the runner (:func:`hilbench.runners.sweep.run_plan`): the whole plan is
    checked against the actuator's limits before anything moves, every command passes the rig's
    clamp and slew limit. ``plan`` may be anything :meth:`Bench.plan` takes. ``label`` names the runs:
    a one-run plan's run is called ``label``, a longer plan's runs ``label-<run label>``.
    ``options``: ``realtime``, ``chunk_samples``, ``progress``, ``on_event`` of ``run_plan``.
    Returns the :class:`~hilbench.runners.sweep.SweepResult` (``file``, ``status``, ``runs``); a
    sweep interrupted by Ctrl-C ends the script (``KeyboardInterrupt``) after its recording is closed.
``bench.fit(data, spec, **kw)``
    :func:`hilbench.identify.fitting.fit_or_evaluate` on one or more recordings (paths, relative to
    ``output_dir``, or sweep results): a spec (``"pmpi+dynamics"``) is fitted, a model ``.json`` is
    evaluated. ``kw``: ``train``, ``test`` (run names, labels or numbers), ``train_fraction``.
    Returns a :class:`~hilbench.identify.fitting.FitResult` (``metrics["train"|"validation"]`` with the
    metric keys of DESIGN.md, per-run ``runs[i].metrics``, ``model``, ``save(path)``).
``bench.diagnose(data, spec, **kw)``
    :func:`hilbench.diagnosis.diagnose.diagnose` (``kw``: ``train``, ``test``, ``add``, ``auto``,
    ``max_steps``, ``train_fraction``); returns the :class:`~hilbench.diagnosis.diagnose.Diagnosis`.
``bench.track(reference, output, **kw)``
    Closed-loop tracking of a reference (um) on the rig; arrives with the closed-loop work in
    :mod:`hilbench.online`. Until then it raises a :class:`~hilbench.errors.UserError` saying so;
    ``bench.can_track`` tells whether it is there.
``bench.runs(data)``
    The runs of recordings as :class:`hilbench.models.RunData` (``input``, ``output``, ``aux``,
    ``sample_rate_hz``, ``name``), for the script's own analysis.
``bench.open_rig(name_or_path)``
    Another rig (built-in name or config path) as a second :class:`Bench` sharing ``output_dir`` and
    the log; it is made safe and closed with the first.
``bench.rig``, ``bench.config``, ``bench.output_dir``, ``bench.quick``, ``bench.args``
    The open :class:`~hilbench.rig.rig.Rig`, its :class:`~hilbench.rig.config.RigConfig`, the folder
    recordings go to (created), whether a shortened run was asked for (``hilbench run --quick`` or
    ``HILBENCH_QUICK=1``: scripts then play fewer or shorter runs), the script's own arguments
    (``hilbench run SCRIPT.py --rig RIG -- ARGS``; also in ``sys.argv[1:]``).
``bench.log(message)``, ``bench.report(**values)``
    A progress line on stderr; results to keep: ``hilbench run --json`` prints them in its one JSON
    document (with the recordings written and the messages).

Errors: a :class:`~hilbench.errors.UserError` raised by the API or the script ends the run with its
one line and exit status 2; any other exception in the script with one line naming the script's
line and the exception, and exit status 1 (``hilbench --debug run ...`` shows the traceback).
"""

from __future__ import annotations

import contextlib
import os
import sys
import traceback
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from hilbench.errors import UserError

QUICK_ENV = "HILBENCH_QUICK"
_CURRENT: list[Bench] = []


def quick_from_env() -> bool:
    """Whether ``HILBENCH_QUICK`` asks for shortened runs (anything but empty, 0, false, no)."""
    return os.environ.get(QUICK_ENV, "").strip().lower() not in ("", "0", "false", "no")


def current_bench() -> Bench:
    """The :class:`Bench` of the script being run (for modules a script imports)."""
    if not _CURRENT:
        raise UserError("no experiment script is running", hint="run the script with `hilbench run SCRIPT.py --rig RIG`")
    return _CURRENT[-1]


class ScriptFailed(Exception):
    """The script raised something other than a :class:`UserError`; ``line()`` says where and what."""

    def __init__(self, script: Path, error: BaseException):
        self.script = script
        self.error = error
        self.where = _where_in_script(script, error)
        self.outcome: ScriptOutcome | None = None
        super().__init__(self.line())

    def line(self) -> str:
        what = f"{type(self.error).__name__}: {self.error}" if str(self.error) else type(self.error).__name__
        return " ".join(f"{self.where}: {what}".split())


def _where_in_script(script: Path, error: BaseException) -> str:
    """``SCRIPT.py:LINE`` of the innermost frame of the traceback that lies in the script."""
    target = str(script.resolve())
    where = str(script)
    for frame in traceback.extract_tb(error.__traceback__):
        with contextlib.suppress(OSError):
            if str(Path(frame.filename).resolve()) == target:
                where = f"{script}:{frame.lineno}"
    return where


@dataclass
class ScriptOutcome:
    """What ``hilbench run`` reports: the recordings written, the values reported, the messages."""

    script: str
    rig: str
    output_dir: str
    status: str = "complete"  # complete | failed | aborted
    error: str = ""
    recordings: list[dict[str, Any]] = field(default_factory=list)
    results: dict[str, Any] = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        from hilbench.identify.fitting import finite_json

        return finite_json({"script": self.script, "rig": self.rig, "output_dir": self.output_dir,
                            "status": self.status, "error": self.error, "recordings": self.recordings,
                            "results": self.results, "messages": self.messages})


class Bench:
    """The scripting API: one open rig, the runner, fitting and diagnosis (see the module docstring)."""

    def __init__(self, rig: Any, output_dir: str | os.PathLike[str], *, experiment: str = "script",
                 quick: bool = False, args: Sequence[str] = (), log_stream: TextIO | None = None,
                 outcome: ScriptOutcome | None = None, check_rate: bool = True):
        self.rig = rig
        #: on real devices, paced: sweeps and tracking first time the devices and refuse a rate they
        #: cannot hold (hilbench.runners.rate_check); `hilbench run --allow-late` turns it off
        self.check_rate = bool(check_rate)
        self.config = rig.config
        self.output_dir = Path(output_dir).resolve()  # a script that changes directory still finds it
        self.output_dir.mkdir(parents=True, exist_ok=True)
        self.experiment = experiment
        self.quick = bool(quick)
        self.args = list(args)
        self._log_stream = log_stream
        self._outcome = outcome if outcome is not None else ScriptOutcome(experiment, self.config.name, str(self.output_dir))
        self._others: list[Bench] = []
        self._closed = False

    # -- plans and sweeps ---------------------------------------------------------------------------
    def plan(self, *runs: Any) -> list[Any]:
        """Runs from compact strings, run tables, plan-file paths or earlier plans, checked against the rig."""
        from hilbench.excitation.plan import (
            PlannedRun,
            check_plan,
            expand_runs,
            load_plan_file,
            plan_from_compact,
        )

        planned: list[PlannedRun] = []
        for i, item in enumerate(runs):
            if isinstance(item, PlannedRun):
                planned.append(item)
            elif isinstance(item, (list, tuple)) and all(isinstance(r, PlannedRun) for r in item):
                planned.extend(item)
            elif isinstance(item, os.PathLike) or (isinstance(item, str) and item.endswith(".toml")):
                planned.extend(load_plan_file(item))
            elif isinstance(item, str):
                planned.extend(plan_from_compact([item]))
            elif isinstance(item, Mapping):
                planned.extend(expand_runs([dict(item)], file=f"bench.plan() argument {i + 1}", table="run"))
            else:
                raise UserError(f"bench.plan() argument {i + 1}: expected a compact run string "
                                "('sine:amplitude=1,frequency_hz=1,cycles=3'), a run table (dict), a plan file "
                                f"path or a plan, got {type(item).__name__} {item!r}")
        if not planned:
            raise UserError("bench.plan(): no runs given", hint="e.g. bench.plan('sine:amplitude=1,frequency_hz=1,cycles=3')")
        check_plan(planned, self.config.actuator, self.config.sample_rate_hz)
        return planned

    def path(self, name: str | os.PathLike[str]) -> Path:
        """``name`` relative to ``output_dir`` (absolute paths stay as they are)."""
        p = Path(name)
        return p if p.is_absolute() else self.output_dir / p

    def sweep(self, plan: Any, output: str | os.PathLike[str], label: str | None = None, **options: Any) -> Any:
        """Play ``plan`` on the rig into the recording ``output`` through the runner and the safety path."""
        from hilbench.excitation.plan import PlannedRun
        from hilbench.runners.sweep import run_plan

        allowed = {"realtime", "chunk_samples", "progress", "on_event"}
        unknown = sorted(set(options) - allowed)
        if unknown:
            raise UserError(f"bench.sweep(): unknown option {unknown[0]!r}; options: {', '.join(sorted(allowed))}")
        runs = self.plan(*(plan if isinstance(plan, (list, tuple)) else [plan]))
        if label is not None:
            if len(runs) == 1:
                runs = [PlannedRun(label, runs[0].excitation)]
            else:
                runs = [PlannedRun(f"{label}-{r.label}", r.excitation) for r in runs]
        out = self.path(output)
        out.parent.mkdir(parents=True, exist_ok=True)
        self._check_open()
        self.log(f"{self.config.name}: {len(runs)} run(s) -> {out}")
        result = run_plan(self.rig, runs, out, experiment=self.experiment, check_rate=self.check_rate, **options)
        self._outcome.recordings.append({
            "file": str(out), "rig": self.config.name, "status": result.status,
            "runs": [{"name": r.group, "label": r.label, "status": r.status, "samples": r.samples} for r in result.runs],
        })
        if result.status == "aborted":
            raise KeyboardInterrupt(f"sweep into {out} interrupted; the recording says so (status aborted)")
        return result

    # -- analysis -----------------------------------------------------------------------------------
    def _data(self, data: Any) -> list[Path]:
        items = data if isinstance(data, (list, tuple)) else [data]
        paths = []
        for item in items:
            file = getattr(item, "file", None)  # a SweepResult names its file, as written
            if file is not None:
                paths.append(Path(file))
                continue
            if not isinstance(item, (str, os.PathLike)):
                raise UserError(f"expected a recording path or a sweep result, got {type(item).__name__} {item!r}")
            paths.append(self.path(item))
        if not paths:
            raise UserError("no recording given")
        return paths

    def fit(self, data: Any, spec: str, **kw: Any) -> Any:
        """Fit ``spec`` (or evaluate a model ``.json``) on recordings; a ``FitResult``."""
        from hilbench.identify.fitting import fit_or_evaluate

        kw.setdefault("progress", self.log)
        result = fit_or_evaluate(self._data(data), spec, **kw)
        for note in result.notes:
            self.log(f"note: {note}")
        return result

    def diagnose(self, data: Any, spec: str, **kw: Any) -> Any:
        """Where ``spec`` fails on the recordings and which effect is missing; a ``Diagnosis``."""
        from hilbench.diagnosis.diagnose import diagnose

        return diagnose(self._data(data), spec, **kw)

    def runs(self, data: Any) -> list[Any]:
        """Every run of the recordings, in order, as ``RunData``."""
        from hilbench.identify.fitting import load_runs

        return [run for path in self._data(data) for run in load_runs(path)]

    # -- closed loop ----------------------------------------------------------------------------------
    @property
    def can_track(self) -> bool:
        """Always True now that hilbench.online has the closed loop (kept for scripts that ask)."""
        return True

    def track(self, reference: Any, model: Any, **kw: Any) -> Any:
        """Track ``reference`` (um: an array at the rig's rate or a compact excitation) in closed loop with
        the inverse of ``model`` (a fitted Model or a FIT.json path); see :func:`hilbench.online.tracking.track`
        for ``feedback``, ``online``, ``output`` (relative to the output folder) and the rest."""
        from hilbench.online import tracking

        self._check_open()
        if "output" in kw:
            kw["output"] = self.path(kw["output"])
        kw.setdefault("check_rate", self.check_rate)
        return tracking.track(self.rig, model, reference, **kw)

    # -- more rigs, messages, results -----------------------------------------------------------------
    def open_rig(self, name_or_path: str | os.PathLike[str]) -> Bench:
        """Open another rig; it is made safe and closed with this one."""
        from hilbench.rig.config import load_rig
        from hilbench.rig.rig import Rig

        self._check_open()
        other = Bench(Rig(load_rig(name_or_path)), self.output_dir, experiment=self.experiment, quick=self.quick,
                      args=self.args, log_stream=self._log_stream, outcome=self._outcome, check_rate=self.check_rate)
        self._others.append(other)
        self.log(f"opened rig {other.config.name}")
        return other

    def log(self, message: str) -> None:
        """One progress line on stderr (kept in the run's messages)."""
        text = str(message)
        self._outcome.messages.append(text)
        stream = self._log_stream if self._log_stream is not None else sys.stderr
        print(text, file=stream, flush=True)

    def report(self, **values: Any) -> None:
        """Results to keep: ``hilbench run --json`` prints them under ``results``."""
        self._outcome.results.update(values)

    @property
    def results(self) -> dict[str, Any]:
        return self._outcome.results

    # -- the end ----------------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise UserError("the bench is closed: the script has ended")

    def __enter__(self) -> Bench:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        self.close(success=exc_type is None)

    def __repr__(self) -> str:
        return f"Bench(rig={self.config.name!r}, output_dir={str(self.output_dir)!r}{', closed' if self._closed else ''})"

    def close(self, success: bool) -> None:
        """Make every rig safe (ramp to rest; ``success=False`` tells the device it was a failure), close it."""
        if self._closed:
            return
        self._closed = True
        from hilbench.runners.sweep import deferred_interrupts

        errors: list[BaseException] = []
        with deferred_interrupts():  # Ctrl-C must not cut the ramp to rest short
            for bench in [*self._others, self]:
                for step in (lambda b=bench: b.rig.stop(success), lambda b=bench: b.rig.close()):
                    try:
                        step()
                    except Exception as exc:  # noqa: BLE001 - every rig is made safe, then the first error is raised
                        errors.append(exc)
            for other in self._others:
                other._closed = True
        if errors:
            raise errors[0]


# -- running a script ---------------------------------------------------------------------------------


def rig_named_by(script: Path) -> str | None:
    """The script's top-level ``RIG = "name"`` (read, never executed): the default for ``--rig``."""
    import ast

    try:
        tree = ast.parse(script.read_text(encoding="utf-8"), filename=str(script))
    except (OSError, SyntaxError, ValueError):
        return None
    for node in tree.body:
        if (isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name)
                and node.targets[0].id == "RIG" and isinstance(node.value, ast.Constant)
                and isinstance(node.value.value, str)):
            return node.value.value
    return None


def _compile(script: Path) -> Any:
    if not script.is_file():
        raise UserError("no such script", where=str(script), hint="give the path of a Python file, e.g. experiments/paper-001-characterisation.py")
    try:
        source = script.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read the script: {exc}", where=str(script)) from None
    try:
        return compile(source, str(script), "exec")
    except SyntaxError as exc:
        raise UserError(f"invalid Python: {exc.msg}", where=f"{script}:{exc.lineno}") from None


@contextlib.contextmanager
def _script_environment(script: Path, args: Sequence[str], stdout: TextIO | None) -> Iterator[None]:
    """sys.argv, sys.path[0] and (with --json) stdout as ``python SCRIPT.py ARGS`` would see them."""
    old_argv, old_path = sys.argv[:], sys.path[:]
    sys.argv = [str(script), *args]
    sys.path.insert(0, str(script.resolve().parent))
    try:
        if stdout is not None:
            with contextlib.redirect_stdout(stdout):
                yield
        else:
            yield
    finally:
        sys.argv, sys.path[:] = old_argv, old_path


def run_script(
    script: str | os.PathLike[str],
    rig: str | os.PathLike[str] | None,
    output_dir: str | os.PathLike[str],
    *,
    quick: bool = False,
    args: Sequence[str] = (),
    script_stdout: TextIO | None = None,
    log_stream: TextIO | None = None,
    check_rate: bool = True,
) -> ScriptOutcome:
    """Open the rig once, run the script with ``bench`` in its globals, always make the rig safe.

    ``rig``: a config path or built-in rig name; ``None`` takes the script's ``RIG = "..."``.
    ``script_stdout``: where the script's ``print`` goes (``hilbench run --json`` sends it to stderr).
    ``check_rate``: on real devices, each sweep and tracking run first times the devices and refuses a
    rate they cannot hold (``hilbench run --allow-late``: False).
    Raises :class:`UserError` (the script's or the API's), :class:`ScriptFailed` (any other exception
    of the script; the outcome is attached as ``outcome``) or ``KeyboardInterrupt``; in every case
    the rig was ramped to rest and closed, and the recordings closed with their status.
    """
    from hilbench.rig.config import load_rig
    from hilbench.rig.rig import Rig

    path = Path(script)
    code = _compile(path)
    rig_name = rig if rig is not None else rig_named_by(path)
    if not rig_name:
        raise UserError("no rig given", where=str(path),
                        hint="give --rig NAME|CONFIG.toml, or write RIG = \"name\" at the top of the script")
    config = load_rig(rig_name)
    experiment = path.stem
    outcome = ScriptOutcome(str(path), config.name, str(output_dir))
    bench = Bench(Rig(config), output_dir, experiment=experiment, quick=quick, args=args, log_stream=log_stream,
                  outcome=outcome, check_rate=check_rate)
    success = False
    _CURRENT.append(bench)
    try:
        with _script_environment(path, args, script_stdout):
            try:
                exec(code, {"bench": bench, "__file__": str(path), "__name__": "__main__"})  # noqa: S102 - running the user's experiment is the point
            except SystemExit as exc:
                if exc.code not in (None, 0):
                    raise
        success = True
    except UserError as exc:
        outcome.status, outcome.error = "failed", exc.line()
        raise
    except KeyboardInterrupt:
        outcome.status, outcome.error = "aborted", "interrupted"
        raise
    except SystemExit as exc:
        outcome.status, outcome.error = "failed", f"the script exited with status {exc.code}"
        raise
    except Exception as exc:
        failed = ScriptFailed(path, exc)
        outcome.status, outcome.error = "failed", failed.line()
        failed.outcome = outcome
        raise failed from exc
    finally:
        _CURRENT.pop()
        bench.close(success)
    return outcome


__all__ = ["Bench", "ScriptFailed", "ScriptOutcome", "current_bench", "quick_from_env", "rig_named_by", "run_script"]
