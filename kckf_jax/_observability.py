"""Observability of the standard KF and the KCKF (paper Sec. 3.3, Eq. 21)."""

from __future__ import annotations

import numpy as np

from ._model import paper_matrices
from ._robot import Robot


def observability_matrix(robot: Robot, constrained: bool, ts: float = 0.01) -> np.ndarray:
    """``O = [C; C A; ...; C A^(N-1)]`` (Eq. 21) with ``C`` of Eq. 8 (KF) or Eq. 19 (KCKF)."""
    pm = paper_matrices(robot, ts=ts)
    C = np.vstack([pm.C, pm.D]) if constrained else pm.C
    blocks, CA = [], C
    for _ in range(robot.n_states):
        blocks.append(CA)
        CA = CA @ pm.A
    return np.vstack(blocks)


def observability_ranks(robot: Robot, ts: float = 0.01) -> dict[str, int]:
    """``{"n_states": N, "rank_kf": r1, "rank_kckf": r2}`` for ``robot``.

    The paper finds ``N - 6`` for the KF of a 3D robot (the torso angle and its bias, three
    axes each, are unobservable) and ``N`` for the KCKF; in general the KF loses ``2 P``.

    Example:
        >>> observability_ranks(Robot.from_spec("x,y,x,y"))
        {'n_states': 12, 'rank_kf': 8, 'rank_kckf': 12}
    """
    return {
        "n_states": robot.n_states,
        "rank_kf": int(np.linalg.matrix_rank(observability_matrix(robot, False, ts))),
        "rank_kckf": int(np.linalg.matrix_rank(observability_matrix(robot, True, ts))),
    }
