"""Compensators: inverse models as numba step functions over explicit state (block and step mode).

A compensator turns a desired displacement ``y_d`` (um) into the command ``u`` (V or A) that makes
the actuator produce it. It keeps its own copy of the fitted model's forward memory (the flat
arrays of :func:`hilbench.models.stepping.compile_model`) and, after the rig's safety path, commits
the command that was *really applied* to it, so the inverse's memory always matches what the
actuator went through (a clamped or slew-limited command does not desynchronise it).

Kinds (chosen from the model spec by :class:`Compensator`, ``method="auto"``):

``pi``       classical inverse Prandtl-Ishlinskii (004 eq. 14-15): the inverse is itself a PI on
             ``y`` with its own thresholds ``r'_i = p0 s_i + sum_{j<i} p_j (s_i - s_j)`` and weights
             ``p'_0 = 1/p0``, ``p'_i = -p_i / ((p0 + sum_{j<=i} p_j)(p0 + sum_{j<i} p_j))``. It is the
             exact inverse of a PI whose cumulative slopes are positive (weights >= 0, p0 > 0).
             M-play operators (eta != 1, ``pmpi``; one-sided play, ``pi1``/``fpmpi``) are written
             exactly as play operators: ``max(v - r, min(v + eta r, w))`` is the play of threshold
             ``s = (1 + eta) r / 2`` on ``v`` plus the constant ``c = (eta - 1) r / 2``, so the
             inverse is exact for any eta (004 eq. 14 reuses eta with the play's thresholds, which is
             exact only for eta = 1). The inverse operators' states are not integrated separately:
             they are read off the forward operators' states every sample,
             ``w'_i = Y - p0 (x - x_i) - sum_{j<i} p_j (x_j - x_i)`` (sorted thresholds), which is
             what they would be after the same history, so the compensator commits applied
             commands to one memory only. Each result is checked against the forward operators
             (one O(n) evaluation); operator states that no common history produces (virgin M-play
             operators with different eta) are corrected by bracketed Newton steps on the
             piecewise-linear forward map (counted as ``analytic_inverse_corrected``).
``mpi``      PI part inverted analytically, the memoryless polynomial (002's cubic, 004's P, the
             ``asymmetry`` effect) by a safeguarded secant/bisection solve per sample of the fixed
             point ``v = Gamma^-1[y - P(v) + k_e v]`` (exact inverse).
``im``       004's iterative inverse-model (I-M) compensator, eq. 13: ``u_d(k) = Gamma^-1[y_d(k) -
             P(u_d(k-1))]`` (``iterations`` fixed-point passes per sample, 1 as in the paper). The
             small-gain condition eq. 16, ``p0 > max |P'(u)|`` over the actuator's range, is checked;
             when it fails, eq. 20's proportional gain ``k_e`` moves ``k_e u`` from the polynomial
             to the PI part (``gain="auto"`` picks one, a number sets it; ``gain=None`` refuses).
``fpmpi``    000's FPMPI: the one-sided play part is inverted analytically (it acts on the shaped
             input ``x``), then the fractional polynomial ``x(v) = sum w_i sgn(v)|v|^e_i`` is
             solved. When the exponents are multiples of 1/q (000's are of 1/12), it is a
             polynomial in ``s = sgn(v)|v|^(1/q)`` (multiplications only), solved by Newton steps
             warm-started from the last solutions extrapolated (about 2 evaluations per sample;
             counter ``newton_samples``); a step that leaves the command range or meets a falling
             part of the polynomial hands the sample to the safeguarded solver below. The commit
             then updates the static model's operators directly with that shaped input (checked
             against ``model_step`` when the compensator is built), and an identifier with the
             same front end reuses it.
``general``  ANY compiled model (creep, temperature, load and other aux channels, rate-dependence,
             saturation, Duhem, Bouc-Wen, ...): a bounded 1-D solve of ``model_step`` on a copy of
             the state per sample (safeguarded secant with bisection on the rising static map),
             then the applied command is committed to the real state. The compensator reads the
             same auxiliary channels the model does.

Dynamics and delay: the compensator inverts the static part (its copy of the model has the
``dynamics`` and ``delay`` effects switched off). When the whole reference is known before the run
(tracking), :meth:`Compensator.enable_preview` inverts the dynamics and the delay over it
(:mod:`hilbench.online.preview`: stable inversion, non-causal where the zeros demand it) and the
static part is given that target per sample. Step by step without a preview, the dynamics' inverse
``A(z)/B(z)`` is a feed-forward pre-filter of the reference only when ``B`` is minimum phase (zeros
inside the unit circle with a margin, ``b0 != 0``); otherwise, and for the delay, it is left to
feedback.

Feedback (optional): a PID in the output domain (um of error in, um added to the reference out,
before the inverse), so the PID sees the compensated plant: the rig after the inverse, whose local
gain is the rig's over the model's slope, with the model's dynamics and delay, one sample of
measurement delay and the lag the model misses. :mod:`hilbench.online.feedback_design` identifies
that loop from the model's training data, with this compensator's own response to a correction
(:meth:`Compensator.correction_response`, decision 0123); ``feedback=True`` designs the gains on it (margins of
6 dB and 45 deg over the whole local-gain range), a :class:`PID` is checked on it and refused when a
closed-loop pole leaves the unit circle at any gain of the range. Derivative on the measurement
with a first-order filter; anti-windup by conditional integration (no integration while the
applied command differs from the command, at a limit or at the slew rate, in the direction the
error pushes) and a clamped integrator. The reversal guard (``PID.reversal_guard``, on by default)
holds the command rather than move it against the reference's direction, so feedback adds no
reversals (decision 0080); a held command counts as a limit for the integrator.

Online adaptation (optional, paper 000): an :class:`hilbench.online.oiir.OIIR` identifier with the
model's FPMPI front end is updated every sample with (applied command, measured output); its
current weights give a gain ``G = sum p / (1 - sum q)`` and an offset ``b / (1 - sum q)`` between
the front end's output and the measured displacement, and the inverse is asked for
``(y_d - offset) / G`` instead of ``y_d``.

The per-sample kernels and their array layout are in :mod:`hilbench.online.inverse_kernels`;
the output-domain feedback is :class:`hilbench.online.pid.PID`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hilbench.errors import UserError
from hilbench.models import stepping as ST
from hilbench.online import feedback_design as FD
from hilbench.online import inverse_kernels as K
from hilbench.online.feedback_design import InstabilityError
from hilbench.online.operating_range import FALL_TOLERANCE, narrowed, operating_range
from hilbench.online.pid import PID

__all__ = ["PID", "Compensator", "InstabilityError", "inverse_pi_parameters"]


def inverse_pi_parameters(p0: float, s: np.ndarray, p: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """004 eq. 15 for a PI ``p0 v + sum p_i F_{s_i}[v]`` with thresholds ``s`` sorted ascending
    (all > 0): ``(p'_0, r', p')`` of the inverse PI ``p'_0 y + sum p'_i F_{r'_i}[y]``."""
    s = np.asarray(s, float)
    p = np.asarray(p, float)
    cum = p0 + np.concatenate([[0.0], np.cumsum(p)])  # p0 + sum_{j<=i} p_j, i = 0..n
    if np.any(cum <= 0):
        raise ValueError("the PI's cumulative slopes p0 + sum_{j<=i} p_j must be positive")
    r_hat = np.array([p0 * s[i] + np.sum(p[:i] * (s[i] - s[:i])) for i in range(s.size)])
    p_hat = -p / (cum[1:] * cum[:-1])
    return 1.0 / p0, r_hat, p_hat


def _pi_structure(model: Any) -> dict[str, Any] | None:
    """Equivalent play form of an operator base: sorted positive thresholds, weights, constants."""
    from hilbench.models import bases as C

    base = model.base
    w = np.asarray(model.weights, float)
    if isinstance(base, C.FPMPI):
        n = int(base.constants["n"])
        span = float(base.constants["shaped_max"]) or 1.0
        r = np.arange(n) / n * span
        eta = np.zeros(n)
    elif isinstance(base, C.OperatorBase) and not isinstance(base, C.PD):
        r = np.asarray(base.constants["thresholds"], float)
        eta = base.eta()
    else:
        return None
    p_ops = w[1 : 1 + r.size]
    s = (1.0 + eta) * r / 2.0
    c = (eta - 1.0) * r / 2.0
    zero = s <= 0.0
    p0 = float(np.sum(p_ops[zero]))
    const = float(w[0] + np.sum(p_ops * c))
    idx = np.flatnonzero(~zero)
    order = idx[np.argsort(s[idx], kind="stable")]
    return {"p0": p0, "const": const, "perm": order, "s": s[order], "p": p_ops[order], "c": c[order],
            "n_ops": r.size}


def _polynomial(model: Any, n_ops: int) -> np.ndarray:
    """Coefficients c_0..c_deg of the memoryless polynomial of mpi/pmpi and the asymmetry effect."""
    from hilbench.models import bases as C

    w = np.asarray(model.weights, float)
    coef = np.zeros(9)
    k = 1 + n_ops
    if isinstance(model.base, C.MPI):
        coef[2] += w[k]
        coef[3] += w[k + 1]
        k += 2
    asym = model.effect("asymmetry")
    if asym is not None:
        for power in range(2, asym.order() + 1):
            coef[power] += w[k]
            k += 1
    deg = int(np.max(np.flatnonzero(coef), initial=0))
    return coef[: deg + 1]


def _approach_targets(y0: float, targets: np.ndarray, reach: tuple[float, float], leg: int, hold: int) -> np.ndarray:
    """The targets (um) that bring a planned run to its first target the way the run leaves it: from
    ``y0`` to half the reference's span (at least a tenth of the ``reach``) beyond the first target,
    on the side the reference does not head for, then to that target (two half-cosine legs of ``leg``
    samples), held ``hold`` samples."""
    t0 = float(targets[0])
    moving = np.flatnonzero(np.diff(targets) != 0.0)
    first = 1.0 if moving.size == 0 else float(np.sign(targets[moving[0] + 1] - t0))
    span = float(np.ptp(targets))
    far = float(np.clip(t0 - first * max(0.5 * span, 0.1 * (reach[1] - reach[0])), reach[0], reach[1]))
    ease = 0.5 * (1.0 - np.cos(np.pi * np.arange(leg) / (leg - 1)))
    return np.concatenate([y0 + (far - y0) * ease, far + (t0 - far) * ease, np.full(hold, t0)])


#: effects the analytic kinds cover (dynamics and delay are handled outside the static inverse)
_OUTSIDE_STATIC = ("dynamics", "delay")


def _range_aux(model: Any, channels: list[str], values: dict[str, float] | None) -> tuple[np.ndarray, str]:
    """The aux channels' values the operating range is traced at, and how the notes name them: each
    channel's value in ``values`` (read on the rig before the run) where it is there and finite, else
    the model's reference value for it."""
    if not channels:
        return np.zeros(1), "no aux channels"
    refs = [float(model.effect(c).constants["reference"]) for c in channels]
    read = [None if values is None or c not in values or not math.isfinite(float(values[c])) else float(values[c])
            for c in channels]
    used = [r if v is None else v for r, v in zip(refs, read, strict=True)]
    if all(v is None for v in read):
        return np.array(used), "aux channels at their references"
    parts = [f"{c} {u:.4g} ({'read before the run' if v is not None else 'its reference'}; the model's reference {r:.4g})"
             for c, u, v, r in zip(channels, used, read, refs, strict=True)]
    return np.array(used), "aux channels " + ", ".join(parts)


class Compensator:
    """An inverse-model compensator for a fitted model, with optional PID feedback and online
    adaptation; see the module docstring for the kinds.

    ``limits`` (lo, hi) is the command range (the rig's actuator ``min``/``max``): the inverse never
    asks for more. ``method``: ``auto`` (pi -> ``pi``, pmpi -> ``im``, mpi / pi+asymmetry -> ``mpi``,
    fpmpi -> ``fpmpi``, anything else -> ``general``) or a kind name. ``gain`` is eq. 20's k_e
    (``"auto"``, a number, or None: refuse when eq. 16 fails). ``iterations``: I-M passes per
    sample. ``feedback``: True (gains designed from the identified loop) or a :class:`PID` (checked
    on it). ``online``: True or a dict of :class:`hilbench.online.oiir.OIIR` options (``M``, ``N``,
    ``bias``, ``lam``, ...).
    """

    def __init__(
        self,
        model: Any,
        sample_rate_hz: float,
        limits: tuple[float, float],
        *,
        method: str = "auto",
        gain: float | str | None = "auto",
        iterations: int = 1,
        feedback: PID | bool | None = None,
        online: dict[str, Any] | bool | None = None,
        dynamics_feedforward: bool = True,
        reference_span: float | None = None,
        max_iterations: int = 60,
        unit: str = "",
        plannable: bool = False,
        aux_values: dict[str, float] | None = None,
    ):

        if model.weights is None:
            raise UserError("the model has no weights yet: fit it first")
        if getattr(model, "structure", None) is not None:
            # the hysteresis inside the mechanics is one state equation: no static map to invert
            raise UserError(f"{model.spec!r} cannot be tracked: its hysteresis sits inside the mechanics "
                            "(restoring-force), which has no static inverse; track with a model whose "
                            "hysteresis comes before its dynamics (e.g. bouc-wen+dynamics)")
        self.model = model
        self.fs = float(sample_rate_hz)
        lo, hi = float(limits[0]), float(limits[1])
        if not hi > lo:
            raise UserError(f"command limits [{lo:g}, {hi:g}]: expected min < max")
        self.limits = (lo, hi)
        self.notes: list[str] = []
        self.checks: dict[str, Any] = {}
        try:
            compiled = ST.compile_model(model, self.fs)
        except ST.NotCompilable as exc:
            raise UserError(f"model {model.spec!r} cannot be compiled for a compensator: {exc}") from None
        I = compiled.I.copy()
        # the static part: dynamics and delay are inverted (or not) outside the model
        I[ST.I_DYN_ON] = 0
        I[ST.I_DELAY] = 0
        P = compiled.P.copy()
        P[ST.P_RATE_LAG] = 1.0  # rate terms on the previous sample's rate: see model_step
        self.I, self.P = I, P
        self.X = np.zeros(int(I[ST.I_NX]))
        self.channels = list(compiled.channels)
        self.unit = unit
        us = float(model.norm["u_scale"])
        # what the model knows and reaches: the static map over the fitted inputs (see operating_range),
        # at the aux channels' values read before the run where given (a load or a temperature moves
        # the whole loop: judged at the model's reference values, a reference the rig reaches now is
        # refused, or one it does not is run), else at the model's references
        aux_ref, self._aux_note = _range_aux(model, self.channels, aux_values)
        self.range = operating_range(model, I, P, aux_ref, (lo, hi), sample_rate_hz=self.fs)

        extra = [e.name for e in model.effects if e.name not in _OUTSIDE_STATIC and e.name != "asymmetry"]
        structure = None if extra else _pi_structure(model)
        base = model.base.name
        if method == "auto":
            asym = model.effect("asymmetry") is not None
            # the analytic inverses hold for a map rising over the whole fitted range; a falling one, or
            # one monotone only on part of it, is solved per sample on its operating range
            rising = self.range.direction > 0
            if base == "fpmpi" and structure is not None and not asym and rising and self.range.invertible:
                # its analytic inverse (operators inverted, the polynomial solved by Newton) holds on a
                # monotone part of the fitted range too: the solve is kept inside it
                kind = "fpmpi"
            elif structure is None or (base == "fpmpi" and asym) or not rising or not self.range.rising:
                kind = "general"
            elif base in ("pi", "pi1") and not asym:
                kind = "pi"
            elif base == "pmpi":
                kind = "im"
            else:
                kind = "mpi"
        else:
            kind = method
        if kind == "fpmpi" and self.range.sub_range:
            kind = self._fpmpi_on_rising_part(I, P, aux_ref, us) if method == "auto" else kind
        if kind not in K.KINDS:
            raise UserError(f"compensator method {kind!r}: expected auto or one of {', '.join(K.KINDS)}")
        if kind != "general" and structure is None:
            raise UserError(f"compensator method {kind!r} needs an operator base without effects other than "
                            f"asymmetry, dynamics, delay; model {model.spec!r} has {', '.join(extra) or base}",
                            hint="use method='general' (a per-sample solve of the whole model)")
        if kind == "fpmpi" and base != "fpmpi":
            raise UserError(f"compensator method 'fpmpi' needs an fpmpi model, not {base!r}")
        poly = np.zeros(0)
        if structure is not None and kind in ("mpi", "im"):
            poly = _polynomial(model, structure["n_ops"])
        if kind == "pi" and structure is not None and _polynomial(model, structure["n_ops"]).size > 1:
            raise UserError(f"compensator method 'pi' cannot invert the polynomial of {model.spec!r}",
                            hint="use method='mpi' or 'im'")
        self.kind = kind
        # the general inverse solves the static map per sample: it needs that map rising, and it
        # brackets its solve by the operating range (outside it the model is extrapolated, and a
        # map that turns over there gives a second, falling root or a rail)
        if kind == "general" and not self.range.invertible and not plannable:
            raise InstabilityError(self.range.not_rising(model.spec, unit),
                                   hint="fit the model on the range you will track in, where the actuator rises")
        # the polynomial kinds too: 004 eq. 16/20 and the I-M clamp hold where the model is known (a
        # cubic fitted on 0..4 V turns over by 13 V, which made eq. 20 fail over the rig's range)
        on_range = (kind == "general" or (kind in ("mpi", "im") and self.range.rising and self.range.direction > 0)
                    or (kind == "fpmpi" and self.range.sub_range and self.range.direction > 0))
        self.bracket = self.range.command if on_range else (lo, hi)
        self._range_notes(kind)
        ke = 0.0
        if kind in ("mpi", "im"):
            ke = self._check_eq16(structure["p0"], poly, us, gain, kind)
        n_sorted = 0 if structure is None else int(structure["perm"].size)

        # -- CP ---------------------------------------------------------------------------------------
        cp: list[float] = [0.0] * K.N_CP
        cp[K.C_US] = us
        cp[K.C_ULO], cp[K.C_UHI] = self.bracket
        cp[K.C_SIGN] = float(self.range.direction) if kind == "general" else 1.0
        ci = np.zeros(K.N_CI, dtype=np.int64)
        ci[K.CI_KIND] = K.KINDS[kind]
        ci[K.CI_NX] = self.X.size
        ci[K.CI_MAXIT] = int(max_iterations)
        ci[K.CI_IMIT] = int(max(1, iterations))

        def put(values: Any) -> int:
            at = len(cp)
            cp.extend(float(x) for x in np.asarray(values, float).ravel())
            return at

        perm = np.zeros(0, dtype=np.int64)
        if structure is not None and kind != "general":
            p0 = structure["p0"] + ke
            if not p0 > 0:
                raise InstabilityError(
                    f"the PI part of {model.spec!r} has p0 = {structure['p0']:.4g} um <= 0 (+ k_e = {ke:.4g}): "
                    "the analytic inverse needs p0 > 0 (004 eq. 15)", hint="use method='general'")
            try:
                ph0, r_hat, p_hat = inverse_pi_parameters(p0, structure["s"], structure["p"])
            except ValueError as exc:
                raise InstabilityError(f"{model.spec!r}: {exc}; the PI part is not invertible",
                                       hint="use method='general'") from None
            cp[K.C_P0], cp[K.C_PH0], cp[K.C_CONST], cp[K.C_KE] = p0, ph0, structure["const"], ke
            cumulative = p0 + np.concatenate([[0.0], np.cumsum(structure["p"])])
            cp[K.C_SMIN] = float(np.min(cumulative))
            cp[K.C_PITOL] = 1e-13 * (abs(p0) + float(np.sum(np.abs(structure["p"]))))
            ci[K.CI_NOPS] = n_sorted
            perm = structure["perm"].astype(np.int64)
            ci[K.CI_O_S] = put(structure["s"])
            ci[K.CI_O_P] = put(structure["p"])
            ci[K.CI_O_C] = put(structure["c"])
            ci[K.CI_O_RH] = put(r_hat)
            ci[K.CI_O_PH] = put(p_hat)
            self.inverse_pi = {"p0_hat": ph0, "thresholds": r_hat.tolist(), "weights": p_hat.tolist()}
        ci[K.CI_NPOLY] = poly.size
        ci[K.CI_O_POLY] = put(poly if poly.size else [0.0])
        # -- dynamics feed-forward ------------------------------------------------------------------
        ff_num, ff_den = np.ones(1), np.ones(1)
        dyn = model.effect("dynamics")
        self.dynamics = None
        if dyn is not None:
            b, a = dyn.coefficients(self.fs)
            self.dynamics = (np.asarray(b, float), np.asarray(a, float))
            zeros = np.roots(np.trim_zeros(b, "b")) if np.count_nonzero(b) > 1 else np.zeros(0)
            radius = float(np.max(np.abs(zeros), initial=0.0))
            if not dynamics_feedforward:
                self.notes.append("dynamics feed-forward off: the dynamics are left to feedback")
            elif abs(b[0]) < 1e-9 * np.sum(np.abs(b)) or radius >= 0.98:
                self.notes.append(f"dynamics not inverted in feed-forward: non-minimum-phase (zero at "
                                  f"|z| = {radius:.3g}) or no direct term; left to feedback")
            else:
                ff_num, ff_den = a / b[0], b / b[0]
                self.notes.append(f"dynamics inverse A(z)/B(z) fed forward (zeros at |z| <= {radius:.3g})")
        if model.effect("delay") is not None:
            self.notes.append("delay not compensated in feed-forward (no preview): left to feedback")
        self.preview: dict[str, Any] | None = None
        self.plan: dict[str, Any] | None = None  # what plan_path found (a path planned over the reference)
        #: samples the rig was held at the run's first command for the dynamics to settle (tracking)
        self.held_before_run = 0
        #: samples of pre-actuation a tracking run starts with (:meth:`enable_preview`)
        self.lead = 0
        self.settle_note = ""  # set when the rig's output had not settled before the run
        nf = max(ff_num.size, ff_den.size) - 1
        ci[K.CI_FF] = nf
        if nf > 0:
            from scipy import signal as sps

            n_ = nf + 1
            ff_num = np.pad(ff_num, (0, n_ - ff_num.size))
            ff_den = np.pad(ff_den, (0, n_ - ff_den.size))
            ci[K.CI_O_FFN] = put(ff_num)
            ci[K.CI_O_FFD] = put(ff_den)
            ci[K.CI_O_FFZI] = put(sps.lfilter_zi(ff_num, ff_den))
        # -- solver tolerances and the slope start ----------------------------------------------------
        span_u = hi - lo
        cp[K.C_TOLU] = 1e-12 * span_u
        cp[K.C_T] = 1.0 / self.fs
        cp[K.C_GUARD] = 1.0  # feed-forward too: the command reverses only where its target does
        self.loop: FD.IdentifiedLoop | None = None
        self.margins: dict[str, Any] | None = None
        self.pid: PID | None = None
        # -- online adaptation ------------------------------------------------------------------------------
        self.oiir = None
        if online:
            from hilbench.online.oiir import OIIR

            opts = dict(online) if isinstance(online, dict) else {}
            M, N = int(opts.pop("M", 0)), int(opts.pop("N", 0))
            bias = bool(opts.pop("bias", True))
            cp[K.C_GMIN] = float(opts.pop("gain_min", 0.2))
            cp[K.C_GMAX] = float(opts.pop("gain_max", 5.0))
            cp[K.C_WARM] = float(opts.pop("warmup", self.fs))  # 1 s of data before the correction is used
            opts.setdefault("lam", 0.9995)
            opts.setdefault("delta", 1.0)
            theta0 = np.zeros(M + 1 + N + (1 if bias else 0))
            theta0[0] = 1.0  # start from the model being right: y = u_r
            try:
                self.oiir = OIIR.from_model(model, M, N, bias=bias, theta0=theta0, **opts)
            except ValueError as exc:
                raise UserError(f"online adaptation needs the OIIR's FPMPI front end: {exc}",
                                hint="fit an 'fpmpi' model for --online (paper 000)") from None
            ci[K.CI_ADAPT] = 1
            ci[K.CI_M], ci[K.CI_N], ci[K.CI_BIAS] = M, N, 1 if bias else 0
        self._dummy_oiir = None
        # -- state ----------------------------------------------------------------------------------------
        ci = np.concatenate([ci, perm]) if perm.size else ci
        ci[K.CI_PERM] = K.N_CI
        self.CI = ci
        self.CP = np.array(cp, dtype=np.float64)
        nx_total = K.N_CX
        self.CI[K.CI_O_XM] = nx_total
        nx_total += self.X.size + 2  # + the (value, slope) buffer of the PI check
        self.CI[K.CI_O_XFF] = nx_total
        nx_total += max(nf, 1)
        self._nx_total = nx_total
        self.CP[K.C_SLOPE0] = self._slope0()
        self.CP[K.C_TOLF] = self._tol_f()
        if kind == "fpmpi":
            self._fast_fpmpi()
        self.reset()
        # -- PID: True designs the gains on the identified loop, a PID is checked on it; after the
        # state, as the loop holds the compensator's own response to a correction
        if feedback is True or isinstance(feedback, PID):
            self._feedback(feedback)
            pid = self.pid
            self.CI[K.CI_PID] = 1
            self.CP[K.C_KP] = pid.kp
            self.CP[K.C_KIT] = pid.ki / self.fs
            self.CP[K.C_KD] = pid.kd
            self.CP[K.C_TF] = pid.tf_s if pid.tf_s is not None else 4.0 / self.fs
            self.CP[K.C_ILIM] = pid.i_limit if pid.i_limit is not None else (reference_span or 1e300)
            self.CP[K.C_GUARD] = 1.0 if pid.reversal_guard else 0.0

    def _fpmpi_on_rising_part(self, I: np.ndarray, P: np.ndarray, aux_ref: np.ndarray, us: float) -> str:
        """``fpmpi`` on a monotone part of the fitted range: its Newton solve needs the fractional
        polynomial rising over the whole bracket, but the part was found on a grid whose loop may fall
        within :data:`FALL_TOLERANCE` at an end (the polynomial's turn). The bracket is narrowed to
        the polynomial's widest rising stretch; kept when that loses at most twice the tolerance of
        the reach (the sliver the grid admitted), else ``general`` (a turn inside the part)."""
        lo, hi = self.range.command
        v = np.linspace(lo / us, hi / us, 4001)
        x = np.array([K.shaped_input(I, P, float(t)) for t in v])
        rising = np.diff(x) >= -1e-12 * max(float(np.ptp(x)), 1e-300)
        best, start, run = (0, 0), 0, 0
        for i, ok in enumerate(rising):  # the longest run of rising steps
            start, run = (start, run + 1) if ok else (i + 1, 0)
            if run > best[1] - best[0]:
                best = (start, start + run)
        if best[1] == best[0]:
            return "general"
        part = narrowed(self.range, I, P, aux_ref, (float(v[best[0]] * us), float(v[best[1]] * us)), self.fs)
        reach = self.range.output[1] - self.range.output[0]
        if part is None or part.output[1] - part.output[0] < (1.0 - 2.0 * FALL_TOLERANCE) * reach:
            return "general"
        if part.command != self.range.command:
            part.notes.append(f"the fpmpi inverse's fractional polynomial turns at the edge of [{lo:.4g}, {hi:.4g}]: "
                              f"the operating range narrowed to [{part.command[0]:.4g}, {part.command[1]:.4g}]")
        self.range = part
        return "fpmpi"

    def _fast_fpmpi(self) -> None:
        """The fpmpi fast path (see :func:`K._fpmpi_newton`): the exponents as multiples of 1/q (q <= 24,
        powers <= 96), and the direct commit when the compiled static model is offset + fractional
        polynomial + operators; each checked against the general path on a random walk over the
        command range, and left off when it does not agree."""
        I, P = self.I, self.P
        nin = int(I[ST.I_NIN])
        exps = P[I[ST.I_INEXP] : I[ST.I_INEXP] + nin]
        w = P[I[ST.I_INW] : I[ST.I_INW] + nin]
        q = next((q for q in range(1, 25)
                  if np.all(np.abs(exps * q - np.round(exps * q)) <= 1e-9 * q) and np.all(exps >= 0)
                  and np.max(np.round(exps * q), initial=0) <= 96), 0)
        lo, hi = self.bracket  # the rig's limits, or the monotone part of the fitted range
        us = float(self.CP[K.C_US])
        rng = np.random.default_rng(0)
        walk = np.clip(np.cumsum(rng.normal(0.0, 0.02 * (hi - lo), 400)) + 0.5 * (lo + hi), lo, hi)
        if nin > 0 and q > 0:
            k = np.round(exps * q).astype(np.int64)
            powers = np.unique(k[k > 0])
            weights = np.array([np.sum(w[k == p]) for p in powers])
            self.CI[K.CI_NT] = powers.size
            self.CI[K.CI_O_TK] = self.CI.size
            self.CI[K.CI_O_TW] = self.CP.size
            self.CI = np.concatenate([self.CI, powers])
            self.CP = np.concatenate([self.CP, weights])
            self.CP[K.C_TQ] = q
            self.CP[K.C_TC0] = float(np.sum(w[k == 0]))
            self.CP[K.C_SLO], self.CP[K.C_SHI] = (float(np.sign(b) * abs(b / us) ** (1.0 / q)) for b in (lo, hi))
            s = np.sign(walk) * np.abs(walk / us) ** (1.0 / q)
            fast = np.array([K.tpoly_call(self.CI, self.CP, abs(x))[0] for x in s])
            fast = self.CP[K.C_TC0] + np.sign(s) * fast
            slow = np.array([K.shaped_input(I, P, float(x / us)) for x in walk])
            if not np.allclose(fast, slow, rtol=1e-12, atol=1e-12 * max(1.0, float(np.max(np.abs(slow))))):
                self.CI[K.CI_NT] = 0
        # the direct commit: the compiled static model must be offset + operators on the shaped input
        structure_ok = (int(I[ST.I_BASE]) == 1 and int(I[ST.I_EXTRA]) == 0 and int(I[ST.I_ASYM]) == 0
                        and int(I[ST.I_SAT]) == 0 and int(I[ST.I_NCREEP]) == 0 and int(I[ST.I_RATE]) == 0
                        and int(I[ST.I_NAUX]) == 0 and int(I[ST.I_OFF]) == 0 and int(I[ST.I_DYN_ON]) == 0
                        and int(I[ST.I_DELAY]) == 0 and int(I[ST.I_H]) == 1 + int(I[ST.I_NOPS]))
        if structure_ok and not self.channels:
            self.CI[K.CI_FASTCOMMIT] = 1
            X_fast, X_slow = np.zeros_like(self.X), np.zeros_like(self.X)
            CX = np.zeros(self._nx_total)
            aux = np.zeros(1)
            for u in walk:
                CX[K.S_USOL] = math.nan
                y_fast = K.fpmpi_commit(self.CI, self.CP, CX, I, P, X_fast, float(u))
                y_slow = K.model_step_call(I, P, X_slow, float(u), aux)
                if not abs(y_fast - y_slow) <= 1e-10 * (1.0 + abs(y_slow)):
                    self.CI[K.CI_FASTCOMMIT] = 0
                    break
        fe = self.oiir.front_end if self.oiir is not None else None
        if (fe is not None and self.CI[K.CI_FASTCOMMIT] != 0 and fe.exps.shape == exps.shape
                and np.array_equal(fe.exps, exps) and np.array_equal(fe.w_p, w)
                and fe.fe[0] == P[ST.P_USCALE]):
            self.CI[K.CI_FESHARED] = 1

    # -- checks -------------------------------------------------------------------------------------
    def _check_eq16(self, p0: float, poly: np.ndarray, us: float, gain: float | str | None, kind: str) -> float:
        """004 eq. 16 over the command range (the operating range when the map rises there, else the
        rig's limits); eq. 20's k_e when it fails. Returns k_e."""
        lo, hi = self.bracket
        v = np.linspace(lo / us, hi / us, 2001)
        dp = np.polyval(np.polyder(poly[::-1]), v) if poly.size > 1 else np.zeros_like(v)
        worst = float(np.max(np.abs(dp)))
        self.checks["eq16"] = {"p0": p0, "max_abs_dP": worst, "holds": bool(p0 > worst),
                               "unit": "um per normalised input", "range": [lo, hi]}
        if isinstance(gain, (int, float)) and not isinstance(gain, bool):
            ke = float(gain)
        elif p0 > worst:
            ke = 0.0
        elif gain == "auto":
            ke = max(0.0, float(np.max(dp))) + 0.05 * max(worst, 1e-12)
        else:
            raise InstabilityError(
                f"004 eq. 16 fails for {self.model.spec!r}: p0 = {p0:.4g} <= max|dP/dv| = {worst:.4g} "
                f"(um per normalised input) over the command range [{lo:g}, {hi:g}], and no proportional "
                "gain k_e was given (eq. 20)", hint="pass gain='auto' or a k_e with p0 + k_e > max|dP/dv - k_e|")
        margin = float(np.max(np.abs(dp - ke)))
        holds = p0 + ke > margin
        self.checks["eq20"] = {"k_e": ke, "p0_plus_ke": p0 + ke, "max_abs_dP_minus_ke": margin, "holds": bool(holds)}
        if not holds and kind == "im":
            raise InstabilityError(
                f"004 eq. 20 fails for {self.model.spec!r} with k_e = {ke:.4g}: p0 + k_e = {p0 + ke:.4g} <= "
                f"max|dP/dv - k_e| = {margin:.4g}: the I-M iteration would not contract (the model's "
                "initial loading curve is not rising over the command range)",
                hint="use method='general', or fit the model as pmpi(invertible=yes), which keeps eq. 16")
        if ke:
            self.notes.append(f"eq. 16 fails (p0 = {p0:.4g} <= {worst:.4g}); eq. 20 gain k_e = {ke:.4g} applied"
                              if p0 <= worst else f"eq. 20 gain k_e = {ke:.4g} applied")
        return ke

    def _feedback(self, feedback: PID | bool) -> None:
        """Design (True) or check (a PID) the output-domain feedback on the identified loop
        (:mod:`hilbench.online.feedback_design`); the margins go into checks and notes."""
        runs = FD.training_runs(self.model)
        self.loop = loop = FD.identify_loop(self.model, self.fs, runs=runs)
        loop.compensator = self.correction_response(runs, loop.noise_um)
        designed = feedback is True
        if designed:
            self.pid, self.margins = FD.design(loop)
        else:
            self.pid = feedback  # type: ignore[assignment]
            self.margins = FD.check(self.pid, loop)
        m = self.margins
        lo, hi = loop.gain_range
        self.checks["closed_loop"] = {**{k: (float(v) if isinstance(v, (int, float)) and not isinstance(v, bool)
                                             else v) for k, v in m.items()},
                                      "designed": designed, "loop": loop.describe()}
        self.notes.append(
            f"feedback {'designed' if designed else 'given'}: kp {self.pid.kp:.4g}, ki {self.pid.ki:.4g} 1/s, "
            f"kd {self.pid.kd:.4g} s (um/um); gain margin {m['gain_margin_db']:.3g} dB, phase margin "
            f"{m['phase_margin_deg']:.3g} deg, crossover {m['crossover_hz']:.3g} Hz over local gains "
            f"{lo:.3g}-{hi:.3g}, unmodelled lag {loop.lag_s * 1e3:.3g} ms ({loop.source})")
        if m.get("feedforward_error_um") and not m.get("open"):
            ratio = m["predicted_error_um"] / m["feedforward_error_um"]
            self.notes.append(
                f"feedback gain chosen for this model's training error ({m['feedforward_error_um']:.3g} um rms, sensor "
                f"noise included): predicted {m['predicted_error_um']:.3g} um with the loop closed at the worst local "
                f"gain ({ratio:.2f}x)"
                + (f"; on the rows the fit held out {m['feedforward_held_out_error_um']:.3g} -> "
                   f"{m['predicted_held_out_error_um']:.3g} um" if "feedforward_held_out_error_um" in m else "")
                + (f"; the margins allowed ki up to {m['ki_max_per_s']:.4g} 1/s, more would "
                   "raise the error near the crossover" if m["error_limited"] else ""))
        if m.get("open"):
            self.notes.append(
                f"feedback left open (ki = 0): every integral gain up to {m['ki_max_per_s']:.4g} 1/s is predicted to raise "
                f"this model's error on this rig ({m['feedforward_error_um']:.3g} um rms on its training runs"
                + (f", {m['feedforward_held_out_error_um']:.3g} um on the rows the fit held out"
                   if "feedforward_held_out_error_um" in m else "")
                + ": the sensor's noise, or error near the crossover the margins allow); the run is feed-forward")

    #: samples of training data the compensator's response to a correction is simulated on, at most
    CORRECTION_SAMPLES = 60_000

    def correction_response(self, runs: list, amplitude_um: float | None) -> Any:
        """How this compensator answers a correction added to its target, as the loop's PID adds one
        (:func:`hilbench.online.loop_response.compensator_response`): the training runs (``runs`` of
        :func:`hilbench.online.feedback_design.training_runs`, those at this rate) give the static
        model's output on the recorded command as targets; the compensator is run on them without and
        with a white correction of ``amplitude_um`` rms (the sensor's noise: what the loop feeds back;
        at least 1e-4 of the targets' span), and the fitted model's static part (the rig as far as the
        model knows) answers both command sequences, the reversal guard off. Runs until
        CORRECTION_SAMPLES are used. Leaves the compensator's state as it was; None without runs at
        this rate."""
        from hilbench.online.loop_response import compensator_response

        # the rig as far as the model knows it, for a correction: the compensator's own static part
        # (the loop's dynamics are the model's b, a) without the rate terms
        I, P = ST.without_rate_terms(self.I), self.P
        pieces = []
        used = 0
        saved = (self.CI.copy(), self.CP.copy(), self.CX.copy(), self.X.copy())
        rng = np.random.default_rng(0x10C)  # a fixed draw: the same design from the same data
        try:
            for run in runs:
                u, _y, aux, run_fs = run[:4]
                if abs(run_fs - self.fs) > 1e-9 * self.fs or used >= self.CORRECTION_SAMPLES:
                    continue
                u = np.ascontiguousarray(u[: self.CORRECTION_SAMPLES - used], dtype=np.float64)
                n = u.size
                a = self.aux_matrix(aux, n)
                targets = np.empty(n)
                ST.model_block(I, P, np.zeros(int(I[ST.I_NX])), u, a, targets)
                if not np.all(np.isfinite(targets)):
                    continue
                amp = max(float(amplitude_um or 0.0), 1e-4 * float(np.ptp(targets)))
                if not amp > 0.0:
                    continue
                p = amp * rng.standard_normal(n)
                outs = []
                for corr in (np.zeros(n), p):
                    self.reset()
                    self.CI[K.CI_PID] = 1
                    self.CI[K.CI_PREVIEW] = 1
                    self.CI[K.CI_FF] = 0
                    # the reversal guard off: it holds a correction against the reference's direction,
                    # a gain below one that depends on the correction's size and sign, not counted on
                    self.CP[K.C_GUARD] = 0.0
                    commands = np.empty(n)
                    K.comp_block_corrected(self.CI, self.CP, self.CX, self.I, self.P, self.X, self.oiir_arrays(),
                                           targets, corr, a, commands)
                    y = np.empty(n)
                    ST.model_block(I, P, np.zeros(int(I[ST.I_NX])), commands, a, y)
                    outs.append(y)
                d = outs[1] - outs[0]
                if np.all(np.isfinite(d)):
                    pieces.append((p, d))
                    used += n
        finally:
            self.CI, self.CP, self.CX, self.X = saved
        return compensator_response(pieces, self.fs)

    def _range_notes(self, kind: str) -> None:
        r, u = self.range, self.unit
        self.notes.append(
            f"fitted input range [{r.fitted[0]:.4g}, {r.fitted[1]:.4g}] {u} ({r.source}); operating range "
            f"[{r.command[0]:.4g}, {r.command[1]:.4g}] {u}; reachable output [{r.output[0]:.4g}, {r.output[1]:.4g}] um: "
            f"the static map's major loop over the operating range (dynamics and delay off, {self._aux_note})"
            .replace("  ", " "))
        self.notes.extend(r.notes)
        if r.sub_range:
            self.notes.append(r.sub_range_note(u))
        if r.direction < 0 and kind == "general":
            self.notes.append("the static map falls with the command over the operating range: solved on its sign")
        if kind == "general" or r.sub_range:
            self.notes.append(f"the {kind} inverse solves within [{self.bracket[0]:.4g}, {self.bracket[1]:.4g}] {u}"
                              .replace("  ", " "))
        elif not r.rising:
            self.notes.append(f"the static map does not rise over the fitted range (largest fall {r.fall_um:.4g} um on "
                              f"its {r.fall_branch} branch); the {kind} inverse relies on its own checks")
        self.notes.append("dynamics: inverted by a feed-forward pre-filter when minimum phase, else left to feedback; "
                          "delay: left to feedback" if self.model.effect("dynamics") is not None or
                          self.model.effect("delay") is not None else "no dynamics or delay in the model")

    def _slope0(self) -> float:
        lo, hi = self.bracket
        us = self.CP[K.C_US]
        if self.kind == "general":
            # the ascending branch's mean slope over the bracket, in the solver's sense (positive)
            self._y_span = abs(self.range.output[1] - self.range.output[0])
            return float(self.range.direction * self.range.slope)
        if self.kind == "fpmpi":
            v = np.linspace(lo / us, hi / us, 4001)
            x = np.array([K.shaped_input(self.I, self.P, float(t)) for t in v])
            if np.any(np.diff(x) < -1e-12 * np.ptp(x)):
                self.notes.append("the fractional polynomial is not monotone over the command range: the solve "
                                  "returns a bracketed root")
            return max(float((x[-1] - x[0]) / (v[-1] - v[0])), 1e-9)
        return 1.0

    def _tol_f(self) -> float:
        lo, hi = self.limits
        if self.kind == "general":
            return 1e-9 * max(getattr(self, "_y_span", 1.0), 1e-12)
        return 1e-11 * (hi - lo)

    # -- state ----------------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Fresh model memory, feedback and identifier; the command at the range's low end."""
        self.X[:] = 0.0
        #: every command fed to the model's memory by :meth:`precondition` since (what the actuator went
        #: through before a run: a replay of the model needs it)
        self.preconditioned: list[np.ndarray] = []
        self.CX = np.zeros(self._nx_total)
        self.CX[K.S_U] = self.CX[K.S_UAPP] = min(max(0.0, self.bracket[0]), self.bracket[1])
        self.CX[K.S_VPREV] = self.CX[K.S_U] / self.CP[K.C_US]
        self.CX[K.S_SLOPE] = self.CP[K.C_SLOPE0]
        self.CX[K.S_GAIN] = 1.0
        self.CX[K.S_YPREV] = math.nan
        self.CX[K.S_RPREV] = math.nan
        if self.oiir is not None:
            self.oiir.reset()
        self._aux = np.zeros(max(len(self.channels), 1))

    def settling_samples(self, floor: float = 1e-3, most_s: float = 1.0) -> int:
        """Samples for the model's dynamics to settle to ``floor`` of a step (plus its delay), at most
        ``most_s`` seconds: how long the rig is held at a run's first command before the run."""
        from hilbench.online.preview import settling_samples

        n = settling_samples(*self.dynamics, floor=floor) if self.dynamics is not None else 0
        delay = self.model.effect("delay")
        if delay is not None:
            n += int(math.ceil(float(delay.param("seconds")) * self.fs))
        return int(min(n, most_s * self.fs))

    def enable_preview(self, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Invert the model's dynamics and delay over the whole ``reference`` (um), known before the run
        (:mod:`hilbench.online.preview`): returns (pre-actuation, targets), what the static part must
        deliver before the reference's first sample and over its samples (pass them to
        :meth:`step`/:meth:`feedforward` as ``target``), and switches the causal pre-filter off. A
        model without dynamics or delay returns no pre-actuation and the reference as it is, and
        changes nothing."""
        from hilbench.online.preview import REGULARIZATION, preview_with_lead

        delay = self.model.effect("delay")
        delay_samples = float(delay.param("seconds")) * self.fs if delay is not None else 0.0
        if self.dynamics is None and delay_samples == 0.0:
            return np.zeros(0), np.ascontiguousarray(reference, dtype=np.float64)
        b, a = self.dynamics if self.dynamics is not None else (None, None)
        lead, target = preview_with_lead(reference, b, a, delay_samples)
        self.CI[K.CI_PREVIEW] = 1
        self.CI[K.CI_FF] = 0
        self.notes = [n for n in self.notes if not n.startswith(("dynamics", "delay not compensated"))]
        parts = (["the dynamics B/A (stable inversion, non-causal where its zeros demand it; gain limited where "
                  f"|B/A| < {REGULARIZATION ** 0.5:.2g} of its static gain)"] if b is not None else []) + \
                ([f"the delay of {delay_samples:.3g} samples"] if delay_samples else [])
        self.notes.append("feed-forward: " + " and ".join(parts) + " inverted with a preview of the whole reference"
                          + (f", {lead.size} samples of pre-actuation before its first sample (recorded at the "
                             "run's start, left out of its figures)" if lead.size else ""))
        self.preview = {"dynamics": b is not None, "delay_samples": delay_samples,
                        "preactuation_samples": int(lead.size),
                        "target_range_um": [float(min(np.min(target), np.min(lead, initial=np.inf))),
                                            float(max(np.max(target), np.max(lead, initial=-np.inf)))]}
        return lead, target

    #: the approach before a planned run: each of its two legs lasts at least this long (s) ...
    APPROACH_LEG_S = 0.25
    #: ... and the planned path holds the run's first target this long before it (s)
    APPROACH_HOLD_S = 0.05

    def plan_path(self, targets: np.ndarray, max_step: float, aux: dict[str, float] | None = None,
                  lead_in: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Plan the commands over the whole reference's ``targets`` (um; the preview's) on a static map
        that is not monotone (:mod:`hilbench.online.path_plan`), from the model's memory after the
        commands ``lead_in`` (what the rig goes through first: the full-range cycle), and install the
        run's part: feed-forward then replays it, and feedback adds its correction over the model's
        slope along it, inside its monotone stretches (:func:`hilbench.online.path_plan.feedback_samples`).
        A model that reads channels (a load, a temperature) is planned at their values in ``aux``
        (read before the run); each sample is then solved at the values read with it, inside the
        plan's stretch around its command (decision 0124): a load that steps during the run moves the
        loop the plan was made on.

        The run's first target may need an overshoot to be reached (a reference starting at its
        extremum), so an *approach* is planned before it: from where the lead-in leaves the output to
        half the reference's span beyond its first target, on the side it comes from, then to that
        target (two half-cosine legs of :data:`APPROACH_LEG_S` at least, and at least the time the
        command needs to cross the range twice at ``max_step``), held :data:`APPROACH_HOLD_S`.
        Returns the approach's commands (to apply after the lead-in) and the model's error along the
        run's plan (um)."""
        from hilbench.online import path_plan as PP

        if not self.range.planned:
            raise ValueError("plan_path needs an operating range set to plan over the fitted range")
        t = np.ascontiguousarray(targets, dtype=np.float64)
        a, b = self.range.fitted
        y_lo, y_hi = self.range.loop_output
        row = self._aux_row(aux).copy()
        X = self.X.copy()
        u0 = float(self.CX[K.S_UAPP])
        if lead_in is not None and np.size(lead_in):
            lead = np.ascontiguousarray(lead_in, dtype=np.float64)
            ST.model_block(self.I, self.P, X, lead, np.ascontiguousarray(np.broadcast_to(row, (lead.size, row.size))),
                           np.empty(lead.size))
            u0 = float(lead[-1])
        y0 = float(K.model_step_call(self.I, self.P, X.copy(), u0, row))
        step = max_step if math.isfinite(max_step) and max_step > 0 else b - a
        leg = max(math.ceil(self.APPROACH_LEG_S * self.fs), math.ceil(2.0 * (b - a) / step), 2)
        approach = _approach_targets(y0, t, (y_lo, y_hi), leg, max(int(self.APPROACH_HOLD_S * self.fs), 1))
        whole = np.concatenate([approach, t])
        plan = PP.plan_path(self.I, self.P, X, row, u0, whole, (a, b), step, y_hi - y_lo)
        na = approach.size
        run = slice(na, None)
        error = plan.output[run] - t
        n = t.size
        o = self.CP.size
        feedback_here = PP.feedback_samples(plan, whole, (a, b))[run]
        self.CP = np.concatenate([self.CP, plan.command[run], plan.stretch_lo[run], plan.stretch_hi[run],
                                  plan.slope[run], plan.direction[run], feedback_here.astype(np.float64)])
        # feedback's correction is divided by the model's slope along the plan, floored at a quarter of
        # its median: near a flat spot (an overshoot's extreme) it gets less gain, never more
        self.CP[K.C_PLANG] = max(0.25 * float(np.median(np.abs(plan.slope[run]))), 1e-9)
        self.CI[K.CI_PLAN], self.CI[K.CI_O_PLAN] = n, o
        # planned at the channels' values read before the run; solved per sample at their values then
        self.CI[K.CI_PLANAUX] = 1 if self.channels else 0
        self.CP[K.C_ULO], self.CP[K.C_UHI] = a, b
        self.bracket = (a, b)
        self.CX[K.S_PLANK] = 0.0
        turns = int(np.count_nonzero(np.diff(plan.direction[run])))
        r = self.range
        self.notes = [f"fitted input range [{a:.4g}, {b:.4g}] {self.unit} ({r.source}); reachable output "
                      f"[{y_lo:.4g}, {y_hi:.4g}] um: the static map's major loop over it, overshoots included"
                      .replace("  ", " ")] + \
                     [note for note in self.notes if not note.startswith(("fitted input range", "the general inverse solves",
                                                                          "the static map is not monotone over"))]
        self.plan = {"samples": n, "approach_samples": na, "command_range": [float(np.min(plan.command[run])),
                                                                              float(np.max(plan.command[run]))],
                     "model_error_rms_um": float(np.sqrt(np.mean(error ** 2))), "model_error_max_um": float(np.max(np.abs(error))),
                     "reversals": turns, "feedback_samples_pct": 100.0 * float(np.mean(feedback_here))}
        self.notes.append((
            f"the static map turns over in the fitted [{a:.4g}, {b:.4g}] {self.unit}: the commands are a path planned "
            f"over the whole reference ({turns} reversals, some before the reference turns so the output's overshoot "
            f"lands on its extremum); along it the model misses the reference by {self.plan['model_error_rms_um']:.3g} um "
            f"rms, {self.plan['model_error_max_um']:.3g} um at most; approached in {na / self.fs:.3g} s").replace("  ", " "))
        return plan.command[:na].copy(), error

    def oiir_arrays(self) -> tuple:
        """The identifier's kernel arguments (a small unused one when not adaptive, so the compiled
        loop has one signature)."""
        if self.oiir is not None:
            return self.oiir.kernel_args()
        if self._dummy_oiir is None:
            from hilbench.online.oiir import OIIR, FPMPIFrontEnd

            fe = FPMPIFrontEnd(1.0, np.ones(1), np.ones(1), np.zeros(1), np.ones(1))
            self._dummy_oiir = OIIR(fe, 0, 0)
        return self._dummy_oiir.kernel_args()

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(CI, CP, CX, I, P, X)`` for compiled callers."""
        return self.CI, self.CP, self.CX, self.I, self.P, self.X

    def _aux_row(self, aux: dict[str, float] | None) -> np.ndarray:
        if self.channels:
            for i, c in enumerate(self.channels):
                self._aux[i] = aux[c]  # type: ignore[index]
        return self._aux

    def step(self, y_d: float, aux: dict[str, float] | None = None, target: float | None = None) -> float:
        """Step mode: the command for y_d (um); then call :meth:`update` with what was applied.
        ``target``: this sample's previewed target (:meth:`enable_preview`)."""
        if target is not None:
            self.CX[K.S_TARGET] = target
        return K.comp_step(self.CI, self.CP, self.CX, self.I, self.P, self.X, float(y_d), self._aux_row(aux))

    def update(self, y_d: float, u_applied: float, y_meas: float = math.nan,
               aux: dict[str, float] | None = None) -> None:
        """Commit the applied command; feed the measured output to feedback and identifier."""
        K.comp_update(self.CI, self.CP, self.CX, self.I, self.P, self.X, self.oiir_arrays(), float(y_d),
                    float(u_applied), float(y_meas), self._aux_row(aux))

    def feedforward(self, y_d: np.ndarray, aux: dict[str, np.ndarray] | None = None,
                    targets: np.ndarray | None = None) -> np.ndarray:
        """Block mode, open loop: the commands for a reference, each committed as applied
        (``targets``: the previewed targets of :meth:`enable_preview`)."""
        y = np.ascontiguousarray(y_d, dtype=np.float64)
        out = np.empty_like(y)
        t = y if targets is None else np.ascontiguousarray(targets, dtype=np.float64)
        K.comp_block(self.CI, self.CP, self.CX, self.I, self.P, self.X, self.oiir_arrays(), y,
                     self.aux_matrix(aux, y.shape[0]), out, t)
        return out

    def aux_matrix(self, aux: dict[str, np.ndarray] | None, n: int) -> np.ndarray:
        if not self.channels:
            return np.zeros((n, 1))
        missing = [c for c in self.channels if aux is None or c not in aux]
        if missing:
            raise UserError(f"the model reads channel(s) {', '.join(missing)}, which were not given")
        return np.ascontiguousarray(np.column_stack([np.asarray(aux[c], float)[:n] for c in self.channels]))  # type: ignore[index]

    def precondition(self, applied: np.ndarray, aux: dict[str, np.ndarray] | None = None) -> None:
        """Feed commands the actuator went through (a ramp before the run) into the model's memory."""
        u = np.ascontiguousarray(applied, dtype=np.float64)
        if u.size == 0:
            return
        out = np.empty_like(u)
        ST.model_block(self.I, self.P, self.X, u, self.aux_matrix(aux, u.shape[0]), out)
        self.preconditioned.append(u.copy())
        self.CX[K.S_XP_OK] = 0.0  # the model's memory moved without the fast commit
        self.CX[K.S_U] = self.CX[K.S_UAPP] = float(u[-1])
        self.CX[K.S_VPREV] = float(u[-1]) / self.CP[K.C_US]

    def warm_up(self, y_d: float, aux: dict[str, float] | None = None) -> None:
        """Compile (or load from numba's cache) :meth:`step` and :meth:`update`'s kernels by one sample
        on copies of the state, before a fixed-rate loop's first deadline; changes no state."""
        CI, CP, CX, I, P, X = (a.copy() for a in self.arrays())
        oa = tuple(a.copy() if isinstance(a, np.ndarray) else a for a in self.oiir_arrays())
        row = self._aux_row(aux).copy()
        u = K.comp_step(CI, CP, CX, I, P, X, float(y_d), row)
        K.comp_update(CI, CP, CX, I, P, X, oa, float(y_d), float(u), float(y_d), row)

    def peek(self, y_d: float, aux: dict[str, float] | None = None) -> float:
        """The command for y_d without changing any state."""
        saved = (self.CX.copy(), self.X.copy())
        try:
            u = self.step(y_d, aux)
            # the I-M iteration starts from the last command: converge it where the output jumps
            for _ in range(60 if self.kind == "im" else 0):
                self.CX[:], self.X[:] = saved
                self.CX[K.S_VPREV] = u / self.CP[K.C_US]
                u_next = self.step(y_d, aux)
                if abs(u_next - u) <= 1e-12 * (self.limits[1] - self.limits[0]):
                    break
                u = u_next
            return u
        finally:
            self.CX[:], self.X[:] = saved

    def counters(self) -> dict[str, Any]:
        return {"samples": int(self.CX[K.S_NOBS]), "solver_evaluations": int(self.CX[K.S_EVALS]),
                "limited_samples": int(self.CX[K.S_SATN]), "references_held": int(self.CX[K.S_HELD]),
                "analytic_inverse_corrected": int(self.CX[K.S_FIXED]), "newton_samples": int(self.CX[K.S_NEWTON]),
                "reversals_held": int(self.CX[K.S_GUARDN]),
                "gain": float(self.CX[K.S_GAIN]), "offset_um": float(self.CX[K.S_BIAS])}

    def describe(self) -> dict[str, Any]:
        """What the recording keeps: kind, checks, notes, feedback, identifier."""
        doc: dict[str, Any] = {"model": self.model.spec, "method": self.kind, "limits": list(self.limits),
                               "operating_range": self.range.describe(self.unit),
                               "checks": self.checks, "notes": self.notes}
        if self.kind == "im":
            doc["iterations_per_sample"] = int(self.CI[K.CI_IMIT])
        if self.pid is not None:
            doc["feedback"] = {"kp": self.pid.kp, "ki_per_s": self.pid.ki, "kd_s": self.pid.kd,
                               "units": "output domain: um of error in, um added to the reference out",
                               "designed": bool(self.checks.get("closed_loop", {}).get("designed", False)),
                               "margins": {k: self.margins[k] for k in ("gain_margin_db", "phase_margin_deg",
                                                                        "crossover_hz", "max_pole_radius",
                                                                        "predicted_error_um", "feedforward_error_um",
                                                                        "predicted_held_out_error_um",
                                                                        "feedforward_held_out_error_um")
                                           if k in self.margins}
                               if self.margins else None,
                               "loop": self.loop.describe() if self.loop is not None else None}
        if self.oiir is not None:
            doc["online"] = {"M": self.oiir.M, "N": self.oiir.N, "bias": self.oiir.bias}
        if self.preview is not None:
            doc["preview"] = self.preview
        if self.plan is not None:
            doc["planned_path"] = self.plan
        if self.held_before_run:
            doc["held_before_run_samples"] = self.held_before_run
        if self.settle_note:
            doc["notes"] = [*self.notes, self.settle_note]
        return doc
