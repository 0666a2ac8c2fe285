"""Independent plain-NumPy (float64) reference of the paper's standard KF and KCKF.

This module is a test oracle. It is written from the paper (Sections 2.2, 2.3, 3.1, 3.2,
Eqs. 1-21) and the project's conventions only; it does not import or read ``kckf_jax``.

Conventions (the paper's 3-axes-per-joint formulation restricted to the active axes):

* ``joints`` is a list of lists of axes, e.g. ``[["x"], ["y"], ["x"], ["y"]]``. Links are
  1..n+1 and joint i connects links i and i+1.
* Joint axes (J): (i, a) for i = 1..n and a in joint i's axes (x, y, z order).
* Torso axes (P): the axes used by at least one joint, in x, y, z order.
* K = J + P angle coordinates (theta then phi); state (Eq. 7) x = [theta, phi, b, b_phi],
  N = 2K.
* Gyro input u (Eq. 6): 3(n+1) values, [link1 x, y, z, link2 x, y, z, ...].
* Hall sensors (Eq. 5): M = 2J, for every joint axis sensor "l" then sensor "r".

Everything is written with explicit loops and dense matrices for clarity, not speed.
"""

from __future__ import annotations

import numpy as np

AXES = ("x", "y", "z")


# ---------------------------------------------------------------------------------------
# Layout of the state, input and measurement vectors (Eqs. 5-7)
# ---------------------------------------------------------------------------------------
def layout(joints) -> dict:
    """Index bookkeeping for a robot with the given joint axes."""
    n = len(joints)
    joint_axes: list[tuple[int, str]] = []  # (joint i in 1..n, axis)
    for i, axes in enumerate(joints, start=1):
        axes = list(axes)
        for a in axes:
            if a not in AXES:
                raise ValueError(f"unknown axis {a!r}")
        if sorted(axes, key=AXES.index) != axes or len(set(axes)) != len(axes):
            raise ValueError(f"joint {i} axes must be unique and in x, y, z order: {axes}")
        for a in axes:
            joint_axes.append((i, a))
    used = {a for _, a in joint_axes}
    torso_axes = [a for a in AXES if a in used]

    J = len(joint_axes)
    P = len(torso_axes)
    K = J + P
    N = 2 * K
    M = 2 * J
    n_gyro = 3 * (n + 1)

    def gyro_index(link: int, axis: str) -> int:
        """Column of u for link (1..n+1) and axis."""
        return 3 * (link - 1) + AXES.index(axis)

    # Rate map (Eq. 2 / Eqs. 9-10): each angle coordinate's rate is u[plus] - u[minus].
    rate_plus = np.zeros(K, dtype=int)
    rate_minus = np.zeros(K, dtype=int)
    for j, (i, a) in enumerate(joint_axes):
        rate_plus[j] = gyro_index(i + 1, a)  # omega_{i+1}
        rate_minus[j] = gyro_index(i, a)  # omega_i
    for p, a in enumerate(torso_axes):
        rate_plus[J + p] = gyro_index(n + 1, a)  # end-effector link
        rate_minus[J + p] = gyro_index(1, a)  # base link

    # Forward kinematics selection (Eq. 14): phi_p = sum of joint angles about axis p.
    S = np.zeros((P, J))
    for j, (_, a) in enumerate(joint_axes):
        S[torso_axes.index(a), j] = 1.0

    # Hall sensors (Eq. 5): sensor 2j is "l", 2j+1 is "r", both for joint axis j.
    sensors = []
    for j in range(J):
        sensors.append((j, "l"))
        sensors.append((j, "r"))
    sensor_joint_axis = np.array([s[0] for s in sensors], dtype=int)

    return dict(
        n=n,
        J=J,
        P=P,
        K=K,
        N=N,
        M=M,
        n_gyro=n_gyro,
        joint_axes=joint_axes,
        torso_axes=torso_axes,
        S=S,
        rate_plus=rate_plus,
        rate_minus=rate_minus,
        sensors=sensors,
        sensor_joint_axis=sensor_joint_axis,
    )


# ---------------------------------------------------------------------------------------
# Hall sensor model (Eq. 1 generalised per sensor) and its noise (Eq. 20 generalised)
# ---------------------------------------------------------------------------------------
def hall_angle(V, params, m):
    """Eq. 1: angle = sign_m (a_m exp(b_m V) - c_m exp(-d_m V)), in radians."""
    a, b, c, d, s = (float(np.asarray(params[k])[m]) for k in ("a", "b", "c", "d", "sign"))
    return s * (a * np.exp(b * V) - c * np.exp(-d * V))


def hall_slope(V, params, m):
    """d angle / d V of Eq. 1."""
    a, b, c, d, s = (float(np.asarray(params[k])[m]) for k in ("a", "b", "c", "d", "sign"))
    return s * (a * b * np.exp(b * V) + c * d * np.exp(-d * V))


def hall_variance(V, params, m):
    """Measurement noise variance of sensor m given its voltage reading V."""
    sig = float(np.asarray(params["sigma_hall"])[m])
    model = params.get("hall_noise", "angle")
    if model == "angle":
        return sig**2
    if model == "voltage":
        sig_v = float(np.asarray(params["sigma_hall_v"])[m])
        return (hall_slope(V, params, m) * sig_v) ** 2 + sig**2
    raise ValueError(f"unknown hall_noise model {model!r}")


# ---------------------------------------------------------------------------------------
# Model matrices (Eqs. 8, 11, 12, 13, 17, 20)
# ---------------------------------------------------------------------------------------
def _A(L, ts):
    """Eq. 11: angles integrate minus their bias times ts; biases are constant."""
    K, N = L["K"], L["N"]
    A = np.eye(N)
    for k in range(K):
        A[k, K + k] = -ts
    return A


def _B(L, ts):
    """Eq. 12 (rows follow Eqs. 9 and 10): angle rate = u[plus] - u[minus]; bias rows 0."""
    K, N = L["K"], L["N"]
    B = np.zeros((N, L["n_gyro"]))
    for k in range(K):
        B[k, L["rate_plus"][k]] += ts
        B[k, L["rate_minus"][k]] -= ts
    return B


def _Q(L, params, ts):
    """Eq. 13 per angle/bias pair, scaled by q_k, plus optional random walks."""
    K, N = L["K"], L["N"]
    q = np.asarray(params["q"], dtype=float)
    arw = np.asarray(params["angle_rw"], dtype=float)
    brw = np.asarray(params["bias_rw"], dtype=float)
    Q = np.zeros((N, N))
    for k in range(K):
        Q[k, k] = q[k] * ts**4 / 4.0 + arw[k] ** 2 * ts
        Q[k, K + k] = q[k] * ts**3 / 2.0
        Q[K + k, k] = q[k] * ts**3 / 2.0
        Q[K + k, K + k] = q[k] * ts**2 + brw[k] ** 2 * ts
    return Q


def _C(L):
    """Eq. 8: both Hall sensors of joint axis j measure theta_j."""
    C = np.zeros((L["M"], L["N"]))
    for m, j in enumerate(L["sensor_joint_axis"]):
        C[m, j] = 1.0
    return C


def _D(L):
    """Eq. 17: D = [S, -I_P, 0, 0] so that D x = sum(theta) - phi = 0 (Eqs. 14, 15)."""
    J, P, K, N = L["J"], L["P"], L["K"], L["N"]
    D = np.zeros((P, N))
    D[:, :J] = L["S"]
    D[:, J:K] = -np.eye(P)
    return D


def paper_matrices(joints, params, ts) -> dict:
    """A, B, Q, C, D and R (all M sensors, "angle" noise model) for step ts."""
    L = layout(joints)
    sig = np.asarray(params["sigma_hall"], dtype=float)
    R = np.diag(sig**2)  # Eq. 20, Hall block
    return dict(A=_A(L, ts), B=_B(L, ts), Q=_Q(L, params, ts), C=_C(L), D=_D(L), R=R)


# ---------------------------------------------------------------------------------------
# Initial covariance
# ---------------------------------------------------------------------------------------
def _P0(L, params, method):
    J, K, N = L["J"], L["K"], L["N"]
    p0a = np.asarray(params["p0_angle"], dtype=float)
    p0b = np.asarray(params["p0_bias"], dtype=float)
    if method == "kf":
        return np.diag(np.concatenate([p0a**2, p0b**2]))
    # KCKF: the prior must satisfy D x = 0. With z = [theta (J), b (J), b_phi (P)],
    # x = T z where phi = S theta and everything else is copied.
    T = np.zeros((N, J + K))
    T[:J, :J] = np.eye(J)  # theta
    T[J:K, :J] = L["S"]  # phi = S theta  (Eq. 14)
    T[K:, J:] = np.eye(K)  # b, b_phi
    Pz = np.diag(np.concatenate([p0a[:J] ** 2, p0b**2]))
    return T @ Pz @ T.T


def _dt(t):
    t = np.asarray(t, dtype=float)
    dt = np.zeros_like(t)
    dt[1:] = np.diff(t)
    return dt


def usable_readings(joints, gyro, hall_v, params):
    """The readings the filter may use (the session format's rules, written here again):

    * a Hall voltage outside ``params["hall_v_range"]``, or within 0.5 % of its span of
      either end (a railed ADC), or whose Eq. 1 angle exceeds ``params["joint_range_rad"]``
      in magnitude, is not a measurement;
    * a gyro rate at 99.9 % of ``params["gyro_range_rad_s"]`` or beyond is saturated;
    * then a gyro channel that a rate uses (Eq. 2) and that has no reading takes the reading
      of the nearest link turning with it about that axis (no joint about that axis in
      between, the lower link first at equal distance), if that one has one.
    """
    L = layout(joints)
    gyro = np.array(gyro, dtype=float)
    hall_v = np.array(hall_v, dtype=float)
    lo, hi = params.get("hall_v_range", (0.0, 3.3))
    rail = 0.005 * (hi - lo)
    reach = params.get("joint_range_rad", 2 * np.pi / 3)
    full = params.get("gyro_range_rad_s", 4000 * np.pi / 180)
    for m in range(L["M"]):
        V = hall_v[:, m]
        with np.errstate(over="ignore", invalid="ignore"):
            ang = hall_angle(np.where(np.isfinite(V), V, 1.65), params, m)
            bad = (V < lo + rail) | (V > hi - rail) | (np.abs(ang) > reach)
        hall_v[bad, m] = np.nan
    with np.errstate(invalid="ignore"):
        gyro[np.abs(gyro) >= 0.999 * full] = np.nan
    n = L["n"]
    used = set(L["rate_plus"]) | set(L["rate_minus"])
    cols = []
    for c in range(L["n_gyro"]):
        link, a = c // 3 + 1, AXES[c % 3]
        col = gyro[:, c].copy()
        if c in used:
            # Candidate links, nearest first; walking stops at a joint about axis a.
            down, up = [], []
            k = link
            while k > 1 and a not in joints[k - 2]:  # joint k-1 joins links k-1 and k
                k -= 1
                down.append(k)
            k = link
            while k < n + 1 and a not in joints[k - 1]:  # joint k joins links k and k+1
                k += 1
                up.append(k)
            order = []
            for d in range(max(len(down), len(up))):
                order += down[d:d + 1] + up[d:d + 1]
            for other in order:
                src = gyro[:, 3 * (other - 1) + AXES.index(a)]
                col = np.where(np.isnan(col), src, col)
        cols.append(col)
    return np.stack(cols, axis=1), hall_v


def _update_hold(hold, row):
    """Gyro hold: keep the last finite value of each channel."""
    row = np.asarray(row, dtype=float)
    ok = np.isfinite(row)
    hold = hold.copy()
    hold[ok] = row[ok]
    return hold


# ---------------------------------------------------------------------------------------
# The filters (Eqs. 3, 4, 16, 18-20)
# ---------------------------------------------------------------------------------------
def reference_filter(joints, t, gyro, hall_v, params, method) -> dict:
    """Run the standard KF ("kf") or the KCKF ("kckf") over a recording."""
    if method not in ("kf", "kckf"):
        raise ValueError(f"unknown method {method!r}")
    L = layout(joints)
    K, N, M = L["K"], L["N"], L["M"]
    t = np.asarray(t, dtype=float)
    gyro = np.asarray(gyro, dtype=float)
    gyro, hall_v = usable_readings(joints, gyro, hall_v, params)
    T_len = t.shape[0]
    assert gyro.shape == (T_len, L["n_gyro"])
    assert hall_v.shape == (T_len, M)
    dt = _dt(t)
    C = _C(L)
    D = _D(L)

    x = np.zeros(N)
    P = _P0(L, params, method)
    u_hold = np.zeros(L["n_gyro"])

    xs = np.zeros((T_len, N))
    Ps = np.zeros((T_len, N, N))
    xp, Pp, As = np.zeros((T_len, N)), np.zeros((T_len, N, N)), np.zeros((T_len, N, N))
    for k in range(T_len):
        ts = dt[k]
        # --- Prediction (Eq. 3 with A Eq. 11, B Eq. 12, Q Eq. 13), held rates of row k-1.
        A = np.eye(N)
        if ts > 0:
            A = _A(L, ts)
            B = _B(L, ts)
            Q = _Q(L, params, ts)
            x = A @ x + B @ u_hold
            P = A @ P @ A.T + Q
        xp[k], Pp[k], As[k] = x, P, A  # the prediction of row k (the smoother's)

        # --- Measurement update (Eqs. 4, 8 / 16, 18-20).
        H_rows, y_rows, r_rows = [], [], []
        for m in range(M):
            V = hall_v[k, m]
            if not np.isfinite(V):
                continue  # a missing reading removes only its own row
            H_rows.append(C[m])
            y_rows.append(hall_angle(V, params, m))  # Eq. 1
            r_rows.append(hall_variance(V, params, m))  # Eq. 20 (generalised)
        if method == "kckf" and ts > 0:
            for p in range(L["P"]):
                H_rows.append(D[p])  # Eq. 19, last block row
                y_rows.append(0.0)  # Eq. 18, d = 0
                r_rows.append(0.0)  # Eq. 20, perfect measurement
        if H_rows:
            H = np.array(H_rows)
            y = np.array(y_rows)
            R = np.diag(np.array(r_rows))
            Sinn = H @ P @ H.T + R
            # K = P H^T S^-1  <=>  S K^T = H P^T  (S symmetric)
            Kg = np.linalg.solve(Sinn, H @ P.T).T
            x = x + Kg @ (y - H @ x)
            IKH = np.eye(N) - Kg @ H
            P = IKH @ P @ IKH.T + Kg @ R @ Kg.T  # Joseph form

        xs[k] = x
        Ps[k] = P
        # --- Gyro hold takes row k's finite values after the update of step k.
        u_hold = _update_hold(u_hold, gyro[k])

    return dict(angles=xs[:, :K].copy(), bias=xs[:, K:].copy(), P=Ps, x=xs, x_pred=xp,
                P_pred=Pp, A=As)


# ---------------------------------------------------------------------------------------
# Baselines: pure gyro integration (Eq. 2) and single-side Hall sensors (Eq. 1)
# ---------------------------------------------------------------------------------------
def reference_baseline(joints, t, gyro, hall_v, params, method) -> np.ndarray:
    L = layout(joints)
    J, K = L["J"], L["K"]
    t = np.asarray(t, dtype=float)
    gyro = np.asarray(gyro, dtype=float)
    gyro, hall_v = usable_readings(joints, gyro, hall_v, params)
    T_len = t.shape[0]
    dt = _dt(t)
    out = np.full((T_len, K), np.nan)

    if method == "gyro":
        angle = np.zeros(K)
        u_hold = np.zeros(L["n_gyro"])
        for k in range(T_len):
            rate = u_hold[L["rate_plus"]] - u_hold[L["rate_minus"]]  # Eqs. 2, 9, 10
            angle = angle + dt[k] * rate
            out[k] = angle
            u_hold = _update_hold(u_hold, gyro[k])
        return out

    if method in ("hall_l", "hall_r"):
        side = 0 if method == "hall_l" else 1
        last = np.full(J, np.nan)
        for k in range(T_len):
            for j in range(J):
                m = 2 * j + side
                V = hall_v[k, m]
                if np.isfinite(V):
                    last[j] = hall_angle(V, params, m)
            out[k, :J] = last
        return out

    raise ValueError(f"unknown baseline {method!r}")


# ---------------------------------------------------------------------------------------
# Observability (Eq. 21)
# ---------------------------------------------------------------------------------------
def observability_rank(joints, constrained: bool, ts=0.01) -> int:
    """Rank of O = [C; C A; ...; C A^(N-1)] with C -> [C; D] for the KCKF (Eq. 19)."""
    L = layout(joints)
    N = L["N"]
    A = _A(L, ts)
    C = _C(L)
    if constrained:
        C = np.vstack([C, _D(L)])
    blocks = []
    Ak = np.eye(N)
    for _ in range(N):
        blocks.append(C @ Ak)
        Ak = Ak @ A
    return int(np.linalg.matrix_rank(np.vstack(blocks)))


# ---------------------------------------------------------------------------------------
# The fixed-interval (RTS) smoother, on the paper's full state
# ---------------------------------------------------------------------------------------
def reference_smoother(joints, t, gyro, hall_v, params, method) -> dict:
    """The RTS smoother over ``reference_filter``'s recursion, in the paper's coordinates.

    Forward: ``reference_filter`` itself (prediction, then every measurement row, Joseph
    form), which keeps each row's prediction. Backward (Rauch, Tung and Striebel 1965):
    ``G_k = P_k A' pinv(P^-_{k+1})``, ``x^s_k = x_k + G_k (x^s_{k+1} - x^-_{k+1})``,
    ``P^s_k = P_k + G_k (P^s_{k+1} - P^-_{k+1}) G_k'``. The KCKF's perfect measurement leaves
    ``P`` singular in the constraint's direction, hence the pseudo-inverse (float64)."""
    f = reference_filter(joints, t, gyro, hall_v, params, method)
    xs, Ps, xp, Pp, As = f["x"], f["P"], f["x_pred"], f["P_pred"], f["A"]
    K, T_len = layout(joints)["K"], xs.shape[0]
    x_s, P_s = xs.copy(), Ps.copy()
    for k in range(T_len - 2, -1, -1):
        G = Ps[k] @ As[k + 1].T @ np.linalg.pinv(Pp[k + 1], rcond=1e-13, hermitian=True)
        x_s[k] = xs[k] + G @ (x_s[k + 1] - xp[k + 1])
        P_s[k] = Ps[k] + G @ (P_s[k + 1] - Pp[k + 1]) @ G.T
    return dict(angles=x_s[:, :K], bias=x_s[:, K:], P=P_s, filtered=xs[:, :K])
