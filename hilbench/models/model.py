"""A model: spec, components, weights; simulation (block and step mode) and JSON persistence.

A spec is a base model and effects joined by ``+`` (DESIGN.md): ``pi``, ``pmpi+dynamics``,
``pi+creep+temperature``. Options go in parentheses: ``pi(n=16)``, ``rate-dependence(form=frequency)``.
Any name that is neither a base nor an effect names an auxiliary channel of the recording.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal as sps

from hilbench import __version__
from hilbench.errors import UserError
from hilbench.models import kernels as MK
from hilbench.models.components import Columns, Component, ShapeParam, Signals
from hilbench.models.effect_components import AuxChannel

MODEL_FORMAT = "hilbench-model"
MODEL_FORMAT_VERSION = 1


# Spec parsing and validation live in hilbench.models.spec; imported here for existing callers.
from hilbench.models.spec import SpecError, available_names, build_components, split_spec  # noqa: E402, F401


@dataclass
class RunData:
    """One run of data for fitting or simulation: input, output, auxiliary channels."""

    input: np.ndarray
    output: np.ndarray | None
    aux: dict[str, np.ndarray]
    sample_rate_hz: float
    name: str = ""
    source: dict[str, Any] = field(default_factory=dict)
    #: the run continues from the previous one in a list (same actuator, recorded in sequence): the
    #: model's memory is carried over, through a ramp from the previous run's last input to this
    #: run's first, as the rig moves between runs
    chain: bool = False
    #: for a run that does not chain: the command the rig ramped from to the run's first sample
    #: (its rest value after power-up), or None when unknown (imported data)
    approach_from: float | None = None

    def __len__(self) -> int:
        return int(self.input.shape[0])


class Model:
    """A hysteresis model with effects, identified by :func:`hilbench.identify.fit_model`."""

    def __init__(self, spec: str, channels: list[str] | None = None):
        self.base, self.effects = build_components(spec, channels)
        self.spec = self.canonical_spec()
        self.norm: dict[str, Any] = {}
        self.sample_rate_hz: float = 0.0
        self.weights: np.ndarray | None = None
        self.weight_names: list[str] = []
        self.info: dict[str, Any] = {}

    # -- structure -----------------------------------------------------------------------------
    @property
    def components(self) -> list[Component]:
        return [self.base, *self.effects]

    @property
    def structure(self) -> Component | None:
        """The effect that is the whole model's state equation (``restoring-force``: the base's
        hysteresis inside the mechanics), or None for the columns-and-weights models."""
        return next((e for e in self.effects if getattr(e, "whole_model", False)), None)

    def _searched_components(self) -> list[Component]:
        """The components whose shape parameters define the model (a structure's alone)."""
        return [self.structure] if self.structure is not None else self.components

    def structure_output(self, run: RunData, state: dict[str, Any]) -> np.ndarray:
        """The structure's free-run output of one run from ``state`` (updated)."""
        nu = float(self.base.options.get("n", 1.0))
        return self.structure.simulate(run.input, run.sample_rate_hz, nu, state)

    def effect(self, name: str) -> Component | None:
        return next((e for e in self.effects if e.name == name or getattr(e, "channel", None) == name), None)

    def weight_constraints(self, names: list[str]) -> np.ndarray | None:
        """The components' linear inequalities on the weights, ``G @ w >= 0`` (None: none)."""
        rows = [g for g in (c.weight_constraints(names) for c in self.components) if g is not None]
        return np.vstack(rows) if rows else None

    @property
    def aux_channels(self) -> list[str]:
        return [e.channel for e in self.effects if isinstance(e, AuxChannel)]

    def canonical_spec(self) -> str:
        def part(c: Component) -> str:
            label = getattr(c, "channel", c.name)
            opts = ",".join(f"{k}={v}" for k, v in c.options.items())
            return f"{label}({opts})" if opts else label

        return "+".join(part(c) for c in self.components)

    def shape_params(self) -> list[ShapeParam]:
        return [p for c in self._searched_components() for p in c.shape()]

    def set_shape(self, theta: np.ndarray) -> None:
        k = 0
        for c in self._searched_components():
            n = len(c.shape())
            c.set_shape(theta[k : k + n])
            k += n

    # -- signals -----------------------------------------------------------------------------------
    def _signals(self, run: RunData, u_delayed: np.ndarray, u_before: float | None = None) -> Signals:
        """Normalised input and its rate; ``u_before`` is the sample before the first (chunks)."""
        scale = float(self.norm["u_scale"])
        v = u_delayed / scale
        shaping = self.input_shaping()
        if shaping is not None:
            # the drive saturates before everything else (a Hammerstein model): every component,
            # the base's memory included, sees the shaped drive, in command units as in normalised
            v = shaping.shape_input(v)
            u_delayed = v * scale
        # backward difference: causal, as the step mode and a real-time compensator compute it
        vdot = np.empty_like(v)
        vdot[1:] = np.diff(v) * run.sample_rate_hz
        if u_before is not None:
            v_before = u_before / scale
            if shaping is not None:
                v_before = float(shaping.shape_input(np.array([v_before]))[0])
            vdot[:1] = (v[:1] - v_before) * run.sample_rate_hz
        else:
            vdot[:1] = 0.0  # nothing before the first sample: at rest, as the step mode starts
        return Signals(u_delayed, v, vdot, run.aux, run.sample_rate_hz, self.norm)

    def input_shaping(self) -> Component | None:
        """The effect that shapes the drive before the base (``saturation(form=hammerstein)``), or None."""
        return next((e for e in self.effects if getattr(e, "shapes_input", False)), None)

    def _delayed(self, run: RunData) -> np.ndarray:
        return np.ascontiguousarray(run.input, dtype=np.float64)

    def _delay_rows(self, x: np.ndarray, fs: float) -> np.ndarray:
        """The delay effect: the static part's output (every column) delayed, fractional samples.

        A pure delay of amplifier, sensor or DAQ delays the actuator's response as a whole; on the
        columns it is a linear operation, so it commutes with the weights and costs no refit.
        """
        delay = self.effect("delay")
        if delay is None:
            return x
        return MK.delay_rows(np.ascontiguousarray(x), delay.param("seconds") * fs)

    def joined_signals(self, runs: list[RunData]) -> Signals:
        """The signals :meth:`finalize` computes its constants from: the runs joined."""
        return self._joined_signals(runs, np.concatenate([r.input for r in runs]))

    def _joined_signals(self, runs: list[RunData], u: np.ndarray) -> Signals:
        """The training runs joined, each run's first rate zero (nothing is measured across a junction)."""
        joined = RunData(u, None, {c: np.concatenate([r.aux[c] for r in runs]) for c in self.aux_channels},
                         self.sample_rate_hz)
        signals = self._signals(joined, u)
        starts = np.cumsum([0] + [len(r.input) for r in runs[:-1]])
        signals.vdot[starts] = 0.0
        signals.starts = tuple(int(i) for i in starts)
        return signals

    def prepare(self, runs: list[RunData]) -> None:
        """Set normalisation and data-dependent constants from training runs (before fitting)."""
        u = np.concatenate([r.input for r in runs])
        self.sample_rate_hz = runs[0].sample_rate_hz
        self.norm.setdefault("u_scale", float(np.max(np.abs(u))) or 1.0)
        # the operating range a compensator may rely on (hilbench.online.operating_range): the
        # inputs the model has seen, command units; files without them fall back to +-u_scale
        self.norm.setdefault("u_min", float(np.min(u)))
        self.norm.setdefault("u_max", float(np.max(u)))
        signals = self._joined_signals(runs, u)
        if any(c.name == "dynamics" for c in self.components):
            for c in self.components:
                if c.name == "creep" and not c.params and "taus" not in c.constants:
                    c.beside_dynamics()  # creep slower than the dynamics' settling (decision 0111)
        for c in self._searched_components():
            c.prepare(signals)
            c.fix_from_options()

    def finalize(self, runs: list[RunData], signals: Signals | None = None) -> None:
        """Freeze data-dependent constants after the shape search (e.g. FPMPI thresholds).
        ``signals``: the runs' :meth:`joined_signals`, when the caller keeps them (a shape search:
        they change only with the drive's shaping)."""
        if signals is None:
            signals = self.joined_signals(runs)
        for c in self.components:
            c.finalize(signals)

    # -- regressors ----------------------------------------------------------------------------------
    def new_states(self) -> list[dict[str, Any]]:
        """Fresh memory of every component (virgin operators, empty filters)."""
        return [c.new_state() for c in self.components]

    def static_columns(
        self, run: RunData, states: list[dict[str, Any]] | None = None, u_before: float | None = None,
        until: Component | None = None,
    ) -> list[Columns]:
        """The static regressor blocks of one run (before dynamics); ``states`` carry memory in/out.
        ``until``: only the blocks of the components before that one."""
        states = self.new_states() if states is None else states
        s = self._signals(run, self._delayed(run), u_before)
        blocks: list[Columns] = []
        for c, state in zip(self.components, states):
            if c is until:
                break
            block = c.columns(s, state, blocks)
            if block is not None:
                blocks.append(block)
        return blocks

    def advance(self, states: list[dict[str, Any]], u_from: float, u_to: float, aux: dict[str, float]) -> None:
        """Carry the memory across the rig's unrecorded ramp from one run's end to the next's start."""
        ramp = self.ramp(u_from, u_to, aux)
        if ramp is None:
            return
        if self.structure is not None:
            self.structure_output(ramp, states[self.components.index(self.structure)])
            return
        self.static_columns(ramp, states)

    def ramp(self, u_from: float, u_to: float, aux: dict[str, float]) -> RunData | None:
        """The rig's unrecorded ramp from one command to another (64 samples), or None when the two
        are the same command (:meth:`advance` walks it)."""
        if abs(u_from - u_to) <= 1e-12 * float(self.norm.get("u_scale", 1.0)):
            return None
        n = 64
        u = np.linspace(u_from, u_to, n)
        return RunData(u, None, {k: np.full(n, v) for k, v in aux.items()}, self.sample_rate_hz or 1.0)

    def _walk(self, runs: list[RunData]):
        """Yield (run, states ready for it): memory chained between runs marked ``chain``, else
        fresh (after the rig's approach ramp when known). The consumer advances the states."""
        states = self.new_states()
        previous: RunData | None = None
        for run in runs:
            first_aux = {k: float(v[0]) for k, v in run.aux.items()}
            if run.chain and previous is not None:
                self.advance(states, float(previous.input[-1]), float(run.input[0]), first_aux)
            else:
                states = self.new_states()
                if run.approach_from is not None:
                    self.advance(states, float(run.approach_from), float(run.input[0]), first_aux)
            yield run, states
            previous = run

    def design(self, run: RunData) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray]:
        """Regressor matrix of one run from fresh memory, dynamics applied, names and weight bounds."""
        return self.apply_dynamics(run, self.static_columns(run))

    def apply_dynamics(
        self, run: RunData, blocks: list[Columns], rows: np.ndarray | None = None, out: np.ndarray | None = None
    ) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray]:
        """Stack the static blocks, apply the dynamics and the delay; ``rows`` (indices) selects rows.

        Dynamics and delay are linear and time invariant, so their order does not matter; the
        delay is applied last so that only the wanted rows are computed. ``out``: a C-contiguous
        array of the result's shape to fill (a stretch of several runs' matrix), else a new one.
        """
        names = [n for b in blocks for n in b.names]
        lower = np.concatenate([b.lower for b in blocks])
        upper = np.concatenate([b.upper for b in blocks])
        # Every column is filtered and delayed on its own, so the blocks are processed one by one
        # and only the wanted rows are stacked: stacking every row first (then selecting a thinned
        # training set) copied the whole matrix once more per evaluation of a fit.
        ba, zi = self._dynamics_filter(run.sample_rate_hz)
        delay = self.effect("delay")
        d = delay.param("seconds") * run.sample_rate_hz if delay is not None else None
        n = len(run) if rows is None else rows.shape[0]
        matrix = np.empty((n, len(names))) if out is None else out
        first = 0
        for block in blocks:
            m = block.matrix
            p = m.shape[1]
            if ba is not None:
                m = MK.filter_columns(ba[0], ba[1], np.ascontiguousarray(m), np.outer(zi, m[0]))
            if d is not None:
                matrix[:, first : first + p] = MK.delay_gather(np.ascontiguousarray(m), rows, d) \
                    if rows is not None else MK.delay_rows(np.ascontiguousarray(m), d)
            elif rows is not None:
                MK.gather_rows_into(np.ascontiguousarray(m), rows, matrix, first)
            else:
                matrix[:, first : first + p] = m
            first += p
        return matrix, names, lower, upper

    def _dynamics_filter(self, fs: float) -> tuple[Any, np.ndarray | None]:
        """The dynamics' discrete filter (b, a) at ``fs`` and its steady state per unit input, or
        (None, None) without dynamics; kept while the dynamics' shape holds (a shape search asks
        for it once per run at every evaluation, mostly with the dynamics unchanged)."""
        dyn = self.effect("dynamics")
        if dyn is None:
            return None, None
        key = (id(dyn), float(fs), tuple(p.value for p in dyn.params))
        kept = getattr(self, "_filter_memo", None)
        if kept is None or kept[0] != key:
            ba = dyn.coefficients(fs)
            kept = self._filter_memo = (key, ba, sps.lfilter_zi(*ba))  # steady state at each column's first value
        return kept[1], kept[2]

    # -- simulation ----------------------------------------------------------------------------------
    def simulate(self, run: RunData) -> np.ndarray:
        """Free-run model output of one run (block mode), um; memory fresh, or after the rig's
        approach ramp when ``run.approach_from`` is known."""
        return self.simulate_runs([run])[0]

    def simulate_runs(self, runs: list[RunData]) -> list[np.ndarray]:
        """Free-run outputs of runs, memory chained between runs marked ``chain``."""
        return [self._output(run, states) for run, states in self._walk(runs)]

    #: samples per block when simulating: the regressor columns of a block stay in the cache
    SIMULATION_BLOCK = 4096

    def _output(self, run: RunData, states: list[dict[str, Any]]) -> np.ndarray:
        """Weighted sum of the static columns block by block (memory carried in ``states``), then
        the delay and the dynamics on the one resulting signal (they are linear)."""
        if self.weights is None:
            raise UserError("the model has no weights yet: fit it first")
        if self.structure is not None:
            return self.structure_output(run, states[self.components.index(self.structure)])
        n = len(run)
        h = np.empty(n)
        u_before: float | None = None
        for start in range(0, n, self.SIMULATION_BLOCK):
            stop = min(n, start + self.SIMULATION_BLOCK)
            part = RunData(run.input[start:stop], None, {k: v[start:stop] for k, v in run.aux.items()},
                           run.sample_rate_hz)
            s = self._signals(part, self._delayed(part), u_before)
            blocks: list[Columns] = []
            first: list[int] = []  # each block's first weight
            acc = np.zeros(stop - start)
            k = 0
            for c, state in zip(self.components, states):
                block = c.columns(s, state, blocks)
                if block is not None:
                    blocks.append(block)
                    first.append(k)
                    k += block.matrix.shape[1]
            # weighted once every component has had its say: rate-dependence and aux channels scale
            # the hysteresis blocks before them in place (a gain times y_RI, 003 eq. 9)
            for block, k0 in zip(blocks, first):
                acc += block.matrix @ self.weights[k0 : k0 + block.matrix.shape[1]]
            h[start:stop] = acc
            u_before = float(run.input[stop - 1])
        h = self._delay_rows(h[:, None], run.sample_rate_hz)[:, 0]
        dyn = self.effect("dynamics")
        if dyn is not None:
            bb, aa = dyn.coefficients(run.sample_rate_hz)
            h = sps.lfilter(bb, aa, h, zi=sps.lfilter_zi(bb, aa) * h[0])[0]
        return h

    def stepper(self, sample_rate_hz: float) -> ModelStepper:
        """Step mode: feed one sample at a time through the same component kernels."""
        return ModelStepper(self, sample_rate_hz)

    # -- persistence ------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": MODEL_FORMAT,
            "format_version": MODEL_FORMAT_VERSION,
            "hilbench_version": __version__,
            "spec": self.spec,
            "sample_rate_hz": self.sample_rate_hz,
            "normalisation": self.norm,
            "components": [c.to_dict() for c in self.components],
            "parameters": {
                "shape": [{"component": getattr(c, "channel", c.name), "name": p.name, "value": p.value,
                           "unit": p.unit} for c in self.components for p in c.shape()],
                "weights": [{"name": n, "value": float(w), "unit": "um"}
                            for n, w in zip(self.weight_names, self.weights if self.weights is not None else [])],
            },
            **self.info,
        }

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.write_text(json.dumps(self.to_dict(), indent=2, default=_json_default) + "\n", encoding="utf-8")
        return path

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, where: str = "<model>") -> Model:
        if data.get("format") != MODEL_FORMAT:
            raise UserError(f"not a hilbench model (format={data.get('format')!r}, expected {MODEL_FORMAT!r})", where=where)
        if data.get("format_version") != MODEL_FORMAT_VERSION:
            raise UserError(f"model format_version {data.get('format_version')} is not supported", where=where)
        model = cls(data["spec"])
        model.sample_rate_hz = float(data.get("sample_rate_hz", 0.0))
        model.norm = dict(data.get("normalisation", {}))
        for component, saved in zip(model.components, data["components"]):
            try:
                component.load_dict(saved)
            except UserError as exc:  # name the file: the component does not know it
                raise UserError(exc.message, where=exc.where or where, hint=exc.hint) from None
        weights = data["parameters"]["weights"]
        model.weight_names = [w["name"] for w in weights]
        model.weights = np.array([float(w["value"]) for w in weights])
        model.info = upgrade_model_document(
            {k: v for k, v in data.items() if k in ("fitted_on", "metrics", "fit", "train", "validation", "health")})
        return model

    @classmethod
    def load(cls, path: str | Path) -> Model:
        path = Path(path)
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise UserError("file not found", where=str(path)) from None
        except json.JSONDecodeError as exc:
            raise UserError(f"not valid JSON: {exc}", where=str(path)) from None
        except (OSError, UnicodeDecodeError) as exc:
            raise UserError(f"cannot read ({exc.__class__.__name__})", where=str(path)) from None
        if not isinstance(data, dict):
            raise UserError("not a hilbench model (expected a JSON object)", where=str(path))
        try:
            return cls.from_dict(data, where=str(path))
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise UserError(f"not a valid hilbench model file ({exc.__class__.__name__}: {exc})", where=str(path),
                            hint="write it again with `hilbench fit ... -o FIT.json`") from None


#: metric keys renamed in hilbench 0.1 (the papers' MAE is the maximum absolute error): old -> new
RENAMED_METRIC_KEYS = {"mae": "max_abs_error", "mad": "mean_abs_error"}


def upgrade_model_document(value: Any) -> Any:
    """A model file's document with the metric keys of files written before 0.1 renamed, at any depth."""
    if isinstance(value, dict):
        return {RENAMED_METRIC_KEYS.get(k, k) if isinstance(k, str) else k: upgrade_model_document(v)
                for k, v in value.items()}
    if isinstance(value, list):
        return [upgrade_model_document(v) for v in value]
    return value


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot serialise {type(value).__name__}")


class ModelStepper:
    """Per-sample evaluation of a fitted model with persistent state (step mode).

    The model is compiled (:mod:`hilbench.models.stepping`): one numba step over flat parameter and
    state arrays, the loop body of the compiled block kernel, about a microsecond per sample. A model
    with a part the compiled step does not cover falls back to the block-mode Python code called on
    blocks of one sample (``self.compiled is None``; ``self.fallback_reason`` says why). Both agree
    with :meth:`Model.simulate` on the same input to rounding (rates are backward differences).
    """

    def __init__(self, model: Model, sample_rate_hz: float):
        from hilbench.models.stepping import NotCompilable, compile_model

        if model.weights is None:
            raise UserError("the model has no weights yet: fit it first")
        self.model = model
        self.fs = sample_rate_hz
        self.fallback_reason = ""
        try:
            self.compiled = StructureStepper(model, sample_rate_hz) if model.structure is not None \
                else compile_model(model, sample_rate_hz)
        except NotCompilable as exc:
            self.compiled = None
            self.fallback_reason = str(exc)
        if self.compiled is not None:
            self.step = self.compiled.step  # type: ignore[method-assign]  # no wrapper call per sample
        self.states = [c.new_state() for c in model.components]
        self.u_prev: float | None = None
        self.history: list[float] = []
        dyn = model.effect("dynamics")
        self.filter = dyn.coefficients(sample_rate_hz) if dyn is not None else None
        self.zi: np.ndarray | None = None

    def reset(self) -> None:
        """Back to fresh memory."""
        if self.compiled is not None:
            self.compiled.reset()
        self.states = [c.new_state() for c in self.model.components]
        self.u_prev = None
        self.history = []
        self.zi = None

    def step(self, u: float, aux: dict[str, float] | None = None) -> float:
        """Model output (um) for this sample's input and aux channel values."""
        if self.compiled is not None:
            return self.compiled.step(u, aux)
        return self.step_python(u, aux)

    def step_python(self, u: float, aux: dict[str, float] | None = None) -> float:
        """The Python step mode: the block-mode component code on blocks of one sample."""
        m = self.model
        one = RunData(np.array([float(u)]), None, {k: np.array([x]) for k, x in (aux or {}).items()}, self.fs)
        # the block path's signals on a block of one sample (the drive shaped, the rate from the last)
        s = m._signals(one, one.input, self.u_prev)
        self.u_prev = u
        blocks: list[Columns] = []
        for c, state in zip(m.components, self.states):
            block = c.columns(s, state, blocks)
            if block is not None:
                blocks.append(block)
        row = np.concatenate([b.matrix[0] for b in blocks])
        h = float(row @ m.weights)
        delay = m.effect("delay")
        if delay is not None:  # the static part's output, delayed (fractional samples)
            hist = self.history
            hist.append(h)
            d = delay.param("seconds") * self.fs
            di = int(np.floor(d))
            frac = d - di
            a = hist[-1 - di] if len(hist) > di else hist[0]
            b = hist[-2 - di] if len(hist) > di + 1 else hist[0]
            h = (1 - frac) * a + frac * b
            if len(hist) > di + 4:
                del hist[1 : len(hist) - di - 3]  # keep the first value (held before the start)
        if self.filter is None:
            return h
        b, a = self.filter
        if self.zi is None:
            self.zi = sps.lfilter_zi(b, a) * h
        y, self.zi = sps.lfilter(b, a, [h], zi=self.zi)
        return float(y[0])


class StructureStepper:
    """Step mode of a structure model (``restoring-force``): its block kernel on a one-sample block,
    the parameter vector and buffers made once (no allocation per sample)."""

    def __init__(self, model: Model, sample_rate_hz: float):
        from hilbench.models.restoring_force import restoring_force_block

        structure = model.structure
        assert structure is not None
        self._kernel = restoring_force_block
        self._params = structure.kernel_params(sample_rate_hz, float(model.base.options.get("n", 1.0)))
        self._state = structure.new_state()["x"]
        self._u = np.zeros(1)
        self._y = np.zeros(1)

    def reset(self) -> None:
        self._state[:] = 0.0

    def step(self, u: float, aux: dict[str, float] | None = None) -> float:
        self._u[0] = u
        self._kernel(self._u, self._params, self._state, self._y)
        return float(self._y[0])
