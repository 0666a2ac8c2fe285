"""The arm exoskeleton + IMU filter (Chen et al.): NumPy reference, agreement, invariants.

The reference below is an independent plain-NumPy float64 implementation written from the paper
(Eqs. 2-13) and the conventions in ``kckf_jax/filters/arm_imu.py``'s docstring: one dense
15-state filter (``[p, v, a]`` per axis, then ``[phi, phi_dot]`` per axis), the stacked update
``K = P H^T S^-1`` with a linear solve in three stages per step, its own rotation formulas
(quaternion logarithm, the left Jacobian ``J_l`` solved for rather than its closed-form
inverse). It imports nothing of the filter module.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import TypeCheckError

# conftest.py imports every module of the package under its runtime shape-checking hook.
from kckf_jax.filters import (
    ArmImuParams,
    ArmImuSeries,
    ArmSimConfig,
    arm_imu_batch,
    arm_imu_experiment,
    arm_imu_init,
    arm_imu_series,
    arm_imu_step,
    first_valid_rotation,
    pad_arm_imu,
    remove_gyro_bias,
    run_arm_imu,
    scan_arm_imu,
    simulate_arm_trial,
)

DEG = np.pi / 180
G = 9.81


# ---------------------------------------------------------------------------------------
# Reference: rotations
# ---------------------------------------------------------------------------------------
def ref_skew(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]], dtype=np.float64)


def ref_exp(w):
    t = np.linalg.norm(w)
    K = ref_skew(w)
    if t < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(t) / t * K + (1 - np.cos(t)) / t**2 * K @ K


def ref_log(R):
    """Rotation vector via the unit quaternion (Shepperd's method) and 2 atan2(|v|, w)."""
    tr = np.trace(R)
    cands = [tr, R[0, 0], R[1, 1], R[2, 2]]
    i = int(np.argmax(cands))
    if i == 0:
        w = 0.5 * np.sqrt(1 + tr)
        v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (4 * w)
    else:
        a = i - 1
        b, c = (a + 1) % 3, (a + 2) % 3
        v = np.zeros(3)
        v[a] = 0.5 * np.sqrt(1 + R[a, a] - R[b, b] - R[c, c])
        w = (R[c, b] - R[b, c]) / (4 * v[a])
        v[b] = (R[b, a] + R[a, b]) / (4 * v[a])
        v[c] = (R[c, a] + R[a, c]) / (4 * v[a])
    if w < 0:
        w, v = -w, -v
    n = np.linalg.norm(v)
    if n < 1e-15:
        return 2 * v
    return 2 * np.arctan2(n, w) * v / n


def ref_left_jacobian(phi):
    t = np.linalg.norm(phi)
    K = ref_skew(phi)
    if t < 1e-8:
        return np.eye(3) + 0.5 * K
    return np.eye(3) + (1 - np.cos(t)) / t**2 * K + (t - np.sin(t)) / t**3 * K @ K


# ---------------------------------------------------------------------------------------
# Reference: the filter
# ---------------------------------------------------------------------------------------
def ref_params(params) -> dict:
    names = ("q_jerk", "q_alpha", "sigma_pos", "sigma_rot", "sigma_acc", "sigma_gyro",
             "p0_pos", "p0_vel", "p0_acc", "p0_rot", "p0_rate")
    out = {k: np.asarray(getattr(params, k), np.float64) for k in names}
    out["mount"] = np.asarray(params.imu_mount, np.float64)
    out["g"] = float(params.gravity_mps2)
    return out


POS = [[0, 1, 2], [3, 4, 5], [6, 7, 8]]  # [p, v, a] of axis x, y, z
ROT = [[9, 10], [11, 12], [13, 14]]  # [phi, phi_dot] of axis x, y, z


def ref_model(p, dt):
    """Eqs. 8-9 and the continuous white-jerk / white-angular-acceleration Q (15 states)."""
    F = np.eye(15)
    Q = np.zeros((15, 15))
    F3 = np.array([[1, dt, dt**2 / 2], [0, 1, dt], [0, 0, 1]])
    Q3 = np.array([[dt**5 / 20, dt**4 / 8, dt**3 / 6], [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                   [dt**3 / 6, dt**2 / 2, dt]])
    F2 = np.array([[1, dt], [0, 1]])
    Q2 = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    for a in range(3):
        F[np.ix_(POS[a], POS[a])] = F3
        Q[np.ix_(POS[a], POS[a])] = p["q_jerk"][a] * Q3
        F[np.ix_(ROT[a], ROT[a])] = F2
        Q[np.ix_(ROT[a], ROT[a])] = p["q_alpha"][a] * Q2
    return F, Q


def ref_update(x, P, rows):
    """Stacked update y = H x + v, v ~ N(0, diag(r)), Joseph form; rows = [(state, y, r)]."""
    if not rows:
        return x, P
    H = np.zeros((len(rows), 15))
    for j, (i, _, _) in enumerate(rows):
        H[j, i] = 1.0
    y = np.array([r[1] for r in rows])
    R = np.diag([r[2] for r in rows])
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T  # P H^T S^-1 (S symmetric)
    x = x + K @ (y - H @ x)
    A = np.eye(15) - K @ H
    P = A @ P @ A.T + K @ R @ K.T
    return x, 0.5 * (P + P.T)


def reference_filter(p, dt, exo_pos, exo_rot, imu_acc, imu_gyro):
    T = len(dt)
    ok_rot = np.all(np.isfinite(exo_rot), axis=(1, 2))
    ref = exo_rot[np.argmax(ok_rot)] if ok_rot.any() else np.eye(3)
    x = np.zeros(15)
    p0 = np.zeros(15)
    for a in range(3):
        p0[POS[a]] = [p["p0_pos"][a], p["p0_vel"][a], p["p0_acc"][a]]
        p0[ROT[a]] = [p["p0_rot"][a], p["p0_rate"][a]]
    P = np.diag(p0**2)
    last, since, has = np.zeros(3), np.zeros(3), np.zeros(3, bool)
    out = {k: np.zeros((T, 3)) for k in ("pos", "vel", "acc", "rotvec", "rate")}
    out["rot"] = np.zeros((T, 3, 3))
    phi = lambda x: x[[ROT[a][0] for a in range(3)]]  # noqa: E731
    for k in range(T):
        F, Q = ref_model(p, dt[k])
        x, P = F @ x, F @ P @ F.T + Q
        since = since + dt[k]
        # Stage 1: exoskeleton orientation (rotation vector relative to the reference).
        rows = []
        if ok_rot[k]:
            z = ref_log(exo_rot[k] @ ref.T)
            if np.linalg.norm(z) < 150 * DEG:
                rows = [(ROT[a][0], z[a], p["sigma_rot"][a] ** 2) for a in range(3)]
        x, P = ref_update(x, P, rows)
        # Stage 2: gyro, rotated into the exoskeleton frame (Eq. 3), as the rotation vector's
        # rate: solve J_l(phi) phi_dot = omega.
        rows = []
        if np.all(np.isfinite(imu_gyro[k])):
            R_ee = ref_exp(phi(x)) @ ref
            omega = R_ee @ p["mount"] @ imu_gyro[k]
            rate = np.linalg.solve(ref_left_jacobian(phi(x)), omega)
            rows = [(ROT[a][1], rate[a], p["sigma_gyro"][a] ** 2) for a in range(3)]
        x, P = ref_update(x, P, rows)
        # Stage 3: position, velocity pseudo-measurement, acceleration (Eqs. 2, 10).
        rows = []
        new_last = last.copy()
        for a in range(3):
            if np.isfinite(exo_pos[k, a]):
                r = p["sigma_pos"][a] ** 2
                rows.append((POS[a][0], exo_pos[k, a], r))
                if has[a] and since[a] > 0:
                    rows.append((POS[a][1], (exo_pos[k, a] - last[a]) / since[a],
                                 2 * r / since[a] ** 2))
                new_last[a], since[a], has[a] = exo_pos[k, a], 0.0, True
        last = new_last
        if np.all(np.isfinite(imu_acc[k])):
            acc = ref_exp(phi(x)) @ ref @ p["mount"] @ imu_acc[k] - np.array([0, 0, p["g"]])
            rows += [(POS[a][2], acc[a], p["sigma_acc"][a] ** 2) for a in range(3)]
        x, P = ref_update(x, P, rows)
        for a in range(3):
            out["pos"][k, a], out["vel"][k, a], out["acc"][k, a] = x[POS[a]]
            out["rotvec"][k, a], out["rate"][k, a] = x[ROT[a]]
        out["rot"][k] = ref_exp(phi(x)) @ ref
    out["x"], out["P"] = x, P
    return out


# ---------------------------------------------------------------------------------------
# Test data
# ---------------------------------------------------------------------------------------
def _trial(seed, duration_s=2.0):
    rng = np.random.default_rng(seed)
    tr = simulate_arm_trial(rng, ArmSimConfig(duration_s=duration_s, rest_s=0.3))
    gyro = remove_gyro_bias(tr.t_imu, tr.imu_gyro, 0.25)
    _, _, _, series = arm_imu_series(tr.t_exo, tr.exo_pos, tr.exo_rot, tr.t_imu, tr.imu_acc,
                                     gyro)
    return tr, series


def _with_missing(series, rng, frac=0.1):
    """NaN in ``frac`` of the position components, orientation readings and IMU readings (an
    IMU reading with one NaN component counts as missing in full)."""
    pos = np.array(series.exo_pos)
    rot = np.array(series.exo_rot)
    acc = np.array(series.imu_acc)
    gyro = np.array(series.imu_gyro)
    pos[rng.random(pos.shape) < frac] = np.nan
    rot[rng.random(len(rot)) < frac] = np.nan
    acc[rng.random(acc.shape) < frac / 3] = np.nan
    gyro[rng.random(len(gyro)) < frac] = np.nan
    return ArmImuSeries(dt=series.dt, exo_pos=pos, exo_rot=rot, imu_acc=acc, imu_gyro=gyro)


def _random_params(rng, mount, dtype=jnp.float64):
    def jitter(x):
        return x * np.exp(rng.uniform(-1, 1, 3))

    return ArmImuParams.from_physical(
        q_jerk=jitter(1e3), q_alpha=jitter(1.0), sigma_pos=jitter(1e-3),
        sigma_rot=jitter(0.5 * DEG), sigma_acc=jitter(0.05), sigma_gyro=jitter(0.005),
        p0_pos=jitter(0.1), p0_vel=jitter(0.5), p0_acc=jitter(5.0), p0_rot=jitter(0.1),
        p0_rate=jitter(1.0), imu_mount=mount, dtype=dtype)


def _reference_of(params, series):
    s = {k: np.asarray(getattr(series, k), np.float64)
         for k in ("dt", "exo_pos", "exo_rot", "imu_acc", "imu_gyro")}
    return reference_filter(ref_params(params), s["dt"], s["exo_pos"], s["exo_rot"],
                            s["imu_acc"], s["imu_gyro"])


# ---------------------------------------------------------------------------------------
# Tests
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed,missing", [(0, 0.0), (1, 0.1), (2, 0.3)])
def test_matches_numpy_reference(seed, missing):
    """Random parameters, the merged 100 Hz + 400 Hz timeline, missing readings: 1e-6."""
    rng = np.random.default_rng(100 + seed)
    tr, series = _trial(seed)
    series = _with_missing(series, rng, missing)
    params = _random_params(rng, tr.imu_mount)
    final, est = run_arm_imu(params, series)
    ref = _reference_of(params, series)
    for name in ("pos", "vel", "acc", "rotvec", "rate", "rot"):
        np.testing.assert_allclose(getattr(est, name), ref[name], atol=1e-6, rtol=0,
                                   err_msg=name)
    x = np.concatenate([np.ravel(final.pos), np.ravel(final.rot)])
    np.testing.assert_allclose(x, ref["x"][sum(POS, []) + sum(ROT, [])], atol=1e-6, rtol=0)
    for a in range(3):
        np.testing.assert_allclose(final.pos_cov[a], ref["P"][np.ix_(POS[a], POS[a])],
                                   atol=1e-12, rtol=1e-6)
        np.testing.assert_allclose(final.rot_cov[a], ref["P"][np.ix_(ROT[a], ROT[a])],
                                   atol=1e-12, rtol=1e-6)


def test_missing_rows_are_dropped_independently():
    """A missing y position leaves the x and z updates exactly as with a full reading."""
    tr, series = _trial(3, duration_s=0.5)
    params = ArmImuParams.paper_defaults().astype(jnp.float64)
    k = int(np.flatnonzero(np.isfinite(series.exo_pos[:, 0]))[5])
    state, _ = run_arm_imu(params, jax.tree_util.tree_map(lambda x: x[:k], series))
    row = jax.tree_util.tree_map(lambda x: np.array(x[k]), series)
    step = eqx.filter_jit(arm_imu_step)
    full, _ = step(params, state, row)
    row.exo_pos[1] = np.nan
    part, _ = step(params, state, row)
    pos, pos_cov = np.asarray(part.pos), np.asarray(part.pos_cov)
    np.testing.assert_array_equal(pos[[0, 2]], np.asarray(full.pos)[[0, 2]])
    np.testing.assert_array_equal(pos_cov[[0, 2]], np.asarray(full.pos_cov)[[0, 2]])
    assert not np.allclose(pos[1], full.pos[1])
    assert float(part.since_s[1]) > 0 and float(full.since_s[1]) == 0


def test_padding_rows_are_no_ops():
    _, series = _trial(4, duration_s=0.5)
    params = ArmImuParams.paper_defaults().astype(jnp.float64)
    padded = pad_arm_imu([series], length=len(series.dt) + 7)
    a, _ = run_arm_imu(params, series)
    b, _ = run_arm_imu(params, jax.tree_util.tree_map(lambda x: x[0], padded))
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(x, y)


@pytest.mark.long
def test_jit_equals_eager():
    rng = np.random.default_rng(5)
    tr, series = _trial(5, duration_s=0.5)
    series = jax.tree_util.tree_map(lambda x: x[100:106], _with_missing(series, rng, 0.1))
    params = _random_params(rng, tr.imu_mount)
    _, jitted = run_arm_imu(params, series)
    state = arm_imu_init(params, first_valid_rotation(series.exo_rot))
    with jax.disable_jit():
        for k in range(len(series.dt)):
            state, est = arm_imu_step(params, state,
                                      jax.tree_util.tree_map(lambda x, k=k: x[k], series))
            np.testing.assert_allclose(jitted.pos[k], est.pos, atol=1e-10, rtol=0)
            np.testing.assert_allclose(jitted.rotvec[k], est.rotvec, atol=1e-10, rtol=0)


def test_vmap_equals_loop():
    """Trials of uneven length and different missing rows, padded and vmapped."""
    rng = np.random.default_rng(6)
    trials = [_trial(s, duration_s=d) for s, d in ((6, 1.0), (7, 0.7), (8, 1.2))]
    series = [_with_missing(s, rng, 0.1) for _, s in trials]
    params = ArmImuParams.from_physical(imu_mount=trials[0][0].imu_mount, dtype=jnp.float64)
    batch = arm_imu_batch(params, pad_arm_imu(series))
    for i, s in enumerate(series):
        _, one = run_arm_imu(params, s)
        T = len(s.dt)
        np.testing.assert_allclose(batch.pos[i, :T], one.pos, atol=1e-10, rtol=0)
        np.testing.assert_allclose(batch.rot[i, :T], one.rot, atol=1e-10, rtol=0)


def test_float32_long_run_stays_finite_and_positive_definite():
    """60 s at 500 rows/s (30,000 steps) with 5 % missing readings, in float32."""
    rng = np.random.default_rng(9)
    tr, series = _trial(9, duration_s=60.0)
    series = _with_missing(series, rng, 0.05)
    series32 = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float32), series)
    params = ArmImuParams.from_physical(imu_mount=tr.imu_mount, dtype=jnp.float32)

    @eqx.filter_jit
    def covariances(params, series):
        def body(state, row):
            state, est = arm_imu_step(params, state, row)
            return state, (state.pos_cov, state.rot_cov, est.pos, est.rotvec)

        state = arm_imu_init(params, first_valid_rotation(series.exo_rot))
        return jax.lax.scan(body, state, series)[1]

    pos_cov, rot_cov, pos, rotvec = covariances(params, series32)
    assert pos_cov.dtype == jnp.float32
    for P in (np.asarray(pos_cov, np.float64), np.asarray(rot_cov, np.float64)):
        assert np.all(np.isfinite(P))
        np.testing.assert_array_equal(P, np.swapaxes(P, -1, -2))
        assert np.linalg.eigvalsh(P).min() > 0
    # And float32 follows float64.
    _, est64 = run_arm_imu(params.astype(jnp.float64), series)
    np.testing.assert_allclose(pos, est64.pos, atol=1e-5, rtol=0)  # m
    np.testing.assert_allclose(rotvec, est64.rotvec, atol=1e-4, rtol=0)  # rad


@pytest.mark.long
def test_gradient_is_finite_with_missing_readings():
    rng = np.random.default_rng(10)
    tr, series = _trial(10, duration_s=0.4)
    series = _with_missing(series, rng, 0.2)
    params = ArmImuParams.from_physical(imu_mount=tr.imu_mount, dtype=jnp.float64)
    exo = np.nan_to_num(np.asarray(series.exo_pos))

    @eqx.filter_jit
    @eqx.filter_grad
    def grad(params):
        _, est = scan_arm_imu(params, series)
        return jnp.mean((est.pos - exo) ** 2) + jnp.mean(est.rotvec**2)

    leaves = jax.tree_util.tree_leaves(grad(params))
    assert leaves and all(np.all(np.isfinite(g)) for g in leaves)


def test_runtime_shape_checking_is_on():
    with pytest.raises(TypeCheckError, match="exo_pos"):
        ArmImuSeries(dt=np.float64(0.01), exo_pos=np.zeros(4), exo_rot=np.eye(3),
                     imu_acc=np.zeros(3), imu_gyro=np.zeros(3))


def test_structural_errors_name_the_field():
    with pytest.raises(ValueError, match="sigma_pos"):
        ArmImuParams.from_physical(sigma_pos=[1e-3, 1e-3])
    with pytest.raises(ValueError, match="q_jerk"):
        ArmImuParams.from_physical(q_jerk=-1.0)
    with pytest.raises(ValueError, match="unknown value 'sigma_foo'"):
        ArmImuParams.from_physical(sigma_foo=1.0)
    with pytest.raises(ValueError, match="imu_mount"):
        ArmImuParams.from_physical(imu_mount=2 * np.eye(3))
    # Without runtime shape checking arm_imu_series raises the ValueError; with it (the test
    # run) the checker stops the call first. Both name the field.
    with pytest.raises((ValueError, TypeCheckError), match="exo_rot"):
        arm_imu_series(np.arange(3.0), np.zeros((3, 3)), np.zeros((2, 3, 3)), np.arange(4.0),
                       np.zeros((4, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="t_imu"):
        arm_imu_series(np.arange(3.0), np.zeros((3, 3)), np.zeros((3, 3, 3)),
                       np.array([0.0, 2.0, 1.0]), np.zeros((3, 3)), np.zeros((3, 3)))


def test_series_merges_two_timelines():
    t_exo = np.array([0.0, 0.01, 0.02])
    t_imu = np.array([0.0025, 0.005, 0.01, 0.0125])
    t, exo_row, imu_row, s = arm_imu_series(
        t_exo, np.ones((3, 3)), np.tile(np.eye(3), (3, 1, 1)), t_imu, np.ones((4, 3)),
        np.ones((4, 3)))
    np.testing.assert_allclose(t, [0.0, 0.0025, 0.005, 0.01, 0.0125, 0.02])
    np.testing.assert_array_equal(exo_row, [0, 3, 5])
    np.testing.assert_array_equal(imu_row, [1, 2, 3, 4])
    np.testing.assert_allclose(s.dt, [0.0, 0.0025, 0.0025, 0.005, 0.0025, 0.0075])
    np.testing.assert_array_equal(np.isfinite(s.exo_pos[:, 0]), [1, 0, 0, 1, 0, 1])
    np.testing.assert_array_equal(np.isfinite(s.imu_acc[:, 0]), [0, 1, 1, 1, 1, 0])


def test_simulator_is_seeded():
    a = simulate_arm_trial(np.random.default_rng(3), ArmSimConfig(duration_s=2.0))
    b = simulate_arm_trial(np.random.default_rng(3), ArmSimConfig(duration_s=2.0))
    c = simulate_arm_trial(np.random.default_rng(4), ArmSimConfig(duration_s=2.0))
    np.testing.assert_array_equal(a.imu_acc, b.imu_acc)
    np.testing.assert_array_equal(a.exo_pos, b.exo_pos)
    assert not np.allclose(a.exo_pos, c.exo_pos)
    # At rest the accelerometer reads gravity (about 9.81 m/s^2) and the tool is ~0.5 m out.
    rest = a.t_imu < 0.9
    assert abs(np.linalg.norm(a.imu_acc[rest], axis=1).mean() - 9.81) < 0.1
    assert 0.3 < np.linalg.norm(a.true_pos, axis=1).mean() < 0.7


def test_experiment_contract_and_fused_beats_exoskeleton():
    r = arm_imu_experiment(seed=0)
    assert set(r) == {"rmse", "details"}
    assert set(r["rmse"]) == {"exoskeleton", "fused"}
    for source in ("exoskeleton", "fused"):
        assert set(r["rmse"][source]) == {"position_mm", "orientation_deg"}
        assert all(isinstance(v, float) and np.isfinite(v) for v in r["rmse"][source].values())
    exo, fused = r["rmse"]["exoskeleton"], r["rmse"]["fused"]
    assert fused["position_mm"] < 0.8 * exo["position_mm"]
    assert fused["orientation_deg"] < 0.8 * exo["orientation_deg"]
    # Offline (both interpolated) the orientation still gains; nothing beats the manufacturing
    # floor by more than the tracking noise.
    interp = r["details"]["interpolated"]
    assert interp["fused"]["orientation_deg"] < interp["exoskeleton"]["orientation_deg"]
