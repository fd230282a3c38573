"""The hysteresis inside the mechanics: a hysteretic restoring force of a mass-spring-damper.

Every other model of hilbench is a static hysteresis, then (optionally) linear dynamics. Here the
drive is a force on a mass held by a spring, a damper and a hysteretic element driven by the
displacement (the public Bouc-Wen benchmark of Noel and Schoukens; a piezo stack or Terfenol rod
loaded by a mass and a spring):

    m y'' + c y' + k y + alpha w = u,
    w' = y' - gamma |y'| |w|^(nu-1) w - delta y' |w|^nu        (Bouc-Wen, nu = the base's ``n``)

``u`` in the recording's command unit, ``y`` in its output unit; ``alpha w`` is the hysteretic force
and ``w`` a displacement (its small-amplitude slope dw/dy is 1). The benchmark writes the force
z = alpha w with z' = alpha y' - beta (gamma_b |y'| |z|^(nu-1) z + delta_b y' |z|^nu); for nu = 1 it
is this form with gamma = beta gamma_b and delta = beta delta_b (only the products are identifiable):
nominal m = 2, c = 10, k = 5e4, alpha = 5e4, gamma = 800, delta = -1100 (N, m, s).

Nothing here is linear in a weight: the whole model is one state equation, searched on its free-run
error (:mod:`hilbench.identify.restoring_force`). The kernel integrates it per sample with classic
Runge-Kutta sub-steps over the drive interpolated between samples (``hold``): the only
approximation that matters at the benchmark's 750 Hz is that interpolation (decision 0102).
One kernel serves block mode (whole runs) and step mode (blocks of one sample).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
from numba import njit

from hilbench.models.components import Component, ShapeParam, Signals
from hilbench.models.options import Option
from hilbench.models.spec import SpecError

#: how the drive is held between samples, as the kernel's code
HOLDS = {"foh": 1, "zoh": 0, "quadratic": 2}
#: kernel parameter vector: m, c, k, alpha, gamma, delta, nu, sample period (s), sub-steps, hold code
N_PARAMS = 10
#: kernel state: y, y', w, u at the last sample, u one sample before, started (0/1)
N_STATE = 6


@njit(cache=True, inline="always")
def _rates(y: float, v: float, w: float, u: float, p: np.ndarray) -> tuple[float, float, float]:
    """(y', y'', w') of the Bouc-Wen restoring-force oscillator at drive u."""
    aw = abs(w)
    nu = p[6]
    if nu == 1.0:  # the benchmark's exponent: no power function in the inner loop
        dw = v - p[4] * abs(v) * w - p[5] * v * aw
    else:
        q = aw ** (nu - 1.0)
        dw = v - p[4] * abs(v) * q * w - p[5] * v * q * aw
    return v, (u - p[1] * v - p[2] * y - p[3] * w) / p[0], dw


@njit(cache=True)
def restoring_force_block(u: np.ndarray, p: np.ndarray, state: np.ndarray, out: np.ndarray) -> None:
    """Displacement ``out[n]`` at the sample times of the drive ``u`` (block or one sample).

    ``p``: :data:`N_PARAMS` values; ``state``: :data:`N_STATE` values, updated in place. The first
    sample of a fresh state outputs the initial displacement (at rest: 0); every later sample
    integrates from the previous sample time with ``p[8]`` RK4 sub-steps, the drive over the
    interval held (zoh: the previous sample), linear (foh), or the parabola through the last three
    samples (quadratic: causal, a smooth band-limited drive within ~0.1 % at 1/20 of the rate).
    """
    y, v, w, u1, u2 = state[0], state[1], state[2], state[3], state[4]
    started = state[5] != 0.0
    substeps = int(p[8])
    hold = int(p[9])
    h = 1.0 / substeps
    dt = h * p[7]
    for n in range(u.shape[0]):
        un = u[n]
        if not started:
            u1 = un
            u2 = un
            started = True
            out[n] = y
            continue
        # u(s) = u1 + s d + q s (s - 1) over s in [0, 1] from the previous sample to this one
        if hold == 0:
            d = 0.0
            q = 0.0
        elif hold == 1:
            d = un - u1
            q = 0.0
        else:
            d = un - u1
            q = 0.5 * (un - 2.0 * u1 + u2)
        for j in range(substeps):
            s0 = j * h
            sm = s0 + 0.5 * h
            s1 = s0 + h
            ua = u1 + s0 * d + q * s0 * (s0 - 1.0)
            um = u1 + sm * d + q * sm * (sm - 1.0)
            ub = u1 + s1 * d + q * s1 * (s1 - 1.0)
            a1, b1, c1 = _rates(y, v, w, ua, p)
            a2, b2, c2 = _rates(y + 0.5 * dt * a1, v + 0.5 * dt * b1, w + 0.5 * dt * c1, um, p)
            a3, b3, c3 = _rates(y + 0.5 * dt * a2, v + 0.5 * dt * b2, w + 0.5 * dt * c2, um, p)
            a4, b4, c4 = _rates(y + dt * a3, v + dt * b3, w + dt * c3, ub, p)
            y += dt / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            v += dt / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
            w += dt / 6.0 * (c1 + 2.0 * c2 + 2.0 * c3 + c4)
        u2 = u1
        u1 = un
        out[n] = y
    state[0], state[1], state[2], state[3], state[4] = y, v, w, u1, u2
    state[5] = 1.0 if started else 0.0


#: the physical parameters, in the order of the kernel's vector, and their units (input: the
#: command unit, output: the output unit; nu the base's exponent)
PHYSICAL = ("m", "c", "k", "alpha", "gamma", "delta")
UNITS = ("input*s^2/output", "input*s/output", "input/output", "input/output", "1/output^nu", "1/output^nu")


class RestoringForce(Component):
    """The base's hysteresis as the restoring force of a mass-spring-damper driven by the input.

    The spec ``bouc-wen+restoring-force``: see the module docstring for the equations. The shape
    parameters are the physical ones (:data:`PHYSICAL`, units from the recording's command and
    output units); there are no weights. Only the Bouc-Wen law is built; Duhem and play operators
    as the restoring force would add a law code to the kernel and keep the rest.
    """

    name = "restoring-force"
    summary = ("the hysteresis inside the mechanics: m y'' + c y' + k y + alpha w(y) = u, "
               "w the base's hysteresis driven by the displacement (Bouc-Wen)")
    options_schema: ClassVar[dict[str, Option]] = {
        "hold": Option("choice", default="foh", choices=tuple(HOLDS),
                       doc="the drive between samples: foh, linear; zoh, each sample held (a DAC's staircase); "
                           "quadratic, the parabola through the last three samples (a smooth band-limited drive)"),
        "substeps": Option("int", default=8, minimum=1, maximum=200,
                           doc="Runge-Kutta steps per sample (8 at 750 Hz: ~1e-4 of the stroke from the converged "
                               "solution; the benchmark's test errors alike from 5 to 80)"),
    }
    #: the bases whose hysteresis the kernel can put inside the mechanics
    LAWS: ClassVar[tuple[str, ...]] = ("bouc-wen",)
    #: the whole model is this component's state equation (:class:`hilbench.models.Model` asks)
    whole_model: ClassVar[bool] = True

    def check_spec(self, base: Component, effects: list[Component], spec: str) -> None:
        if base.name not in self.LAWS:
            raise SpecError(f"restoring-force puts a {'/'.join(self.LAWS)} hysteresis inside the mechanics; "
                            f"the base {base.name!r} is not built as a restoring force yet (spec {spec!r})",
                            where="--model", hint="e.g. bouc-wen+restoring-force")
        others = [e.name for e in effects if e is not self]
        if others:
            raise SpecError(f"restoring-force is a whole model; it takes no other effect, got {', '.join(others)} "
                            f"in spec {spec!r}", where="--model",
                            hint="bouc-wen+restoring-force; its mass, damper and spring are the dynamics")

    def prepare(self, s: Signals) -> None:
        """Placeholder values and bounds; :mod:`hilbench.identify.restoring_force` sets the starts
        and bounds from the linear fit before searching."""
        if self.params:
            return
        self.params = [ShapeParam(name, 1.0, 0.0, math.inf, unit) for name, unit in zip(PHYSICAL, UNITS)]
        self.params[4].lower = self.params[5].lower = -math.inf
        self.params[4].value = self.params[5].value = 0.0

    def kernel_params(self, fs: float, nu: float) -> np.ndarray:
        p = np.empty(N_PARAMS)
        p[:6] = [self.param(name) for name in PHYSICAL]
        p[6] = nu
        p[7] = 1.0 / fs
        p[8] = float(self.options.get("substeps", 8))
        p[9] = float(HOLDS[str(self.options.get("hold", "foh"))])
        return p

    def new_state(self) -> dict[str, Any]:
        return {"x": np.zeros(N_STATE)}

    def simulate(self, u: np.ndarray, fs: float, nu: float, state: dict[str, Any]) -> np.ndarray:
        """Displacement (output unit) for the drive ``u`` (command unit) at ``fs`` Hz from ``state``."""
        out = np.empty(u.shape[0])
        restoring_force_block(np.ascontiguousarray(u, dtype=np.float64), self.kernel_params(fs, nu), state["x"], out)
        return out

    def columns(self, s: Signals, state: dict[str, Any], previous: list[Any]) -> None:
        return None
