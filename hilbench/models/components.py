"""Model components: what bases and effects are, each a block of regressor columns with shape parameters.

Every model of hilbench is linear in its weights once a few shape parameters (thresholds' eta,
exponents, Duhem alpha, dynamics poles, creep time constants, ...) are fixed:

    y = G_dyn( Phi(u(t - delay), aux; theta) @ w )

``Phi`` stacks the columns of the base (operators, linear and constant terms) and of the effects
(polynomial, saturating, creep, velocity-damping and auxiliary-channel columns, and modulated copies
of the hysteresis columns); rate-dependence and auxiliary channels scale the hysteresis columns by
one gain instead (a shape parameter, decisions 0018 and 0019); ``G_dyn`` is the optional linear dynamics with unit static gain. This is
what makes identification exact and fast (separable least squares, :mod:`hilbench.identify`).

Inputs are normalised, ``v = u / u_scale`` with ``u_scale = max |u|`` of the training data, so
thresholds are in units of the input range and weights in output units (um).

This module holds the protocol (:class:`Component`) and what components exchange (shape parameters,
columns, signals); the bases are in :mod:`hilbench.models.bases`, the effects in
:mod:`hilbench.models.effect_components`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from hilbench.models import kernels as MK
from hilbench.models.options import Option


@dataclass
class ShapeParam:
    """A nonlinear parameter, found by bounded search (weights are found by least squares)."""

    name: str
    value: float
    lower: float
    upper: float
    unit: str = ""
    log: bool = False  # search on a log scale
    doc: str = ""


@dataclass
class Columns:
    """A block of regressor columns with names and weight bounds."""

    matrix: np.ndarray  # (n, p)
    names: list[str]
    lower: np.ndarray  # (p,)
    upper: np.ndarray  # (p,)
    hysteresis: bool = False  # part of the rate-independent hysteresis (modulated by rate/aux effects)

    @staticmethod
    def of(matrix: np.ndarray, names: list[str], lower: float | list[float] = -np.inf,
           upper: float | list[float] = np.inf, hysteresis: bool = False) -> Columns:
        p = matrix.shape[1]
        lo = np.broadcast_to(np.asarray(lower, float), (p,)).copy()
        hi = np.broadcast_to(np.asarray(upper, float), (p,)).copy()
        return Columns(np.ascontiguousarray(matrix), list(names), lo, hi, hysteresis)


@dataclass
class Signals:
    """What components compute their columns from (one run, or one block of a run)."""

    u: np.ndarray  # input after the delay, command unit
    v: np.ndarray  # normalised input u / u_scale
    vdot: np.ndarray  # d v / dt, 1/s
    aux: dict[str, np.ndarray]
    fs: float
    norm: dict[str, Any]
    #: the first row of each run joined here (training runs are joined for ``prepare``): no rate or
    #: turning point is measured across a junction, where the input jumps from one run to the next
    starts: tuple[int, ...] = (0,)
    #: columns that depend on these signals and on nothing searched (a base's constant and
    #: polynomial columns, creep's low-passes of the input at given time constants), kept by the
    #: components that compute them: a shape search reuses one Signals per run across its
    #: evaluations (:class:`hilbench.identify.separable._ColumnCache`), so they are computed once
    memo: dict[Any, Any] = field(default_factory=dict, repr=False, compare=False)

    def pieces(self) -> list[slice]:
        """The rows of each joined run."""
        edges = [*self.starts, self.v.size]
        return [slice(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]

    def turning_point_frequency(self) -> tuple[np.ndarray, np.ndarray]:
        """The drive frequency (Hz) and amplitude at every row from the last turning points, each
        joined run measured on its own."""
        f = np.zeros_like(self.v)
        a = np.zeros_like(self.v)
        v = np.ascontiguousarray(self.v)
        for rows in self.pieces():
            f_part = np.empty(rows.stop - rows.start)
            a_part = np.empty_like(f_part)
            MK.turning_point_frequency(np.ascontiguousarray(v[rows]), self.fs, np.zeros(MK.N_TP), f_part, a_part)
            f[rows], a[rows] = f_part, a_part
        return f, a


class Component:
    """Base class: a named part of a model spec with options, constants and shape parameters."""

    name: ClassVar[str] = ""
    role: ClassVar[str] = "effect"  # "base" or "effect"
    summary: ClassVar[str] = ""
    #: the options a spec may give, typed and bounded (checked by hilbench.models.spec)
    options_schema: ClassVar[dict[str, Option]] = {}
    #: ``columns`` scales the hysteresis blocks before it in place (a gain on the whole loop,
    #: decision 0018): a cache of those blocks must hand out copies
    scales_hysteresis: ClassVar[bool] = False

    def __init__(self, options: dict[str, Any] | None = None):
        self.options = dict(options or {})
        self.constants: dict[str, Any] = {}
        self.params: list[ShapeParam] = []

    # -- set-up --------------------------------------------------------------------------------
    def check_spec(self, base: Component, effects: list[Component], spec: str) -> None:
        """Refuse (:class:`hilbench.models.spec.SpecError`) a spec this component cannot be part of."""

    def prepare(self, signals: Signals) -> None:
        """Set data-dependent constants and shape-parameter starts from training signals."""

    def shape(self) -> list[ShapeParam]:
        return self.params

    def fix_from_options(self) -> None:
        """A spec option named like a shape parameter fixes it: ``dynamics(zeta=0.28)``.

        Fixed parameters (lower == upper) keep their value during identification, e.g. dynamics
        identified beforehand from a step response (002 sec. 3.2.1).
        """
        for p in self.params:
            if p.name in self.options:
                value = float(self.options[p.name])
                p.value = p.lower = p.upper = value

    def set_shape(self, values: np.ndarray) -> None:
        for p, v in zip(self.params, values):
            p.value = float(v)

    def param(self, name: str) -> float:
        return next(p.value for p in self.params if p.name == name)

    def finalize(self, s: Signals) -> None:
        """Freeze data-dependent constants once the shape parameters are found."""

    # -- starts read off the data --------------------------------------------------------------
    def neutral_shape(self) -> dict[str, float] | None:
        """Shape values at which the component leaves the signal as it is (None: it has none)."""
        return None

    def starts_from_residual(self, stretches: list[np.ndarray], fs: float) -> list[dict[str, float]]:
        """Starting points of the shape search (values by parameter name) read off the training
        residual of the model with this component at :meth:`neutral_shape`, in contiguous
        ``stretches`` sampled at ``fs`` Hz. Components whose error surface a coarse scan covers
        return none."""
        return []

    def joint_starts(self, fs: float) -> list[dict[str, float]]:
        """Starting points of the shape search (values by parameter name) to add when this component
        is searched together with another effect: shapes whose error surface is flat except near
        the truth once the other effect's error dominates. Most components have none."""
        return []

    # -- columns -------------------------------------------------------------------------------
    def new_state(self) -> dict[str, Any]:
        return {}

    def columns(self, s: Signals, state: dict[str, Any], previous: list[Columns]) -> Columns | None:
        """This component's regressor block of one run (or block), its memory carried in ``state``.

        The contract the shape search relies on (decision 0020): the block depends on the signals,
        the state, this component's shape parameters and constants and the ``previous`` blocks only.
        A loop gain may scale earlier hysteresis blocks in place; nothing else writes to them."""
        raise NotImplementedError

    def weight_constraints(self, names: list[str]) -> np.ndarray | None:
        """Rows ``G`` of linear inequalities ``G @ w >= 0`` on the model's weights (named ``names``)
        that the weight solve must keep, beyond the per-weight bounds; None: no such constraint."""
        return None

    # -- persistence ----------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "options": self.options,
            "constants": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.constants.items()},
            "shape": [{"name": p.name, "value": p.value, "lower": p.lower, "upper": p.upper, "unit": p.unit,
                       "log": p.log} for p in self.params],
        }

    def load_dict(self, data: dict[str, Any]) -> None:
        self.constants = dict(data.get("constants", {}))
        self.params = [ShapeParam(p["name"], float(p["value"]), float(p["lower"]), float(p["upper"]),
                                  p.get("unit", ""), bool(p.get("log", False))) for p in data.get("shape", [])]
