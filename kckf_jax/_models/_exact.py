"""The rotation-aware KCKF (method ``"kckf3d"``): the paper's filter on the chain's exact
kinematics (``_rotations``; docs/kinematics.md).

* **Joints** (Eqs. 2, 9-12 in finite rotations): joint ``i`` with axes ``a_1..a_m`` and
  coordinates ``theta_i`` turns at ``u_i = J_i^+ (w_{i+1} - R_i^T w_i)``, with ``R_i``,
  ``J_i`` its rotation and body Jacobian (``joint_rotation``, ``joint_jacobian``), ``J_i^+``
  the left inverse ``(J_i' J_i)^-1 J_i'`` (``J_i^-1`` for three axes) and ``w = g - beta``
  the links' gyro rates less their biases. For a one-axis joint ``u_i`` is exactly
  ``w_{i+1,a} - w_{i,a}``: the paper's rate.
* **Biases per gyro channel** (``beta``, Eq. 13's random walk): a link's constant gyro bias
  reaches a joint's rate through ``R_i^T`` and ``J_i^+``, so per joint coordinate (the
  paper's) it would be a bias that changes with the pose; per channel it stays constant. The
  state holds the channels the joints read (``ExactModel.channels``); each channel's noise and
  prior come from the joint coordinates that read it (``gyro_bias_noise``), so ``kckf3d`` takes
  the same ``Params`` as ``kckf``.
* **Constraint** (Eq. 14 in finite rotations): ``phi = euler_xyz(R_1(theta_1) ...
  R_n(theta_n))`` on the robot's torso axes, the perfect measurement, eliminated exactly: the
  state is ``z = [theta, beta]`` and ``phi`` is ``phi(theta)``, so every estimate satisfies the
  exact forward kinematics. With the gyros' biases per channel the torso's rate bias is the
  chain's of theirs, so no separate torso bias is left for the constraint to tie (as the
  linear KCKF's ``b_phi = sum b``).

Each step linearises the model at the filtered state (each joint's rates' Jacobians in its
coordinates and its two links' gyros, and the torso's in the joints', written from the
rotations' closed forms: ``jax.jacfwd`` through every rotation cost several times the chain's
own arithmetic, issue 35; the tests hold them to ``jacfwd``'s); nothing is left to iterate:
the Hall readings measure ``theta`` linearly (one scalar Joseph update per joint coordinate,
as the linear KCKF) and the constraint is eliminated, not approximated. To first order in the
angles and rates the model is the paper's.

Designs measured and left (docs/kinematics.md): the paper's biases per joint coordinate and
torso axis (fitted, 3D walking 0.55 deg against 0.26 per channel); the torso propagated on its
own gyros, ``E(phi)^-1 (g_{n+1} - R(phi)^T g_1)``, with the constraint as a perfect
measurement, which pushed errors of the pose into the biases and diverged (60 s of walking);
a residual's covariance formed as a difference of large terms (not float32-stable).

Working range: ``J_i`` of full column rank (a three-axis joint's middle coordinate away from
+-90 deg: the left inverse's condition number is 1.7 at 30 deg, 3.7 at 60, 23 at 85) and the
torso's y Euler angle away from +-90 deg (gimbal lock of the angles the session format
defines). No matrix inverse or LAPACK call in a step: the 2 x 2 and 3 x 3 solves are written
out (``solve_small``).
"""

from __future__ import annotations

import dataclasses
import functools

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._blocks import ProcessNoise
from ._kalman import coordinate_update, symmetrise
from ._robot import AXES, Robot
from ._rotations import (
    chain_rotation,
    chain_rotation_axes,
    euler_xyz,
    euler_xyz_jacobian,
    joint_jacobian,
    joint_rotation,
)


@dataclasses.dataclass(frozen=True, eq=False)
class ExactModel:
    """The static layout of the exact model for one robot (``exact_model``).

    ``joint_slices[i]``: the coordinates of joint ``i`` in ``theta``; ``torso_axes``: the
    indices (into x, y, z) of the robot's torso axes; ``channels``: the gyro channels (into
    ``Robot.gyro_names``) whose biases are states, those the joints' rates read (a one-axis
    joint its axis on its two links, a joint of several axes all three); ``share`` (``Gb x
    J``): each channel's share of the joint coordinates that read it (rows sum to 1), which
    sets its bias parameters from theirs. ``n_z = J + Gb`` filter coordinates ``[theta,
    beta]``; no constraint row is left (``n_e = 0``): the torso is the chain's.
    """

    robot: Robot
    joint_slices: tuple[tuple[int, ...], ...]
    torso_axes: tuple[int, ...]
    channels: tuple[int, ...]
    share: np.ndarray
    J: int
    P: int

    @property
    def G(self) -> int:
        return 3 * self.robot.n_links

    @property
    def n_z(self) -> int:
        return self.J + len(self.channels)

    @property
    def n_e(self) -> int:
        return 0

    @functools.cached_property
    def select(self) -> np.ndarray:
        """``(G x Gb)``: every gyro channel's bias from the state's (0 for the others)."""
        out = np.zeros((self.G, len(self.channels)))
        out[np.asarray(self.channels), np.arange(len(self.channels))] = 1.0
        return out


@functools.lru_cache(maxsize=64)
def exact_model(robot: Robot) -> ExactModel:
    """The ``ExactModel`` of ``robot``."""
    slices, k = [], 0
    reads: dict[int, list[int]] = {}
    for i, axes in enumerate(robot.joints):
        sl = tuple(range(k, k + len(axes)))
        slices.append(sl)
        k += len(axes)
        cols = (range(3) if len(axes) > 1 else [AXES.index(axes[0])])
        for link in (i, i + 1):
            for c in cols:
                reads.setdefault(3 * link + c, []).extend(sl)
    channels = tuple(sorted(reads))
    share = np.zeros((len(channels), robot.n_joint_axes))
    for r, c in enumerate(channels):
        js = sorted(set(reads[c]))
        share[r, js] = 1.0 / len(js)
    return ExactModel(robot, tuple(slices), tuple(AXES.index(a) for a in robot.torso_axes),
                      channels, share, robot.n_joint_axes, robot.n_torso_axes)


def solve_small(A: Float[Array, "m m"], b: Float[Array, " m"]) -> Float[Array, " m"]:
    """``A^-1 b`` for ``m <= 3``, written out (Cramer's rule; no LAPACK call)."""
    m = A.shape[0]
    if m == 1:
        return b / A[0, 0]
    if m == 2:
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        return jnp.stack([A[1, 1] * b[0] - A[0, 1] * b[1], A[0, 0] * b[1] - A[1, 0] * b[0]]) / det
    if m != 3:
        raise ValueError(f"solve_small: m must be 1, 2 or 3, got {m}")
    c0, c1, c2 = A[:, 0], A[:, 1], A[:, 2]
    det = jnp.dot(c0, jnp.cross(c1, c2))
    return jnp.stack([jnp.dot(b, jnp.cross(c1, c2)), jnp.dot(c0, jnp.cross(b, c2)),
                      jnp.dot(c0, jnp.cross(c1, b))]) / det


def coordinate_rates(axes, angles: Float[Array, " m"], relative: Float[Array, " 3"]
                     ) -> Float[Array, " m"]:
    """The coordinate rates ``J^+ w`` of a joint whose child turns at ``w`` relative to its
    parent, in the child's frame (``J``: ``joint_jacobian``; least squares for fewer than
    three axes)."""
    Jm = joint_jacobian(axes, angles, jnp)
    if len(axes) == 3:
        return solve_small(Jm, relative)
    if len(axes) == 1:
        return (Jm[:, 0] @ relative)[None]  # a unit column
    return solve_small(Jm.T @ Jm, Jm.T @ relative)


def torso_euler(model: ExactModel, theta: Float[Array, " J"]) -> Float[Array, " 3"]:
    """The x-y-z Euler angles of link ``n + 1`` relative to link 1 (all three): the
    simulator's ``chain_rotation`` of each joint's coordinates (static slices)."""
    angles = [theta[sl[0]:sl[-1] + 1] for sl in model.joint_slices]
    return euler_xyz(chain_rotation(model.robot.joints, angles, jnp), jnp)


def torso_angles(model: ExactModel, theta: Float[Array, " J"]) -> Float[Array, " P"]:
    """``phi(theta)`` on the robot's torso axes (the exact Eq. 14)."""
    phi = torso_euler(model, theta)  # static indices: slices, not a gather
    return jnp.stack([phi[i] for i in model.torso_axes])


def torso_angles_jacobian(model: ExactModel, theta: Float[Array, " J"]
                          ) -> tuple[Float[Array, " P"], Float[Array, "P J"]]:
    """``torso_angles`` (the same values) and their Jacobian ``C = d phi / d theta`` from the
    closed forms: each coordinate's axis in link 1's frame (``chain_rotation_axes``: the
    product rule over the chain) through the Euler angles' derivative in the rotation's
    entries (``euler_xyz_jacobian``)."""
    angles = [theta[sl[0]:sl[-1] + 1] for sl in model.joint_slices]
    R, S = chain_rotation_axes(model.robot.joints, angles, jnp)
    phi, dphi = euler_xyz(R, jnp), euler_xyz_jacobian(R, S, jnp)
    return (jnp.stack([phi[i] for i in model.torso_axes]),
            jnp.stack([dphi[i] for i in model.torso_axes]))


def joint_rate_jacobians(axes, angles: Float[Array, " m"], g_parent: Float[Array, " 3"],
                         g_child: Float[Array, " 3"]
                         ) -> tuple[Float[Array, " m"], Float[Array, "m m"], Float[Array, "m 6"]]:
    """One joint's coordinate rates ``u = J^+ r``, ``r = g_child - R^T g_parent``, and their
    Jacobians in its coordinates and in ``[g_parent, g_child]``, from the rotations' closed
    forms (no ``jacfwd``). With ``v = R^T g_parent`` and ``j_k`` the columns of ``J``:

    * ``dR / dtheta_k = R hat(j_k)``, so ``dr / dtheta_k = j_k x v``;
    * column ``l`` of ``dJ / dtheta_k`` is ``j_l x j_k`` for ``l < k`` (the rotations after
      axis ``l`` include ``k``'s), 0 otherwise, so ``dJ/dtheta_k u = w_k x j_k`` with ``w_k =
      sum_{l<k} u_l j_l``;
    * ``du / dtheta_k = J^+ (dr - dJ u) + (J'J)^-1 dJ' (r - J u)`` (the left inverse's
      derivative; the last term is 0 for three axes, where ``r = J u``), and
      ``J^+ (dr - dJ u) = J^+ (j_k x (v + w_k))``;
    * ``du / dg_parent = -J^+ R^T``, ``du / dg_child = J^+``.

    A one-axis joint: ``u = g_child,a - g_parent,a`` (``R e_a = e_a``), independent of its
    angle."""
    m = len(axes)
    dtype = angles.dtype
    if m == 1:
        e = np.zeros((1, 3))
        e[0, AXES.index(axes[0])] = 1.0
        e = jnp.asarray(e, dtype)
        return ((g_child - g_parent)[AXES.index(axes[0])][None], jnp.zeros((1, 1), dtype),
                jnp.concatenate([-e, e], axis=1))
    R = joint_rotation(axes, angles, jnp)
    Jm = joint_jacobian(axes, angles, jnp)
    cols = [Jm[:, k] for k in range(m)]
    if m == 3:  # J^-1: the adjugate's rows over the determinant
        c0, c1, c2 = cols
        adj = jnp.stack([jnp.cross(c1, c2), jnp.cross(c2, c0), jnp.cross(c0, c1)])
        Jp = adj / jnp.dot(c0, adj[0])
        Minv = None
    elif m == 2:  # (J'J)^-1 J' (J'J is the identity in exact arithmetic: orthogonal axes)
        M = Jm.T @ Jm
        Minv = jnp.stack([jnp.stack([M[1, 1], -M[0, 1]]), jnp.stack([-M[1, 0], M[0, 0]])]) / (
            M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0])
        Jp = Minv @ Jm.T
    else:
        raise ValueError(f"a joint has 1, 2 or 3 axes, got {axes!r}")
    v = R.T @ g_parent
    r = g_child - v
    u = Jp @ r
    w, T = v, []
    for k in range(m):
        if k:
            w = w + u[k - 1] * cols[k - 1]
        T.append(jnp.cross(cols[k], w))
    Du = Jp @ jnp.stack(T, axis=1)
    if Minv is not None:  # the least-squares residual's term: dJ/dtheta_2 = [j_1 x j_2, 0]
        resid = jnp.dot(jnp.cross(cols[0], cols[1]), r - Jm @ u)
        Du = Du + jnp.concatenate([jnp.zeros((2, 1), dtype), Minv[:, :1] * resid], axis=1)
    return u, Du, jnp.concatenate([-Jp @ R.T, Jp], axis=1)


def joint_rates_jacobian(model: ExactModel, theta: Float[Array, " J"], gyro: Float[Array, " G"]
                         ) -> tuple[Float[Array, " J"], Float[Array, "J J"], Float[Array, "J G"]]:
    """The joint coordinates' rates the (bias-free) gyro rates ``gyro`` give, ``u_i = J_i^+
    (g_{i+1} - R_i^T g_i)`` per joint, and their Jacobians in ``theta`` and in ``gyro``,
    joint by joint from the rotations' closed forms (``joint_rate_jacobians``; ``jacfwd``
    through the rotations cost about 10x the chain's own arithmetic, issue 35): block
    diagonal in ``theta`` (a one-axis joint's rate does not depend on its angle), each joint
    reading its two links' gyros."""
    g = gyro.reshape(-1, 3)
    dtype = theta.dtype
    us, d_theta, d_gyro = [], [], []
    for i, (axes, sl) in enumerate(zip(model.robot.joints, model.joint_slices, strict=True)):
        u, Du, Dg = joint_rate_jacobians(axes, theta[sl[0]:sl[-1] + 1], g[i], g[i + 1])
        us.append(u)
        d_theta.append(Du)
        d_gyro.append(Dg)
    # Block matrices by concatenation (an indexed update inside the step's loop is a
    # scatter, which keeps XLA's CPU compiler from making the loop one kernel).
    sizes = [d.shape[0] for d in d_theta]
    n = len(sizes)
    Du = jnp.block([[d_theta[i] if i == k else jnp.zeros((sizes[i], sizes[k]), dtype)
                     for k in range(n)] for i in range(n)])
    Dg = jnp.concatenate([jnp.concatenate([jnp.zeros((sizes[i], 3 * i), dtype), d_gyro[i],
                                           jnp.zeros((sizes[i], 3 * (n - 1 - i)), dtype)],
                                          axis=1) for i in range(n)])
    return jnp.concatenate(us), Du, Dg


def gyro_bias_noise(model: ExactModel, q, bias_rw, p0_bias):
    """Each bias channel's Eq. 13 scale ``q``, random walk and prior from the parameters of the
    joint coordinates that read it (``ExactModel.share``), each a variance halved: a joint's
    rate is the difference of two gyros, whose biases are independent."""
    share = jnp.asarray(model.share, q.dtype)
    J = model.J
    return (share @ q[:J] / 2, share @ bias_rw[:J] ** 2 / 2, share @ p0_bias[:J] ** 2 / 2)


def process_noise_diagonal(model: ExactModel, alpha, bias_q, bias_rw2, dt):
    """The process noise of ``z = [theta, beta]`` (diagonal, ``... Nz``) over a step ``dt``
    (any leading axes, as ``alpha``'s): each joint coordinate's Eq. 13 angle variance
    (``alpha``, per angle: its first ``J``), each bias channel's ``bias_q dt^2 + bias_rw2 dt``
    (``gyro_bias_noise``)."""
    dt = jnp.asarray(dt)[..., None]
    return jnp.concatenate([alpha[..., :model.J], bias_q * dt**2 + bias_rw2 * dt], axis=-1)


def predicted_moments(model: ExactModel, z: Float[Array, " Nz"], P: Float[Array, "Nz Nz"],
                      gyro: Float[Array, " G"], noise: ProcessNoise, bias_q, bias_rw2,
                      dt: Float[Array, ""]):
    """The predicted ``y = z' = [theta', beta']``, its covariance ``S`` and its Jacobian ``F``
    in the filtered ``z`` (the smoother's): ``theta' = theta + dt u(theta, g - beta) +
    w_theta`` (``u``: ``joint_rates_jacobian``), ``beta' = beta + w_beta``; the model
    linearised at the filtered state (``joint_rates_jacobian``). ``noise``: Eq. 13's terms per angle
    coordinate (the joints' angle variance); ``bias_q``, ``bias_rw2``: each bias channel's
    (``gyro_bias_noise``)."""
    J = model.J
    dtype = z.dtype
    theta, beta = z[:J], z[J:]
    sel = jnp.asarray(model.select, dtype)
    u, Du, Dg = joint_rates_jacobian(model, theta, gyro - sel @ beta)
    A = jnp.eye(J, dtype=dtype) + dt * Du
    B = -dt * (Dg @ sel)  # d theta' / d beta
    nb = beta.shape[0]
    F = jnp.block([[A, B], [jnp.zeros((nb, J), dtype), jnp.eye(nb, dtype=dtype)]])
    q = process_noise_diagonal(model, noise[0], bias_q, bias_rw2, dt)
    S = F @ P @ F.T + q[:, None] * jnp.eye(q.shape[0], dtype=dtype)
    return jnp.concatenate([theta + dt * u, beta]), symmetrise(S), F


def exact_step(model: ExactModel, z: Float[Array, " Nz"], P: Float[Array, "Nz Nz"],
               gyro: Float[Array, " G"], noise: ProcessNoise, bias_q, bias_rw2,
               h: Float[Array, " J"], rh: Float[Array, " J"], vh: Bool[Array, " J"],
               dt: Float[Array, ""]):
    """Predict, then update with each joint coordinate's fused Hall reading (one scalar
    Joseph update each). Returns ``(z, P, y, S, F, nu, s)``: the new state, the predicted
    moments of ``z`` and their Jacobian in the previous ``z`` (the smoother's), and each Hall
    innovation and its variance (as ``_kernel.block_step``)."""
    y_pred, S_pred, F = predicted_moments(model, z, P, gyro, noise, bias_q, bias_rw2, dt)
    z_new, P_new = y_pred, S_pred
    nus, ss = [], []
    for i in range(model.J):
        nus.append(h[i] - z_new[i])
        ss.append(P_new[i, i] + rh[i])
        z_new, P_new = coordinate_update(z_new, P_new, i, nus[-1], rh[i], vh[i])
    return z_new, symmetrise(P_new), y_pred, S_pred, F, jnp.stack(nus), jnp.stack(ss)


def exact_estimate(model: ExactModel, z: Float[Array, " Nz"], P: Float[Array, "Nz Nz"]
                   ) -> tuple[Float[Array, " K"], Float[Array, " K"], Float[Array, " K"]]:
    """Angles (joint coordinates, then the chain's torso angles), their standard deviations
    (the torso's through the chain's Jacobian ``C``) and each angle's rate bias at this pose
    (rad/s: the gyros' biases through the joints' rates, ``L(theta) beta``, and ``C`` of
    those for the torso)."""
    J = model.J
    theta = z[:J]
    phi, C = torso_angles_jacobian(model, theta)  # C: (P, J)
    Ptt = P[:J, :J]
    var = jnp.concatenate([jnp.diag(Ptt), jnp.sum((C @ Ptt) * C, axis=1)])
    _, _, Dg = joint_rates_jacobian(model, theta, jnp.zeros(model.G, z.dtype))
    rate_bias = Dg @ (jnp.asarray(model.select, z.dtype) @ z[J:])
    return (jnp.concatenate([theta, phi]),
            jnp.sqrt(jnp.maximum(var, 0.0)), jnp.concatenate([rate_bias, C @ rate_bias]))


def initial_covariance(model: ExactModel, p0_angle: Float[Array, " K"], p0_bias_var
                       ) -> Float[Array, "Nz Nz"]:
    """The prior of ``z``: the joints' ``p0_angle`` and each bias channel's variance
    (``gyro_bias_noise``; the torso's angle follows from the joints')."""
    v = jnp.concatenate([p0_angle[:model.J] ** 2, p0_bias_var])
    return v[:, None] * jnp.eye(v.shape[0], dtype=v.dtype)
