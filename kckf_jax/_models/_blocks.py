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
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._params import Params
from ._robot import Robot


@dataclass(frozen=True)
class PaperMatrices:
    """The paper's model for one time step ``ts`` (NumPy float64)."""

    A: np.ndarray  # (N, N)  Eq. 11
    B: np.ndarray  # (N, 3(n+1))  Eq. 12 (columns for every gyro channel)
    Q: np.ndarray  # (N, N)  Eq. 13 (+ random walks)
    C: np.ndarray  # (M, N)  Eq. 8
    D: np.ndarray  # (P, N)  Eq. 17
    R: np.ndarray  # (M, M)  Eq. 20 (Hall block; the constraint rows have zero noise)


class ProcessNoise(NamedTuple):
    """Per angle coordinate, the discrete process noise of its ``(angle, bias)`` pair: the
    angle's variance ``alpha``, the covariance ``beta`` and the bias's variance ``gamma`` (any
    leading axes; laid out by block where a step takes them)."""

    alpha: Array
    beta: Array
    gamma: Array


def q_blocks(q, angle_rw, bias_rw, ts) -> ProcessNoise:
    """Per-coordinate ``(angle var, cross cov, bias var)`` of the discrete process noise.

    Eq. 13 scaled by ``q`` (``[[ts^4/4, ts^3/2], [ts^3/2, ts^2]]``), plus an angle random walk
    ``angle_rw^2 ts`` and a bias random walk ``bias_rw^2 ts`` (zero in the paper).
    """
    alpha = q * ts**4 / 4 + angle_rw**2 * ts
    beta = q * ts**3 / 2
    gamma = q * ts**2 + bias_rw**2 * ts
    return ProcessNoise(alpha, beta, gamma)


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


@dataclass(frozen=True, eq=False)
class Structure:
    """The filter's constant matrices, per axis block (NumPy float64).

    With the paper's diagonal noise (``Q``, ``R`` and ``P0`` all per coordinate), the model
    splits exactly into independent blocks, one per torso axis ``a``: the joints rotating about
    ``a`` (``m_a`` of them), the torso angle ``phi_a`` and their biases. No matrix couples two
    blocks, so each block is filtered on its own and the blocks run side by side (``vmap``).
    Blocks are padded to ``m = max_a m_a`` joints; a padding joint has zero rate, noise and
    covariance and no sensor, so it stays exactly zero.

    Block coordinates (``xb``, the paper's order within the block): ``[theta_1..theta_m, phi,
    b_1..b_m, b_phi]``. The filter runs in ``y = Mb xb = [z, e]``:

    * KF: ``y = z = xb`` (``n_e = 0``);
    * KCKF: ``z = [theta_1..theta_m, b_1..b_m, b_phi]``, ``e = sum theta - phi`` (Eq. 17), the
      perfect measurement ``e = 0`` (``n_e = 1``); ``phi = sum theta`` after every step.

    With time step ``ts`` and block rates ``r`` (``m + 1``: joint rates, then the torso rate):

    * predicted mean ``y = (F0 + ts F1) z + ts G1 r``;
    * predicted covariance ``F P F^T + Ma diag(alpha) Ma^T + Ma diag(beta) Mb^T +
      Mb diag(beta) Ma^T + Mb diag(gamma) Mb^T`` (``alpha, beta, gamma`` from ``q_blocks``);
    * the Hall pair of block joint ``i`` measures ``z[i]``;
    * ``xb = T z``.

    Gather maps (``-1`` marks padding): ``joint_index[p, i]`` is the joint axis (``0..J-1``)
    in slot ``i`` of block ``p``; ``angle_index[p, i]`` the angle coordinate (``0..K-1``) of
    block coordinate ``i`` (``i = m`` is the torso); ``block_of[k]``, ``slot_of[k]`` the way
    back for every angle coordinate ``k``.
    """

    constrained: bool
    m: int
    n_z: int
    n_e: int
    F0: np.ndarray
    F1: np.ndarray
    G1: np.ndarray
    Ma: np.ndarray
    Mb: np.ndarray
    T: np.ndarray
    joint_index: np.ndarray  # (P, m)
    angle_index: np.ndarray  # (P, m + 1)
    block_of: np.ndarray  # (K,)
    slot_of: np.ndarray  # (K,)
    z_p0_angle: np.ndarray  # (n_z,) block angle coordinate whose p0_angle sets z's prior, or -1
    z_p0_bias: np.ndarray  # (n_z,) block angle coordinate whose p0_bias sets z's prior, or -1

    @functools.cached_property
    def Qa(self) -> np.ndarray:
        """``Qa[k] = Ma[:, k] Ma[:, k]^T``: ``Qy = sum_k alpha_k Qa[k] + beta_k Qab[k] + gamma_k
        Qb[k]`` (precomputed outer products, (m + 1, Ny, Ny))."""
        return np.einsum("ik,jk->kij", self.Ma, self.Ma)

    @functools.cached_property
    def Qab(self) -> np.ndarray:
        return np.einsum("ik,jk->kij", self.Ma, self.Mb) + np.einsum("ik,jk->kij", self.Mb,
                                                                      self.Ma)

    @functools.cached_property
    def Qb(self) -> np.ndarray:
        return np.einsum("ik,jk->kij", self.Mb, self.Mb)


@functools.lru_cache(maxsize=64)
def block_structure(robot: Robot, constrained: bool) -> Structure:
    """The constant block matrices of the paper's linear filter for ``robot``: the KCKF's
    (``constrained``: the forward-kinematics constraint) or the standard KF's
    (``_classes.structure`` by method)."""
    J, P = robot.n_joint_axes, robot.n_torso_axes
    members = [[j for j, (_, a) in enumerate(robot.joint_axes) if a == ax]
               for ax in robot.torso_axes]
    m = max(len(x) for x in members)
    nb = 2 * m + 2  # block state size in the paper's coordinates
    A1 = np.zeros((nb, nb))
    A1[np.arange(m + 1), m + 1 + np.arange(m + 1)] = -1.0  # Eqs. 9-11: -ts b
    Bu = np.zeros((nb, m + 1))
    Bu[np.arange(m + 1), np.arange(m + 1)] = 1.0  # Eq. 12: + ts rate
    if not constrained:
        Mx = np.eye(nb)
        n_z, n_e = nb, 0
        z_p0_angle = np.r_[np.arange(m + 1), -np.ones(m + 1, int)]
        z_p0_bias = np.r_[-np.ones(m + 1, int), np.arange(m + 1)]
    else:
        Mx = np.zeros((nb, nb))
        Mx[np.arange(m), np.arange(m)] = 1.0  # theta
        Mx[m + np.arange(m + 1), m + 1 + np.arange(m + 1)] = 1.0  # b, b_phi
        Mx[2 * m + 1, :m] = 1.0  # e = sum theta - phi (Eq. 17)
        Mx[2 * m + 1, m] = -1.0
        n_z, n_e = nb - 1, 1
        z_p0_angle = np.r_[np.arange(m), -np.ones(m + 1, int)]
        z_p0_bias = np.r_[-np.ones(m, int), np.arange(m + 1)]
    Minv = np.linalg.inv(Mx)
    # Mx is a permutation plus one integer row; its inverse is exact in float64.
    assert np.allclose(Minv @ Mx, np.eye(nb)) and np.all(Minv == np.round(Minv))
    joint_index = -np.ones((P, m), int)
    angle_index = -np.ones((P, m + 1), int)
    block_of = np.zeros(J + P, int)
    slot_of = np.zeros(J + P, int)
    for p, js in enumerate(members):
        joint_index[p, : len(js)] = js
        angle_index[p, : len(js)] = js
        angle_index[p, m] = J + p
        block_of[js], slot_of[js] = p, np.arange(len(js))
        block_of[J + p], slot_of[J + p] = p, m
    return Structure(
        constrained=constrained, m=m, n_z=n_z, n_e=n_e,
        F0=(Mx @ Minv)[:, :n_z], F1=(Mx @ A1 @ Minv)[:, :n_z], G1=Mx @ Bu,
        Ma=Mx[:, : m + 1], Mb=Mx[:, m + 1:], T=Minv[:, :n_z],
        joint_index=joint_index, angle_index=angle_index, block_of=block_of, slot_of=slot_of,
        z_p0_angle=z_p0_angle, z_p0_bias=z_p0_bias,
    )


def static_take(x: Array, idx, axis: int = 0, in_loop: bool = True) -> Array:
    """``x`` indexed along ``axis`` by a constant index array ``idx`` (any shape): the result
    has ``idx``'s shape in place of that axis. The one place that decides how constant indices
    are taken: a gather, whose derivative inside a loop (``in_loop``, a step inside a
    ``lax.scan``) is a select against a constant mask and a sum instead of the gather's
    transpose, a scatter: XLA's CPU compiler (jax 0.12) keeps a gather with constant indices,
    and a loop holding its scatter is not compiled as one kernel (``_cpu_loops``: the
    sequential path's gradient ran 1.5x slower). The forward stays a gather: the mask there
    cost the vmapped sequential step of 64 trials 1.31x (``benchmarks/cpu_loops.py``), slices
    and a concatenation 10-15 %. Outside loops (``in_loop=False``: every row at once, the
    steady, parallel and lanes layouts) the gather's own transpose is kept.
    """
    idx = np.asarray(idx, dtype=np.int64)
    if not in_loop or not jnp.issubdtype(x.dtype, jnp.inexact):
        return _gather(x, idx, axis % x.ndim)
    return _loop_take(x, _Index(idx), axis % x.ndim)


def _gather(x: Array, idx: np.ndarray, axis: int) -> Array:
    return x[(slice(None),) * axis + (idx,)]


class _Index:
    """A constant index array as a static argument (hashed by its contents)."""

    def __init__(self, idx: np.ndarray):
        self.idx = idx
        self._key = (idx.shape, idx.tobytes())

    def __hash__(self) -> int:
        return hash(self._key)

    def __eq__(self, other) -> bool:
        return isinstance(other, _Index) and self._key == other._key


@functools.partial(jax.custom_jvp, nondiff_argnums=(1, 2))
def _loop_take(x: Array, index: _Index, axis: int) -> Array:
    return _gather(x, index.idx, axis)


@_loop_take.defjvp
def _loop_take_jvp(index: _Index, axis: int, primals, tangents):
    (x,), (dx,) = primals, tangents
    return _loop_take(x, index, axis), _masked_take(dx, index.idx, axis)


def _masked_take(x: Array, idx: np.ndarray, axis: int) -> Array:
    """``static_take`` as a select against a constant mask and a sum (a NaN elsewhere in
    ``x`` stays out): linear in ``x``, and its transpose a broadcast and a select."""
    n = x.shape[axis]
    mask = idx.reshape(-1)[:, None] == np.arange(n)[None, :]  # (K, n), constant
    xm = jnp.moveaxis(x, axis, -1)[..., None, :]  # (..., 1, n)
    out = jnp.sum(jnp.where(mask, xm, jnp.zeros((), x.dtype)), axis=-1)
    out = out.reshape(out.shape[:-1] + idx.shape)
    return jnp.moveaxis(out.reshape(x.shape[:axis] + x.shape[axis + 1:] + idx.shape),
                        tuple(range(x.ndim - 1, x.ndim - 1 + idx.ndim)),
                        tuple(range(axis, axis + idx.ndim)))


def block_gather(st: Structure, values: Float[Array, " K"], in_loop: bool = True
                 ) -> Float[Array, "P m1"]:
    """Per-angle-coordinate values (K,) laid out by block (P, m + 1); padding gets 0.
    ``in_loop``: as ``static_take``."""
    idx = st.angle_index
    ext = jnp.concatenate([values, jnp.zeros(1, values.dtype)])
    at = np.where(idx >= 0, idx, values.shape[0])
    return static_take(ext, at, in_loop=in_loop)


def predicted_moments(
    st: Structure,
    z: Float[Array, " Nz"],
    P: Float[Array, "Nz Nz"],
    rates: Float[Array, " m1"],
    noise: tuple[Float[Array, " m1"], Float[Array, " m1"], Float[Array, " m1"]],
    ts: Float[Array, ""],
) -> tuple[Float[Array, " Ny"], Float[Array, "Ny Ny"]]:
    """Mean and covariance of one block's ``y = [z, e]`` one step ahead (Eqs. 3, 9-13)."""
    # The matrices are a few rows wide: broadcast-multiply-sum lets XLA fuse each product into
    # one loop instead of calling a matmul kernel per product (the step is overhead-bound).
    dtype = z.dtype
    F = jnp.asarray(st.F0, dtype) + ts * jnp.asarray(st.F1, dtype)
    y = jnp.sum(F * z, axis=1) + ts * jnp.sum(jnp.asarray(st.G1, dtype) * rates, axis=1)
    alpha, beta, gamma = noise
    Qy = (jnp.sum(jnp.asarray(st.Qa, dtype) * alpha[:, None, None], axis=0)
          + jnp.sum(jnp.asarray(st.Qab, dtype) * beta[:, None, None], axis=0)
          + jnp.sum(jnp.asarray(st.Qb, dtype) * gamma[:, None, None], axis=0))
    FP = jnp.sum(F[:, :, None] * P[None, :, :], axis=1)
    return y, jnp.sum(FP[:, None, :] * F[None, :, :], axis=2) + Qy


def initial_covariance(st: Structure, params: Params) -> Float[Array, "P Nz Nz"]:
    """Diagonal prior per block from ``params.p0_angle`` and ``params.p0_bias``; padding 0."""
    pa = block_gather(st, params.p0_angle**2)  # (P, m + 1)
    pb = block_gather(st, params.p0_bias**2)
    ia, ib = st.z_p0_angle, st.z_p0_bias
    var = (jnp.where(ia >= 0, static_take(pa, np.maximum(ia, 0), axis=1), 0.0)
           + jnp.where(ib >= 0, static_take(pb, np.maximum(ib, 0), axis=1), 0.0))
    return jax.vmap(jnp.diag)(var)


def full_state(st: Structure, z: ArrayLike, P: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """The paper's state ``x = [theta, phi, b, b_phi]`` (N,) and its covariance (N, N) from a
    block state ``z`` (P, Nz), ``P`` (P, Nz, Nz) (NumPy; for tests and inspection)."""
    z, P = np.asarray(z, np.float64), np.asarray(P, np.float64)
    K = st.block_of.shape[0]
    xb = np.einsum("ij,pj->pi", st.T, z)  # (P, 2m + 2)
    Pb = np.einsum("ij,pjk,lk->pil", st.T, P, st.T)
    # full index of every block coordinate: angle coordinates then biases (+K).
    idx = np.concatenate([st.angle_index, np.where(st.angle_index >= 0, st.angle_index + K,
                                                   -1)], axis=1)
    x = np.zeros(2 * K)
    Pf = np.zeros((2 * K, 2 * K))
    for p in range(idx.shape[0]):
        ok = idx[p] >= 0
        x[idx[p][ok]] = xb[p][ok]
        Pf[np.ix_(idx[p][ok], idx[p][ok])] = Pb[p][np.ix_(ok, ok)]
    return x, Pf
