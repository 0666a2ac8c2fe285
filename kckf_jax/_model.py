"""State-space matrices of the standard KF and the KCKF for a robot layout and parameters.

Two views of the same model live here:

* the **paper's matrices** (``paper_matrices``): state ``x = [theta, phi, b, b_phi]`` (Eq. 7,
  restricted to active axes), transition ``A`` (Eq. 11), input ``B`` (Eq. 12), ``Q`` (Eq. 13,
  plus optional random walks), Hall measurement ``C`` (Eq. 8), constraint ``D`` (Eq. 17) and
  ``R`` (Eq. 20). Used for observability (Eq. 21) and as documentation of the model.
* the **filter coordinates** (``Structure``) in which the filters run. For the standard KF
  they are the paper's. For the KCKF the state is changed to ``y = [theta, b, b_phi, e]`` with
  ``e = D x = sum theta - phi``: the constraint of Eqs. 15-19 says exactly ``e = 0``, so after
  every update the estimate lives in ``z = [theta, b, b_phi]`` and ``phi = S theta``. The
  change of basis ``y = M x`` is an integer matrix, so ``M A M^-1``, ``M B`` and ``M Q M^T``
  are formed without round-off, and the near-singular quantity ``D P D^T`` of the paper's
  update is never formed by cancellation: the predicted ``e`` depends on ``z`` only through
  ``ts (S b - b_phi)`` (see docs/numerics.md).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._params import Params
from ._robot import Robot

FILTER_METHODS = ("kckf", "kf")


@dataclass(frozen=True)
class PaperMatrices:
    """The paper's model for one time step ``ts`` (NumPy float64)."""

    A: np.ndarray  # (N, N)  Eq. 11
    B: np.ndarray  # (N, 3(n+1))  Eq. 12 (columns for every gyro channel)
    Q: np.ndarray  # (N, N)  Eq. 13 (+ random walks)
    C: np.ndarray  # (M, N)  Eq. 8
    D: np.ndarray  # (P, N)  Eq. 17
    R: np.ndarray  # (M, M)  Eq. 20 (Hall block; the constraint rows have zero noise)


def q_blocks(q, angle_rw, bias_rw, ts):
    """Per-coordinate ``(angle var, cross cov, bias var)`` of the discrete process noise.

    Eq. 13 scaled by ``q`` (``[[ts^4/4, ts^3/2], [ts^3/2, ts^2]]``), plus an angle random walk
    ``angle_rw^2 ts`` and a bias random walk ``bias_rw^2 ts`` (zero in the paper).
    """
    alpha = q * ts**4 / 4 + angle_rw**2 * ts
    beta = q * ts**3 / 2
    gamma = q * ts**2 + bias_rw**2 * ts
    return alpha, beta, gamma


def paper_matrices(robot: Robot, params: Params | None = None, ts: float = 0.01) -> PaperMatrices:
    """The paper's ``A, B, Q, C, D, R`` for ``robot`` at time step ``ts`` (float64)."""
    K = robot.n_angles
    N = 2 * K
    if params is None:
        params = Params.paper_defaults(robot)
    p = {k: np.asarray(getattr(params, k), dtype=np.float64)
         for k in ("q", "angle_rw", "bias_rw", "sigma_hall")}
    A1, Bu, C, D = _structural(robot)
    A, B = np.eye(N) + ts * A1, ts * Bu
    a, b, g = q_blocks(p["q"], p["angle_rw"], p["bias_rw"], ts)
    Q = np.zeros((N, N))
    idx = np.arange(K)
    Q[idx, idx] = a
    Q[idx, K + idx] = b
    Q[K + idx, idx] = b
    Q[K + idx, K + idx] = g
    R = np.diag(p["sigma_hall"] ** 2)
    return PaperMatrices(A=A, B=B, Q=Q, C=C, D=D, R=R)


def _structural(robot: Robot) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``A1, Bu, C, D`` with ``A = I + ts A1`` (Eq. 11) and ``B = ts Bu`` (Eq. 12)."""
    K, J, M = robot.n_angles, robot.n_joint_axes, robot.n_hall
    N = 2 * K
    A1 = np.zeros((N, N))
    A1[np.arange(K), K + np.arange(K)] = -1.0
    Bu = np.zeros((N, 3 * robot.n_links))
    Bu[:K] = robot.rate_map
    C = np.zeros((M, N))
    C[np.arange(M), robot.hall_joint_axis] = 1.0
    D = np.zeros((robot.n_torso_axes, N))
    D[:, :J] = robot.torso_sum
    D[:, J:K] = -np.eye(robot.n_torso_axes)
    return A1, Bu, C, D


@dataclass(frozen=True)
class Structure:
    """Constant matrices of one filter in its own coordinates (NumPy float64).

    ``y = [z, e]`` has ``Ny = Nz + Ne`` entries; the estimate is ``z`` (``Nz`` entries) and ``e``
    are perfect pseudo-measurements conditioned to zero at every step (``Ne = P`` for the KCKF,
    0 for the KF). With time step ``ts``:

    * predicted mean ``y = (F0 + ts F1) z + ts G1 u``, ``u`` the flattened gyro rates;
    * predicted covariance ``(F0 + ts F1) P (F0 + ts F1)^T + Qy`` with
      ``Qy = Ma diag(alpha) Ma^T + Ma diag(beta) Mb^T + Mb diag(beta) Ma^T + Mb diag(gamma) Mb^T``
      (``alpha, beta, gamma`` from ``q_blocks``);
    * Hall sensor ``m`` measures ``z[hall_index[m]]``;
    * the paper's state is ``x = T z``; ``T[:K]`` gives the angles, ``T[K:]`` the biases.
    """

    method: str
    n_z: int
    n_e: int
    F0: np.ndarray
    F1: np.ndarray
    G1: np.ndarray
    Ma: np.ndarray
    Mb: np.ndarray
    T: np.ndarray
    hall_index: tuple[int, ...]
    p0_angle_index: tuple[int, ...]  # which angle coordinate's p0 each z entry uses (or -1)
    p0_bias_index: tuple[int, ...]


@functools.lru_cache(maxsize=64)
def structure(robot: Robot, method: str) -> Structure:
    """The constant matrices of ``method`` (``"kckf"`` or ``"kf"``) for ``robot``."""
    if method not in FILTER_METHODS:
        raise ValueError(f"structure: method must be one of {FILTER_METHODS}, got {method!r}")
    K, J, P = robot.n_angles, robot.n_joint_axes, robot.n_torso_axes
    N = 2 * K
    A1, Bu, _, D = _structural(robot)
    if method == "kf":
        Mx = np.eye(N)
        n_z, n_e = N, 0
        p0_angle_index = tuple(range(K)) + (-1,) * K
        p0_bias_index = (-1,) * K + tuple(range(K))
    else:
        # y = [theta (J), b (J), b_phi (P), e (P)] with e = D x = S theta - phi.
        Mx = np.zeros((N, N))
        Mx[:J, :J] = np.eye(J)
        Mx[J:2 * J, K:K + J] = np.eye(J)
        Mx[2 * J:2 * J + P, K + J:] = np.eye(P)
        Mx[2 * J + P:, :] = D
        n_z, n_e = N - P, P
        p0_angle_index = tuple(range(J)) + (-1,) * (J + P)
        p0_bias_index = (-1,) * J + tuple(range(K))
    Minv = np.linalg.inv(Mx)
    # Mx is a permutation plus integer rows; its inverse is exact in float64.
    assert np.allclose(Minv @ Mx, np.eye(N)) and np.all(Minv == np.round(Minv))
    return Structure(
        method=method, n_z=n_z, n_e=n_e,
        F0=(Mx @ Minv)[:, :n_z], F1=(Mx @ A1 @ Minv)[:, :n_z], G1=Mx @ Bu,
        Ma=Mx[:, :K], Mb=Mx[:, K:], T=Minv[:, :n_z],
        hall_index=tuple(int(j) for j in robot.hall_joint_axis),
        p0_angle_index=p0_angle_index, p0_bias_index=p0_bias_index,
    )


def predicted_moments(
    st: Structure,
    params: Params,
    z: Float[Array, " Nz"],
    P: Float[Array, "Nz Nz"],
    u: Float[Array, " G"],
    ts: Float[Array, ""],
) -> tuple[Float[Array, " Ny"], Float[Array, "Ny Ny"]]:
    """Mean and covariance of ``y = [z, e]`` one step ahead (Eqs. 3, 9-13 in filter coordinates)."""
    dtype = z.dtype
    F = jnp.asarray(st.F0, dtype) + ts * jnp.asarray(st.F1, dtype)
    y = F @ z + ts * (jnp.asarray(st.G1, dtype) @ u)
    alpha, beta, gamma = q_blocks(params.q, params.angle_rw, params.bias_rw, ts)
    Ma, Mb = jnp.asarray(st.Ma, dtype), jnp.asarray(st.Mb, dtype)
    Qy = (Ma * alpha) @ Ma.T + (Ma * beta) @ Mb.T + (Mb * beta) @ Ma.T + (Mb * gamma) @ Mb.T
    return y, F @ P @ F.T + Qy


def initial_covariance(st: Structure, params: Params) -> Float[Array, "Nz Nz"]:
    """Diagonal prior in filter coordinates from ``params.p0_angle`` and ``params.p0_bias``."""
    pa, pb = params.p0_angle, params.p0_bias
    ia, ib = np.asarray(st.p0_angle_index), np.asarray(st.p0_bias_index)
    var = jnp.where(jnp.asarray(ia >= 0), pa[np.maximum(ia, 0)] ** 2, 0.0) + jnp.where(
        jnp.asarray(ib >= 0), pb[np.maximum(ib, 0)] ** 2, 0.0)
    return jnp.diag(var)
