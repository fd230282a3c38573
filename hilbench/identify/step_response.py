"""Step-response identification of the linear dynamics, paper 002 sec. 3.2.1 (the ADT approach, eq. 9-10).

Static gain, peak time, settling time and overshoot of a small step, and from them zeta and omega_n of
``G(s) = K wn^2 / (s^2 + 2 zeta wn s + wn^2)`` (eq. 7, 11). Input in the actuator unit (A or V), output in um,
time in s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import optimize

from hilbench.errors import UserError
from hilbench.identify.array_checks import as_1d, require_finite, same_length
from hilbench.identify.peaks import moving_average, quad_vertex
from hilbench.identify.statistics import robust_std

SETTLING_BAND = 0.02  # the 2 % band of the settling time




# ------------------------------------------------------------------------------------------------
# paper 002 eq. 9 and 10
# ------------------------------------------------------------------------------------------------
def second_order_step(t_s: np.ndarray, zeta: float, wn_rad_s: float) -> np.ndarray:
    """Unit step response of wn^2 / (s^2 + 2 zeta wn s + wn^2) at times t_s (s from the step; 0 before)."""
    tau = np.clip(np.asarray(t_s, float), 0.0, None)
    if abs(zeta - 1.0) < 1e-9:
        return 1.0 - np.exp(-wn_rad_s * tau) * (1.0 + wn_rad_s * tau)
    root = np.sqrt(complex(zeta**2 - 1.0))
    p1, p2 = wn_rad_s * (-zeta + root), wn_rad_s * (-zeta - root)
    return np.real(1.0 + (p2 * np.exp(p1 * tau) - p1 * np.exp(p2 * tau)) / (p1 - p2))


def zeta_wn_from_overshoot(overshoot: float, peak_time_s: float) -> tuple[float, float]:
    """Paper 002 eq. 10: zeta and omega_n (rad/s) from the overshoot (a fraction, 0.25 = 25 %)
    and the peak time (s) of an ideal step response."""
    if not (0 < overshoot < 1) or not peak_time_s > 0:
        return math.nan, math.nan
    lo = math.log(overshoot)
    zeta = -lo / math.sqrt(math.pi**2 + lo**2)
    return zeta, math.pi / (peak_time_s * math.sqrt(1 - zeta**2))


def zeta_wn_from_times(peak_time_s: float, settling_time_s: float) -> tuple[float, float]:
    """Paper 002 eq. 9: zeta and omega_n (rad/s) from the peak time and the settling time (s).

    Eq. 9 solves t_p = pi / (wn sqrt(1 - zeta^2)) and t_s = 4 / (zeta wn) (the 2 % envelope)."""
    tp, ts = peak_time_s, settling_time_s
    if not (tp > 0 and ts > 0) or not (math.isfinite(tp) and math.isfinite(ts)):
        return math.nan, math.nan
    root = math.hypot(math.pi * ts, 4 * tp)
    return 4 * tp / root, root / (ts * tp)


# ------------------------------------------------------------------------------------------------
# step response (002 eq. 9-10)
# ------------------------------------------------------------------------------------------------
@dataclass
class StepIdentification:
    """Result of :func:`step_response`. Output unit: that of ``y`` (um); input unit: that of
    ``u_step`` (A or V); times in s, measured from the step.

    ``zeta``/``wn_rad_s`` are the values used: eq. 10 (overshoot) when the overshoot is measurable
    above the noise, else eq. 9 (peak and settling time); both sets are kept. When the applied input
    was given, ``peak_time_s``, ``overshoot`` and ``settling_time_s`` are those of the equivalent ideal
    step (corrected for a ramped or staircase transition, exactly for linear dynamics); the values
    read off the record are kept in the ``measured_*`` fields.
    """

    gain: float  # K, output unit per input unit (um/A)
    zeta: float
    wn_rad_s: float
    used: str  # "eq10" or "eq9"
    zeta_eq10: float
    wn_eq10_rad_s: float
    zeta_eq9: float
    wn_eq9_rad_s: float
    y0: float  # output before the step, um
    y_ss: float  # steady-state output after the step, um
    u_step: float  # step size, input unit
    t_step_s: float  # time of the step in the t array, s
    peak_time_s: float
    peak_value: float  # um
    overshoot: float  # fraction of the step, 0.2 = 20 %
    settling_time_s: float  # 2 % band
    measured_peak_time_s: float
    measured_overshoot: float
    measured_settling_time_s: float
    noise_std: float  # sensor noise estimated from the settled part, um
    input_corrected: bool
    overshoot_measurable: bool

    @property
    def overshoot_pct(self) -> float:
        return 100.0 * self.overshoot

    @property
    def natural_frequency_hz(self) -> float:
        return self.wn_rad_s / (2 * math.pi)

    @property
    def num(self) -> np.ndarray:
        """Continuous numerator [K wn^2] of G(s) (descending powers of s)."""
        return np.array([self.gain * self.wn_rad_s**2])

    @property
    def den(self) -> np.ndarray:
        """Continuous denominator [1, 2 zeta wn, wn^2] of G(s)."""
        return np.array([1.0, 2 * self.zeta * self.wn_rad_s, self.wn_rad_s**2])

    def to_table(self) -> dict[str, Any]:
        """A rig-config ``[plant.dynamics]`` table: ``kind = "second-order"``."""
        return {"kind": "second-order", "gain": float(self.gain), "zeta": float(self.zeta),
                "natural_frequency_hz": float(self.natural_frequency_hz)}

    def response(self, t_s: np.ndarray) -> np.ndarray:
        """Output (um) of the identified model to the ideal step, at times t_s (s, on the data's
        clock): y0 before t_step_s, then y0 + (y_ss - y0) times the unit step response of G/K."""
        t = np.asarray(t_s, float) - self.t_step_s
        unit = second_order_step(t, self.zeta, self.wn_rad_s)
        return np.where(t > 0, self.y0 + (self.y_ss - self.y0) * unit, self.y0)

    def to_dict(self) -> dict[str, Any]:
        out = {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in self.__dict__.items()}
        out.update(natural_frequency_hz=self.natural_frequency_hz, overshoot_pct=self.overshoot_pct,
                   num=self.num.tolist(), den=self.den.tolist())
        return out



def _local_extremum(t: np.ndarray, r: np.ndarray, centre_s: float, half_width_s: float,
                    want_max: bool, dt: float) -> tuple[float, float] | None:
    """Extremum of r near centre_s: a parabola fitted over +-half_width_s (at least 3 samples)
    around the extreme sample, else that sample."""
    lo = np.searchsorted(t, centre_s - half_width_s - 1e-9 * dt)
    hi = np.searchsorted(t, centre_s + half_width_s + 1e-9 * dt, side="right")
    if hi - lo < 1 or lo >= t.size:
        return None
    seg = slice(lo, hi)
    k = lo + (int(np.argmax(r[seg])) if want_max else int(np.argmin(r[seg])))
    hw = max(1, int(round(half_width_s / dt)))
    a, b = max(0, k - hw), min(t.size, k + hw + 1)
    v = quad_vertex(t[a:b], r[a:b], want_max)
    if v is None:
        return float(t[k]), float(r[k])
    return v


def _damped_extremum(t: np.ndarray, r: np.ndarray, centre_s: float, sigma: float, wd: float,
                     want_max: bool, t_min: float) -> tuple[float, float] | None:
    """Extremum of r near centre_s from a local least-squares fit of the second-order ringing,
    ``c0 + e^(-sigma tau) (c1 cos(wd tau) + c2 sin(wd tau))``, tau = t - centre_s, over +-0.35 of a
    half period (at least the 3 nearest samples, none before t_min): exact for a second-order
    response, where a parabola through 3 samples of a 6-samples-per-period ringing is biased."""
    half = math.pi / wd
    idx = np.nonzero((np.abs(t - centre_s) <= 0.35 * half) & (t >= t_min))[0]
    if idx.size < 3:
        order = np.argsort(np.abs(t - centre_s))
        order = order[t[order] >= t_min]
        idx = np.sort(order[:3])
    if idx.size < 3:
        return None
    tau = t[idx] - centre_s
    env = np.exp(-sigma * tau)
    A = np.column_stack([np.ones_like(tau), env * np.cos(wd * tau), env * np.sin(wd * tau)])
    (c0, c1, c2), *_ = np.linalg.lstsq(A, r[idx], rcond=None)
    theta = math.atan2(wd * c2 - sigma * c1, sigma * c2 + wd * c1)
    cands = [(theta + k * math.pi) / wd for k in range(-3, 4)]
    tau_x = min(cands, key=abs)
    if abs(tau_x) > 0.6 * half:
        return None

    def f(x: float) -> float:
        return float(c0 + math.exp(-sigma * x) * (c1 * math.cos(wd * x) + c2 * math.sin(wd * x)))

    value = f(tau_x)
    probe = 0.25 * half
    is_max = value >= max(f(tau_x - probe), f(tau_x + probe))
    is_min = value <= min(f(tau_x - probe), f(tau_x + probe))
    if (want_max and not is_max) or (not want_max and not is_min):
        return None
    return centre_s + tau_x, value



def _refine_onset(t: np.ndarray, r: np.ndarray, k0: int, k_end: int, noise_r: float, fallback: float) -> float:
    """Onset time (s) of a response from rest, between samples: least-squares fit of
    ``r = tau^2 (alpha + beta tau + gamma tau^2)``, tau = t - t0 (the start of a second-order step
    response), to the samples from a few before k0 up to where r passes 30 % of the step;
    ``fallback`` when the rise is too fast to hold enough samples (the onset is then within a
    sample of k0 anyway)."""
    lo = max(0, k0 - 5)
    above = np.nonzero(r[k0:k_end] > 0.3)[0]
    if above.size == 0:
        return fallback
    hi = k0 + int(above[0])
    if hi - k0 < 4 or np.count_nonzero(r[k0:hi] > 3 * noise_r) < 3:
        return fallback
    tt, rr = t[lo:hi], r[lo:hi]
    scale = t[hi] - t[k0]

    def resid(p: np.ndarray) -> np.ndarray:
        tau = np.clip((tt - p[0]) / scale, 0.0, None)
        return tau**2 * (p[1] + tau * (p[2] + p[3] * tau)) - rr

    x0 = np.array([float(t[k0]), 0.3, 0.0, 0.0])
    try:
        bounds = ([t[lo], 0.0, -np.inf, -np.inf], [t[hi - 1], np.inf, np.inf, np.inf])
        res = optimize.least_squares(resid, x0, bounds=bounds, x_scale=[scale, 1.0, 1.0, 1.0])
    except ValueError:
        return fallback
    return float(res.x[0]) if res.success else fallback


def _detect_onset(y: np.ndarray) -> int:
    """Index of the last baseline sample before the output departs (for a step with unknown time)."""
    n = y.size
    m = max(3, n // 20)
    base = float(np.median(y[:m]))
    noise = robust_std(np.diff(y[:m])) / math.sqrt(2) if m > 3 else 0.0
    dev = np.abs(y - base)
    big = float(np.max(dev))
    threshold = max(8 * noise, 0.25 * big)
    if big <= 0 or big < 8 * noise:
        raise UserError("no step found in the output: it never departs from its initial level by more than the noise")
    k = int(np.argmax(dev > threshold))
    floor = max(3 * noise, 1e-6 * big)
    while k > 0 and dev[k - 1] > floor:
        k -= 1
    return max(k - 1, 0)


def step_response(
    t_s: np.ndarray,
    y: np.ndarray,
    *,
    u_step: float,
    t_step_s: float | None = None,
    u: np.ndarray | None = None,
    t_end_s: float | None = None,
) -> StepIdentification:
    """Identify K, zeta, omega_n of 002 eq. 7 from a measured small step response (002 eq. 9-10).

    t_s: sample times (s, increasing, uniform); y: output (um); u_step: size of the input step
    (A or V, signed). t_step_s: time of the step (s); detected from ``u`` if given, else from where
    the output departs (to within a sample: give it when known). u: the applied input (same length);
    it locates the step and the end of its hold, and a non-ideal transition (a ramp of ``rise_s``,
    the slew of an amplifier) is corrected for exactly in the linear dynamics: the oscillation of the
    response to input increments du_k at times tau_k is that of the ideal step times
    F(p) = sum du_k e^(-p tau_k) / sum du_k (p the pole), i.e. scaled and delayed. Pass the input
    of the linear part when it is known better (e.g. the quasi-static hysteresis output): only the
    shape of its transition is used. t_end_s: end of the analysed hold (s); default: where u leaves
    the step level, or where the output leaves it (a return step, or a rise above the first peak).

    Steady state: median of the last 30 % of the hold; K = (y_ss - y0) / u_step (output per input
    unit). Peak: a parabola around the largest sample, refined by a local least-squares fit of the
    damped ringing (exact for a second-order response and robust to noise; a parabola through 3
    samples of a 6-samples-per-period ringing, as at 20 kHz for 3.2 kHz, is biased). Settling time:
    the last time the response is outside +-2 % of the step, found on the extrema of the ringing
    (local fits) and the decay between them, so sensor noise does not keep it "unsettled". Eq. 10
    is used when the overshoot stands out of the noise (4 sigma), else eq. 9. Eq. 9 rests on
    t_s = 4 / (zeta wn), the 2 % envelope; the last exit from the band comes earlier, so eq. 9
    overestimates zeta of an underdamped response.
    """
    t = as_1d(t_s, "t_s")
    y = as_1d(y, "y")
    n = same_length(t_s=t, y=y, **({"u": as_1d(u, "u")} if u is not None else {}))
    if n < 20:
        raise UserError(f"too few samples for a step response: {n} (need at least 20)")
    require_finite(t, "t_s")
    require_finite(y, "y")
    u_step = float(u_step)
    if not math.isfinite(u_step) or u_step == 0:
        raise UserError(f"u_step: expected a nonzero step size, got {u_step!r}")
    dts = np.diff(t)
    if np.any(dts <= 0):
        raise UserError("t_s: sample times must increase")
    dt = float(np.median(dts))

    # -- the step: onset k0 (last sample before the response), end of its hold k_end ------------
    k_end = n
    weights = np.ones(1)
    taus = np.zeros(1)
    corrected = False
    if u is not None:
        ua = as_1d(u, "u")
        require_finite(ua, "u")
        m = max(3, min(n // 20, 50))
        base_u = float(np.median(ua[:m]))
        noise_u = robust_std(np.diff(ua[:m])) / math.sqrt(2)
        moved = np.abs(ua - base_u) > max(1e-3 * abs(u_step), 5 * noise_u)
        if t_step_s is not None:
            k0 = int(np.searchsorted(t, float(t_step_s) - 1e-6 * dt))
        elif not moved.any():
            raise UserError("no step found in u: the input never changes")
        else:
            k0 = int(np.argmax(moved))
        if k0 < 1 or k0 >= n - 10:
            raise UserError("the step must come after the first sample and leave at least 10 samples of its hold")
        base_u = float(np.median(ua[max(0, k0 - 20):k0]))
        target = base_u + u_step
        near = np.abs(ua[k0:] - target) <= 0.01 * abs(u_step)
        if not near.any():
            # u is another signal than the command (e.g. the hysteresis output): its own level
            target = float(np.median(ua[k0:k0 + max(10, (n - k0) // 10)]))
            if abs(target - base_u) <= 1e-3 * max(abs(target), abs(base_u), 1e-300):
                raise UserError("no step found in u: it does not settle at a new level after the change")
            near = np.abs(ua[k0:] - target) <= 0.01 * abs(target - base_u)
        k1 = k0 + int(np.argmax(near))
        away = ~near[k1 - k0:]
        if away.any():
            k_end = k1 + int(np.argmax(away))
        du = np.diff(ua[k0 - 1:k1 + 1])
        if np.sum(du) != 0 and k1 > k0:
            weights = du / np.sum(du)
            taus = t[k0:k1 + 1] - t[k0]
            corrected = True
    elif t_step_s is not None:
        k0 = int(np.searchsorted(t, float(t_step_s) - 1e-6 * dt))
        if k0 < 1 or k0 >= n - 10:
            raise UserError(f"t_step_s = {t_step_s!r} s leaves no baseline or fewer than 10 samples after the step")
    else:
        k0 = _detect_onset(y)
        if k0 < 1:
            raise UserError("no step found: the output changes from the first sample, so there is no baseline")
    if t_end_s is not None:
        k_end = min(k_end, int(np.searchsorted(t, float(t_end_s), side="right")))
    t_step = float(t[k0]) if (u is not None or t_step_s is None) else float(t_step_s)
    detected = u is None and t_step_s is None
    y0 = float(np.median(y[max(0, k0 - max(10, k0 // 2)):k0 + 1]))

    # -- the settled level; cut a later return step seen in the output alone ----------------------
    def settled(hi: int) -> tuple[float, float]:
        seg = y[k0 + 1 + int(0.7 * (hi - k0 - 1)):hi]
        return float(np.median(seg)), robust_std(seg)

    if k_end - k0 < 10:
        raise UserError(f"too few samples in the step's hold: {k_end - k0} (need at least 10)")
    y_ss, noise = settled(k_end)
    if u is None and t_end_s is None:
        # A return step (back past 25 % of the step) or a further rise above the first peak ends the hold.
        delta = y_ss - y0
        r_all = (y[k0:k_end] - y0) / delta if delta != 0 else np.zeros(k_end - k0)
        kp = int(np.argmax(r_all[: max(2, (k_end - k0) // 2)]))
        noise_r = abs(noise / delta) if delta != 0 else math.inf
        later = np.arange(r_all.size) > kp
        out = later & ((r_all < 0.25) | (r_all > r_all[kp] + 6 * noise_r + 0.02))
        if out.any():
            k_end = k0 + int(np.argmax(out))
            while k_end > k0 + 10 and abs(r_all[k_end - k0 - 1] - 1) > 0.5:
                k_end -= 1
            y_ss, noise = settled(k_end)
    delta = y_ss - y0
    if delta == 0 or abs(delta) < 5 * noise:
        raise UserError(
            f"no step found in the output: the change {delta:.3g} is within the noise ({noise:.3g}); "
            "check u_step, t_step_s and the output channel"
        )
    gain = delta / u_step
    noise_r = abs(noise / delta)
    if detected:
        t_step = _refine_onset(t, (y - y0) / delta, k0, k_end, noise_r, t_step)

    tt = t[k0:k_end] - t_step
    r = (y[k0:k_end] - y0) / delta  # normalised response: 0 before, 1 settled
    n_hold = r.size

    # -- peak: a parabola first, then the local damped-sinusoid fit --------------------------------
    search = slice(1, max(3, int(0.7 * n_hold)))
    kmax = 1 + int(np.argmax(r[search]))
    hw_s = max(dt, 0.1 * tt[kmax])
    pk = _local_extremum(tt, r, tt[kmax], hw_s, True, dt)
    tp_m, rp = pk if pk is not None else (float(tt[kmax]), float(r[kmax]))
    os_m = rp - 1.0
    n_pts = max(3, 2 * int(round(hw_s / dt)) + 1)
    os_threshold = max(0.002, 4 * noise_r)
    # A true overshoot comes down again below the settled level, and peaks early: an underdamped
    # second-order response peaks at most twice the time it takes to first reach the settled level.
    after = r[kmax:]
    reach = np.nonzero(moving_average(r, max(1, n_pts // 2)) >= 1.0)[0]
    t_reach = float(tt[reach[0]]) if reach.size else math.inf
    overshoot_measurable = bool(os_m > os_threshold and after.size > 2 and np.min(after) < 1 + 0.5 * os_m
                                and tp_m <= 2.2 * max(t_reach, dt))
    if not overshoot_measurable:
        os_m = max(os_m, 0.0)
    t_last_change = float(taus[-1]) if corrected else 0.0

    def ideal(tp_meas: float, os_meas: float) -> tuple[float, float, float, float, float, float]:
        """eq. 10 on the measured peak, corrected for the input transition:
        (zeta, wn, tp, os, phi, c) with the measured oscillation = c x ideal(t + phi / wd)."""
        zeta, wn = zeta_wn_from_overshoot(os_meas, tp_meas)
        tp, os_, phi, c = tp_meas, os_meas, 0.0, 1.0
        if not corrected or not math.isfinite(zeta):
            return zeta, wn, tp, os_, phi, c
        for _ in range(200):
            sigma, wd = zeta * wn, wn * math.sqrt(1 - zeta**2)
            F = complex(np.sum(weights * np.exp(-complex(-sigma, wd) * taus)))
            phi = math.atan2(F.imag, F.real)
            c = abs(F) * math.exp(sigma * phi / wd)
            tp_new, os_new = tp_meas + phi / wd, os_meas / c if c > 0 else math.nan
            if not (0 < os_new < 1 and tp_new > 0):
                return math.nan, math.nan, tp, os_, phi, c
            z_new, w_new = zeta_wn_from_overshoot(os_new, tp_new)
            done = abs(z_new - zeta) < 1e-13 and abs(w_new - wn) < 1e-12 * wn
            zeta, wn, tp, os_ = z_new, w_new, tp_new, os_new
            if done:
                break
        return zeta, wn, tp, os_, phi, c

    zeta10 = wn10 = math.nan
    tp, os_, phi, c_osc = tp_m, os_m, 0.0, 1.0
    if overshoot_measurable:
        for _ in range(4):
            zeta10, wn10, tp, os_, phi, c_osc = ideal(tp_m, os_m)
            if not math.isfinite(zeta10):
                break
            sigma, wd = zeta10 * wn10, wn10 * math.sqrt(1 - zeta10**2)
            ex = _damped_extremum(tt, r, tp_m, sigma, wd, True, t_last_change)
            if ex is None:
                break
            tp_m, os_m = ex[0], ex[1] - 1.0
        zeta10, wn10, tp, os_, phi, c_osc = ideal(tp_m, os_m)

    # -- settling time: the last exit from the 2 % band ---------------------------------------------
    band = SETTLING_BAND

    def rising_crossing(level: float, upto: int) -> float:
        rs = moving_average(r, max(1, int(round(0.01 * n_hold))))
        below = np.nonzero(rs[: upto + 1] < level)[0]
        if below.size == 0:
            return float(tt[0])
        k = int(below[-1])
        if k + 1 >= rs.size:
            return float(tt[k])
        frac = (level - rs[k]) / (rs[k + 1] - rs[k]) if rs[k + 1] != rs[k] else 0.0
        return float(tt[k] + np.clip(frac, 0, 1) * (tt[k + 1] - tt[k]))

    if overshoot_measurable and math.isfinite(zeta10):
        sigma, wd = zeta10 * wn10, wn10 * math.sqrt(1 - zeta10**2)
        half = math.pi / wd
        extrema = [(tp_m, os_m)]
        want_max = False
        centre = tp_m + half
        fit_noise = noise_r / math.sqrt(max(1.0, 0.7 * half / dt))
        while centre < tt[-1]:
            ex = _damped_extremum(tt, r, centre, sigma, wd, want_max, t_last_change)
            if ex is None:
                ex = _local_extremum(tt, r, centre, 0.3 * half, want_max, dt)
            if ex is None:
                break
            te, ve = ex
            d = ve - 1.0
            if (d > 0) != want_max or abs(d) <= 3 * fit_noise:
                break
            extrema.append((te, abs(d)))
            centre = te + half
            want_max = not want_max
        times = np.array([e[0] for e in extrema])
        amps = np.array([e[1] for e in extrema])
        decay = -float(np.polyfit(times, np.log(amps), 1)[0]) if amps.size >= 2 and np.all(amps > 0) else math.nan
        if not decay > 0:
            decay = sigma
        outside = np.nonzero(amps > band)[0]
        if outside.size:
            k = int(outside[-1])
            t_k, a_k = float(times[k]), float(amps[k])

            def env(tau: float) -> float:
                return a_k * math.exp(-decay * tau) * abs(math.cos(math.pi * tau / half)) - band

            ts_m = t_k + (optimize.brentq(env, 0.0, 0.5 * half) if env(0.5 * half) < 0 else 0.5 * half)
        else:
            ts_m = rising_crossing(1 - band, kmax)
        # the settling of the equivalent ideal step: its envelope is 1 / c and shifted by phi / wd
        ts = ts_m + phi / wd - (math.log(c_osc) / sigma if c_osc > 0 and sigma > 0 else 0.0)
    else:
        overshoot_measurable = False
        ts_m = rising_crossing(1 - band, n_hold - 1)
        rs = moving_average(r, max(1, int(round(0.02 * n_hold))))
        tp_m = float(tt[int(np.argmax(rs))])
        centroid = float(np.sum(weights * taus)) if corrected else 0.0
        tp, ts, os_ = tp_m - centroid, ts_m - centroid, os_m

    if overshoot_measurable:
        zeta10, wn10 = zeta_wn_from_overshoot(os_, tp)
    zeta9, wn9 = zeta_wn_from_times(tp, ts)
    used = "eq10" if overshoot_measurable and math.isfinite(zeta10) else "eq9"
    zeta, wn = (zeta10, wn10) if used == "eq10" else (zeta9, wn9)
    if not (math.isfinite(zeta) and math.isfinite(wn)):
        raise UserError("the step response gives no peak and settling time to read zeta and omega_n from; "
                        "is the hold long enough for the response to settle?")
    return StepIdentification(
        gain=float(gain), zeta=float(zeta), wn_rad_s=float(wn), used=used,
        zeta_eq10=float(zeta10), wn_eq10_rad_s=float(wn10), zeta_eq9=float(zeta9), wn_eq9_rad_s=float(wn9),
        y0=y0, y_ss=y_ss, u_step=u_step, t_step_s=t_step,
        peak_time_s=float(tp), peak_value=float(y0 + delta * (1 + os_m)) if overshoot_measurable else float(y_ss),
        overshoot=float(os_), settling_time_s=float(ts),
        measured_peak_time_s=float(tp_m), measured_overshoot=float(os_m), measured_settling_time_s=float(ts_m),
        noise_std=float(noise), input_corrected=corrected, overshoot_measurable=overshoot_measurable,
    )
