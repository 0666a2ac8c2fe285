"""Independent plain-NumPy (float64) reference of the rotation-aware KCKF (``kckf3d``).

A test oracle written from the equations (docs/kinematics.md), not from ``kckf_jax``: it does
not import the package. It shares with ``reference.py`` the screening of the readings
(``usable_readings``, given the exact model's gyro pairs: none), Eq. 1 and the Hall noise,
which the linear reference already checks.

Model (``z = [theta (J), beta (Gb)]``, the torso angles ``phi = euler(chain(theta))``):

* a joint with axes ``a_1..a_m`` turns by ``R = R_a1(t_1) ... R_am(t_m)``; its body Jacobian's
  column ``k`` is ``(R_a(k+1) ... R_am)^T e_ak``; bias-free gyros give its coordinate rates
  ``u = lstsq(J, w_{i+1} - R^T w_i)``, ``w = g - beta`` (a gyro channel not in the state: no
  bias);
* the state's bias channels: those the joints read (a one-axis joint its axis on both links,
  a joint of several axes all three); each channel's Eq. 13 scale, random walk and prior are
  the mean of the joint coordinates' that read it, halved as variances;
* predicted ``[theta + dt u + w_theta, beta + w_beta]``, linearised in ``z`` by central
  differences, ``S = F P F' + Q`` (diagonal: the joints' angle variance, the channels' bias
  variance);
* every Hall reading as its own row (Eqs. 5, 8, 20), one joint update in Joseph form.
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
        reads = {}
        for i, axes in enumerate(self.joints):
            s = list(range(k, k + len(axes)))
            self.sl.append(s)
            k += len(axes)
            cols = [0, 1, 2] if len(axes) > 1 else [AXES.index(axes[0])]
            for link in (i, i + 1):
                for c in cols:
                    reads.setdefault(3 * link + c, set()).update(s)
        self.channels = sorted(reads)
        self.share = np.zeros((len(self.channels), self.J))
        for r, c in enumerate(self.channels):
            self.share[r, sorted(reads[c])] = 1.0 / len(reads[c])

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

    def full_bias(self, beta) -> np.ndarray:
        out = np.zeros(3 * (len(self.joints) + 1))
        out[self.channels] = beta
        return out

    def predict(self, z, g, dt) -> np.ndarray:
        J = self.J
        th, beta = z[:J], z[J:]
        return np.concatenate([th + dt * self.rates(th, g - self.full_bias(beta)), beta])


def _jac(f, x) -> np.ndarray:
    cols = []
    for k in range(x.shape[0]):
        d = np.zeros_like(x)
        d[k] = H
        cols.append((f(x + d) - f(x - d)) / (2 * H))
    return np.stack(cols, axis=1)


def reference_exact_filter(joints, t, gyro, hall_v, params) -> dict:
    """Run the rotation-aware KCKF over a recording: the estimated angles (joints, then the
    torso's), each angle's rate bias and the final ``z``, ``P``."""
    model = Exact(joints)
    J, K = model.J, model.K
    L = model.L
    t = np.asarray(t, float)
    params = dict(params, no_gyro_pairs=True)
    gyro, hall_v = usable_readings(model.joints, t, np.asarray(gyro, float), hall_v, params)
    dt = np.zeros_like(t)
    dt[1:] = np.diff(t)
    q, arw, brw, p0a, p0b = (np.asarray(params[k], float)
                             for k in ("q", "angle_rw", "bias_rw", "p0_angle", "p0_bias"))
    share = model.share
    q_c, brw2_c, p0_c = share @ q[:J] / 2, share @ brw[:J] ** 2 / 2, share @ p0b[:J] ** 2 / 2
    nz = J + len(model.channels)
    z = np.zeros(nz)
    Pz = np.diag(np.concatenate([p0a[:J] ** 2, p0_c]))
    hold = np.zeros(L["n_gyro"])
    angles, bias = np.zeros((t.size, K)), np.zeros((t.size, K))
    for k in range(t.size):
        ts = dt[k]
        if ts > 0:
            F = _jac(lambda v: model.predict(v, hold, ts), z)
            z = model.predict(z, hold, ts)
            Q = np.diag(np.concatenate([q[:J] * ts**4 / 4 + arw[:J] ** 2 * ts,
                                        q_c * ts**2 + brw2_c * ts]))
            Pz = F @ Pz @ F.T + Q
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
        th = z[:J]
        rate_bias = model.rates(th, model.full_bias(z[J:]))  # u is linear in the gyros
        C = _jac(lambda v: model.torso_angles(v)[model.torso], th)
        angles[k] = np.concatenate([th, model.torso_angles(th)[model.torso]])
        bias[k] = np.concatenate([rate_bias, C @ rate_bias])
        hold = _update_hold(hold, gyro[k])
    return dict(angles=angles, bias=bias, z=z, P=Pz)
