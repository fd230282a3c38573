"""numba kernels of the simulated plant: one sample loop, explicit state, caller-provided outputs.

One per-sample function, :func:`plant_step`, is the body of the block kernel :func:`plant_block`
(whole arrays, offline simulation and sweeps) and serves step mode directly (the runner's per-sample
loop, or a closed loop compiled with numba): state lives in arrays the caller owns, so a block of n
samples and n single steps give identical results.

Signal chain per sample (each stage switchable, see :mod:`hilbench.sim.plant` for parameters):

    command -> amplifier (gain, bandwidth, slew, output limit) -> delay -> normalise (input_scale)
      -> input shaping (fractional polynomial, FPMPI)            [saturation at the input]
      -> hysteresis (M-play family: play / one-sided / M-play, ISSF-Duhem, Preisach relays or
         Bouc-Wen) + asymmetry polynomial
      -> saturation (tanh) -> rate-dependence (m-th power velocity damping, 003)
      -> output_scale (um) x temperature gain x load gain -> creep (Kelvin-Voigt chain)
      -> - load compliance -> dynamics (IIR, direct form II transposed) -> + thermal strain
      -> sensor (noise, quantisation, range)

Branch-free min/max in the operator loop; the time loop is outermost.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# -- indices into the scalar parameter vector S --------------------------------------------------
S_AMP_ON = 0
S_AMP_GAIN = 1
S_AMP_ALPHA = 2  # first-order low-pass coefficient per sample (1 = no filter)
S_AMP_SLEW = 3  # max change per sample (inf = none)
S_AMP_LO = 4
S_AMP_HI = 5
S_INPUT_SCALE = 6
S_MODEL = 7  # 0 linear, 1 M-play family (PI), 2 ISSF-Duhem, 3 Preisach, 4 Bouc-Wen
S_P0 = 8  # linear term of the PI family
S_DUHEM_ALPHA = 9
S_DUHEM_BETA = 10
S_DUHEM_SHAPE = 11  # 0 none (z = w), 1 Gompertz (G), 2 modified tanh (M), 3 dead-zone (D)
S_DUHEM_K1 = 12
S_DUHEM_K2 = 13
S_MU_A = 14  # mu1 or mu3
S_MU_B = 15  # mu2 or mu4
S_SAT_LEVEL = 16  # 0 = no saturation
S_RATE_MODE = 17  # 0 off, 1 fixed damping, 2 frequency polynomials (003)
S_RATE_K = 18
S_RATE_C = 19
S_RATE_M = 20
S_RATE_Q = 21  # reference rate, normalised input units per s
S_OUT_SCALE = 22
S_TEMP_ON = 23
S_TEMP_REF = 24
S_TEMP_GAIN = 25  # relative gain change per degC
S_TEMP_STRAIN = 26  # um per degC
S_LOAD_ON = 27
S_LOAD_GAIN = 28  # relative gain change per N
S_LOAD_COMPLIANCE = 29  # um per N
S_NOISE_STD = 30
S_QUANT = 31
S_RANGE_LO = 32
S_RANGE_HI = 33
S_RANGE_NAN = 34  # 1: out-of-range readings are NaN, 0: clipped to the range
S_FS = 35
S_DYN_ON = 36
S_DELAY = 37  # samples
S_BW_A = 38  # Bouc-Wen A (z per normalised input unit)
S_BW_BETA = 39
S_BW_GAMMA = 40
S_BW_N = 41
S_BW_DU_MAX = 42  # largest input change of one Bouc-Wen sub-step (see bouc_wen_step)
S_BW_W = 43  # weight of z in the output: +1 y = k u + z, -1 the piezo form y = k u - z
N_SCALARS = 44

# -- indices into the scalar state vector X ------------------------------------------------------
X_AMP_Y = 0
X_V_PREV = 1  # previous normalised input (Duhem, rate)
X_DUHEM_W = 2
X_RATE_V_PREV = 3
X_BW_Z = 4  # Bouc-Wen hysteretic state z
X_DELAY_IDX = 9
X_N = 10  # samples processed
X_STARTED = 11
N_STATES = 12


@njit(cache=True, inline="always")
def sgnpow(x: float, e: float) -> float:
    """sgn(x) |x|^e with 0^0 = 1 (the terms of the fractional polynomial, 000 eq. 4-5).

    The exponents of 000 (0, 1, 2, 3, 4, 1/2, 1/4) take fast paths of multiplications and square
    roots: pow costs ~15 ns, and the plant and the online chain evaluate eight terms per sample.
    They agree with pow to the last bit or two (sqrt and products are correctly rounded)."""
    if e == 0.0:
        return 1.0
    a = abs(x)
    if e == 1.0:
        p = a
    elif e == 2.0:
        p = a * a
    elif e == 3.0:
        p = a * a * a
    elif e == 4.0:
        p = (a * a) * (a * a)
    elif e == 0.5:
        p = math.sqrt(a)
    elif e == 0.25:
        p = math.sqrt(math.sqrt(a))
    else:
        p = a**e
    return p if x >= 0.0 else -p


@njit(cache=True, inline="always")
def _poly(c: np.ndarray, x: float) -> float:
    acc = 0.0
    for k in range(c.shape[0] - 1, -1, -1):
        acc = acc * x + c[k]
    return acc


# -- turning-point estimate of the drive frequency (003 rate-dependence) ---------------------------
TP_V1 = 0  # previous input
TP_V2 = 1  # input two samples back
TP_DIR = 2  # +1 rising, -1 falling, 0 unknown
TP_TURN_V = 3  # input at the last turning point
TP_TURN_T = 4  # time of the last turning point, samples (sub-sample)
TP_F = 5  # estimated frequency, Hz
TP_A = 6  # estimated amplitude (half the mean excursion of the last two half cycles)
TP_N = 7  # samples seen
TP_HALF = 8  # duration of the last half cycle, s (0 before the first)
TP_EXC = 9  # excursion of the last half cycle, input unit
N_TP = 10


@njit(cache=True, inline="always")
def turning_point_update(st: np.ndarray, v: float, fs: float) -> None:
    """Update the drive frequency/amplitude estimate with one input sample.

    At each reversal of the input the turning point is located to a fraction of a sample by a
    parabola through the three samples around it (so the estimate does not jump by a whole sample
    period at high drive frequencies). The period is measured as a frequency counter does, between
    turning points of the same kind (maximum to maximum, minimum to minimum): f = 1 / (the last two
    half periods), A = a quarter of their two excursions. A single half period would read a step
    between two segments (the input falls for a sample or two, then rises on) as a drive near
    fs / 2 held until the next reversal, and an unsymmetric wave (a sawtooth) as two
    alternating frequencies; the full cycle holds the true half period on each side of such a
    pair, so a cycle cut by a junction reads at most a few times fast. Until a whole cycle is seen
    f = 0 (the rate-independent loop, k(0)), and the start of motion from rest is not a turning
    point: the input did not reverse there (a first step and the drive after it read as a
    one-sample half cycle).
    """
    n = st[TP_N]
    if n == 0.0:
        st[TP_V1] = v
        st[TP_V2] = v
        st[TP_TURN_V] = v
        st[TP_TURN_T] = -1.0  # no turning point yet
    dv = v - st[TP_V1]
    d = 1.0 if dv > 0.0 else (-1.0 if dv < 0.0 else 0.0)
    if d != 0.0 and d != st[TP_DIR]:
        a, b, c = st[TP_V2], st[TP_V1], v  # the extremum is near the previous sample
        den = a - 2.0 * b + c
        delta = 0.0
        peak = b
        if n >= 2.0 and den != 0.0:
            delta = min(max(0.5 * (a - c) / den, -0.5), 0.5)
            peak = b - 0.25 * (a - c) * delta
        t_turn = n - 1.0 + delta
        if st[TP_DIR] != 0.0 and st[TP_TURN_T] >= 0.0:
            half = (t_turn - st[TP_TURN_T]) / fs
            if half > 0.0:
                exc = abs(peak - st[TP_TURN_V])
                if st[TP_HALF] > 0.0:
                    st[TP_F] = 1.0 / (half + st[TP_HALF])
                    st[TP_A] = 0.25 * (exc + st[TP_EXC])
                st[TP_HALF] = half
                st[TP_EXC] = exc
        if st[TP_DIR] != 0.0:
            st[TP_TURN_V] = peak
            st[TP_TURN_T] = t_turn
        st[TP_DIR] = d
    st[TP_V2] = st[TP_V1]
    st[TP_V1] = v
    st[TP_N] = n + 1.0


@njit(cache=True)
def mplay_block(v: np.ndarray, r: np.ndarray, eta: np.ndarray, state: np.ndarray, out: np.ndarray) -> None:
    """M-play operator outputs (004 eq. 6) for every sample: out[n, i] = max(v - r_i, min(v + eta_i r_i, w_i)).

    eta = 1 gives the play (backlash) operator, eta = 0 the one-sided play operator (000 eq. 1,
    003 eq. 2). The one-sided play with threshold r is the play with threshold r/2 shifted down
    by r/2, F1_r[v] = F_{r/2}[v] - r/2, once the input has risen above r (before that the two
    differ only by their initial states). ``state`` holds each operator's last output and is
    updated in place.
    """
    for n in range(v.shape[0]):
        x = v[n]
        for i in range(r.shape[0]):
            w = min(x + eta[i] * r[i], state[i])
            w = max(x - r[i], w)
            state[i] = w
            out[n, i] = w


@njit(cache=True)
def duhem_w_block(u: np.ndarray, alpha: float, beta: float, state: np.ndarray, out: np.ndarray) -> None:
    """Inertial-system Duhem state w (001 eq. 17), exact for an input linear between samples.

    dw/du = beta u - alpha w on rising input, alpha w - beta u on falling input; state = [w, u_prev].
    """
    w = state[0]
    u_prev = state[1]
    ba = beta / alpha
    for n in range(u.shape[0]):
        du = u[n] - u_prev
        if du != 0.0:
            s = 1.0 if du > 0.0 else -1.0
            w_eq_prev = ba * u_prev - s * ba / alpha
            w_eq = ba * u[n] - s * ba / alpha
            w = w_eq + (w - w_eq_prev) * math.exp(-alpha * abs(du))
        u_prev = u[n]
        out[n] = w
    state[0] = w
    state[1] = u_prev


@njit(cache=True, inline="always")
def _bw_slope(z: float, h: float, ah: float, a: float, beta: float, gamma: float, n: float) -> float:
    """dz over an input change h (|h| = ah): A h - beta |h| |z|^(n-1) z - gamma h |z|^n."""
    az = abs(z)
    if n == 1.0:
        return a * h - beta * ah * z - gamma * h * az
    azn1 = az ** (n - 1.0)
    return a * h - beta * ah * azn1 * z - gamma * h * azn1 * az


@njit(cache=True, inline="always")
def bouc_wen_step(z: float, du: float, a: float, beta: float, gamma: float, n: float, du_max: float) -> float:
    """Bouc-Wen z after an input change du: z' = A u' - beta |u'| |z|^(n-1) z - gamma u' |z|^n.

    The equation is rate independent (dz/du depends on the sign of du only), so it is integrated over
    the input, classic RK4 in ceil(|du| / du_max) equal sub-steps: du_max = 0.25 / L with L the
    largest slope of dz/du in z over |z| <= z_max (:func:`bouc_wen_du_max`), so a sub-step is
    well inside RK4's stability limit (|h L| < 2.78) and its error (h L)^5 is negligible; a
    full-range step of the drive then takes a few dozen sub-steps, a smooth drive one.
    """
    if du == 0.0:
        return z
    m = min(int(abs(du) / du_max) + 1, 100000)
    h = du / m
    ah = abs(h)
    for _ in range(m):
        k1 = _bw_slope(z, h, ah, a, beta, gamma, n)
        k2 = _bw_slope(z + 0.5 * k1, h, ah, a, beta, gamma, n)
        k3 = _bw_slope(z + 0.5 * k2, h, ah, a, beta, gamma, n)
        k4 = _bw_slope(z + k3, h, ah, a, beta, gamma, n)
        z += (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0
    return z


def bouc_wen_z_max(a: float, beta: float, gamma: float, n: float) -> float:
    """The bound of |z| from rest, (A / (beta + gamma))^(1/n) (beta >= |gamma|, beta + gamma > 0)."""
    return (a / (beta + gamma)) ** (1.0 / n)


def bouc_wen_du_max(a: float, beta: float, gamma: float, n: float) -> float:
    """Sub-step of :func:`bouc_wen_step`: 0.25 / L, L = n (beta + |gamma|) z_max^(n-1) bounds
    |d(dz/du)/dz| for |z| <= z_max."""
    slope = n * (beta + abs(gamma)) * bouc_wen_z_max(a, beta, gamma, n) ** (n - 1.0)
    return 0.25 / slope


@njit(cache=True, inline="always")
def _shape(S: np.ndarray, dz_r: np.ndarray, dz_g: np.ndarray, w: float) -> float:
    shape = S[S_DUHEM_SHAPE]
    if shape == 1.0:  # Gompertz, 001 eq. 20
        return 2.0 * math.exp(-math.exp(-S[S_MU_A] * w - S[S_MU_B])) - 2.0 * math.exp(-math.exp(-S[S_MU_B]))
    if shape == 2.0:  # modified tanh, 001 eq. 24
        return 2.0 * math.tanh(-math.exp(-S[S_MU_A] * w - S[S_MU_B])) - 2.0 * math.tanh(-math.exp(-S[S_MU_B]))
    if shape == 3.0:  # one-sided dead-zone operators, 001 eq. 26-27
        z = 0.0
        for i in range(dz_r.shape[0]):
            ri = dz_r[i]
            if ri > 0.0:
                z += dz_g[i] * max(w - ri, 0.0)
            elif ri < 0.0:
                z += dz_g[i] * min(w - ri, 0.0)
            else:
                z += dz_g[i] * w
        return z
    return w


# Refcounting: numba increfs and decrefs every array argument of a non-inlined call, and in a
# function this branchy the pruner keeps them: 44 atomic operations, ~250 ns per sample. So the step
# is inlined (numba IR) into its callers, and the kernels that call it run without NRT (_nrt=False:
# they allocate nothing, the caller owns every array), which makes the block kernel as fast as a
# hand-written loop (14 ns/sample). A compiled closed loop calling plant_step should do the same.
# The kernels use numpy's error model: the inlined step's divisions then skip the zero test that
# Python's model adds to raise ZeroDivisionError (its divisors are checked when the plant is built).
@njit(cache=True, inline="always", _nrt=False)
def plant_step(
    u: float,
    temperature: float,
    load: float,
    noise: float,
    S: np.ndarray,
    in_exp: np.ndarray,
    in_w: np.ndarray,
    op_r: np.ndarray,
    op_w: np.ndarray,
    op_eta: np.ndarray,
    relay_a: np.ndarray,
    relay_b: np.ndarray,
    asym: np.ndarray,
    dz_r: np.ndarray,
    dz_g: np.ndarray,
    rate_kp: np.ndarray,
    rate_cp: np.ndarray,
    rate_mp: np.ndarray,
    creep_g: np.ndarray,
    creep_a: np.ndarray,
    dyn_b: np.ndarray,
    dyn_a: np.ndarray,
    X: np.ndarray,
    op_state: np.ndarray,
    creep_state: np.ndarray,
    dyn_state: np.ndarray,
    delay_buf: np.ndarray,
    tp_state: np.ndarray,
) -> tuple[float, float, float]:
    """One sample of the plant: returns (measured output um, true output um, drive).

    ``temperature`` (degC) and ``load`` (N) are read only when their stage is on; ``noise`` is the
    output sensor's standard-normal draw for this sample. State arrays are updated in place; callable
    from other njit code (a fused closed loop) and the body of :func:`plant_block`.
    """
    fs = S[S_FS]
    n_ops = op_r.shape[0]
    n_in = in_exp.shape[0]
    n_creep = creep_g.shape[0]
    n_dyn = dyn_state.shape[0]
    delay = int(S[S_DELAY])
    model = S[S_MODEL]
    # -- amplifier ---------------------------------------------------------------------
    drive = u
    if S[S_AMP_ON] != 0.0:
        target = min(max(S[S_AMP_GAIN] * drive, S[S_AMP_LO]), S[S_AMP_HI])
        y_amp = X[X_AMP_Y]
        if X[X_STARTED] == 0.0:
            y_amp = target
        step = S[S_AMP_ALPHA] * (target - y_amp)
        step = min(max(step, -S[S_AMP_SLEW]), S[S_AMP_SLEW])
        y_amp += step
        X[X_AMP_Y] = y_amp
        drive = y_amp
    out_drive = drive
    # -- pure delay (ring buffer of `delay` samples) --------------------------------------
    if delay > 0:
        idx = int(X[X_DELAY_IDX])
        if X[X_STARTED] == 0.0:
            for k in range(delay):
                delay_buf[k] = drive
        delayed = delay_buf[idx]
        delay_buf[idx] = drive
        X[X_DELAY_IDX] = (idx + 1) % delay
        drive = delayed
    v = drive / S[S_INPUT_SCALE]
    if X[X_STARTED] == 0.0:
        X[X_V_PREV] = v
        X[X_RATE_V_PREV] = v
        X[X_STARTED] = 1.0
    # -- input shaping: fractional polynomial (000 eq. 4-5) --------------------------------
    vs = v
    if n_in > 0:
        vs = 0.0
        for k in range(n_in):
            vs += in_w[k] * sgnpow(v, in_exp[k])
    # -- hysteresis ---------------------------------------------------------------------
    if model == 1.0:
        h = S[S_P0] * vs
        for i in range(n_ops):
            w = min(vs + op_eta[i] * op_r[i], op_state[i])
            w = max(vs - op_r[i], w)
            op_state[i] = w
            h += op_w[i] * w
    elif model == 2.0:
        alpha = S[S_DUHEM_ALPHA]
        ba = S[S_DUHEM_BETA] / alpha
        du = vs - X[X_V_PREV]
        wd = X[X_DUHEM_W]
        if du != 0.0:
            s = 1.0 if du > 0.0 else -1.0
            wd = ba * vs - s * ba / alpha + (wd - (ba * X[X_V_PREV] - s * ba / alpha)) * math.exp(-alpha * abs(du))
            X[X_DUHEM_W] = wd
        h = S[S_DUHEM_K1] * vs + S[S_DUHEM_K2] * _shape(S, dz_r, dz_g, wd)
    elif model == 3.0:
        # Preisach: relay hysterons (up at alpha_i = relay_a, down at beta_i = relay_b <= alpha_i),
        # states +-1 in op_state, weights op_w
        h = S[S_P0] * vs
        for i in range(relay_a.shape[0]):
            r = op_state[i]
            r = 1.0 if vs >= relay_a[i] else r
            r = -1.0 if vs <= relay_b[i] else r
            op_state[i] = r
            h += op_w[i] * r
    elif model == 4.0:
        z = bouc_wen_step(X[X_BW_Z], vs - X[X_V_PREV], S[S_BW_A], S[S_BW_BETA], S[S_BW_GAMMA], S[S_BW_N],
                          S[S_BW_DU_MAX])
        X[X_BW_Z] = z
        h = S[S_P0] * vs + S[S_BW_W] * z
    else:
        h = S[S_P0] * vs
    X[X_V_PREV] = vs
    if asym.shape[0] > 0:
        h += _poly(asym, v)
    # -- saturation ---------------------------------------------------------------------
    if S[S_SAT_LEVEL] > 0.0:
        h = S[S_SAT_LEVEL] * math.tanh(h / S[S_SAT_LEVEL])
    # -- rate-dependence: m-th power velocity damping (003 eq. 6-10) -------------------------
    rate_mode = S[S_RATE_MODE]
    if rate_mode != 0.0:
        vdot = (v - X[X_RATE_V_PREV]) * fs
        X[X_RATE_V_PREV] = v
        k_gain = S[S_RATE_K]
        c = S[S_RATE_C]
        m = S[S_RATE_M]
        q = S[S_RATE_Q]
        if rate_mode == 2.0:
            # The drive frequency and amplitude are estimated from the last cycle between
            # turning points, as a bench would see them; k(f), c(f), m(f) follow 003 eq. 13.
            turning_point_update(tp_state, v, fs)
            f = tp_state[TP_F]
            k_gain = _poly(rate_kp, f)
            c = _poly(rate_cp, f)
            m = _poly(rate_mp, f)
            q = 2.0 * math.pi * f * tp_state[TP_A]
        h = k_gain * h
        if q > 0.0 and vdot != 0.0:
            mag = abs(vdot / q) ** m
            h += c * mag if vdot > 0.0 else -c * mag
    # -- scale to output units, temperature and load gains ----------------------------------
    h *= S[S_OUT_SCALE]
    temp = 0.0
    if S[S_TEMP_ON] != 0.0:
        temp = temperature - S[S_TEMP_REF]
        h *= 1.0 + S[S_TEMP_GAIN] * temp
    force = 0.0
    if S[S_LOAD_ON] != 0.0:
        force = load
        h *= 1.0 - S[S_LOAD_GAIN] * force
    # -- creep: Kelvin-Voigt chain driven by the hysteresis output ----------------------------
    for k in range(n_creep):
        creep_state[k] += creep_a[k] * (creep_g[k] * h - creep_state[k])
    for k in range(n_creep):
        h += creep_state[k]
    h -= S[S_LOAD_COMPLIANCE] * force
    # -- linear dynamics, direct form II transposed (scipy.signal.lfilter convention) ------
    y = h
    if S[S_DYN_ON] != 0.0:
        y = dyn_b[0] * h + dyn_state[0]
        for k in range(n_dyn - 1):
            dyn_state[k] = dyn_b[k + 1] * h + dyn_state[k + 1] - dyn_a[k + 1] * y
        dyn_state[n_dyn - 1] = dyn_b[n_dyn] * h - dyn_a[n_dyn] * y
    y += S[S_TEMP_STRAIN] * temp
    # -- sensor -------------------------------------------------------------------------
    meas = y + S[S_NOISE_STD] * noise
    if S[S_QUANT] > 0.0:
        meas = S[S_QUANT] * math.floor(meas / S[S_QUANT] + 0.5)
    if meas < S[S_RANGE_LO] or meas > S[S_RANGE_HI]:
        if S[S_RANGE_NAN] != 0.0:
            meas = math.nan
        else:
            meas = min(max(meas, S[S_RANGE_LO]), S[S_RANGE_HI])
    X[X_N] += 1.0
    return meas, y, out_drive


@njit(cache=True, _nrt=False, error_model="numpy")
def plant_block(
    u: np.ndarray,
    temperature: np.ndarray,
    load: np.ndarray,
    noise: np.ndarray,
    S: np.ndarray,
    in_exp: np.ndarray,
    in_w: np.ndarray,
    op_r: np.ndarray,
    op_w: np.ndarray,
    op_eta: np.ndarray,
    relay_a: np.ndarray,
    relay_b: np.ndarray,
    asym: np.ndarray,
    dz_r: np.ndarray,
    dz_g: np.ndarray,
    rate_kp: np.ndarray,
    rate_cp: np.ndarray,
    rate_mp: np.ndarray,
    creep_g: np.ndarray,
    creep_a: np.ndarray,
    dyn_b: np.ndarray,
    dyn_a: np.ndarray,
    X: np.ndarray,
    op_state: np.ndarray,
    creep_state: np.ndarray,
    dyn_state: np.ndarray,
    delay_buf: np.ndarray,
    tp_state: np.ndarray,
    out_measured: np.ndarray,
    out_true: np.ndarray,
    out_drive: np.ndarray,
) -> None:
    """Simulate n = len(u) samples of the plant; see the module docstring for the chain."""
    temp_on = S[S_TEMP_ON] != 0.0
    load_on = S[S_LOAD_ON] != 0.0
    for n in range(u.shape[0]):
        meas, y, drive = plant_step(
            u[n], temperature[n] if temp_on else 0.0, load[n] if load_on else 0.0, noise[n],
            S, in_exp, in_w, op_r, op_w, op_eta, relay_a, relay_b, asym, dz_r, dz_g, rate_kp, rate_cp, rate_mp, creep_g, creep_a,
            dyn_b, dyn_a, X, op_state, creep_state, dyn_state, delay_buf, tp_state,
        )
        out_measured[n] = meas
        out_true[n] = y
        out_drive[n] = drive


#: The plant's parameter and state arrays in :func:`plant_step` order, plus ``out`` (true output,
#: drive of the last step); :class:`hilbench.sim.plant.Plant` keeps them as views of one flat
#: buffer so that step mode passes two arrays instead of twenty-four (each array argument of a
#: numba call from Python costs about 50 ns to unbox). The first N_PARAM_ARRAYS are parameters.
PLANT_ARRAYS = (
    "S", "in_exp", "in_w", "op_r", "op_w", "op_eta", "relay_a", "relay_b", "asym", "dz_r", "dz_g", "rate_kp", "rate_cp", "rate_mp",
    "creep_g", "creep_a", "dyn_b", "dyn_a", "X", "op_state", "creep_state", "dyn_state", "delay_buf", "tp_state",
    "out",
)
N_PARAM_ARRAYS = 18
#: rows of the per-sample inputs of :func:`plant_step_flat`
B_NOISE = 0
B_TEMPERATURE = 1
B_LOAD = 2


@njit(cache=True, inline="always")
def _view(F: np.ndarray, L: np.ndarray, k: int) -> np.ndarray:
    return F[L[2 * k] : L[2 * k + 1]]


@njit(cache=True, inline="always")
def plant_views(F: np.ndarray, L: np.ndarray) -> tuple:
    """The 24 parameter and state arrays of :func:`plant_step` as views of the flat buffer ``F``
    (array k is ``F[L[2k]:L[2k+1]]``, see :data:`PLANT_ARRAYS`). A compiled loop takes them once
    before its time loop: built per sample they cost ~35 ns (the offsets are reloaded every time,
    since the compiler cannot rule out that writes to F change L)."""
    return (
        _view(F, L, 0), _view(F, L, 1), _view(F, L, 2), _view(F, L, 3), _view(F, L, 4), _view(F, L, 5),
        _view(F, L, 6), _view(F, L, 7), _view(F, L, 8), _view(F, L, 9), _view(F, L, 10), _view(F, L, 11),
        _view(F, L, 12), _view(F, L, 13), _view(F, L, 14), _view(F, L, 15), _view(F, L, 16), _view(F, L, 17),
        _view(F, L, 18), _view(F, L, 19), _view(F, L, 20), _view(F, L, 21), _view(F, L, 22), _view(F, L, 23),
    )


@njit(cache=True, inline="always", _nrt=False)
def plant_step_views(u: float, temperature: float, load: float, noise: float, V: tuple) -> tuple[float, float, float]:
    """:func:`plant_step` with its 24 arrays as the tuple of :func:`plant_views`."""
    return plant_step(
        u, temperature, load, noise, V[0], V[1], V[2], V[3], V[4], V[5], V[6], V[7], V[8], V[9], V[10], V[11],
        V[12], V[13], V[14], V[15], V[16], V[17], V[18], V[19], V[20], V[21], V[22], V[23],
    )


@njit(cache=True, inline="always")
def plant_out_offset(L: np.ndarray) -> int:
    """Where the true output and the drive of the last step sit in the flat buffer (``out``)."""
    return L[48]


@njit(cache=True, _nrt=False, error_model="numpy")
def plant_step_flat(F: np.ndarray, L: np.ndarray, B: np.ndarray, pos: int, u: float) -> float:
    """:func:`plant_step` over the flat buffer ``F`` (array k is ``F[L[2k]:L[2k+1]]``, see
    :data:`PLANT_ARRAYS`) with this sample's noise, temperature and load from column ``pos`` of
    ``B`` (rows :data:`B_NOISE`, :data:`B_TEMPERATURE`, :data:`B_LOAD`). Returns the measured
    output; the true output and the drive go to ``out``."""
    meas, y, drive = plant_step_views(u, B[B_TEMPERATURE, pos], B[B_LOAD, pos], B[B_NOISE, pos], plant_views(F, L))
    o = plant_out_offset(L)
    F[o] = y
    F[o + 1] = drive
    return meas
