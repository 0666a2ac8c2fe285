"""The Markovian (MJLS) filter and its per-segment KF baseline (kckf_jax.filters.markov).

The reference below is an independent NumPy float64 implementation of the paper's equations
in the paper's own coordinates (Eqs. 16-19, 21-30): the full matrix Kalman update with a
stacked measurement vector and an explicit inverse of the innovation covariance, where the JAX
filter works in encoder coordinates with sequential scalar Joseph updates.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from kckf_jax.filters.markov import (
    GaitConfig,
    MarkovParams,
    fit_markov,
    gait_series,
    gated_accel_error,
    markov_batch,
    markov_experiment,
    markov_init,
    markov_loss,
    markov_step,
    matched_markov_params,
    perturb_markov_params,
    run_markov,
    scan_markov,
    simulate_gait,
    to_paper,
)
from kckf_jax.filters.markov._filter import METHODS, N_SYSTEM, SEGMENTS, TABLE2
from kckf_jax.filters.markov._sim import gait_pattern, reliability

DEG = math.pi / 180
G = 9.80665
#: Short trials that still walk: 0.3 s standing, 0.5 s start-up, then about two strides.
SHORT = GaitConfig(stand_s=0.3, start_s=0.5, duration_s=3.0)


# ----------------------------------------------------------------------------- reference
def reference_filter(trial: dict, p: dict, method: str) -> dict:
    """Paper Secs. 2.2-3 in float64, state ``x = [theta_B, b_B, ..., theta_F, b_F]``."""
    dt, gyro, accel, enc = (np.asarray(trial[k], np.float64)
                            for k in ("dt", "gyro", "accel", "encoder"))
    T, S = gyro.shape
    N = 2 * S
    x = np.zeros(N)
    x[0::2] = np.arcsin(np.clip(accel[0, :, 0] / G, -1, 1))
    P = np.diag(np.ravel(np.column_stack([p["p0_angle"] ** 2, p["p0_bias"] ** 2])))
    Q = np.diag(np.ravel(np.column_stack([p["sigma_g"] ** 2, p["sigma_bg"] ** 2])))
    prev = gyro[0]
    xs, Ps, modes, updated = [], [], [], []
    for k in range(T):
        # Eqs. 19, 21-22: Phi = I + A T, G = T I; angles by the trapezoid rule.
        Phi = np.eye(N)
        for i in range(S):
            Phi[2 * i, 2 * i + 1] = dt[k]
            Phi[2 * i + 1, 2 * i + 1] = 1 - dt[k] / p["tau_g"][i]
        new = x.copy()
        for i in range(S):
            new[2 * i] = x[2 * i] + dt[k] * (0.5 * (prev[i] + gyro[k, i]) + x[2 * i + 1])
            new[2 * i + 1] = (1 - dt[k] / p["tau_g"][i]) * x[2 * i + 1]
        x = new
        P = Phi @ P @ Phi.T + dt[k] ** 2 * Q
        prev = gyro[k]
        # Eqs. 28-30.
        rho = np.abs(np.sqrt(np.sum(accel[k] ** 2, axis=1)) / G - 1)
        theta_a = np.arcsin(np.clip(accel[k, :, 0] / G, -1, 1))
        mode = int(np.argmin(rho))
        rows, ys, rs = [], [], []
        if method == "kf":
            use = rho < p["zeta"]
            for i in np.flatnonzero(use):
                h = np.zeros(N)
                h[2 * i] = 1
                rows.append(h)
                ys.append(theta_a[i])
                rs.append(p["sigma_a"][i] ** 2)
        else:
            use = np.zeros(S, bool)
            if rho[mode] < p["zeta"][mode]:
                use[mode] = True
                h = np.zeros(N)
                h[2 * mode] = 1  # C(Theta) of Eq. 18, Table 1
                rows.append(h)
                ys.append(theta_a[mode])
                rs.append(p["sigma_a"][mode] ** 2)
                for j in range(S - 1):
                    h = np.zeros(N)
                    h[2 * j], h[2 * j + 2] = 1, -1
                    rows.append(h)
                    ys.append(enc[k, j])
                    rs.append(p["sigma_enc"][j] ** 2)
        if rows:  # Eqs. 23-25, Joseph form
            H, y, R = np.array(rows), np.array(ys), np.diag(rs)
            K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
            x = x + K @ (y - H @ x)
            J = np.eye(N) - K @ H
            P = J @ P @ J.T + K @ R @ K.T
        xs.append(x.copy())
        Ps.append(P.copy())
        modes.append(mode)
        updated.append(use)
    xs = np.array(xs)
    return {"angles": xs[:, 0::2], "bias": xs[:, 1::2], "P": np.array(Ps),
            "mode": np.array(modes), "updated": np.array(updated)}


def physical(params: MarkovParams) -> dict:
    return {k: np.asarray(getattr(params, k), np.float64)
            for k in ("zeta", "sigma_g", "sigma_bg", "sigma_a", "tau_g", "sigma_enc",
                      "p0_angle", "p0_bias")}


def random_params(rng: np.random.Generator, dtype=jnp.float64) -> MarkovParams:
    def logu(lo, hi, n=4):
        return np.exp(rng.uniform(np.log(lo), np.log(hi), n))

    return MarkovParams.from_physical(
        zeta=logu(0.005, 0.05), sigma_g=logu(0.01, 5) * DEG, sigma_bg=logu(1e-3, 10) * DEG,
        sigma_a=logu(0.5, 300) * DEG, tau_g=logu(20, 4000),
        sigma_enc=logu(0.02, 1.0, 3) * DEG, p0_angle=logu(0.3, 10) * DEG,
        p0_bias=logu(0.05, 2) * DEG, dtype=dtype)


def trial_dict(trials, b: int) -> dict:
    return {k: getattr(trials, k)[b] for k in ("dt", "gyro", "accel", "encoder")}


@pytest.fixture(scope="module")
def short_trials():
    return simulate_gait(3, seed=11, config=SHORT)


# ----------------------------------------------------------------------------- reference tests
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("method", METHODS)
def test_matches_numpy_reference(seed, method, short_trials):
    """Random parameters on walking trials, mode switches included: 1e-6 rad."""
    rng = np.random.default_rng(seed)
    params = random_params(rng)
    b = seed % short_trials.n_trials
    ref = reference_filter(trial_dict(short_trials, b), physical(params), method)
    final, est = run_markov(params, gait_series(short_trials, jnp.float64, index=b), method)
    np.testing.assert_allclose(est.angles, ref["angles"], atol=1e-6, rtol=0)
    np.testing.assert_allclose(est.bias, ref["bias"], atol=1e-6, rtol=0)
    np.testing.assert_array_equal(est.mode, ref["mode"])
    np.testing.assert_array_equal(est.updated, ref["updated"])
    x, P = to_paper(final.z, final.P)
    np.testing.assert_allclose(x[0::2], ref["angles"][-1], atol=1e-6, rtol=0)
    np.testing.assert_allclose(P, ref["P"][-1], atol=1e-9, rtol=1e-6)
    np.testing.assert_allclose(est.angle_std[-1], np.sqrt(np.diag(ref["P"][-1])[0::2]),
                               atol=1e-9, rtol=1e-6)
    # The test means something: the trial switches modes and has both kinds of steps.
    assert len(set(ref["mode"].tolist())) >= 3
    assert 0.05 < ref["updated"].any(axis=1).mean() < 0.95


def test_mode_is_eq29_and_gated_by_eq30(short_trials):
    params = MarkovParams.table2(jnp.float64)
    _, est = run_markov(params, gait_series(short_trials, jnp.float64, index=0), "mkf")
    rho = reliability(short_trials.accel[0])
    np.testing.assert_allclose(est.rho, rho, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(est.mode, rho.argmin(axis=1))
    reliable = rho.min(axis=1) < 0.01
    np.testing.assert_array_equal(np.asarray(est.updated).any(axis=1), reliable)
    assert np.all(np.asarray(est.updated).sum(axis=1) <= 1)  # one inertial sensor at a time


# ----------------------------------------------------------------------------- agreement
def test_jit_equals_eager(short_trials):
    params = MarkovParams.table2(jnp.float64)
    series = jax.tree_util.tree_map(lambda a: a[:4],
                                    gait_series(short_trials, jnp.float64, index=1))
    _, jitted = run_markov(params, series, "mkf")
    with jax.disable_jit():
        _, eager = scan_markov(params, series, "mkf")
    np.testing.assert_allclose(jitted.angles, eager.angles, atol=1e-12, rtol=0)
    np.testing.assert_allclose(jitted.angle_std, eager.angle_std, atol=1e-12, rtol=1e-10)


def test_step_by_step_equals_scan(short_trials):
    params = MarkovParams.table2(jnp.float64)
    series = jax.tree_util.tree_map(lambda a: a[:30],
                                    gait_series(short_trials, jnp.float64, index=2))
    _, est = run_markov(params, series, "kf")
    state = markov_init(params, jax.tree_util.tree_map(lambda a: a[0], series))
    step = jax.jit(markov_step, static_argnums=3)
    for k in range(30):
        state, out = step(params, state, jax.tree_util.tree_map(lambda a, k=k: a[k], series),
                          "kf")
        np.testing.assert_allclose(out.angles, est.angles[k], atol=1e-12, rtol=0)


@pytest.mark.parametrize("method", METHODS)
def test_vmap_equals_loop(method, short_trials):
    params = matched_markov_params(SHORT, calibration_trials=2, dtype=jnp.float64)
    series = gait_series(short_trials, jnp.float64)
    batch = markov_batch(params, series, method)
    for b in range(short_trials.n_trials):
        _, one = run_markov(params, gait_series(short_trials, jnp.float64, index=b), method)
        np.testing.assert_allclose(batch.angles[b], one.angles, atol=1e-12, rtol=0)
    # One parameter set per trial, as the Monte Carlo uses.
    factors = jnp.asarray(np.random.default_rng(0).uniform(0.8, 1.2, (3, N_SYSTEM)))
    per = jax.vmap(lambda f: perturb_markov_params(params, f))(factors)
    batch = markov_batch(per, series, method, batched_params=True)
    _, one = run_markov(perturb_markov_params(params, factors[1]),
                        gait_series(short_trials, jnp.float64, index=1), method)
    np.testing.assert_allclose(batch.angles[1], one.angles, atol=1e-12, rtol=0)


# ----------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("method", METHODS)
def test_gradients_finite(method, short_trials):
    params = MarkovParams.table2(jnp.float64)
    series = jax.tree_util.tree_map(lambda a: a[:2, :150], gait_series(short_trials,
                                                                         jnp.float64))
    truth = jnp.asarray(short_trials.angles[:2, :150])
    grads = jax.grad(markov_loss)(params, series, truth, method)
    leaves = {name: np.asarray(getattr(grads, name)) for name in (
        "log_zeta", "log_sigma_g", "log_sigma_bg", "log_sigma_a", "log_tau_g",
        "log_sigma_enc", "log_p0_angle", "log_p0_bias")}
    for name, g in leaves.items():
        assert np.all(np.isfinite(g)), name
    # The mode is discrete: zeta gets no gradient; everything the filter uses gets one.
    assert np.all(leaves["log_zeta"] == 0)
    used = [n for n in leaves if n != "log_zeta" and (method == "mkf" or n != "log_sigma_enc")]
    for name in used:
        assert np.any(leaves[name] != 0), name


def test_check_grads(short_trials):
    params = MarkovParams.table2(jnp.float64)
    series = jax.tree_util.tree_map(lambda a: a[:1, 60:80], gait_series(short_trials,
                                                                         jnp.float64))
    truth = jnp.asarray(short_trials.angles[:1, 60:80])

    def f(log_sigma_a, log_sigma_enc, log_tau_g):
        # check_grads evaluates with NumPy perturbations; the leaves are JAX arrays.
        log_sigma_a, log_sigma_enc, log_tau_g = map(jnp.asarray, (log_sigma_a, log_sigma_enc,
                                                                  log_tau_g))
        p = MarkovParams(params.log_zeta, params.log_sigma_g, params.log_sigma_bg, log_sigma_a,
                         log_tau_g, log_sigma_enc, params.log_p0_angle, params.log_p0_bias)
        return markov_loss(p, series, truth, "mkf")

    check_grads(f, (params.log_sigma_a, params.log_sigma_enc, params.log_tau_g), order=1,
                modes=["rev"], atol=1e-5, rtol=1e-4)


# ----------------------------------------------------------------------------- float32
@pytest.fixture(scope="module")
def long_trial():
    return simulate_gait(1, seed=4, config=GaitConfig(duration_s=60.0))


@pytest.mark.parametrize("method", METHODS)
def test_float32_long_run_is_finite_and_positive_definite(method, long_trial):
    """6000 steps in float32 with the paper's Table 2 (the hardest conditioning: gyros declared
    quieter than the encoders can confirm): finite, symmetric, positive definite throughout."""
    params = MarkovParams.table2(jnp.float32)
    series = gait_series(long_trial, jnp.float32, index=0)

    def body(state, row):
        state, est = markov_step(params, state, row, method)
        return state, (state.P, est.angles)

    init = markov_init(params, jax.tree_util.tree_map(lambda a: a[0], series))
    _, (Ps, angles) = jax.jit(lambda: jax.lax.scan(body, init, series))()
    Ps = np.asarray(Ps)
    assert Ps.dtype == np.float32 and np.all(np.isfinite(Ps))
    assert np.all(np.isfinite(np.asarray(angles)))
    np.testing.assert_array_equal(Ps, np.swapaxes(Ps, 1, 2))
    assert np.linalg.eigvalsh(Ps.astype(np.float64)).min() > 0


@pytest.mark.parametrize("method", METHODS)
def test_float32_follows_float64(method, long_trial):
    params = matched_markov_params(calibration_trials=2, dtype=jnp.float64)
    _, est32 = run_markov(params.astype(jnp.float32),
                          gait_series(long_trial, jnp.float32, index=0), method)
    _, est64 = run_markov(params, gait_series(long_trial, jnp.float64, index=0), method)
    diff = np.abs(np.asarray(est32.angles, np.float64) - np.asarray(est64.angles))
    assert diff.max() < 1e-4  # rad, over 6000 steps


# ----------------------------------------------------------------------------- parameters
def test_params_roundtrip_and_validation():
    p = MarkovParams.table2()
    np.testing.assert_allclose(np.asarray(p.sigma_a) / DEG, TABLE2["sigma_a_deg"], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(p.tau_g), TABLE2["tau_g_s"], rtol=1e-6)
    assert set(p.to_dict()) >= {"zeta", "sigma_g_rad_s", "tau_g_s", "sigma_enc_rad"}
    with pytest.raises(ValueError, match="sigma_a"):
        MarkovParams.from_physical(zeta=0.01, sigma_g=1e-3, sigma_bg=1e-3, sigma_a=[1, 2],
                                   tau_g=100)
    with pytest.raises(ValueError, match="tau_g"):
        MarkovParams.from_physical(zeta=0.01, sigma_g=1e-3, sigma_bg=1e-3, sigma_a=0.1,
                                   tau_g=-1)
    with pytest.raises(ValueError, match="log_sigma_enc"):
        MarkovParams(*(jnp.zeros(4) for _ in range(5)), jnp.zeros(4), jnp.zeros(4),
                     jnp.zeros(4))
    with pytest.raises(ValueError, match="factors"):
        perturb_markov_params(p, jnp.ones(3))
    with pytest.raises(ValueError, match="method"):
        run_markov(p, gait_series(simulate_gait(1, 0, SHORT), index=0), "ukf")


# ----------------------------------------------------------------------------- simulator
def test_simulator_is_seeded_and_plausible():
    a = simulate_gait(2, seed=5)
    b = simulate_gait(2, seed=5)
    np.testing.assert_array_equal(a.accel, b.accel)
    assert not np.array_equal(a.accel, simulate_gait(2, seed=6).accel)
    walking = a.phase > 1.5
    joints = np.degrees(a.joints[walking])
    lo, hi = joints.min(axis=0), joints.max(axis=0)
    assert -15 < lo[0] < -5 and 25 < hi[0] < 40  # hip about -10..+30
    assert 0 <= lo[1] < 10 and 50 < hi[1] < 70  # knee 0..60
    assert -22 < lo[2] < -10 and 5 < hi[2] < 15  # ankle -15..+10
    # Encoders: the paper's relative angles, 12-bit quantised.
    step = 2 * np.pi / 4096
    np.testing.assert_allclose(a.encoder / step, np.round(a.encoder / step), atol=1e-9)
    rel = a.angles[..., :3] - a.angles[..., 1:]
    assert np.abs(a.encoder - rel).max() < 0.2 * DEG
    # The pattern itself: ankle from -15 to +10 deg.
    ankle = np.degrees(gait_pattern(np.linspace(0, 1, 1001))["ankle"])
    assert -17 < ankle.min() < -12 and 8 < ankle.max() < 12


def test_each_accelerometer_is_unreliable_in_its_own_phase():
    trials = simulate_gait(4, seed=2)
    rho = reliability(trials.accel)
    phase = np.mod(trials.phase, 1.0)
    walking = trials.phase > 1.5

    def median(i, lo, hi):
        return np.median(rho[..., i][walking & (phase >= lo) & (phase < hi)])

    foot, shank = SEGMENTS.index("foot"), SEGMENTS.index("shank")
    assert median(foot, 0.15, 0.30) < 0.01  # flat foot: gravity alone
    assert median(foot, 0.60, 0.90) > 0.3  # push-off and swing
    assert median(shank, 0.70, 0.90) > 0.2  # swing
    assert median(shank, 0.15, 0.30) < 0.05
    # Standing still at the start: every accelerometer reads gravity.
    assert np.all(rho[:, :50] < 0.03)
    err = np.degrees(gated_accel_error(trials))
    assert np.all(err > 1) and err[foot] < err[0]


# ----------------------------------------------------------------------------- experiment
def test_experiment_keys_and_markov_wins():
    out = markov_experiment(runs=3, seed=1)
    assert out["levels"] == [0, 5, 10, 15, 20]
    assert {"levels", "kf_deg", "mkf_deg", "published_ratio", "our_ratio"} <= set(out)
    assert len(out["kf_deg"]) == len(out["mkf_deg"]) == 5
    for kf, mkf in zip(out["kf_deg"], out["mkf_deg"]):
        assert np.isfinite(kf) and np.isfinite(mkf) and mkf < kf
    assert out["published_ratio"] == pytest.approx(0.94 / 1.20)
    assert out["our_ratio"] == pytest.approx(out["mkf_deg"][0] / out["kf_deg"][0])
    assert {"kf_deg", "mkf_deg"} <= set(out["details"]["table2"])


@pytest.mark.long  # a heavy check beside a lighter default one (the default run within 4 min)
def test_fitting_lowers_heldout_error():
    out = fit_markov("mkf", train_trials=2, test_trials=2, steps=5, learning_rate=0.1,
                     config=GaitConfig(duration_s=8.0))
    assert np.all(np.isfinite(out["loss_deg"]))
    assert out["heldout_fitted_deg"] < out["heldout_table2_deg"]
    assert out["gain"] > 0
    np.testing.assert_allclose(np.asarray(out["params"].zeta), TABLE2["zeta"], rtol=1e-12)
