"""The RTS smoother and the likelihood of the Hall readings, against independent NumPy float64
implementations of the textbook equations (``tests/reference.py``), and their invariants."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as R
from helpers import joints_of, random_params, random_recording, random_robot, reference_params
from helpers import series_of as make_series
from jax.test_util import check_grads
from reference import reference_smoother

from kckf_jax import (
    Params,
    Robot,
    SensorSeries,
    pad_series,
    run_filter,
    simulate,
    smooth,
    smooth_batch,
)
from kckf_jax._paths._likelihood import chi2_interval, hall_nll


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("method", ["kckf", "kf"])
@pytest.mark.long
def test_smoother_matches_numpy_rts(seed, method):
    """Random robots and parameters, irregular time steps, 10 % missing readings, both noise
    models: 1e-8 rad against the pseudo-inverse RTS smoother on the paper's full state."""
    rng = np.random.default_rng(seed)
    robot = random_robot(rng)
    params = random_params(rng, robot, hall_noise="voltage" if seed % 2 else "angle")
    t, gyro, hall_v = random_recording(rng, robot, T=80)
    ref = reference_smoother(joints_of(robot), t, gyro, hall_v, reference_params(params),
                             method)
    est = smooth(params, make_series(t, gyro, hall_v), method)
    assert est.path == "smoothed"
    np.testing.assert_allclose(est.angles, ref["angles"], atol=1e-8, rtol=0)
    np.testing.assert_allclose(est.bias, ref["bias"], atol=1e-8, rtol=0)
    K = robot.n_angles
    std = np.sqrt(np.maximum(np.diagonal(ref["P"], axis1=1, axis2=2)[:, :K], 0.0))
    np.testing.assert_allclose(est.angle_std, std, atol=1e-8, rtol=1e-6)
    # Smoothing uses later readings: it moves the estimates, the last row excepted.
    _, filt = run_filter(params, make_series(t, gyro, hall_v), method)
    assert np.abs(np.asarray(est.angles) - np.asarray(filt.angles))[:-1].max() > 1e-4
    np.testing.assert_allclose(est.angles[-1], filt.angles[-1], atol=1e-12)
    if method == "kckf":  # the constraint holds for the smoothed estimates too
        a = np.asarray(est.angles)
        np.testing.assert_allclose(a[:, robot.n_joint_axes:],
                                   a[:, :robot.n_joint_axes] @ robot.torso_sum.T, atol=1e-12)


@pytest.mark.long
def test_smooth_batch_equals_a_loop_padding_and_float32_hold():
    robot = Robot.from_spec("x,y,x,y")
    trials = [simulate(robot, "human", seed=s, duration_s=d, drop_prob=0.02)
              for s, d in ((1, 3.0), (2, 2.3))]
    series = [SensorSeries(s.dt(), s.gyro, s.hall_v) for s in trials]
    params = Params.from_physical(robot, hall_models=trials[0].hall_models, hall_noise="voltage",
                                  dtype=jnp.float64)
    batch = smooth_batch(params, pad_series(series))
    for b, s in enumerate(series):
        one = smooth(params, s)
        n = s.dt.shape[0]
        np.testing.assert_allclose(batch.angles[b, :n], one.angles, atol=1e-12, rtol=0)
    # float32 over 12,000 rows: finite, positive standard deviations, close to float64.
    long = simulate(robot, "cyclic", seed=5, duration_s=120.0, drop_prob=0.01)
    s64 = SensorSeries(long.dt(), long.gyro, long.hall_v)
    e64 = smooth(params, s64)
    e32 = smooth(params.astype(jnp.float32),
                 jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), s64))
    assert np.isfinite(np.asarray(e32.angles)).all()
    assert (np.asarray(e32.angle_std) > 0).all()
    assert np.abs(np.asarray(e32.angles, np.float64) - np.asarray(e64.angles)).max() < 1e-3


def test_smoother_gradient_is_finite_and_checks():
    rng = np.random.default_rng(4)
    robot = Robot.from_spec("x,y")
    params = random_params(rng, robot, hall_noise="voltage")
    series = make_series(*random_recording(rng, robot, T=25))
    diff, static = eqx.partition(params, eqx.is_inexact_array)

    def f(*leaves):
        d = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(diff), leaves)
        return jnp.mean(smooth(eqx.combine(d, static), series).angles ** 2)

    check_grads(jax.jit(f), jax.tree_util.tree_leaves(diff), order=1, modes=["rev"],
                atol=1e-6, rtol=1e-4, eps=1e-6)


def _reference_nll(joints, t, gyro, hall_v, p, method):
    """-log p(every Hall voltage | the earlier ones) per reading, on the paper's full state:
    after each prediction and the constraint, the predictive density of the vector of the
    row's present Hall angles, and each reading's Eq. 1 slope (the voltage's density)."""
    L = R.layout(joints)
    N, M = L["N"], L["M"]
    dt = R._dt(np.asarray(t, float))
    C, D = R._C(L), R._D(L)
    gyro, hall_v = R.usable_readings(joints, t, gyro, hall_v, p)  # the readings used
    x, P, u = np.zeros(N), R._P0(L, p, method), np.zeros(L["n_gyro"])
    total, count = 0.0, 0
    for k in range(len(dt)):
        ts = dt[k]
        if ts > 0:
            A = R._A(L, ts)
            x, P = A @ x + R._B(L, ts) @ u, A @ P @ A.T + R._Q(L, p, ts)
        if method == "kckf" and ts > 0:  # the perfect measurement first (it is no data)
            Kg = np.linalg.solve(D @ P @ D.T, D @ P).T
            x = x + Kg @ (0.0 - D @ x)
            P = (np.eye(N) - Kg @ D) @ P
            P = 0.5 * (P + P.T)
        rows = [m for m in range(M) if np.isfinite(hall_v[k, m])]
        if rows:
            H = C[rows]
            y = np.array([R.hall_angle(hall_v[k, m], p, m) for m in rows])
            Rm = np.diag([R.hall_variance(hall_v[k, m], p, m) for m in rows])
            S = H @ P @ H.T + Rm
            nu = y - H @ x
            total += 0.5 * (len(rows) * math.log(2 * math.pi) + np.linalg.slogdet(S)[1]
                            + nu @ np.linalg.solve(S, nu))
            total -= sum(math.log(abs(R.hall_slope(hall_v[k, m], p, m))) for m in rows)
            count += len(rows)
            Kg = np.linalg.solve(S, H @ P).T
            x = x + Kg @ nu
            IKH = np.eye(N) - Kg @ H
            P = IKH @ P @ IKH.T + Kg @ Rm @ Kg.T
        u = R._update_hold(u, gyro[k])
    return total / count


@pytest.mark.parametrize("seed", range(2))  # the angle and the voltage noise model
def test_likelihood_matches_numpy_and_has_gradients(seed):
    rng = np.random.default_rng(10 + seed)
    robot = random_robot(rng, max_joints=3)
    params = random_params(rng, robot, hall_noise="voltage" if seed % 2 else "angle")
    t, gyro, hall_v = random_recording(rng, robot, T=60)
    nll = eqx.filter_jit(hall_nll)  # one program a call, not one per operation
    for method in ("kckf", "kf"):
        ref = _reference_nll(joints_of(robot), t, gyro, hall_v, reference_params(params), method)
        got = float(nll(params, make_series(t, gyro, hall_v), method))
        assert got == pytest.approx(ref, rel=1e-9, abs=1e-9), method
    g = eqx.filter_jit(eqx.filter_grad(lambda p: hall_nll(p, make_series(t, gyro, hall_v))))(
        params)
    leaves = jax.tree_util.tree_leaves(eqx.filter(g, eqx.is_inexact_array))
    assert all(np.isfinite(np.asarray(x)).all() for x in leaves)
    assert np.abs(np.asarray(g.log_sigma_hall_v if seed % 2 else g.log_sigma_hall)).max() > 0


def test_chi2_interval():
    lo, hi = chi2_interval(1000)
    assert 0.91 < lo < 0.92 and 1.08 < hi < 1.09  # chi2(1000)/1000: 0.9146, 1.0885
    lo, hi = chi2_interval(100_000)
    assert 0.99 < lo < 1.0 < hi < 1.01


@pytest.mark.long
def test_likelihood_on_lanes_equals_the_step_values_and_gradients():
    """A batch (uneven trials, padded; missing readings, irregular steps, the voltage model):
    the lanes path's innovations give the kernel step's likelihood and gradients, float64."""
    rng = np.random.default_rng(40)
    # Two blocks, one with a padded joint (random robots are covered by test_paths' lanes
    # tests; a 3D robot's written-out lanes step took most of this test's 50 s to compile).
    robot = Robot.from_spec("xz,y")
    params = random_params(rng, robot, hall_noise="voltage")
    trials = [make_series(*random_recording(rng, robot, T=int(T)))
              for T in rng.integers(30, 50, size=8)]
    batch = pad_series(trials)
    nll = eqx.filter_jit(hall_nll)  # one program a call, not one per operation
    for method in ("kckf", "kf"):
        seq = float(nll(params, batch, method, path="sequential"))
        assert float(nll(params, batch, method, path="lanes")) == pytest.approx(seq, rel=1e-12)
    grads = [eqx.filter_jit(eqx.filter_grad(lambda p, path=path: hall_nll(p, batch,
                                                                          path=path)))(params)
             for path in ("sequential", "lanes")]
    a, b = (jax.tree_util.tree_leaves(eqx.filter(g, eqx.is_inexact_array)) for g in grads)
    for x, y in zip(a, b):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-9, atol=1e-12)


@pytest.mark.long
def test_likelihood_gradient_matches_finite_differences():
    """The likelihood's reverse mode against central differences (float64), voltage model."""
    rng = np.random.default_rng(7)
    robot = Robot.from_spec("x,y")
    params = random_params(rng, robot, hall_noise="voltage")
    series = make_series(*random_recording(rng, robot, T=25))
    leaves, tree = jax.tree_util.tree_flatten(eqx.filter(params, eqx.is_inexact_array))
    rest = eqx.filter(params, eqx.is_inexact_array, inverse=True)

    def f(*xs):
        p = eqx.combine(jax.tree_util.tree_unflatten(tree, list(xs)), rest)
        return hall_nll(p, series)

    check_grads(jax.jit(f), leaves, order=1, modes=["rev"], atol=1e-5, rtol=1e-5)


def test_the_gain_solve_loads_the_diagonal_below_double_precision():
    """``cholesky_solve``: float64 as it is; float32 with each diagonal entry loaded by
    ``SOLVE_JITTER n eps`` of itself (``_kalman``), so two nearly equal coordinates, whose
    difference float32 does not resolve, get a bounded gain."""
    from kckf_jax._models._kalman import SOLVE_JITTER, cholesky_solve

    rng = np.random.default_rng(0)
    A = rng.standard_normal((4, 6))
    S = A @ A.T + 0.1 * np.eye(4)
    B = rng.standard_normal((4, 2))
    got = np.asarray(cholesky_solve(jnp.asarray(S), jnp.asarray(B)))  # float64: conftest
    np.testing.assert_allclose(got, np.linalg.solve(S, B), rtol=1e-12)
    load = np.diag(np.diag(S)) * SOLVE_JITTER * 4 * np.finfo(np.float32).eps
    got = np.asarray(cholesky_solve(jnp.asarray(S, jnp.float32), jnp.asarray(B, jnp.float32)))
    np.testing.assert_allclose(got, np.linalg.solve(S + load, B), rtol=1e-4)
    twins = np.array([[1.0, 1.0 - 1e-9], [1.0 - 1e-9, 1.0]])  # difference below float32's eps
    got = np.asarray(cholesky_solve(jnp.asarray(twins, jnp.float32),
                                    jnp.asarray([[1.0], [-1.0]], jnp.float32)))
    assert np.all(np.isfinite(got)) and np.abs(got).max() < 1e7, got


@pytest.mark.long
def test_float32_smoother_of_fitted_exact_parameters_is_finite():
    """A fit of ``kckf3d`` (x,y,x,y, human motion, 300 steps) leaves a filtered covariance
    whose eigenvalues span 1e-7 to 0.1, more than float32 resolves: the smoother in float32
    gave angles 23 deg off float64's (infinite on 638 of 4,000 rows with XLA's CPU loops).
    Now within 2 % of float64's RMSE."""
    import kckf_jax as kk

    def session(seed):
        return kk.simulate("x,y,x,y", "human", seed=seed, duration_s=40.0, device_seed=7,
                           kinematics="exact", drop_prob=0.01)

    res = kk.fit([session(701), session(702)], [session(703)],
                 kk.FitConfig(steps=300, method="kckf3d", val_every=10, patience=300),
                 dtype=jnp.float32)
    val = [session(703)]
    rmse = {}
    for dtype in (jnp.float32, jnp.float64):
        (est,) = kk.filter_sessions(val, "kckf3d", res.params, smooth=True, dtype=dtype)
        assert np.all(np.isfinite(est.angles))
        rmse[dtype] = kk.rmse_table(val, [est.angles])["mean_rmse_deg"]
    assert rmse[jnp.float32] <= 1.02 * rmse[jnp.float64], rmse
