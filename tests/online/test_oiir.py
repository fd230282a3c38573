"""OIIR identifier of paper 000 on the simulated gmm-fpmpi rig: regressor indices, front end,
tracking a gain change, guards, block == step.

The data come from the simulated plant's own kernel (``hilbench.sim.kernels.plant_block``) with
the parameters of configs/gmm-fpmpi.toml (000 Table 3 FPMPI, one sample of delay, 40 Hz / zeta 0.6
second-order dynamics, 1 kHz, laser-sensor noise 0.03 um and 0.01 um quantisation) and the plant's
temperature gain switched on: the stroke drops as the actuator cools (000 Fig. 5).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal as sps

from hilbench.models import Model, RunData
from hilbench.online.oiir import OIIR, FPMPIFrontEnd, re_n2_pct, re_ninf_pct
from hilbench.sim import kernels as K

FS = 1000.0
IN_EXP = np.array([0.0, 1.0, 2.0, 0.5, 3.0, 1.0 / 3.0, 4.0, 0.25])
IN_W = np.array([0.0057, 0.4640, 0.2343, -1.0113, 0.5568, 0.7493, -0.9740, 0.4889])
OP_R = np.array([0.0000, 0.0669, 0.1338, 0.2007, 0.2676, 0.3345, 0.4014, 0.4683, 0.5352, 0.6021])
OP_W = np.array([0.3955, 0.2042, 0.4940, 0.3927, 0.7198, 0.1228, 0.1889, 0.1550, 0.2058, -0.0060])
T_REF = 42.5  # degC, 000 Fig. 5
GAIN_PER_DEGC = 0.02  # relative stroke change per degC (42.5 -> 30.4 degC: -24 %)


def dynamics() -> tuple[np.ndarray, np.ndarray]:
    """Second-order 40 Hz, zeta 0.6, unit gain, zero-order hold at 1 kHz (the plant's discretisation)."""
    wn = 2 * math.pi * 40.0
    bd, ad, _ = sps.cont2discrete(([wn**2], [1.0, 2 * 0.6 * wn, wn**2]), 1.0 / FS, method="zoh")
    b, a = np.ravel(bd), np.ravel(ad)
    return b / a[0], a / a[0]


def gmm_plant(u: np.ndarray, temperature_degC: np.ndarray, seed: int = 0) -> np.ndarray:
    """Measured displacement (um) of the simulated gmm-fpmpi actuator for command u (A)."""
    n = u.shape[0]
    S = np.zeros(K.N_SCALARS)
    S[K.S_FS] = FS
    S[K.S_AMP_GAIN] = S[K.S_AMP_ALPHA] = 1.0
    S[K.S_AMP_SLEW] = math.inf
    S[K.S_AMP_LO], S[K.S_AMP_HI] = -math.inf, math.inf
    S[K.S_INPUT_SCALE], S[K.S_OUT_SCALE], S[K.S_MODEL] = 3.0, 37.0, 1.0
    S[K.S_DELAY] = 1
    S[K.S_DYN_ON] = 1.0
    S[K.S_TEMP_ON], S[K.S_TEMP_REF], S[K.S_TEMP_GAIN] = 1.0, T_REF, GAIN_PER_DEGC
    S[K.S_NOISE_STD], S[K.S_QUANT] = 0.03, 0.01
    S[K.S_RANGE_LO], S[K.S_RANGE_HI] = -math.inf, math.inf
    b, a = dynamics()
    e = np.zeros(0)
    out, true, drive = np.empty(n), np.empty(n), np.empty(n)
    K.plant_block(np.ascontiguousarray(u, float), np.ascontiguousarray(temperature_degC, float), e,
                  np.random.default_rng(seed).standard_normal(n), S, IN_EXP, IN_W, OP_R, OP_W,
                  np.zeros(OP_R.size), e, e, e, e, e, np.ones(1), np.zeros(1), np.ones(1), e, e, b, a,
                  np.zeros(K.N_STATES), np.zeros(OP_R.size), e, np.zeros(a.size - 1), np.zeros(1),
                  np.zeros(K.N_TP), out, true, drive)
    return out


@pytest.fixture(scope="module")
def offline_model() -> Model:
    """FPMPI fitted offline (000 sec. 4.1): 0.05 Hz sine, amplitude growing 0.15 -> 1.5 A around
    1.5 A, at the reference temperature. Shape (w_P) at the rig's values, scaled so that the linear
    term is 1 as hilbench's FPMPI fixes it; weights (offset, w_H) by linear least squares."""
    n = 200_000
    t = np.arange(n) / FS
    u = 1.5 - (0.15 + 1.35 * t / t[-1]) * np.cos(2 * np.pi * 0.05 * t)
    y = gmm_plant(u, np.full(n, T_REF), seed=1)
    run = RunData(u, y, {}, FS)
    model = Model("fpmpi")
    model.prepare([run])
    model.set_shape(np.array([w / IN_W[1] for w, e in zip(IN_W, IN_EXP) if e != 1.0]))
    model.finalize([run])
    X, names, _, _ = model.design(run)
    model.weights = np.linalg.lstsq(X, y, rcond=None)[0]
    model.weight_names = names
    assert re_n2_pct(y, model.simulate(run)) < 1.0  # the static fit itself is good
    return model


def test_front_end_is_the_models_fpmpi(offline_model):
    fe = FPMPIFrontEnd.from_model(offline_model)
    t = np.arange(5000) / FS
    u = 1.4 - 1.3 * np.cos(2 * np.pi * 3.0 * t) * np.exp(-t / 3)  # minor loops too
    np.testing.assert_allclose(fe.simulate(u), offline_model.simulate(RunData(u, None, {}, FS)), rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match="fpmpi"):
        FPMPIFrontEnd.from_model(Model("pi"))


def identity_front_end() -> FPMPIFrontEnd:
    """u_r = u: one operator with threshold 0, polynomial u^1."""
    return FPMPIFrontEnd(1.0, np.array([1.0]), np.array([1.0]), np.array([0.0]), np.array([1.0]))


def test_regressor_follows_eq_11():
    """y(k) = sum_{i=0..M} p_i u_r(k-i) + sum_{j=1..N} q_j y(k-j): exact recovery pins the indices."""
    rng = np.random.default_rng(3)
    p = np.array([0.3, -0.2, 0.5, 0.1])  # p_0..p_3
    poles = np.array([0.8, 0.5 + 0.4j, 0.5 - 0.4j, -0.3, 0.2])
    q = -np.real(np.poly(poles))[1:]  # q_1..q_5 of 1 - Q(z^-1)
    u = rng.standard_normal(4000)
    y = sps.lfilter(p, np.concatenate([[1.0], -q]), u)
    oiir = OIIR(identity_front_end(), M=3, N=5, lam=1.0, outlier="off")
    res = oiir.run(u, y, decimate=100)
    np.testing.assert_allclose(oiir.theta, np.concatenate([p, q]), atol=1e-3)
    assert oiir.weight_names == ["p0", "p1", "p2", "p3", "q1", "q2", "q3", "q4", "q5"]
    assert res["weights"].shape == (40, 9)
    np.testing.assert_array_equal(res["u_r"], u)
    b, a = oiir.transfer_function()
    np.testing.assert_allclose(b, p, atol=1e-3)
    np.testing.assert_allclose(a[1:], -q, atol=1e-3)


def test_tracks_a_gain_change_offline_model_cannot(offline_model):
    """000 Fig. 10 / Table 4 on the simulated rig: 4 Hz, 0-2.5 A drive; at 5 s the actuator has
    cooled from 42.5 to 30.4 degC (stroke -24 %). Online prediction error (000 eq. 18) against the
    offline model with fixed weights (the fitted FPMPI with the rig's true dynamics and delay)."""
    n = 10_000
    t = np.arange(n) / FS
    u = 1.25 - 1.25 * np.cos(2 * np.pi * 4.0 * t)
    temperature = np.where(t < 5.0, T_REF, 30.4)
    y = gmm_plant(u, temperature, seed=2)
    fe = FPMPIFrontEnd.from_model(offline_model)
    b, a = dynamics()
    offline = sps.lfilter(b, a, np.concatenate([[0.0], fe.simulate(u)[:-1]]))  # one sample of delay

    oiir = OIIR.from_model(offline_model, M=3, N=5, lam=0.995)
    res = oiir.run(u, y, decimate=10)
    y_m = res["y_m"]
    half = n // 2
    on, off = re_n2_pct(y, y_m), re_n2_pct(y, offline)
    on2, off2 = re_n2_pct(y[half:], y_m[half:]), re_n2_pct(y[half:], offline[half:])
    persistence = re_n2_pct(y[1:], y[:-1])  # predict y(k) by y(k-1): what the measured lags give for free
    assert re_n2_pct(y[:half], offline[:half]) < 1.0  # the offline model was right before the change
    assert off2 > 20.0  # ... and is wrong after it
    assert on < off / 30.0 and on2 < off2 / 30.0, (on, off, on2, off2)
    assert on < persistence / 3.0, (on, persistence)
    assert re_ninf_pct(y[half:], y_m[half:]) < re_ninf_pct(y[half:], offline[half:]) / 10.0
    # the weights track the physics: the OIIR's static gain falls by the stroke's factor
    w = res["weights"]
    before, after = oiir.static_gain(w[half // 10 - 1]), oiir.static_gain(w[-1])
    expected = 1.0 + GAIN_PER_DEGC * (30.4 - T_REF)
    assert before == pytest.approx(1.0, abs=0.02)
    assert after / before == pytest.approx(expected, abs=0.02), (before, after, expected)
    assert np.all(np.isfinite(w)) and oiir.counters()["covariance_resets"] == 0


def test_bad_samples_do_not_poison_the_identifier(offline_model):
    n = 6000
    t = np.arange(n) / FS
    u = 1.25 - 1.25 * np.cos(2 * np.pi * 4.0 * t)
    y = gmm_plant(u, np.full(n, T_REF), seed=3)
    clean = OIIR.from_model(offline_model, lam=0.995)
    ref = clean.run(u, y)
    rng = np.random.default_rng(4)
    bad = rng.choice(np.arange(1000, n), 120, replace=False)
    y_bad, u_bad = y.copy(), u.copy()
    y_bad[bad[:40]] = np.nan
    y_bad[bad[40:100]] += rng.choice([-1.0, 1.0], 60) * 30.0  # 1000-sigma sensor spikes
    u_bad[bad[100:]] = np.inf
    guarded = OIIR.from_model(offline_model, lam=0.995)
    res = guarded.run(u_bad, y_bad)
    c = guarded.counters()
    assert c["nonfinite_skipped"] == 40 and c["input_held"] == 20 and c["outliers"] >= 60
    assert np.all(np.isfinite(res["weights"]))
    good = np.setdiff1d(np.arange(1000, n), bad)
    assert re_n2_pct(y[good], res["y_m"][good]) < 1.5 * re_n2_pct(y[good], ref["y_m"][good]) + 0.05
    # spikes kept out of the output lags: feeding them in (outlier="off") does visible damage
    naive = OIIR.from_model(offline_model, lam=0.995, outlier="off")
    res_naive = naive.run(u, np.where(np.isnan(y_bad), y, y_bad))
    assert re_n2_pct(y[good], res_naive["y_m"][good]) > 3.0 * re_n2_pct(y[good], res["y_m"][good])


def test_output_history_keeps_weighted_samples_and_drops_gross_ones():
    """A Huber-weighted measurement (moderate error: most likely the plant) enters the output lags
    as measured; a gross error (a sensor spike, skipped) enters as the prediction."""
    from hilbench.online import rls as R

    rng = np.random.default_rng(9)
    u = rng.standard_normal(3000)
    y = sps.lfilter([0.0, 0.5, 0.2], [1.0, -0.6, 0.1], u) + 0.01 * rng.standard_normal(3000)
    base = OIIR(identity_front_end(), M=3, N=5, lam=0.999)
    base.run(u[:2999], y[:2999])
    scale = float(base.st[R.ST_SCALE])
    m1 = base.M + 1
    for jump, status, expect_measured in ((20.0, R.OUTLIER_WEIGHTED, True), (80.0, R.OUTLIER_SKIPPED, False)):
        o = OIIR(identity_front_end(), M=3, N=5, lam=0.999)
        for name in ("theta", "P", "st", "phi", "ops", "xs"):
            getattr(o, name)[:] = getattr(base, name)
        probe = OIIR(identity_front_end(), M=3, N=5, lam=0.999)
        for name in ("theta", "P", "st", "phi", "ops", "xs"):
            getattr(probe, name)[:] = getattr(base, name)
        pred = probe.step(u[2999], y[2999])
        y_bad = pred + jump * scale
        o.step(u[2999], y_bad)
        assert o.st[R.ST_STATUS] == status
        assert o.phi[m1] == (y_bad if expect_measured else pred)


def test_block_mode_equals_step_mode(offline_model):
    n = 1500
    t = np.arange(n) / FS
    u = 1.25 - 1.25 * np.cos(2 * np.pi * 4.0 * t)
    y = gmm_plant(u, np.where(t < 0.7, T_REF, 35.0), seed=5)
    y[300] = np.nan
    y[400] += 25.0
    u[500] = np.nan
    block = OIIR.from_model(offline_model, lam=0.995)
    res = block.run(u, y)
    step = OIIR.from_model(offline_model, lam=0.995)
    y_step = np.array([step.step(uk, yk) for uk, yk in zip(u, y)])
    np.testing.assert_array_equal(res["y_m"], y_step)
    np.testing.assert_array_equal(res["weights"][-1], step.theta)
    for name in ("theta", "P", "st", "phi", "ops", "xs"):
        np.testing.assert_array_equal(getattr(block, name), getattr(step, name), err_msg=name)


# -- the guard (decision 0082): a stable filter, divergence resets, bounded predictions -----------


def test_schur_cohn_test_and_projection_agree_with_the_roots():
    """poles_within against np.roots on random denominators; project_poles brings the largest pole
    to the bound and keeps the angles (a radial contraction)."""
    from hilbench.online.oiir import poles_within, project_poles, work_size

    rng = np.random.default_rng(11)
    n_d, m1 = 5, 4
    work = np.zeros(work_size(n_d))
    checked = 0
    for _ in range(400):
        poles = rng.uniform(0.0, 1.3, 2) * np.exp(1j * rng.uniform(0, np.pi, 2))
        real = rng.uniform(-1.3, 1.3)
        all_poles = np.concatenate([poles, poles.conj(), [real]])
        q = -np.real(np.poly(all_poles))[1:]
        theta = np.concatenate([rng.standard_normal(m1), q])
        radius = float(np.max(np.abs(all_poles)))
        if abs(radius - 0.9) < 1e-6:
            continue  # too close to call in floating point
        assert poles_within(theta, m1, n_d, 0.9, work, 0) == (radius < 0.9), radius
        if radius > 0.9:
            P = np.eye(theta.size)  # no cross-information: the numerator stays
            t = theta.copy()
            project_poles(t, P, m1, n_d, 0.9, work, 0)
            new = np.roots(np.concatenate([[1.0], -t[m1:]]))
            assert np.max(np.abs(new)) == pytest.approx(0.9, abs=1e-6)
            assert poles_within(t, m1, n_d, 0.9 + 1e-9, work, 0)
            np.testing.assert_allclose(np.sort(np.abs(new)), np.sort(np.abs(all_poles)) * 0.9 / radius, atol=1e-6)
            np.testing.assert_array_equal(t[:m1], theta[:m1])
            checked += 1
    assert checked > 100


def _arx(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Second-order ARX plant (poles at radius 0.84), white input, 0.01 output noise."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n)
    y = sps.lfilter([0.0, 0.5, 0.2], [1.0, -1.5, 0.7], u) + 0.01 * rng.standard_normal(n)
    return u, y


UNGUARDED = {"pole_radius": None, "diverge_after": None, "bound_predictions": False}


def test_unstable_start_and_dropout_diverge_without_the_guard_and_stay_bounded_with_it():
    """200k samples. The identifier starts from an unstable guess (q1 = 1.2) and the sensor is
    absent for the first 5000 samples, so the output lags hold the filter's own free run: without
    the guard it reaches inf (the dSPACE 20 Hz capture's failure on main); with it the poles are
    projected inside 0.999 at once, the free run stays bounded, and after the dropout the lags are
    refilled before learning: the prediction error is the noise's for the rest of the run."""
    n = 200_000
    u, y = _arx(n, 1)
    y_meas = y.copy()
    y_meas[:5000] = np.nan
    theta0 = np.array([1.0, 0, 0, 0, 1.2, 0, 0, 0, 0])
    bare = OIIR(identity_front_end(), 3, 5, lam=0.9999, theta0=theta0, **UNGUARDED)
    y_bare = bare.run(u, y_meas)["y_m"]
    assert not np.all(np.isfinite(y_bare[:5000]))  # diverged
    guarded = OIIR(identity_front_end(), 3, 5, lam=0.9999, theta0=theta0)
    res = guarded.run(u, y_meas, decimate=1000)
    y_m = res["y_m"]
    c = guarded.counters()
    assert np.all(np.isfinite(y_m)) and np.all(np.isfinite(res["weights"]))
    assert np.max(np.abs(y_m)) < 100.0 * np.max(np.abs(y))
    assert c["poles_projected"] >= 1 and c["nonfinite_skipped"] == 5000 - 5
    assert np.max(np.abs(guarded.poles())) <= 0.999 + 1e-12
    for w in res["weights"]:  # every recorded weight vector has its poles inside the bound
        assert np.max(np.abs(guarded.poles(w))) <= 0.999 + 1e-9
    e = y[5100:] - y_m[5100:]
    assert np.sqrt(np.mean(e**2)) < 0.015  # noise 0.01 (measured 0.0140)
    assert re_n2_pct(y[5100:], y_m[5100:]) < 1.0


def test_a_run_of_gross_errors_resets_the_covariance_and_the_identifier_follows():
    """The sensor is re-zeroed at sample 100k (+50 on a ~2-unit output): every error is gross, so
    the samples are skipped and the lags fill with predictions. After ``diverge_after`` of them the
    identifier resets P, learns the error scale afresh and takes the measurements again; without
    the reset it trails by the whole jump for hundreds of samples."""
    n = 200_000
    u, y = _arx(n, 2)
    y[100_000:] += 50.0
    guarded = OIIR(identity_front_end(), 3, 5, lam=0.9999, bias=True)
    y_m = guarded.run(u, y)["y_m"]
    c = guarded.counters()
    assert c["divergence_resets"] >= 1 and c["covariance_resets"] >= c["divergence_resets"]
    assert np.all(np.isfinite(y_m))
    assert np.max(np.abs(y[100_100:] - y_m[100_100:])) < 1.0
    bare = OIIR(identity_front_end(), 3, 5, lam=0.9999, bias=True, diverge_after=None)
    y_bare = bare.run(u, y)["y_m"]
    assert bare.counters()["divergence_resets"] == 0
    assert np.max(np.abs(y[100_100:101_000] - y_bare[100_100:101_000])) > 20.0


def test_guard_block_mode_equals_step_mode():
    """The guard is inside the one kernel: projections, a dropout, a divergence reset, bounded
    predictions give the same bits in block and step mode."""
    n = 4000
    u, y = _arx(n, 3)
    y[:600] = np.nan
    y[2500:] += 50.0
    theta0 = np.array([1.0, 0, 0, 0, 1.2, 0, 0, 0, 0])
    block = OIIR(identity_front_end(), 3, 5, lam=0.999, theta0=theta0)
    res = block.run(u, y)
    step = OIIR(identity_front_end(), 3, 5, lam=0.999, theta0=theta0)
    y_step = np.array([step.step(uk, yk) for uk, yk in zip(u, y)])
    c = block.counters()
    assert c["poles_projected"] >= 1 and c["divergence_resets"] >= 1
    np.testing.assert_array_equal(res["y_m"], y_step)
    for name in ("theta", "P", "st", "phi", "ops", "xs"):
        np.testing.assert_array_equal(getattr(block, name), getattr(step, name), err_msg=name)


def test_prediction_is_held_within_the_outputs_seen():
    """A front end far outside its range (u_r 1e9 times the output) cannot push the prediction
    beyond the outputs seen widened by their span; the held predictions are counted."""
    rng = np.random.default_rng(5)
    n = 3000
    u = rng.standard_normal(n)
    y = sps.lfilter([0.0, 0.5], [1.0, -0.5], u) + 0.01 * rng.standard_normal(n)
    u_big = u.copy()
    u_big[2000:] *= 1e9  # the front end's input leaves everything seen: u_r follows it
    o = OIIR(identity_front_end(), 1, 2, lam=0.999)
    y_m = o.run(u_big, y)["y_m"]
    lo, hi = y[:2000].min(), y[:2000].max()
    span = max(hi - lo, y.max() - y.min())
    assert np.all(y_m[2000:] <= y.max() + span) and np.all(y_m[2000:] >= y.min() - span)
    assert o.counters()["predictions_bounded"] >= 1
    bare = OIIR(identity_front_end(), 1, 2, lam=0.999, bound_predictions=False)
    assert np.max(np.abs(bare.run(u_big, y)["y_m"][2000:])) > 1e3 * span


def test_front_end_input_range_holds_the_polynomial_within_its_fitted_inputs():
    fe = FPMPIFrontEnd(1.0, np.array([1.0, 4.0]), np.array([1.0, 1.0]), np.array([0.0]), np.array([1.0]),
                       input_range=(-1.0, 1.0))
    free = fe.unbounded()
    u = np.array([0.0, 0.5, 1.0, 3.0, -3.0])
    np.testing.assert_array_equal(fe.simulate(u)[:3], free.simulate(u)[:3])  # within: the same bits
    assert fe.simulate(u)[3] == pytest.approx(2.0) and free.simulate(u)[3] == pytest.approx(84.0)
