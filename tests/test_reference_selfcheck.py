"""Self-checks of the NumPy reference oracle (tests/reference.py); no kckf_jax needed."""

from __future__ import annotations

import numpy as np
import pytest
from reference import (
    layout,
    observability_rank,
    paper_matrices,
    reference_baseline,
    reference_filter,
)

XYXY = [["x"], ["y"], ["x"], ["y"]]
XYZ4 = [["x", "y", "z"]] * 4
MIXED = [["x", "z"], ["y"], ["x", "y", "z"]]


def make_params(joints, hall_noise="angle"):
    L = layout(joints)
    K, M = L["K"], L["M"]
    deg = np.pi / 180.0
    sign = np.tile([1.0, -1.0], M // 2)
    return dict(
        q=np.full(K, 5.0),
        angle_rw=np.full(K, 0.01),
        bias_rw=np.full(K, 1e-3),
        sigma_hall=np.full(M, 3.2 * deg),
        sigma_hall_v=np.full(M, 0.01),
        p0_angle=np.full(K, 0.1),
        p0_bias=np.full(K, 0.05),
        # Eq. 1 coefficients expressed in radians
        a=np.full(M, 0.07 * deg),
        b=np.full(M, 2.87),
        c=np.full(M, 2.22e5 * deg),
        d=np.full(M, 8.43),
        sign=sign,
        hall_noise=hall_noise,
    )


def invert_hall(angle, params, m, lo=0.5, hi=3.0, iters=80):
    """Voltage giving `angle` through Eq. 1 (monotone in V) by bisection."""
    s = params["sign"][m]
    a, b, c, d = (params[k][m] for k in ("a", "b", "c", "d"))
    target = np.asarray(angle) * s
    lo = np.full_like(target, lo)
    hi = np.full_like(target, hi)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        f = a * np.exp(b * mid) - c * np.exp(-d * mid)
        below = f < target
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def make_recording(joints, params, T=300, seed=0, missing=0.1):
    """Synthetic recording: true joint angles, biased noisy gyros, noisy Hall voltages."""
    rng = np.random.default_rng(seed)
    L = layout(joints)
    n, J = L["n"], L["J"]
    t = np.cumsum(rng.uniform(0.005, 0.015, size=T))
    t -= t[0]
    # Kinematically consistent motion (Eqs. 2, 14): the base link moves freely (no fixed
    # base) and link i+1 = link i + the rates of joint i about its own axes only.
    dt = np.diff(t, prepend=t[0])
    w = np.zeros((T, n + 1, 3))
    for ax in range(3):
        f = rng.uniform(0.1, 0.5)
        w[:, 0, ax] = 0.3 * np.sin(2 * np.pi * f * t + rng.uniform(0, 6))
    theta_rate = np.zeros((T, J))
    for j in range(J):
        f = rng.uniform(0.2, 1.0)
        theta_rate[:, j] = 0.5 * np.sin(2 * np.pi * f * t + rng.uniform(0, 6))
    for i in range(1, n + 1):
        w[:, i] = w[:, i - 1]
        for j, (ji, a) in enumerate(L["joint_axes"]):
            if ji == i:
                w[:, i, "xyz".index(a)] += theta_rate[:, j]
    bias = rng.normal(0, 0.02, size=(n + 1, 3))
    gyro = (w + bias + rng.normal(0, 0.01, size=w.shape)).reshape(T, 3 * (n + 1))
    gyro[rng.uniform(size=gyro.shape) < missing] = np.nan
    # true joint angles (rectangle rule with the previous rate, like the filter)
    theta = np.zeros((T, J))
    theta[1:] = np.cumsum(theta_rate[:-1] * dt[1:, None], axis=0)
    # true joint biases b_(i,a) = bias[i+1, a] - bias[i, a], and b_phi
    true_bias = np.array(
        [bias[i, "xyz".index(a)] - bias[i - 1, "xyz".index(a)] for i, a in L["joint_axes"]]
        + [bias[n, "xyz".index(a)] - bias[0, "xyz".index(a)] for a in L["torso_axes"]]
    )
    hall_v = np.zeros((T, L["M"]))
    for m, j in enumerate(L["sensor_joint_axis"]):
        meas = theta[:, j] + rng.normal(0, params["sigma_hall"][m], size=T)
        hall_v[:, m] = invert_hall(meas, params, m)
    hall_v[rng.uniform(size=hall_v.shape) < missing] = np.nan
    return t, gyro, hall_v, theta, true_bias


# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "joints, N, rank_kf, rank_kckf",
    [(XYXY, 12, 8, 12), (XYZ4, 30, 24, 30)],
)
def test_observability_claims(joints, N, rank_kf, rank_kckf):
    L = layout(joints)
    assert L["N"] == N
    assert observability_rank(joints, constrained=False) == rank_kf == N - 2 * L["P"]
    assert observability_rank(joints, constrained=True) == rank_kckf == N


def test_layout_and_matrices_follow_the_paper():
    L = layout(XYXY)
    assert (L["J"], L["P"], L["K"], L["N"], L["M"]) == (4, 2, 6, 12, 8)
    assert L["torso_axes"] == ["x", "y"]
    np.testing.assert_array_equal(L["S"], [[1, 0, 1, 0], [0, 1, 0, 1]])
    ts = 0.01
    mats = paper_matrices(XYXY, make_params(XYXY), ts)
    A, B, C, D = mats["A"], mats["B"], mats["C"], mats["D"]
    # Eq. 11: theta_j <- theta_j - b_j ts
    assert A[0, 6] == -ts and A[4, 10] == -ts and np.allclose(np.diag(A), 1.0)
    # Eq. 9: joint 1 (x) rate = omega_2x - omega_1x; Eq. 10: phi_x = omega_5x - omega_1x
    assert B[0, 3] == ts and B[0, 0] == -ts
    assert B[4, 12] == ts and B[4, 0] == -ts
    assert B[5, 13] == ts and B[5, 1] == -ts
    assert np.all(B[6:] == 0)
    # Eq. 8: both sensors of a joint axis measure it
    assert C[0, 0] == C[1, 0] == 1 and C[6, 3] == C[7, 3] == 1 and C.sum() == 8
    # Eq. 17
    np.testing.assert_array_equal(D[:, :6], [[1, 0, 1, 0, -1, 0], [0, 1, 0, 1, 0, -1]])
    assert np.all(D[:, 6:] == 0)
    # Eq. 13 for q = 1, no random walks
    p = make_params(XYXY)
    p.update(q=np.ones(6), angle_rw=np.zeros(6), bias_rw=np.zeros(6))
    Q = paper_matrices(XYXY, p, ts)["Q"]
    I6 = np.eye(6)
    np.testing.assert_allclose(
        Q, np.block([[ts**4 / 4 * I6, ts**3 / 2 * I6], [ts**3 / 2 * I6, ts**2 * I6]])
    )


@pytest.mark.parametrize("joints", [XYXY, XYZ4, MIXED])
@pytest.mark.parametrize("hall_noise", ["angle", "voltage"])
def test_kckf_constraint_and_covariance(joints, hall_noise):
    params = make_params(joints, hall_noise)
    t, gyro, hall_v, _, _ = make_recording(joints, params, T=200, seed=1)
    L = layout(joints)
    D = paper_matrices(joints, params, 0.01)["D"]
    for method in ("kf", "kckf"):
        out = reference_filter(joints, t, gyro, hall_v, params, method)
        for k in range(len(t)):
            P = out["P"][k]
            assert np.allclose(P, P.T, atol=1e-12)
            assert np.linalg.eigvalsh(0.5 * (P + P.T)).min() > -1e-10
        if method == "kckf":
            assert np.abs(out["x"] @ D.T).max() < 1e-9
        np.testing.assert_array_equal(out["angles"], out["x"][:, : L["K"]])
        np.testing.assert_array_equal(out["bias"], out["x"][:, L["K"] :])


@pytest.mark.parametrize("joints", [XYXY, MIXED])
def test_no_hall_kf_is_pure_integration(joints):
    params = make_params(joints)
    t, gyro, hall_v, _, _ = make_recording(joints, params, T=150, seed=2)
    hall_v[:] = np.nan
    out = reference_filter(joints, t, gyro, hall_v, params, "kf")
    base = reference_baseline(joints, t, gyro, hall_v, params, "gyro")
    np.testing.assert_allclose(out["angles"], base, rtol=0, atol=1e-12)
    assert np.all(out["bias"] == 0)


def test_gyro_baseline_timing_convention():
    joints = [["x"]]
    t = np.array([0.0, 0.1, 0.3, 0.4])
    gyro = np.zeros((4, 6))
    gyro[:, 3] = [1.0, np.nan, 2.0, 5.0]  # link 2 x; link 1 stays 0
    hall_v = np.full((4, 2), np.nan)
    base = reference_baseline(joints, t, gyro, hall_v, make_params(joints), "gyro")
    # angle_k = angle_{k-1} + dt_k * held rate before row k; phi_x is the same here
    expected = np.array([0.0, 0.1 * 1.0, 0.1 + 0.2 * 1.0, 0.3 + 0.1 * 2.0])
    np.testing.assert_allclose(base[:, 0], expected)
    np.testing.assert_allclose(base[:, 1], expected)


def test_hall_baselines_hold_last_value():
    joints = [["x"], ["y"]]
    params = make_params(joints)
    t = np.arange(4) * 0.01
    gyro = np.zeros((4, 9))
    hall_v = np.full((4, 4), 1.6)
    hall_v[0, 0] = np.nan  # l of joint 1 missing first
    hall_v[2, 2] = np.nan  # l of joint 2 missing in the middle
    hall_v[1, 2] = 1.7
    hl = reference_baseline(joints, t, gyro, hall_v, params, "hall_l")
    hr = reference_baseline(joints, t, gyro, hall_v, params, "hall_r")
    assert np.isnan(hl[0, 0]) and np.all(np.isfinite(hl[1:, :2]))
    assert hl[2, 1] == hl[1, 1]
    assert np.all(np.isnan(hl[:, 2:])) and np.all(np.isnan(hr[:, 2:]))
    # sensor signs alternate (+ for l, - for r) in make_params
    np.testing.assert_allclose(hr[3, :2], -hl[3, :2])


def test_kf_update_equals_sequential_scalar_updates():
    """A single stacked update (step 0, dt = 0) equals processing the rows one by one."""
    joints = MIXED
    for hall_noise in ("angle", "voltage"):
        params = make_params(joints, hall_noise)
        L = layout(joints)
        hall_v = np.full((1, L["M"]), np.nan)
        rows = [0, 3, 4, 7]
        hall_v[0, rows] = [1.5, 1.6, 1.7, 1.55]
        out = reference_filter(joints, np.array([0.0]), np.zeros((1, 3 * 4)), hall_v, params, "kf")
        xs = np.zeros(L["N"])
        Ps = np.diag(np.r_[params["p0_angle"] ** 2, params["p0_bias"] ** 2])
        for m in rows:
            V = hall_v[0, m]
            s, a, b, c, d = (params[k][m] for k in ("sign", "a", "b", "c", "d"))
            y = s * (a * np.exp(b * V) - c * np.exp(-d * V))
            r = params["sigma_hall"][m] ** 2
            if hall_noise == "voltage":
                slope = s * (a * b * np.exp(b * V) + c * d * np.exp(-d * V))
                r += (slope * params["sigma_hall_v"][m]) ** 2
            h = np.zeros(L["N"])
            h[L["sensor_joint_axis"][m]] = 1.0
            kg = Ps @ h / (h @ Ps @ h + r)
            xs = xs + kg * (y - h @ xs)
            Ps = Ps - np.outer(kg, h @ Ps)
        np.testing.assert_allclose(out["x"][0], xs, rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(out["P"][0], Ps, rtol=1e-10, atol=1e-13)


def test_kckf_initial_covariance_and_first_step():
    joints = XYXY
    params = make_params(joints)
    L = layout(joints)
    t = np.array([0.0])
    out = reference_filter(
        joints, t, np.zeros((1, 15)), np.full((1, L["M"]), np.nan), params, "kckf"
    )
    P0 = out["P"][0]
    D = paper_matrices(joints, params, 0.01)["D"]
    np.testing.assert_allclose(D @ P0, 0, atol=1e-15)
    np.testing.assert_allclose(np.diag(P0)[: L["J"]], params["p0_angle"][: L["J"]] ** 2)
    np.testing.assert_allclose(np.diag(P0)[L["J"] : L["K"]], 2 * 0.1**2)
    np.testing.assert_allclose(np.diag(P0)[L["K"] :], params["p0_bias"] ** 2)
    out_kf = reference_filter(
        joints, t, np.zeros((1, 15)), np.full((1, L["M"]), np.nan), params, "kf"
    )
    np.testing.assert_allclose(
        out_kf["P"][0], np.diag(np.r_[params["p0_angle"] ** 2, params["p0_bias"] ** 2])
    )


def test_filters_track_truth_and_kf_torso_is_unobserved():
    joints = XYXY
    params = make_params(joints)
    t, gyro, hall_v, theta, _ = make_recording(joints, params, T=1500, seed=4, missing=0.05)
    L = layout(joints)
    J, K = L["J"], L["K"]
    kf = reference_filter(joints, t, gyro, hall_v, params, "kf")
    kckf = reference_filter(joints, t, gyro, hall_v, params, "kckf")
    hall = reference_baseline(joints, t, gyro, hall_v, params, "hall_l")
    gyro_int = reference_baseline(joints, t, gyro, hall_v, params, "gyro")
    tail = slice(500, None)

    def rmse(est):
        return np.sqrt(np.mean((est[tail, :J] - theta[tail]) ** 2))

    assert rmse(kckf["angles"]) < rmse(hall) < rmse(gyro_int)
    assert rmse(kf["angles"]) < rmse(hall)
    # Standard KF: phi and b_phi receive no information (Section 3.3), so phi is the pure
    # gyro integration and b_phi stays at its prior mean 0.
    np.testing.assert_allclose(kf["angles"][:, J:K], gyro_int[:, J:K], atol=1e-12)
    assert np.all(kf["bias"][:, J:] == 0)
    # KCKF: phi follows the forward kinematics of the estimated joints (Eq. 14).
    np.testing.assert_allclose(kckf["angles"][:, J:K], kckf["angles"][:, :J] @ L["S"].T, atol=1e-9)
