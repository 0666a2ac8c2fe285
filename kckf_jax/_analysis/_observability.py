"""Observability of the standard KF and the KCKF (paper Sec. 3.3, Eq. 21), and the local
observability of the rotation-aware KCKF (``kckf3d``) at a pose."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._models._blocks import paper_matrices
from .._models._exact import exact_model, torso_angles
from .._models._robot import Robot


def observability_matrix(robot: Robot, constrained: bool, ts: float = 0.01,
                         pose: np.ndarray | None = None) -> np.ndarray:
    """``O = [C; C A; ...; C A^(N-1)]`` (Eq. 21) with ``C`` of Eq. 8 (KF) or Eq. 19 (KCKF).
    ``pose`` (joint coordinates, rad): the constraint's rows are the exact model's linearised
    there (``kckf3d``: ``[dphi/dtheta, -I, 0, 0]``; at rest its process is Eq. 11's ``A``)."""
    pm = paper_matrices(robot, ts=ts)
    D = pm.D
    if pose is not None:
        theta = jnp.asarray(pose, jnp.float32)
        jac = jax.jacfwd(lambda th: torso_angles(exact_model(robot), th))(theta)
        D = D.copy()
        D[:, : robot.n_joint_axes] = np.asarray(jac, np.float64)
    C = np.vstack([pm.C, D]) if constrained else pm.C
    blocks, CA = [], C
    for _ in range(robot.n_states):
        blocks.append(CA)
        CA = CA @ pm.A
    return np.vstack(blocks)


def observability_ranks(robot: Robot, ts: float = 0.01,
                        pose: np.ndarray | None = None) -> dict[str, int]:
    """``{"n_states": N, "rank_kf": r1, "rank_kckf": r2, "rank_kckf3d": r3}`` for ``robot``.

    The paper finds ``N - 6`` for the KF of a 3D robot (the torso angle and its bias, three
    axes each, are unobservable) and ``N`` for the KCKF; in general the KF loses ``2 P``.
    ``rank_kckf3d``: the rotation-aware KCKF's local rank, its constraint linearised at
    ``pose`` (joint coordinates, rad; default the neutral pose, where it is the KCKF's).

    Example:
        >>> observability_ranks(Robot.from_spec("x,y,x,y"))
        {'n_states': 12, 'rank_kf': 8, 'rank_kckf': 12, 'rank_kckf3d': 12}
    """
    pose = np.zeros(robot.n_joint_axes) if pose is None else np.asarray(pose, np.float64)
    O3 = observability_matrix(robot, True, ts, pose)
    # The exact constraint's rows come from a float32 Jacobian: a tolerance to match.
    s = np.linalg.svd(O3, compute_uv=False)
    return {
        "n_states": robot.n_states,
        "rank_kf": int(np.linalg.matrix_rank(observability_matrix(robot, False, ts))),
        "rank_kckf": int(np.linalg.matrix_rank(observability_matrix(robot, True, ts))),
        "rank_kckf3d": int(np.sum(s > 1e-5 * s[0])),
    }


def pose_from_degrees(robot: Robot, text: str, what: str = "pose") -> np.ndarray:
    """Joint coordinates (rad) from ``"deg,deg,..."``, one per joint axis of ``robot``; a
    ``ValueError`` naming ``what`` and the axes otherwise."""
    try:
        deg = [float(x) for x in text.split(",")]
    except ValueError:
        raise ValueError(f"{what} {text!r}: expected {robot.n_joint_axes} comma-separated joint "
                         f"angles in degrees ({', '.join(robot.joint_angle_names)})") from None
    if len(deg) != robot.n_joint_axes:
        raise ValueError(f"{what}: {len(deg)} angles for {robot.n_joint_axes} joint axes "
                         f"({', '.join(robot.joint_angle_names)})")
    return np.radians(deg)
