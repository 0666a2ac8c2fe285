"""``kckf3d``'s step and estimate written entry by entry, for any trailing lane axes.

``_exact`` writes the exact-rotation KCKF with matrices (``jnp`` products of 3 x 3 rotations
and of the 21 x 21 covariance): the form to differentiate. Under ``vmap`` those small
products cost far more than their arithmetic. Here the same closed forms are written one
entry at a time, each entry an array over the lanes (the trials of a batch,
``_paths/_exact_lanes``), with the model's constants
(0, 1, the one-axis joints' +-1) folded away before anything is traced:

* each joint's rate ``u = J^+ (g_child - R^T g_parent)`` and its Jacobians ``Du``, ``Dg``
  (``joint_rate_entries``: ``_exact.joint_rate_jacobians``' closed forms);
* the prediction uses the model's structure: ``F = I + dt E`` where only the joint rows of
  ``E`` are not zero and each has at most 9 entries (its joint's coordinates and its two
  links' gyro channels), so ``F P F' = P + dt (M + M') + dt^2 M E'`` with ``M = E P``;
* one scalar Joseph update per joint coordinate, as ``_exact.exact_step``'s;
* the estimate: the torso angles and their Jacobian ``C`` from the chain's rotations
  (``torso_entries``: ``chain_rotation_axes`` and ``euler_xyz_jacobian``' closed forms).

The lanes path runs it over a batch (``_paths/_exact_lanes``), the stream and the exported
step on one lane (``ExactKCKF.packet_step``); a fitting loss differentiates the lanes path
through its hand-written reverse pass (``_paths/_exact_adjoint``), which transposes this form
piece by piece. The model's ``step`` (the sequential path, the smoother) stays ``_exact``'s
matrix form, whose gradient JAX takes about five times faster than this form's
(benchmarks/README.md, "Issue 49"). The two forms are held to each other and to the NumPy
reference by tests/test_exact_lanes.py and tests/test_exact.py.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
from jaxtyping import Array, Float

from . import _exact
from ._robot import AXES


# ---------------------------------------------------------------------------- entry arithmetic
# An entry is an array over the trials or a Python number (a constant of the model: 0, 1, -1):
# the constants are folded here, so a zero entry costs nothing in the traced step.
def _mul(a, b):
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return a * b
    for x, y in ((a, b), (b, a)):
        if isinstance(x, (int, float)):
            if x == 0:
                return 0
            if x == 1:
                return y
            if x == -1:
                return -y
    return a * b


def _add(*terms):
    out = 0
    for t in terms:
        if isinstance(t, (int, float)) and t == 0:
            continue
        out = t if isinstance(out, (int, float)) and out == 0 else out + t
    return out


def _neg(a):
    return _mul(-1, a)


def _matmul(A, B):
    return [[_add(*(_mul(A[i][k], B[k][j]) for k in range(len(B))))
             for j in range(len(B[0]))] for i in range(len(A))]


def _cross(a, b):
    return [_add(_mul(a[1], b[2]), _neg(_mul(a[2], b[1]))),
            _add(_mul(a[2], b[0]), _neg(_mul(a[0], b[2]))),
            _add(_mul(a[0], b[1]), _neg(_mul(a[1], b[0])))]


def _dot(a, b):
    return _add(*(_mul(x, y) for x, y in zip(a, b, strict=True)))


def _axis_rotation(axis: str, c, s):
    """``_rotations.axis_rotation`` as entries."""
    if axis == "x":
        return [[1, 0, 0], [0, c, _neg(s)], [0, s, c]]
    if axis == "y":
        return [[c, 0, s], [0, 1, 0], [_neg(s), 0, c]]
    return [[c, _neg(s), 0], [s, c, 0], [0, 0, 1]]


def joint_rate_entries(axes: Sequence[str], angles: list | None, g_parent: list, g_child: list,
                       trig: list | None = None):
    """``_exact.joint_rate_jacobians`` as entries (each an array over the lanes, or a
    constant): ``u`` (``m``), ``Du`` (``m x m``) and ``Dg`` (``m x 6``: the parent's gyro
    channels, then the child's), the same closed forms. ``trig``: the angles' ``(cos,
    sin)`` pairs where already computed (then ``angles`` is not read)."""
    m = len(axes)
    if m == 1:
        a = AXES.index(axes[0])
        Dg = [[0] * 6]
        Dg[0][a], Dg[0][3 + a] = -1, 1
        return [_add(g_child[a], _neg(g_parent[a]))], [[0]], Dg
    if trig is None:
        trig = [(jnp.cos(th), jnp.sin(th)) for th in angles]
    rots = [_axis_rotation(ax, c, s) for ax, (c, s) in zip(axes, trig, strict=True)]
    R = rots[0]
    for Rk in rots[1:]:
        R = _matmul(R, Rk)
    cols, after = [None] * m, None  # column k: (R_{k+1} ... R_m)^T e_{a_k}
    for k in range(m - 1, -1, -1):
        a = AXES.index(axes[k])
        cols[k] = ([1 if i == a else 0 for i in range(3)] if after is None
                   else [after[a][i] for i in range(3)])
        after = rots[k] if after is None else _matmul(rots[k], after)
    if m == 3:  # J^-1: the adjugate's rows over the determinant
        adj = [_cross(cols[1], cols[2]), _cross(cols[2], cols[0]), _cross(cols[0], cols[1])]
        inv_det = 1.0 / _dot(cols[0], adj[0])
        Jp = [[_mul(x, inv_det) for x in row] for row in adj]
        Minv = None
    else:  # (J'J)^-1 J'
        M = [[_dot(cols[i], cols[j]) for j in range(2)] for i in range(2)]
        inv_det = 1.0 / _add(_mul(M[0][0], M[1][1]), _neg(_mul(M[0][1], M[1][0])))
        Minv = [[_mul(M[1][1], inv_det), _neg(_mul(M[0][1], inv_det))],
                [_neg(_mul(M[1][0], inv_det)), _mul(M[0][0], inv_det)]]
        Jt = [[cols[k][i] for i in range(3)] for k in range(2)]
        Jp = _matmul(Minv, Jt)
    v = [_add(*(_mul(R[j][i], g_parent[j]) for j in range(3))) for i in range(3)]  # R^T g_p
    r = [_add(g_child[i], _neg(v[i])) for i in range(3)]
    u = [_dot(Jp[k], r) for k in range(m)]
    w, T = v, []
    for k in range(m):
        if k:
            w = [_add(w[i], _mul(u[k - 1], cols[k - 1][i])) for i in range(3)]
        T.append(_cross(cols[k], w))
    Du = [[_dot(Jp[a], T[k]) for k in range(m)] for a in range(m)]
    if Minv is not None:  # the least-squares residual's term (see joint_rate_jacobians)
        Ju = [_add(*(_mul(cols[k][i], u[k]) for k in range(m))) for i in range(3)]
        resid = _dot(_cross(cols[0], cols[1]), [_add(r[i], _neg(Ju[i])) for i in range(3)])
        Du = [[Du[a][0], _add(Du[a][1], _mul(Minv[a][0], resid))] for a in range(m)]
    JpRt = [[_add(*(_mul(Jp[k][i], R[j][i]) for i in range(3))) for j in range(3)]
            for k in range(m)]
    Dg = [[_neg(x) for x in JpRt[k]] + list(Jp[k]) for k in range(m)]
    return u, Du, Dg



# ---------------------------------------------------------------------------- the step
def prediction_rows(model: _exact.ExactModel, theta, gyro, trig: list | None = None):
    """The joint rows of ``E`` (``F = I + dt E``) as ``(column, entry)`` lists, and the
    coordinates' rates ``u``, at the filtered ``theta`` (``J`` arrays ``B``) with the bias-free
    gyro rates ``gyro`` (``G`` arrays ``B``). ``trig``: ``theta``'s ``(cos, sin)`` pairs where
    already computed (then ``theta`` is not read)."""
    col = {c: model.J + i for i, c in enumerate(model.channels)}
    rows, rates = [], []
    for i, (axes, sl) in enumerate(zip(model.robot.joints, model.joint_slices, strict=True)):
        g_p, g_c = gyro[3 * i:3 * i + 3], gyro[3 * i + 3:3 * i + 6]
        u, Du, Dg = joint_rate_entries(
            axes, None if trig is not None else [theta[k] for k in sl], g_p, g_c,
            None if trig is None else [trig[k] for k in sl])
        rates += u
        for a in range(len(sl)):
            entries = [(sl[b], Du[a][b]) for b in range(len(sl))]
            entries += [(col[3 * i + c], _neg(Dg[a][c])) for c in range(6)
                        if 3 * i + c in col]
            rows.append([(c, e) for c, e in entries
                         if not (isinstance(e, (int, float)) and e == 0)])
    return rows, rates


def times(e, x):
    """An entry times an array whose last axis is the trials'."""
    if isinstance(e, (int, float)):
        return _mul(e, x)
    return x * e.reshape((1,) * (x.ndim - e.ndim) + e.shape)



def entry_step(model: _exact.ExactModel, z: Float[Array, "Nz B"],
              P: Float[Array, "Nz Nz B"], hold: Float[Array, "G B"], ts: Float[Array, " B"],
              h, rh, vh, q: Float[Array, "Nz B"], tape: list | None = None):
    """One row on lanes (``B``: any trailing lane axes): ``_exact.exact_step``'s predict and
    updates, ``q`` the process noise's diagonal. Returns the new ``z``, ``P`` and each joint
    coordinate's innovation and its variance (``J B``). ``tape``: a list that every scalar
    update appends its gain ``k`` (``Nz B``) and ``w = nu / s`` (``B``; both zero where the
    update is not used) to, for the reverse pass (``_paths/_exact_adjoint``)."""
    J = model.J
    dtype = z.dtype
    beta_col = {c: i for i, c in enumerate(model.channels)}
    gyro = [hold[c] - z[J + beta_col[c]] if c in beta_col else hold[c]
            for c in range(model.G)]
    rows, u = prediction_rows(model, [z[k] for k in range(J)], gyro)
    M = jnp.stack([sum((times(e, P[c]) for c, e in row), jnp.zeros_like(P[0]))
                   for row in rows])  # E P: (J, Nz, B)
    MEt = jnp.stack([sum((times(e, M[:, c]) for c, e in row), jnp.zeros_like(M[:, 0]))
                     for row in rows], axis=1)  # E P E': (J, J, B)
    dt = ts[None]
    top = P[:J] + dt * M
    S = jnp.concatenate([top, P[J:]])
    Mt = jnp.moveaxis(M, 0, 1)
    S = jnp.concatenate([jnp.concatenate([S[:J, :J] + dt * Mt[:J] + dt[None] ** 2 * MEt,
                                          S[:J, J:]], axis=1),
                         jnp.concatenate([S[J:, :J] + dt * Mt[J:], S[J:, J:]], axis=1)])
    eye = jnp.eye(z.shape[0], dtype=dtype)[:, :, None]
    S = 0.5 * (S + jnp.moveaxis(S, 0, 1)) + eye * q[None]
    zn = jnp.concatenate([z[:J] + dt * jnp.stack(u), z[J:]])
    Pn = S
    nus, ss = [], []
    for i in range(J):
        c = Pn[:, i]
        s = c[i] + rh[i]
        nu = h[i] - zn[i]
        nus.append(nu)
        ss.append(s)
        ok = vh[i] & (s > 0)
        k = jnp.where(ok[None], c / jnp.where(ok, s, 1.0)[None], 0.0)
        if tape is not None:
            tape.append((k, jnp.where(ok, nu / jnp.where(ok, s, 1.0), 0.0)))
        zn = zn + k * jnp.where(ok, nu, 0.0)[None]
        Pn = Pn - k[:, None] * c[None] - c[:, None] * k[None] + s[None, None] * k[:, None] * k[None]
    Pn = 0.5 * (Pn + jnp.moveaxis(Pn, 0, 1))
    return zn, Pn, jnp.stack(nus), jnp.stack(ss)


# ---------------------------------------------------------------------------- the estimate
def torso_entries(model: _exact.ExactModel, theta: list) -> tuple[list, list]:
    """``_exact.torso_angles_jacobian`` at ``theta`` (``J`` arrays over the lanes): the torso
    angles ``phi`` (``P`` entries: ``euler_xyz`` of the chain's rotation) and their Jacobian
    ``C`` (``P x J`` entries: each coordinate's axis in link 1's frame, ``chain_rotation_axes``,
    through the Euler angles' derivative, ``euler_xyz_jacobian``), the same closed forms."""
    R, S = None, []
    for axes, sl in zip(model.robot.joints, model.joint_slices, strict=True):
        Q = None
        for k, a in enumerate(axes):
            col = AXES.index(a)
            if Q is None and R is None:
                s = [1 if i == col else 0 for i in range(3)]
            elif Q is None:
                s = [R[i][col] for i in range(3)]
            elif R is None:
                s = [Q[i][col] for i in range(3)]
            else:
                s = [_dot(R[i], [Q[j][col] for j in range(3)]) for i in range(3)]
            S.append(s)
            th = theta[sl[k]]
            Rk = _axis_rotation(a, jnp.cos(th), jnp.sin(th))
            Q = Rk if Q is None else _matmul(Q, Rk)
        R = Q if R is None else _matmul(R, Q)

    def d(i, j, s):  # (hat(s) R)_ij = (s x R_j)_i
        Rj = [R[0][j], R[1][j], R[2][j]]
        return _cross(s, Rj)[i]

    euler = [jnp.arctan2(_neg(R[1][2]), R[2][2]),
             jnp.arcsin(jnp.clip(R[0][2], -1.0, 1.0)),
             jnp.arctan2(_neg(R[0][1]), R[0][0])]
    rows = []
    for s in S:
        d02, d12, d22 = d(0, 2, s), d(1, 2, s), d(2, 2, s)
        d00, d01 = d(0, 0, s), d(0, 1, s)
        rows.append((d02, d12, d22, d00, d01))
    r = R
    out = []
    for axis in model.torso_axes:
        if axis == 0:
            den = 1.0 / _add(_mul(r[1][2], r[1][2]), _mul(r[2][2], r[2][2]))
            out.append([_mul(_add(_mul(r[1][2], x[2]), _neg(_mul(r[2][2], x[1]))), den)
                        for x in rows])
        elif axis == 1:
            den = 1.0 / jnp.sqrt(1.0 - jnp.clip(r[0][2], -1.0, 1.0) ** 2)
            out.append([_mul(x[0], den) for x in rows])
        else:
            den = 1.0 / _add(_mul(r[0][1], r[0][1]), _mul(r[0][0], r[0][0]))
            out.append([_mul(_add(_mul(r[0][1], x[3]), _neg(_mul(r[0][0], x[4]))), den)
                        for x in rows])
    return [euler[a] for a in model.torso_axes], out



def angle_variances(model: _exact.ExactModel, z: Float[Array, "Nz ..."],
                    P: Float[Array, "Nz Nz ..."], C: list | None = None) -> Float[Array, "K ..."]:
    """The joint coordinates' variances and the torso angles' through the chain's Jacobian
    ``C`` at ``z`` (``_exact.exact_estimate``'s; ``C``: ``torso_entries``' where known)."""
    J = model.J
    if C is None:
        _, C = torso_entries(model, [z[k] for k in range(J)])
    out = [P[k, k] for k in range(J)]
    for Cp in C:
        CP = [_add(*(times(Cp[j], P[j, k]) for j in range(J))) for k in range(J)]
        out.append(_add(*(_mul(CP[k], Cp[k]) for k in range(J))))
    return jnp.stack([jnp.broadcast_to(x, z.shape[1:]) for x in out])


def entry_estimate(model: _exact.ExactModel, z: Float[Array, "Nz ..."],
                   P: Float[Array, "Nz Nz ..."]):
    """``_exact.exact_estimate`` on lanes: the angles (joint coordinates, then the chain's
    torso angles), their standard deviations and each angle's rate bias at this pose
    (``K`` by the lanes each)."""
    J = model.J
    lanes = z.shape[1:]
    theta = [z[k] for k in range(J)]
    phi, C = torso_entries(model, theta)
    var = angle_variances(model, z, P, C)
    beta = {c: z[J + i] for i, c in enumerate(model.channels)}
    zero = [0, 0, 0]
    rate_bias = []
    for i, (axes, sl) in enumerate(zip(model.robot.joints, model.joint_slices, strict=True)):
        _, _, Dg = joint_rate_entries(axes, [theta[k] for k in sl], zero, zero)
        for a in range(len(sl)):
            rate_bias.append(_add(*(_mul(Dg[a][c], beta[3 * i + c]) for c in range(6)
                                    if 3 * i + c in beta)))
    torso_bias = [_add(*(_mul(Cp[j], rate_bias[j]) for j in range(J))) for Cp in C]

    def stack(xs):
        return jnp.stack([jnp.broadcast_to(jnp.asarray(x, z.dtype), lanes) for x in xs])

    return (jnp.concatenate([z[:J], stack(phi)]), jnp.sqrt(jnp.maximum(var, 0.0)),
            stack(rate_bias + torso_bias))


__all__ = ["angle_variances", "entry_estimate", "entry_step", "joint_rate_entries",
           "prediction_rows", "times", "torso_entries"]
