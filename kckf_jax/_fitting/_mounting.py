"""Each gyro board's mounting from the gyros alone: the start of a fit that learns
``gyro_mounting`` (docs/fitting.md, "Gyros as worn").

The joint-axis idea (Seel, Raisch & Schauer, Sensors 14(4), 2014): across a hinge the two
links turn the same way but about the hinge's axis, so the parts of their rates
perpendicular to the axis have the same size at every instant,

    || g1 x j1 || = || g2 x j2 ||,

``g1``, ``g2`` the two boards' readings and ``j1``, ``j2`` the hinge's axis as each board sees
it (unit vectors). This holds for finite rotations, whatever the joint angle, and needs no
motion capture. Each one-axis joint of the robot gives its axis in both its boards' frames
(Gauss-Newton from the axis the spec names: a board is a few degrees off, so the nearest
solution is the right one and the sign is the spec's). A board then has one known direction
(its link's axis, ``e_a``) per hinge beside it: two or more fix its rotation (the least-squares
rotation taking the seen axes to the named ones, Kabsch); one fixes it up to a turn about
that axis (the smallest rotation is taken); none, and it stays zero. What the motion needs:
each hinge moving while the link below turns about other axes too (the perpendicular rates
must vary); a hinge whose links turn only about its axis says nothing.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .._models._robot import AXES, Robot
from .._sessions._session import Session

DEG = np.pi / 180.0
#: Rows whose perpendicular rates are below this (rad/s) say little: left out.
_MIN_RATE = 0.05


def hinge_axes(g1: np.ndarray, g2: np.ndarray, axis: str, iterations: int = 30
               ) -> tuple[np.ndarray, np.ndarray, int]:
    """A hinge's axis as each of its two boards sees it (unit vectors, sign of the named
    ``axis``) from their readings (``T 3`` each, rad/s; rows with a missing axis left out):
    Gauss-Newton on ``||g1 x j1|| - ||g2 x j2||`` from the named axis. Also returns the rows
    used."""
    ok = np.isfinite(g1).all(axis=1) & np.isfinite(g2).all(axis=1)
    g1, g2 = g1[ok], g2[ok]
    e = np.eye(3)[AXES.index(axis)]
    ok = (np.linalg.norm(np.cross(g1, e), axis=1) > _MIN_RATE) | (
        np.linalg.norm(np.cross(g2, e), axis=1) > _MIN_RATE)
    g1, g2 = g1[ok], g2[ok]
    # Two angles per axis about the named one: j = R_e(a, b) e, tangent coordinates.
    u, v = np.eye(3)[(AXES.index(axis) + 1) % 3], np.eye(3)[(AXES.index(axis) + 2) % 3]

    def unit(p):
        x = e + p[0] * u + p[1] * v
        return x / np.linalg.norm(x)

    def residual(p):
        j1, j2 = unit(p[:2]), unit(p[2:])
        return np.linalg.norm(np.cross(g1, j1), axis=1) - np.linalg.norm(np.cross(g2, j2), axis=1)

    p = np.zeros(4)
    for _ in range(iterations):
        r = residual(p)
        J = np.stack([(residual(p + h) - r) / 1e-7 for h in np.eye(4) * 1e-7], axis=1)
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        p = p + step
        if np.max(np.abs(step)) < 1e-10:
            break
    return unit(p[:2]), unit(p[2:]), int(ok.sum())


def _rotation_vector(R: np.ndarray) -> np.ndarray:
    """The rotation vector (rad) of a rotation matrix (its log)."""
    angle = np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))
    if angle < 1e-12:
        return np.zeros(3)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w * angle / (2 * np.sin(angle))


def board_rotation(seen: Sequence[np.ndarray], named: Sequence[np.ndarray]) -> np.ndarray:
    """The rotation vector (rad) of ``R`` with ``R seen_k ~ named_k``: Kabsch for two or more
    directions, the smallest rotation for one, zero for none."""
    if not seen:
        return np.zeros(3)
    if len(seen) == 1:
        a, b = seen[0], named[0]
        c = np.cross(a, b)
        s = np.linalg.norm(c)
        return np.zeros(3) if s < 1e-12 else c / s * np.arctan2(s, float(a @ b))
    H = np.stack(seen).T @ np.stack(named)  # sum of seen_k named_k'
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return _rotation_vector(R)


def estimate_mounting(robot: Robot, sessions: Sequence[Session]) -> tuple[np.ndarray, list]:
    """Each board's rotation on its link from the gyros of ``sessions`` (the module docstring):
    ``(L, 3)`` rotation vectors in deg (``SensorEffects.mounting``'s form) and, per board, the
    hinges that fixed it (``[]``: none, the board stays as mounted nominally)."""
    seen: list[list] = [[] for _ in range(robot.n_links)]
    named: list[list] = [[] for _ in range(robot.n_links)]
    by: list[list] = [[] for _ in range(robot.n_links)]
    for i, axes in enumerate(robot.joints):  # joint i + 1: links i (below) and i + 1 (above)
        if len(axes) != 1:
            continue
        g1 = np.concatenate([s.gyro[:, 3 * i:3 * i + 3] for s in sessions])
        g2 = np.concatenate([s.gyro[:, 3 * i + 3:3 * i + 6] for s in sessions])
        j1, j2, used = hinge_axes(g1, g2, axes[0])
        if used < 10:
            continue
        e = np.eye(3)[AXES.index(axes[0])]
        for link, j in ((i, j1), (i + 1, j2)):
            seen[link].append(j)
            named[link].append(e)
            by[link].append(f"joint {i + 1} ({axes[0]})")
    rot = np.stack([board_rotation(s, n) for s, n in zip(seen, named)]) / DEG
    return rot, by
