"""Finite rotations of a serial chain: what the paper's first-order model leaves out.

A joint with several axes turns about them in the order written (``xyz``: about x, then about
the new y, then about the new z; its rotation is ``Rx Ry Rz``, ``../shared/spec/
session-format.md``). Each link's gyro measures that link's angular rate in its own frame, so
link ``i + 1``'s body rate is link ``i``'s turned into the new frame plus the joint's own:

    w_{i+1} = R_i^T w_i + J_i(theta_i) dtheta_i / dt,

where ``J_i`` (the joint's body Jacobian) maps its coordinate rates to the relative angular
velocity in the child's frame: column ``k`` is axis ``k`` turned by the rotations after it,
``(R_{k+1} ... R_m)^T e_k``. The torso's orientation is the product of the joints' rotations,
and its angles ``phi`` are the intrinsic x-y-z Euler angles of that product (``euler_xyz``). To
first order in the angles ``R_i = I``, ``J_i = I`` and the Euler angles are the sums of the
joint angles: the paper's Eqs. 2 and 14.

Every function takes ``xp`` (``numpy``, or ``jax.numpy`` for a filter that differentiates
through them) and works on any leading axes. Plain arithmetic, no state.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ._robot import AXES


def axis_rotation(axis: str, angle, xp=np):
    """The rotation about ``axis`` (``"x"``, ``"y"`` or ``"z"``) by ``angle`` (rad, any
    shape): ``(..., 3, 3)``."""
    c, s = xp.cos(angle), xp.sin(angle)
    one, zero = xp.ones_like(c), xp.zeros_like(c)
    if axis == "x":
        rows = ((one, zero, zero), (zero, c, -s), (zero, s, c))
    elif axis == "y":
        rows = ((c, zero, s), (zero, one, zero), (-s, zero, c))
    elif axis == "z":
        rows = ((c, -s, zero), (s, c, zero), (zero, zero, one))
    else:
        raise ValueError(f"axis must be 'x', 'y' or 'z', got {axis!r}")
    return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def joint_rotation(axes: Sequence[str], angles, xp=np):
    """A joint's rotation, ``R_a1(angles[..., 0]) R_a2(angles[..., 1]) ...`` in the order of
    ``axes``: ``(..., 3, 3)``."""
    R = axis_rotation(axes[0], angles[..., 0], xp)
    for k in range(1, len(axes)):
        R = R @ axis_rotation(axes[k], angles[..., k], xp)
    return R


def joint_jacobian(axes: Sequence[str], angles, xp=np):
    """The joint's body Jacobian ``(..., 3, m)``: its coordinate rates to the angular velocity
    of the child link relative to the parent, in the child's frame. Column ``k`` is
    ``(R_{k+1} ... R_m)^T e_{a_k}``."""
    m = len(axes)
    cols = [None] * m
    after = None  # R_{k+1} ... R_m
    for k in range(m - 1, -1, -1):
        e = np.zeros(3)
        e[AXES.index(axes[k])] = 1.0
        e = xp.broadcast_to(xp.asarray(e, dtype=angles.dtype), angles.shape[:-1] + (3,))
        cols[k] = e if after is None else xp.einsum("...ji,...j->...i", after, e)
        R_k = axis_rotation(axes[k], angles[..., k], xp)
        after = R_k if after is None else R_k @ after
    return xp.stack(cols, axis=-1)


def link_rates(joints: Sequence[Sequence[str]], angles: Sequence, rates: Sequence, base_rate,
               xp=np) -> list:
    """Every link's body rate (``n + 1`` arrays ``(..., 3)``), link 1's being ``base_rate``:
    ``w_{i+1} = R_i^T w_i + J_i dtheta_i``. ``angles[i]``, ``rates[i]``: joint ``i``'s
    coordinates and their rates, ``(..., m_i)`` in the order of its axes."""
    out = [base_rate]
    for axes, th, dth in zip(joints, angles, rates, strict=True):
        R = joint_rotation(axes, th, xp)
        J = joint_jacobian(axes, th, xp)
        w = xp.einsum("...ji,...j->...i", R, out[-1]) + xp.einsum("...ik,...k->...i", J, dth)
        out.append(w)
    return out


def chain_rotation(joints: Sequence[Sequence[str]], angles: Sequence, xp=np):
    """The orientation of link ``n + 1`` relative to link 1: the product of the joints'
    rotations, ``(..., 3, 3)``."""
    R = joint_rotation(joints[0], angles[0], xp)
    for axes, th in zip(joints[1:], angles[1:], strict=True):
        R = R @ joint_rotation(axes, th, xp)
    return R


def euler_xyz(R, xp=np):
    """The intrinsic x-y-z Euler angles ``(..., 3)`` of ``R = Rx(a) Ry(b) Rz(c)`` (rad; ``b``
    in ``[-pi/2, pi/2]``: singular at ``|b| = pi/2``, gimbal lock)."""
    a = xp.arctan2(-R[..., 1, 2], R[..., 2, 2])
    b = xp.arcsin(xp.clip(R[..., 0, 2], -1.0, 1.0))
    c = xp.arctan2(-R[..., 0, 1], R[..., 0, 0])
    return xp.stack([a, b, c], axis=-1)


def euler_body_rates(angles, rates, xp=np):
    """The body rate ``(..., 3)`` of an orientation given as intrinsic x-y-z Euler angles and
    their rates: a joint ``xyz``'s Jacobian applied to the rates."""
    return xp.einsum("...ik,...k->...i", joint_jacobian(("x", "y", "z"), angles, xp), rates)


def chain_rotation_axes(joints: Sequence[Sequence[str]], angles: Sequence, xp=np):
    """``chain_rotation`` (the same products in the same order, so the same values) and each
    joint coordinate's axis in link 1's frame, ``(..., 3, J)`` (joints in order, a joint's axes
    in order): coordinate ``k``'s axis ``s_k`` is its own axis turned by every rotation before
    it, ``R_1 ... R_{k-1} e_{a_k}``, so turning it by ``dtheta_k`` turns the chain by
    ``dR = hat(s_k) R dtheta_k`` (the product rule: ``R_{<k} hat(e) R_k R_{>k}``, and
    ``R_{<k} hat(e) R_{<k}^T = hat(R_{<k} e)``)."""
    R, cols = None, []
    for axes, th in zip(joints, angles, strict=True):
        Q = None  # the joint's rotations before this axis (joint_rotation's partial products)
        for k, a in enumerate(axes):
            col = AXES.index(a)
            if Q is None and R is None:
                e = np.zeros(3)
                e[col] = 1.0
                s = xp.broadcast_to(xp.asarray(e, dtype=th.dtype), th.shape[:-1] + (3,))
            elif Q is None:
                s = R[..., :, col]
            elif R is None:
                s = Q[..., :, col]
            else:
                s = xp.einsum("...ij,...j->...i", R, Q[..., :, col])
            cols.append(s)
            R_k = axis_rotation(a, th[..., k], xp)
            Q = R_k if Q is None else Q @ R_k
        R = Q if R is None else R @ Q
    return R, xp.stack(cols, axis=-1)


def euler_xyz_jacobian(R, S, xp=np):
    """The derivative ``(..., 3, K)`` of ``euler_xyz(R)`` when ``R`` turns by ``hat(s_k) R
    dtheta_k`` (``S``: the axes ``s_k``, ``(..., 3, K)``, in ``R``'s outer frame; e.g.
    ``chain_rotation_axes``): the five entries ``euler_xyz`` reads, differentiated
    (``(hat(s) R)_ij = (s x R_j)_i``), through its ``arctan2`` and ``arcsin``. Singular where
    ``euler_xyz`` is (``|b| = pi/2``)."""
    s0, s1, s2 = S[..., 0, :], S[..., 1, :], S[..., 2, :]

    def r(i, j):
        return R[..., i, j][..., None]

    d02 = s1 * r(2, 2) - s2 * r(1, 2)
    d12 = s2 * r(0, 2) - s0 * r(2, 2)
    d22 = s0 * r(1, 2) - s1 * r(0, 2)
    d00 = s1 * r(2, 0) - s2 * r(1, 0)
    d01 = s1 * r(2, 1) - s2 * r(1, 1)
    da = (r(1, 2) * d22 - r(2, 2) * d12) / (r(1, 2) ** 2 + r(2, 2) ** 2)
    db = d02 / xp.sqrt(1.0 - xp.clip(r(0, 2), -1.0, 1.0) ** 2)
    dc = (r(0, 1) * d00 - r(0, 0) * d01) / (r(0, 1) ** 2 + r(0, 0) ** 2)
    return xp.stack([da, db, dc], axis=-2)
