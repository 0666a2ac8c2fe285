"""Independent plain-NumPy (float64) reference of the rotation-aware KCKF (``kckf3d``).

A test oracle written from the equations (docs/kinematics.md), not from ``kckf_jax``: it does
not import the package. It shares with ``reference.py`` the screening of the readings
(``usable_readings``), Eq. 1 and the Hall noise, which the linear reference already checks.

Model (``z = [theta (J), b (J), b_phi (P)]``, the torso angles ``phi = euler(chain(theta))``):

* a joint with axes ``a_1..a_m`` turns by ``R = R_a1(t_1) ... R_am(t_m)``; its body Jacobian's
  column ``k`` is ``(R_a(k+1) ... R_am)^T e_ak``; the gyros give its coordinate rates
  ``u = lstsq(J, g_{i+1} - R^T g_i)``;
* predicted ``y = [theta' = theta + dt (u - b) + w_theta, b + w_b, b_phi + w_bphi,
  euler(chain(theta')) - (euler(chain(theta + dt u)) - dt b_phi + w_phi)]`` (the torso moved
  along the chain by the joints' unbiased rates), linearised in ``z`` and ``w`` by central
  differences; ``S = F P F' + G Q G'`` (Eq. 13's ``Q`` per angle coordinate);
* condition on ``e = 0`` (one joint Gaussian conditioning), then every Hall reading as its own
  row (Eqs. 5, 8, 20), one joint update in Joseph form.
"""

from __future__ import annotations

import numpy as np
from reference import _update_hold, hall_angle, hall_variance, layout, usable_readings

AXES = ("x", "y", "z")
H = 1e-6  # central-difference step, rad


def rot(axis: str, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def joint_rot(axes, th) -> np.ndarray:
    R = np.eye(3)
    for a, x in zip(axes, th, strict=True):
        R = R @ rot(a, x)
    return R


def joint_jac(axes, th) -> np.ndarray:
    cols = []
    for k, a in enumerate(axes):
        after = joint_rot(axes[k + 1:], th[k + 1:])
        cols.append(after.T @ np.eye(3)[AXES.index(a)])
    return np.stack(cols, axis=1)


def euler(R) -> np.ndarray:
    return np.array([np.arctan2(-R[1, 2], R[2, 2]), np.arcsin(np.clip(R[0, 2], -1, 1)),
                     np.arctan2(-R[0, 1], R[0, 0])])


class Exact:
    """The model of one robot (``joints`` as in ``reference.layout``)."""

    def __init__(self, joints):
        self.joints = [list(a) for a in joints]
        self.L = layout(self.joints)
        self.J, self.P, self.K = self.L["J"], self.L["P"], self.L["K"]
        self.torso = [AXES.index(a) for a in self.L["torso_axes"]]
        self.sl, k = [], 0
        for axes in self.joints:
            self.sl.append(list(range(k, k + len(axes))))
            k += len(axes)

    def torso_angles(self, th) -> np.ndarray:
        R = np.eye(3)
        for axes, s in zip(self.joints, self.sl, strict=True):
            R = R @ joint_rot(axes, th[s])
        return euler(R)

    def rates(self, th, g) -> np.ndarray:
        g = g.reshape(-1, 3)
        out = []
        for i, (axes, s) in enumerate(zip(self.joints, self.sl, strict=True)):
            v = g[i + 1] - joint_rot(axes, th[s]).T @ g[i]
            out.append(np.linalg.lstsq(joint_jac(axes, th[s]), v, rcond=None)[0])
        return np.concatenate(out)

    def y(self, z, w, g, dt) -> np.ndarray:
        J, K = self.J, self.K
        th, b, bp = z[:J], z[J:2 * J], z[2 * J:]
        u = self.rates(th, g)
        th_n = th + dt * (u - b) + w[:J]
        phi_n = self.torso_angles(th + dt * u)[self.torso] - dt * bp + w[J:K]
        e = self.torso_angles(th_n)[self.torso] - phi_n
        return np.concatenate([th_n, b + w[K:K + J], bp + w[K + J:], e])


def _jac(f, x) -> np.ndarray:
    cols = []
    for k in range(x.shape[0]):
        d = np.zeros_like(x)
        d[k] = H
        cols.append((f(x + d) - f(x - d)) / (2 * H))
    return np.stack(cols, axis=1)


def _Q(K, params, ts) -> np.ndarray:
    q, arw, brw = (np.asarray(params[k], float) for k in ("q", "angle_rw", "bias_rw"))
    Q = np.zeros((2 * K, 2 * K))
    for k in range(K):
        Q[k, k] = q[k] * ts**4 / 4 + arw[k] ** 2 * ts
        Q[k, K + k] = Q[K + k, k] = q[k] * ts**3 / 2
        Q[K + k, K + k] = q[k] * ts**2 + brw[k] ** 2 * ts
    return Q


def reference_exact_filter(joints, t, gyro, hall_v, params) -> dict:
    """Run the rotation-aware KCKF over a recording: the estimated angles (joints, then the
    torso's), biases and the final ``z``, ``P``."""
    model = Exact(joints)
    J, P, K = model.J, model.P, model.K
    L = model.L
    t = np.asarray(t, float)
    gyro, hall_v = usable_readings(model.joints, t, np.asarray(gyro, float), hall_v, params)
    dt = np.zeros_like(t)
    dt[1:] = np.diff(t)
    nz = 2 * J + P
    z = np.zeros(nz)
    p0a, p0b = (np.asarray(params[k], float) for k in ("p0_angle", "p0_bias"))
    Pz = np.diag(np.concatenate([p0a[:J] ** 2, p0b**2]))
    hold = np.zeros(L["n_gyro"])
    angles, bias = np.zeros((t.size, K)), np.zeros((t.size, K))
    for k in range(t.size):
        ts = dt[k]
        if ts > 0:
            w0 = np.zeros(2 * K)
            y = model.y(z, w0, hold, ts)
            F = _jac(lambda v: model.y(v, w0, hold, ts), z)
            G = _jac(lambda v: model.y(z, v, hold, ts), w0)
            S = F @ Pz @ F.T + G @ _Q(K, params, ts) @ G.T
            # Condition on the perfect measurement e = 0.
            Sze, See = S[:nz, nz:], S[nz:, nz:]
            z = y[:nz] - Sze @ np.linalg.solve(See, y[nz:])
            Pz = S[:nz, :nz] - Sze @ np.linalg.solve(See, Sze.T)
        rows, ys, rs = [], [], []
        for m in range(L["M"]):
            V = hall_v[k, m]
            if np.isfinite(V):
                h = np.zeros(nz)
                h[L["sensor_joint_axis"][m]] = 1.0
                rows.append(h)
                ys.append(hall_angle(V, params, m))
                rs.append(hall_variance(V, params, m))
        if rows:
            Hm, R = np.array(rows), np.diag(rs)
            Kg = np.linalg.solve(Hm @ Pz @ Hm.T + R, Hm @ Pz).T
            z = z + Kg @ (np.array(ys) - Hm @ z)
            I_KH = np.eye(nz) - Kg @ Hm
            Pz = I_KH @ Pz @ I_KH.T + Kg @ R @ Kg.T
        angles[k] = np.concatenate([z[:J], model.torso_angles(z[:J])[model.torso]])
        bias[k] = z[J:]
        hold = _update_hold(hold, gyro[k])
    return dict(angles=angles, bias=bias, z=z, P=Pz)
