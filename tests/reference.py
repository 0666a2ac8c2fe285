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


def _row_rules(joints, gyro, hall_v, params):
    """Readings that cannot be measurements, judged one by one (the session format's rules):

    * a Hall voltage outside ``params["hall_v_range"]``, or within 0.5 % of its span of
      either end (a railed ADC), or whose Eq. 1 angle exceeds ``params["joint_range_rad"]``
      in magnitude, is not a measurement;
    * a gyro rate at 99.9 % of ``params["gyro_range_rad_s"]`` or beyond is saturated.
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
    return gyro, hall_v


def _stand_in_order(joints):
    """Per gyro column a rate uses (Eq. 2), the columns that measure the same rate: the same
    axis on the links reached without crossing a joint about that axis, nearest first (the
    lower link first at equal distance)."""
    L = layout(joints)
    n = L["n"]
    used = set(L["rate_plus"]) | set(L["rate_minus"])
    order = {}
    for c in used:
        link, a = c // 3 + 1, AXES[c % 3]
        down, up = [], []
        k = link
        while k > 1 and a not in joints[k - 2]:  # joint k-1 joins links k-1 and k
            k -= 1
            down.append(k)
        k = link
        while k < n + 1 and a not in joints[k - 1]:  # joint k joins links k and k+1
            k += 1
            up.append(k)
        links = []
        for d in range(max(len(down), len(up))):
            links += down[d:d + 1] + up[d:d + 1]
        order[c] = [3 * (other - 1) + AXES.index(a) for other in links]
    return order


def usable_readings(joints, t, gyro, hall_v, params):
    """The readings the filter may use: ``_row_rules``, then over time (``params["health"]``:
    the monitor's constants, by name):

    * a gyro reading equal to the channel's last CLIP_REPEATS readings, at 90 % or more of the
      largest magnitude the channel has read and at least CLIP_MIN_RAD_S, is clipped: not used;
    * a gyro column a rate uses, with a stand-in (its first), whose difference from it
      (exponential averages over PAIR_FAST_S and, while neither of the two is flagged,
      PAIR_SLOW_S) moves by more than BIAS_STEP_RAD_S, while its joints' evidence (the sum,
      over the joint axes whose rate reads it, of how far the mean residual of the joint's
      used Hall sensors, averaged over CM_FAST_S, is from its average over CM_SLOW_S, as of
      the row before) is at least BIAS_EVIDENCE_RAD and twice its stand-in's, and whose
      stand-in was not flagged on the row before, has a bias step if, as of the row before,
      the pair had been compared for PAIR_SLOW_S (summed time steps with both readings) and
      the move exceeds SPREAD_FACTOR times the pair's spread (the RMS of the move: the mean
      of its square over the rows the pair was compared, weighting each by dt / min(
      PAIR_SPREAD_S, the compared time so far including it), updated while neither is
      flagged): not used until the
      difference is back within half of the larger of BIAS_STEP_RAD_S and SPREAD_FACTOR
      times the spread (as of this row) for READMIT_S;
    * a gyro column a rate uses without a reading for more than HOLD_S (summed time steps)
      takes its first stand-in's (``_stand_in_order``); the rates below hold a column's
      last value;
    * every joint axis has a reference angle: set from the mean of its used Hall angles where
      it starts (the first row, or after a step longer than RESTART_S), else the joint rate
      from the gyros integrated and pulled towards that mean by min(1, dt / REF_TAU_S);
    * every Hall sensor's residual against the reference changes from one reading to its
      next by (Hall angle change) - dt * (joint rate); squared, divided by 2 (slope sigma_v)^2
      (sigma_v: the sensor's voltage noise, or MONITOR_MIN_SIGMA_V where that is larger)
      + (MOTION_FRACTION |dt rate| + MOTION_FLOOR_RAD)^2, averaged with weight
      min(1, dt / ROUGH_TAU_S), it is the roughness; above ROUGH_HIGH the sensor is isolated,
      if its joint's pair roughness is above ROUGH_HIGH too or its partner (the other sensor
      of the joint axis) had no reading or was isolated on the row before. The pair
      roughness: where both sensors' residual changes are judged, the change of their
      difference squared over the sum of the two sensors' noise terms (2 (slope sigma_v)^2
      each) and twice (MOTION_FRACTION m + MOTION_FLOOR_RAD)^2, m the larger of |dt rate| and
      the smaller of the two sensors' own angle changes (residual change + dt rate),
      averaged alike;
    * a sensor whose voltage is unchanged for STUCK_S while the joint moved STUCK_MOVE_RAD is
      isolated;
    * an isolated sensor is used again once calm (roughness below ROUGH_LOW, not stuck, read)
      for READMIT_S.

    ``params["no_gyro_pairs"]``: no stand-ins and no pair check (exact kinematics).
    """
    L = layout(joints)
    J, M, G = L["J"], L["M"], L["n_gyro"]
    gyro, hall_v = _row_rules(joints, gyro, hall_v, params)
    H = params.get("health")
    if H is None:  # the paper's filter alone (this module's own checks)
        return gyro, hall_v
    # Under exact kinematics (the rotation-aware KCKF) no two gyros measure the same rate.
    order = ({c: [] for c in _stand_in_order(joints)} if params.get("no_gyro_pairs")
             else _stand_in_order(joints))
    dt = _dt(t)
    T_len = len(t)
    g_out, v_out = np.full_like(gyro, np.nan), hall_v.copy()
    g_last, g_rep, g_peak, g_miss = np.full(G, np.nan), np.zeros(G), np.zeros(G), np.zeros(G)
    mate = {c: (mates[0] if mates else -1) for c, mates in order.items()}
    d_fast, d_slow = np.full(G, np.nan), np.full(G, np.nan)
    bad, bad_calm = np.zeros(G, bool), np.zeros(G)
    spread, paired = np.zeros(G), np.zeros(G)
    pair_rough = np.zeros(J)
    cm_fast, cm_slow = np.full(J, np.nan), np.full(J, np.nan)
    uses = {c: [j for j in range(J) if c in (L["rate_plus"][j], L["rate_minus"][j])]
            for c in range(G)}
    hold = np.zeros(G)
    ref, ref_ok = np.zeros(J), np.zeros(J, bool)
    last_v, last_e = np.full(M, np.nan), np.full(M, np.nan)
    rough, still, moved = np.zeros(M), np.zeros(M), np.zeros(M)
    iso, calm = np.zeros(M, bool), np.zeros(M)
    for k in range(T_len):
        g = gyro[k].copy()
        for c in range(G):
            if np.isfinite(g[c]):
                g_rep[c] = g_rep[c] + 1 if g[c] == g_last[c] else 0
                g_peak[c] = max(g_peak[c], abs(g[c]))
                g_last[c] = g[c]
                if (g_rep[c] >= H["CLIP_REPEATS"] and abs(g[c]) >= 0.9 * g_peak[c]
                        and abs(g[c]) >= H["CLIP_MIN_RAD_S"]):
                    g[c] = np.nan
            else:
                g_rep[c] = 0
        evid = np.zeros(G)
        for c in range(G):
            for j in uses[c]:
                if np.isfinite(cm_fast[j]) and np.isfinite(cm_slow[j]):
                    evid[c] += abs(cm_fast[j] - cm_slow[j])
        was = bad.copy()
        for c in range(G):
            m = mate.get(c, -1)
            if m < 0:
                continue
            d = g[c] - g[m]
            if np.isfinite(d):
                f = min(1.0, dt[k] / H["PAIR_FAST_S"])
                d_fast[c] = d if np.isnan(d_fast[c]) else d_fast[c] + f * (d - d_fast[c])
                if not (was[c] or was[m]):
                    f = min(1.0, dt[k] / H["PAIR_SLOW_S"])
                    d_slow[c] = d if np.isnan(d_slow[c]) else d_slow[c] + f * (d - d_slow[c])
            dev = abs(d_fast[c] - d_slow[c])
            stepped = (dev > H["BIAS_STEP_RAD_S"] and evid[c] >= H["BIAS_EVIDENCE_RAD"]
                       and evid[c] >= 2 * evid[m] and not was[m]
                       and dev > H["SPREAD_FACTOR"] * np.sqrt(spread[c])
                       and paired[c] >= H["PAIR_SLOW_S"])
            if np.isfinite(d):
                paired[c] += dt[k]
                if not (was[c] or was[m]):
                    f = dt[k] / max(dt[k], min(H["PAIR_SPREAD_S"], paired[c]), 1e-9)
                    spread[c] += f * ((0.0 if np.isnan(dev) else dev) ** 2 - spread[c])
            bar = max(H["BIAS_STEP_RAD_S"], H["SPREAD_FACTOR"] * np.sqrt(spread[c]))
            bad_calm[c] = bad_calm[c] + dt[k] if was[c] and dev < 0.5 * bar else 0.0
            bad[c] = (was[c] and bad_calm[c] < H["READMIT_S"]) or stepped
        g[bad] = np.nan
        g_miss = np.where(np.isnan(g), g_miss + dt[k], 0.0)
        used = g.copy()
        for c, mates in order.items():
            if np.isnan(used[c]) and g_miss[c] > H["HOLD_S"]:
                for other in mates:
                    if not np.isnan(g[other]):
                        used[c] = g[other]
                        break
        g_out[k] = used
        hold = np.where(np.isnan(used), hold, used)
        rate = hold[L["rate_plus"][:J]] - hold[L["rate_minus"][:J]]
        gap = dt[k] > H["RESTART_S"]
        fresh = [gap or not ref_ok[j] for j in range(J)]
        for j in range(J):
            if not gap:
                ref[j] += dt[k] * rate[j]
        angle = np.full(M, np.nan)
        use = np.zeros(M, bool)
        de, div = np.full(M, np.nan), np.full(M, np.nan)  # judged residual changes
        noise = np.full(M, np.nan)
        iso_before = iso.copy()
        for m in range(M):
            j = L["sensor_joint_axis"][m]
            V = hall_v[k, m]
            if not np.isfinite(V):
                continue
            angle[m] = hall_angle(V, params, m)
            e = angle[m] - ref[j]
            if np.isfinite(last_e[m]) and not fresh[j]:
                sv = hall_slope(V, params, m) * max(float(np.asarray(params["sigma_hall_v"])[m]),
                                                    H["MONITOR_MIN_SIGMA_V"])
                move = abs(dt[k] * rate[j])
                noise[m] = 2 * sv**2
                div[m] = noise[m] + (H["MOTION_FRACTION"] * move + H["MOTION_FLOOR_RAD"])**2
                de[m] = e - last_e[m]
        for j in range(J):
            a_, b_ = 2 * j, 2 * j + 1
            if np.isfinite(de[a_]) and np.isfinite(de[b_]):
                move = abs(dt[k] * rate[j])
                pm = max(move, min(abs(de[a_] + dt[k] * rate[j]), abs(de[b_] + dt[k] * rate[j])))
                zp = (de[a_] - de[b_]) ** 2 / (noise[a_] + noise[b_] + 2 * (
                    H["MOTION_FRACTION"] * pm + H["MOTION_FLOOR_RAD"]) ** 2)
                pair_rough[j] += min(1.0, dt[k] / H["ROUGH_TAU_S"]) * (zp - pair_rough[j])
            elif fresh[j]:
                pair_rough[j] = 0.0
        for m in range(M):
            j = L["sensor_joint_axis"][m]
            V = hall_v[k, m]
            move = abs(dt[k] * rate[j])
            if not np.isfinite(V):
                if fresh[j]:
                    rough[m], last_e[m] = 0.0, np.nan
                still[m], moved[m], calm[m], last_v[m] = 0.0, 0.0, 0.0, np.nan
                continue
            if np.isfinite(de[m]):
                z = de[m] ** 2 / div[m]
                rough[m] += min(1.0, dt[k] / H["ROUGH_TAU_S"]) * (z - rough[m])
            elif fresh[j]:
                rough[m] = 0.0
            if V == last_v[m]:
                still[m] += dt[k]
                moved[m] += move
            else:
                still[m], moved[m] = 0.0, 0.0
            stuck = (V == last_v[m]) and still[m] >= H["STUCK_S"] and \
                moved[m] >= H["STUCK_MOVE_RAD"]
            partner = m ^ 1
            partner_out = not np.isfinite(hall_v[k, partner]) or iso_before[partner]
            noisy = rough[m] > H["ROUGH_HIGH"] and (pair_rough[j] > H["ROUGH_HIGH"]
                                                    or partner_out)
            if iso[m] and not noisy and not stuck and rough[m] < H["ROUGH_LOW"]:
                calm[m] += dt[k]
            else:
                calm[m] = 0.0
            iso[m] = (iso[m] and calm[m] < H["READMIT_S"]) or noisy or stuck
            use[m] = not iso[m]
            last_v[m] = V
        for j in range(J):
            mine = [angle[m] for m in range(M) if L["sensor_joint_axis"][m] == j and use[m]]
            if mine:
                mean = float(np.mean(mine))
                if fresh[j]:
                    ref[j] = mean
                else:
                    ref[j] += min(1.0, dt[k] / H["REF_TAU_S"]) * (mean - ref[j])
            ref_ok[j] = (ref_ok[j] and not gap) or bool(mine)
            if gap:
                cm_fast[j], cm_slow[j] = np.nan, np.nan
            if mine:
                cm = float(np.mean(mine)) - ref[j]
                for avg, tau in ((cm_fast, H["CM_FAST_S"]), (cm_slow, H["CM_SLOW_S"])):
                    avg[j] = cm if np.isnan(avg[j]) else \
                        avg[j] + min(1.0, dt[k] / tau) * (cm - avg[j])
        for m in range(M):
            j = L["sensor_joint_axis"][m]
            if np.isfinite(angle[m]):
                last_e[m] = angle[m] - ref[j]
            if not use[m]:
                v_out[k, m] = np.nan
    return g_out, v_out


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
    gyro, hall_v = usable_readings(joints, t, gyro, hall_v, params)
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
    gyro, hall_v = usable_readings(joints, t, gyro, hall_v, params)
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
