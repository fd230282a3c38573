"""Hysteresis bases: the loop itself, as operator sums (PI, PI1, MPI, PMPI, FPMPI, PD), ISSF-Duhem
(G, M, D) and Bouc-Wen, or the memoryless linear base; each a block of regressor columns with
shape parameters (:mod:`hilbench.models.components`). A spec starts with one of :data:`BASES`.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from hilbench.errors import UserError
from hilbench.models import kernels as MK
from hilbench.models.components import Columns, Component, ShapeParam, Signals
from hilbench.models.options import Option

_N_OPERATORS = "number of operators; sized by the memory a fit needs (see --memory-limit)"


def _thresholds(n: int, span: float) -> np.ndarray:
    return np.arange(n, dtype=float) / n * span


class OperatorBase(Component):
    """Shared machinery of the operator bases: M-play columns over thresholds with eta."""

    role = "base"
    options_schema = {"n": Option("int", default=10, minimum=1, doc=_N_OPERATORS)}
    default_n = 10
    eta_fixed: ClassVar[float | None] = 1.0  # play; None: eta searched per operator (PMPI)
    one_sided = False
    nonneg = True
    span_kind: ClassVar[str] = "half-range"  # thresholds up to: half-range | full-range | max

    def prepare(self, s: Signals) -> None:
        n = int(self.options.get("n", self.default_n))
        if n < 1:
            raise UserError(f"{self.name}(n={n}): the number of operators must be at least 1")
        if "thresholds" not in self.constants:
            v = s.v
            # Play: a threshold beyond half the input range never switches; one-sided play: up to
            # the maximum (000 eq. 3); M-play: the whole range (004 Table 4: r = 0..9 V for 0..10 V).
            span = {"half-range": 0.5 * float(np.ptp(v)), "full-range": float(np.ptp(v)),
                    "max": float(np.max(v))}["max" if self.one_sided else self.span_kind]
            self.constants["thresholds"] = _thresholds(n, max(span, 1e-12)).tolist()
        if self.eta_fixed is None and not self.params:
            # eta of the r = 0 operator does nothing (it is the input itself): not a parameter
            self.params = [ShapeParam(f"eta_{i}", 0.5, -0.99, 1.5, doc="M-play delay coefficient (004 eq. 6)")
                           for i, ri in enumerate(self.constants["thresholds"]) if ri > 0]

    def eta(self) -> np.ndarray:
        r = np.asarray(self.constants["thresholds"], float)
        if self.eta_fixed is None:
            eta = np.ones(r.shape)
            eta[r > 0] = [p.value for p in self.params]
            return eta
        return np.full(r.shape, 0.0 if self.one_sided else self.eta_fixed)

    def new_state(self) -> dict[str, Any]:
        return {"ops": np.zeros(len(self.constants["thresholds"]))}

    def operator_columns(self, x: np.ndarray, state: dict[str, Any]) -> np.ndarray:
        r = np.asarray(self.constants["thresholds"], float)
        out = np.empty((x.shape[0], r.shape[0]))
        MK.mplay_block(np.ascontiguousarray(x, dtype=np.float64), r, self.eta(), state["ops"], out)
        return out

    def columns(self, s: Signals, state: dict[str, Any], previous: list[Columns]) -> Columns:
        # The operator with threshold 0 is the input itself: its weight is the linear term p0,
        # free in sign; the others are play operators with weights >= 0 (the inverse needs it).
        ops = self.operator_columns(s.v, state)
        # the offset and the extra columns (MPI's v^2, v^3) depend on the input alone, not on eta:
        # kept with the signals, so a shape search computes them once per run (Signals.memo)
        key = ("operator-base", id(self), tuple(self.constants["thresholds"]))
        fixed = s.memo.get(key)
        if fixed is None:
            r = self.constants["thresholds"]
            names = ["offset"] + [f"w[r={ri:.4g}]" if ri > 0 else "p0*v" for ri in r] + self.extra_names()
            op_lower = [(0.0 if self.nonneg else -np.inf) if ri > 0 else -np.inf for ri in r]
            lower = [-np.inf] + op_lower + [-np.inf] * len(self.extra_names())
            fixed = s.memo[key] = (self.extra(s), names, lower)
        extra, names, lower = fixed
        n, k = ops.shape
        matrix = np.empty((n, 1 + k + len(extra)))
        matrix[:, 0] = 1.0
        matrix[:, 1 : 1 + k] = ops
        for j, column in enumerate(extra):
            matrix[:, 1 + k + j] = column
        return Columns.of(matrix, names, lower, hysteresis=True)

    def extra(self, s: Signals) -> list[np.ndarray]:
        return []

    def extra_names(self) -> list[str]:
        return []


class PI(OperatorBase):
    name = "pi"
    summary = "Prandtl-Ishlinskii: linear term + weighted play operators (weights >= 0)"


class PI1(OperatorBase):
    name = "pi1"
    summary = "PI with one-sided play operators (000 eq. 1, 003 eq. 2), for unipolar drives"
    one_sided = True


class MPI(OperatorBase):
    name = "mpi"
    summary = "modified PI of 002: play operators + cubic polynomial g(i) (eq. 12-14)"

    def extra(self, s: Signals) -> list[np.ndarray]:
        return [s.v**2, s.v**3]

    def extra_names(self) -> list[str]:
        return ["a2*v^2", "a1*v^3"]


#: 004 eq. 16 kept with this margin by pmpi(invertible=yes): p0 * (1 - margin) >= |dP/dv|, so that
#: the I-M iteration contracts by at least this much per pass (eq. 16 alone allows a factor of 1)
EQ16_MARGIN = 0.1
#: points of the training input range at which eq. 16 is imposed (dP/dv is a quadratic: its
#: extremes are at the ends or its vertex, which a grid this fine brackets within 0.3 % of the span)
EQ16_GRID = 201


class PMPI(MPI):
    name = "pmpi"
    summary = "polynomial-modified PI of 004: M-play operators with eta (eq. 5-7) + cubic polynomial"
    eta_fixed = None
    span_kind = "full-range"
    options_schema = {
        "n": Option("int", default=10, minimum=1, doc=_N_OPERATORS),
        "invertible": Option("choice", default="no", choices=("no", "yes"),
                             doc="yes: the weights keep 004 eq. 16, p0 > max|3 a1 v^2 + 2 a2 v| over the training "
                                 f"input range (with a {EQ16_MARGIN:.0%} margin), so that the I-M compensator "
                                 "contracts without a proportional gain"),
    }

    def prepare(self, s: Signals) -> None:
        super().prepare(s)
        if "v_range" not in self.constants:
            self.constants["v_range"] = [float(np.min(s.v)), float(np.max(s.v))]

    def weight_constraints(self, names: list[str]) -> np.ndarray | None:
        if self.options.get("invertible", "no") != "yes":
            return None
        try:
            k0, k2, k3 = names.index("p0*v"), names.index("a2*v^2"), names.index("a1*v^3")
        except ValueError:
            return None
        lo, hi = self.constants["v_range"]
        v = np.linspace(lo, hi, EQ16_GRID)
        slope = np.zeros((v.size, len(names)))  # dP/dv = 2 a2 v + 3 a1 v^2 as rows on the weights
        slope[:, k2] = 2.0 * v
        slope[:, k3] = 3.0 * v**2
        rows = np.vstack([-slope, slope])
        rows[:, k0] = 1.0 - EQ16_MARGIN
        return rows


class PD(OperatorBase):
    name = "pd"
    summary = "PI with one-sided dead-zone operators (memoryless asymmetric shaping, additive form)"
    options_schema = {"n": Option("int", default=10, minimum=1, doc=_N_OPERATORS),
                      "n_dead_zone": Option("int", default=4, minimum=0, maximum=64, doc="number of dead-zone terms")}

    def prepare(self, s: Signals) -> None:
        super().prepare(s)
        if "dead_zones" not in self.constants:
            m = int(self.options.get("n_dead_zone", 4))
            lo, hi = float(np.min(s.v)), float(np.max(s.v))
            self.constants["dead_zones"] = np.linspace(lo, hi, m + 2)[1:-1].tolist()

    def extra(self, s: Signals) -> list[np.ndarray]:
        cols = []
        for d in self.constants["dead_zones"]:
            cols.append(np.maximum(s.v - d, 0.0) if d >= 0 else np.minimum(s.v - d, 0.0))
        return cols

    def extra_names(self) -> list[str]:
        return [f"g[d={d:.3g}]" for d in self.constants["dead_zones"]]


class FPMPI(Component):
    """000 eq. 1-5: one-sided play operators on a fractional polynomial of the input."""

    name = "fpmpi"
    role = "base"
    summary = "fractional-polynomial-modified PI of 000: one-sided play of sum w_P,i u^e_i (eq. 1-5)"
    options_schema = {"n": Option("int", default=10, minimum=1, doc=_N_OPERATORS),
                      "terms": Option("int", default=8, minimum=2, maximum=8,
                                      doc="terms of the fractional polynomial (exponents 0, 1, 2, 1/2, 3, 1/3, 4, 1/4)")}
    exponents_all = (0.0, 1.0, 2.0, 0.5, 3.0, 1.0 / 3.0, 4.0, 0.25)

    def prepare(self, s: Signals) -> None:
        if "exponents" not in self.constants:
            terms = int(self.options.get("terms", 8))
            self.constants["exponents"] = list(self.exponents_all[:terms])
            self.constants["n"] = int(self.options.get("n", 10))
        if not self.params:
            # The linear term's weight is fixed at 1: the operator input's scale is not identifiable.
            self.params = [ShapeParam(f"wP_{i}", 0.0, -3.0, 3.0, doc=f"weight of u^{e:.3g} (000 eq. 5)")
                           for i, e in enumerate(self.constants["exponents"]) if e != 1.0]

    def shaped(self, v: np.ndarray, memo: dict[Any, Any] | None = None) -> np.ndarray:
        """sum w_P,i sign(v) |v|^e_i. The powers depend on the input alone, not on the weights the
        shape search moves: with ``memo`` (the signals' :attr:`Signals.memo`, which holds ``v``'s)
        they are kept there, so a search computes them once per run, not at every evaluation (the
        same numbers: only the weighted sum is done again)."""
        exponents = self.constants["exponents"]
        key = ("fpmpi-powers", id(self), tuple(exponents))
        powers = None if memo is None else memo.get(key)
        if powers is None:
            vv = np.abs(v)
            powers = [np.sign(v) * vv**e if e != 0.0 else None for e in exponents]
            if memo is not None:
                memo[key] = powers
        out = np.zeros_like(v)
        params = iter(self.params)
        for e, power in zip(exponents, powers):
            w = 1.0 if e == 1.0 else next(params).value
            out += w * (power if e != 0.0 else 1.0)
        return out

    def finalize(self, s: Signals) -> None:
        self.constants["shaped_max"] = float(np.max(np.abs(self.shaped(s.v, s.memo)))) or 1.0

    def new_state(self) -> dict[str, Any]:
        return {"ops": np.zeros(int(self.constants["n"]))}

    def columns(self, s: Signals, state: dict[str, Any], previous: list[Columns]) -> Columns:
        x = self.shaped(s.v, s.memo)
        n_ops = int(self.constants["n"])
        # thresholds follow eq. 3 on the shaped input's range seen in training
        span = float(self.constants.get("shaped_max", 0.0)) or float(np.max(np.abs(x))) or 1.0
        r = np.arange(n_ops) / n_ops * span
        ops = np.empty((x.shape[0], n_ops))
        MK.mplay_block(np.ascontiguousarray(x), r, np.zeros(n_ops), state["ops"], ops)
        matrix = np.column_stack([np.ones(x.shape[0]), ops])
        names = ["offset"] + [f"wH[r={ri:.4g}]" for ri in r]
        return Columns.of(matrix, names, hysteresis=True)


class Linear(Component):
    name = "linear"
    role = "base"
    summary = "no memory: y = p0 v + offset"

    def columns(self, s: Signals, state: dict[str, Any], previous: list[Columns]) -> Columns:
        return Columns.of(np.column_stack([s.v, np.ones_like(s.v)]), ["p0*v", "offset"], hysteresis=True)


class DuhemBase(Component):
    """001 eq. 17: w' = alpha |u'| (beta/alpha u - w); y = k1 u + k2 z(w) with a shape function.

    w is linear in beta, so beta merges into the shape function's scale; what is searched is alpha
    and the shape parameters, the rest are weights.
    """

    role = "base"
    shape_kind: ClassVar[str] = ""

    def prepare(self, s: Signals) -> None:
        if self.params:
            return
        u_span = float(np.ptp(s.u)) or 1.0
        self.params = [ShapeParam("alpha", 1.0 / u_span, 0.01 / u_span, 20.0 / u_span, "1/input unit", log=True,
                                  doc="Duhem rate alpha (001 eq. 17), per command unit")]
        self.params += self.shape_params(s)

    def shape_params(self, s: Signals) -> list[ShapeParam]:
        return []

    def new_state(self) -> dict[str, Any]:
        return {"duhem": np.zeros(2), "started": False}

    def w_tilde(self, s: Signals, state: dict[str, Any]) -> np.ndarray:
        """Duhem state with beta = alpha (w follows u one to one far from turning points)."""
        alpha = self.param("alpha")
        if not state["started"]:
            state["duhem"][:] = [s.u[0], s.u[0]]  # start on the anhysteretic line
            state["started"] = True
        out = np.empty_like(s.u)
        MK.duhem_w_block(np.ascontiguousarray(s.u, dtype=np.float64), alpha, alpha, state["duhem"], out)
        return out

    def columns(self, s: Signals, state: dict[str, Any], previous: list[Columns]) -> Columns:
        w = self.w_tilde(s, state)
        shape_cols, names, lower = self.shape_columns(w)
        matrix = np.column_stack([s.u, np.ones_like(s.u), *shape_cols])
        return Columns.of(matrix, ["k1*u", "offset", *names], [-np.inf, -np.inf, *lower], hysteresis=True)

    def shape_columns(self, w: np.ndarray) -> tuple[list[np.ndarray], list[str], list[float]]:
        raise NotImplementedError


class DuhemG(DuhemBase):
    name = "duhem-g"
    summary = "ISSF-Duhem with the Gompertz shape function (001 eq. 20-21)"

    def shape_params(self, s: Signals) -> list[ShapeParam]:
        span = float(np.max(np.abs(s.u))) or 1.0
        return [ShapeParam("mu1", 0.5 / span, 0.001 / span, 10.0 / span, "1/input unit", log=True),
                ShapeParam("mu2", 1.0, -3.0, 3.0)]

    def shape_columns(self, w: np.ndarray) -> tuple[list[np.ndarray], list[str], list[float]]:
        mu1, mu2 = self.param("mu1"), self.param("mu2")
        z = 2.0 * np.exp(-np.exp(-mu1 * w - mu2)) - 2.0 * math.exp(-math.exp(-mu2))
        return [z], ["k2*z"], [-np.inf]


class DuhemM(DuhemG):
    name = "duhem-m"
    summary = "ISSF-Duhem with the modified tanh shape function (001 eq. 24-25)"

    def shape_params(self, s: Signals) -> list[ShapeParam]:
        params = super().shape_params(s)
        params[0].name, params[1].name = "mu3", "mu4"
        return params

    def shape_columns(self, w: np.ndarray) -> tuple[list[np.ndarray], list[str], list[float]]:
        mu3, mu4 = self.param("mu3"), self.param("mu4")
        z = 2.0 * np.tanh(-np.exp(-mu3 * w - mu4)) - 2.0 * math.tanh(-math.exp(-mu4))
        return [z], ["k2*z"], [-np.inf]


class DuhemD(DuhemBase):
    name = "duhem-d"
    summary = "ISSF-Duhem with one-sided dead-zone shape operators (001 eq. 26-31), weights free"
    options_schema = {"n": Option("int", default=6, minimum=1, doc="dead-zone operators per side")}

    def shape_params(self, s: Signals) -> list[ShapeParam]:
        span = float(np.max(np.abs(s.u))) or 1.0
        n = int(self.options.get("n", 6))
        self.constants["n"] = n
        return [ShapeParam("spacing_pos", span / (n + 1), span / (20 * n), 2 * span / n, "input unit", log=True,
                           doc="mu5: threshold spacing for w >= 0 (eq. 28)"),
                ShapeParam("spacing_neg", span / (n + 1), span / (20 * n), 2 * span / n, "input unit", log=True,
                           doc="mu8: threshold spacing for w < 0 (eq. 30)")]

    def thresholds(self) -> np.ndarray:
        n = int(self.constants["n"])
        pos = self.param("spacing_pos") * np.arange(1, n + 1)
        neg = -self.param("spacing_neg") * np.arange(1, n + 1)
        return np.concatenate([neg[::-1], pos])

    def shape_columns(self, w: np.ndarray) -> tuple[list[np.ndarray], list[str], list[float]]:
        cols, names = [], []
        for r in self.thresholds():
            cols.append(np.maximum(w - r, 0.0) if r > 0 else np.minimum(w - r, 0.0))
            names.append(f"g[r={r:.4g}]")
        # the r = 0 operator is w itself
        return [w, *cols], ["g[r=0]", *names], [-np.inf] * (len(cols) + 1)


class BoucWen(Component):
    name = "bouc-wen"
    role = "base"
    summary = "Bouc-Wen: z' = A u' - beta |u'||z|^(n-1) z - gamma u'|z|^n; y = k u + z (n = 1 by default)"
    options_schema = {"n": Option("number", default=1.0, minimum=0.0, exclusive_minimum=True, maximum=20.0,
                                  doc="Bouc-Wen exponent")}

    def prepare(self, s: Signals) -> None:
        if self.params:
            return
        span = float(np.ptp(s.u)) or 1.0
        self.constants["n"] = float(self.options.get("n", 1.0))
        # gamma = g beta with |g| <= 1 keeps z bounded (beta >= |gamma|, the usual stability condition)
        self.params = [ShapeParam("beta", 1.0 / span, 1e-3 / span, 100.0 / span, "1/input unit", log=True),
                       ShapeParam("gamma_over_beta", 0.0, -1.0, 1.0)]

    def new_state(self) -> dict[str, Any]:
        return {"bw": np.zeros(2), "started": False}

    def columns(self, s: Signals, state: dict[str, Any], previous: list[Columns]) -> Columns:
        if not state["started"]:
            state["bw"][1] = s.u[0]
            state["started"] = True
        z = np.empty_like(s.u)
        beta = self.param("beta")
        MK.bouc_wen_block(np.ascontiguousarray(s.u, dtype=np.float64), beta, beta * self.param("gamma_over_beta"),
                          float(self.constants["n"]), state["bw"], z)
        return Columns.of(np.column_stack([s.u, np.ones_like(s.u), z]), ["k*u", "offset", "A*z"], hysteresis=True)


#: the bases a spec can start with, by name
BASES: dict[str, type[Component]] = {
    cls.name: cls for cls in (Linear, PI, PI1, MPI, PMPI, FPMPI, PD, DuhemG, DuhemM, DuhemD, BoucWen)
}
