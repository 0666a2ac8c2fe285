"""The filter step as an affine map of the mean, for the paths that use it.

The Kalman filter's covariance does not depend on the measured values, only on the time steps,
which readings are present and their noise. For a fixed covariance, time step and masks the
new block estimate is *linear* in (previous estimate, rates, fused Hall readings), so each row
is the affine map ``z_k = A_k z_{k-1} + Gr_k r_k + Gh_k h_k``. ``step_maps`` gets ``A_k, Gr_k,
Gh_k`` from ``jax.linearize`` of the kernel's own ``block_update`` (no second implementation of
the filter), and ``covariance_phase`` strings those rows together over a recording.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._models._blocks import Structure
from .._models._classes import structure
from .._models._custom_types import BlockCov, BlockMap, HallMap, RateMap
from .._models._kernel import (
    BlockInputs,
    FilterInput,
    SensorSeries,
    block_estimate,
    block_hall,
    block_inputs,
    block_step,
    block_update,
    fused_pairs,
    hall_measurements,
)
from .._models._params import Params


class StepMaps(NamedTuple):
    """One row as an affine map of the mean, ``z_new = A z + Gr rates + Gh hb``, and the
    covariance after it (``Nb x ...``; a leading row axis ``R`` where every row's are kept).

    Attributes:
        P: the covariance after the row.
        A: the map of the block state.
        Gr: the map of the block rates.
        Gh: the map of the fused Hall readings.
        ok: whether the row was computed (``covariance_phase``; a skipped row's maps are the
            identity and its covariance the one before), or ``None`` where not judged.
    """

    P: BlockCov
    A: BlockMap
    Gr: RateMap
    Gh: HallMap
    ok: Bool[Array, "*R"] | None = None


def step_maps(params: Params, st: Structure, P: Float[Array, "Nb Nz Nz"], row: BlockInputs
              ) -> StepMaps:
    """One covariance step for every block, and the affine maps of the mean (``Nb x Nz x
    ...``)."""
    dt, noise, rb, vb = row.dt, row.noise, row.rb, row.vb
    nz, m1, m = st.n_z, st.m + 1, st.m

    def one_block(P, alpha, beta, gamma, rb, vb):
        def f(z, r, h):
            return block_update(st, z, P, r, alpha, beta, gamma, h, rb, vb, dt)

        zeros = (jnp.zeros(nz, P.dtype), jnp.zeros(m1, P.dtype), jnp.zeros(m, P.dtype))
        (_, P_new), lin = jax.linearize(f, *zeros)
        # Every column at once: the linear map applied to the unit vectors as one batch (one
        # copy of its operations instead of one per column: the covariance phase is a scan,
        # and on a CPU its cost is the number of operations per row).
        eye = jnp.eye(nz + m1 + m, dtype=P.dtype)
        cols = jax.vmap(lambda a, b, c: lin(a, b, c)[0])(
            eye[:, :nz], eye[:, nz:nz + m1], eye[:, nz + m1:])  # (nz + m1 + m, nz)
        return P_new, cols[:nz].T, cols[nz:nz + m1].T, cols[nz + m1:].T

    return StepMaps(*jax.vmap(one_block)(P, *noise, rb, vb))


class InnovationMaps(NamedTuple):
    """The fused Hall innovations of a row read back from its result (``innovation_maps``):
    ``nu = W (hb - z_new[:m])`` per block, and their variances ``s`` (``Nb x ...``; a leading
    row axis ``R`` where every row's are kept).

    Attributes:
        W: the map of the row's residuals ``hb - z_new[:m]`` (``Nb m m``).
        s: each joint's innovation variance (``Nb m``), as the kernel's ``block_step`` gives.
    """

    W: Float[Array, "*R Nb m m"]
    s: Float[Array, "*R Nb m"]


def innovation_maps(st: Structure, P: Float[Array, "R Nb Nz Nz"], rows: BlockInputs
                    ) -> InnovationMaps:
    """How each row's fused Hall innovations follow from its result, for its entering
    covariance (``P``, a leading row axis as ``rows``'): the paths that compute the mean as
    affine maps (steady, parallel) never form the prediction, but they have the new state, and
    that is enough.

    The kernel updates the joints one by one (``block_step``): ``nu_i = hb_i - z^(i)_i``, then
    ``z^(i+1) = z^(i) + K_i nu_i``. So the residual after the row, ``hb - z_new[:m]``, is
    ``U nu`` with ``U`` upper triangular (``U_ij = delta_ij - K_j[i]`` for ``j >= i``; its
    diagonal ``r_i / s_i > 0``), and ``nu = W (hb - z_new[:m])`` with ``W = U^-1``. Both
    sides are linear in the readings, so ``W = Nh (I - C Gh)^-1`` from the Jacobians in ``hb``
    of ``nu`` (``Nh``) and of ``z_new[:m]`` (``C Gh``), taken of the kernel's own step (no
    second implementation of it)."""
    nz, m1, m = st.n_z, st.m + 1, st.m

    def one_block(P, alpha, beta, gamma, rb, vb, dt):
        z0, r0 = jnp.zeros(nz, P.dtype), jnp.zeros(m1, P.dtype)

        def f(h):
            z, _, _, _, nu, s = block_step(st, z0, P, r0, alpha, beta, gamma, h, rb, vb, dt)
            return (z[:m], nu), s

        (CGh, Nh), s = jax.jacfwd(f, has_aux=True)(jnp.zeros(m, P.dtype))
        # W (I - C Gh) = Nh, solved as its transpose.
        W = jnp.linalg.solve((jnp.eye(m, dtype=P.dtype) - CGh).T, Nh.T).T
        return W, s

    def one_row(P, row):
        return jax.vmap(lambda *a: one_block(*a, row.dt))(P, *row.noise, row.rb, row.vb)

    return InnovationMaps(*jax.vmap(one_row)(P, rows))


def read_innovations(params: Params, st: Structure, maps: InnovationMaps,
                     hall_v: Float[Array, "*B T M"], joints: Float[Array, "*B T Nb m"],
                     ok: Bool[Array, " T"]
                     ) -> tuple[Float[Array, "*B T Nb m"], Float[Array, "*B T Nb m"],
                                Bool[Array, "*B T Nb m"]]:
    """Every row's fused Hall innovations ``(nu, s, valid)`` from its new joint angles
    (``joints``: ``z_new[:m]`` per block, 0 at a padding joint) and its Hall voltages, with
    ``maps`` per row (a row axis ``T``: ``innovation_maps``); a row not computed (``ok``
    false: ``covariance_phase``'s skipped rows) uses none of its readings."""
    hb, _, vb = jax.vmap(lambda v: block_hall(params, st, v, in_loop=False))(
        hall_v.reshape(-1, hall_v.shape[-1]))
    hb, vb = hb.reshape(joints.shape), vb.reshape(joints.shape)
    nu = jnp.einsum("...pij,...pj->...pi", maps.W, hb - joints)
    return nu, jnp.broadcast_to(maps.s, nu.shape), vb & ok[:, None, None]


def covariance_phase(params: Params, st: Structure, P0: Float[Array, "Nb Nz Nz"],
                     rows: BlockInputs) -> tuple[Float[Array, "Nb Nz Nz"], StepMaps]:
    """``lax.scan`` of the covariance over ``rows`` (a leading row axis ``R``): the last
    covariance, and per row the covariance after it, its maps ``A, Gr, Gh`` and whether the
    row was computed (``ok``). A row whose covariance or maps are not finite is skipped as the
    kernel's ``step`` skips it: the covariance is kept and the maps are the identity (``A =
    I``, ``Gr = Gh = 0``), so the mean is kept too."""
    # Rematerialised under reverse mode: storing every intermediate of every row as a
    # residual costs more here than computing the row again (the gradient through this
    # phase, 2,048 rows in float32: bench 67 -> 35 ms, 3D 192 -> 151 ms).
    @jax.checkpoint
    def body(P, row):
        P_new, A, Gr, Gh, _ = step_maps(params, st, P, row)
        ok = (jnp.isfinite(P_new).all() & jnp.isfinite(A).all() & jnp.isfinite(Gr).all()
              & jnp.isfinite(Gh).all())
        eye = jnp.broadcast_to(jnp.eye(st.n_z, dtype=P.dtype), A.shape)
        P_new = jnp.where(ok, P_new, P)
        A, Gr, Gh = jnp.where(ok, A, eye), jnp.where(ok, Gr, 0.0), jnp.where(ok, Gh, 0.0)
        return P_new, StepMaps(P_new, A, Gr, Gh, ok)

    return jax.lax.scan(body, P0, rows)


def held_gyro(gyro: Float[Array, "T G"], hold0: Float[Array, " G"]) -> Float[Array, "T G"]:
    """Each channel's last finite value at every row (forward fill, ``hold0`` before any)."""
    T = gyro.shape[0]
    ok = jnp.isfinite(gyro)
    idx = jax.lax.cummax(jnp.where(ok, jnp.arange(T)[:, None], -1), axis=0)
    filled = jnp.take_along_axis(gyro, jnp.maximum(idx, 0), axis=0)
    return jnp.where(idx >= 0, filled, hold0[None, :])


def last_finite(gyro: Float[Array, "T G"], hold0: Float[Array, " G"]) -> Float[Array, " G"]:
    """Each channel's last finite value over the rows (``hold0`` where there is none): the
    ``gyro_hold`` a filter carries out of them."""
    T = gyro.shape[0]
    idx = jnp.max(jnp.where(jnp.isfinite(gyro), jnp.arange(T)[:, None], -1), axis=0)
    last = gyro[jnp.maximum(idx, 0), jnp.arange(gyro.shape[1])]
    return jnp.where(idx >= 0, last, hold0)


def series_inputs(params: Params, st: Structure, series: SensorSeries,
                  hold0: Float[Array, " G"]) -> tuple[BlockInputs, Float[Array, "T G"]]:
    """Every row's block inputs at once (``block_inputs`` with a leading row axis), and the
    held gyro rates after every row."""
    held = held_gyro(series.gyro, hold0)
    prev_hold = jnp.concatenate([hold0[None], held[:-1]], axis=0)
    rows = jax.vmap(lambda g, row: block_inputs(params, st, g, row, in_loop=False))
    return rows(prev_hold, series), held


def reading_maps(params: Params, st: Structure, dtype
                 ) -> tuple[Float[Array, "Nb m1 Gu"], Float[Array, "Nb m M"]]:
    """The readings of a regular row as linear maps of the raw readings: block rates ``r = Jr
    g[used]`` (``robot.used_gyro_index``; constant) and fused Hall readings ``h = Jh angles``
    (the inverse-variance weights of ``fused_pairs`` for the constant Hall noise, every
    reading present). Returns ``(Jr, Jh)``."""
    robot = params.robot
    plus, minus = robot.rate_pairs
    col = {int(c): i for i, c in enumerate(robot.used_gyro_index)}
    Jr = np.zeros(st.angle_index.shape + (len(col),))
    for (p, i), k in np.ndenumerate(st.angle_index):
        if k >= 0:
            Jr[p, i, col[int(plus[k])]] += 1.0
            Jr[p, i, col[int(minus[k])]] -= 1.0
    M = robot.n_hall
    _, r, _ = hall_measurements(params, jnp.zeros(M, dtype))
    ji = st.joint_index

    def readings(angle):
        h, _, _ = fused_pairs(angle, r, jnp.ones(M, bool))
        return jnp.where(ji < 0, 0.0, h[np.maximum(ji, 0)])

    return jnp.asarray(Jr, dtype), jax.jacfwd(readings)(jnp.zeros(M, dtype))


def input_weights(Gr: Float[Array, "*R Nb Nz m1"], Gh: Float[Array, "*R Nb Nz m"],
                  Jr: Float[Array, "Nb m1 Gu"], Jh: Float[Array, "Nb m M"]
                  ) -> tuple[Float[Array, "*R Gu Nb Nz"], Float[Array, "*R M Nb Nz"]]:
    """The maps of the raw readings, ``Wg = Gr Jr`` (used gyro columns) and ``Wh = Gh Jh`` (Hall
    angles), laid out reading first: the rate differences and the fusion of each Hall pair
    folded into the map."""
    return (jnp.einsum("...pij,pjg->...gpi", Gr, Jr), jnp.einsum("...pij,pjm->...mpi", Gh, Jh))


def output_map(st: Structure) -> np.ndarray:
    """``(2K, Nb, Nz)``: the angles, then the biases, as sums over the block states."""
    to_x = np.asarray(st.T)
    K, m1 = len(st.block_of), st.m + 1
    out = np.zeros((2 * K, st.angle_index.shape[0], st.n_z))
    for k, (p, i) in enumerate(zip(st.block_of, st.slot_of)):
        out[k, p], out[K + k, p] = to_x[i], to_x[m1 + i]
    return out


def apply_blocks(A: Float[Array, "Nb Nz Nz"], z: Float[Array, "Nb Nz B"]
                 ) -> Float[Array, "Nb Nz B"]:
    """``A z`` per block for a batch of states (trials last), as broadcast products (a batched
    5 x 5 dot is slower on a CPU)."""
    return sum(A[:, :, j, None] * z[:, j, None, :] for j in range(A.shape[-1]))


class HostMap(NamedTuple):
    """One regular packet as an affine map for the streaming filter's host path
    (``converged_map``): ``z -> A z + g Wg + angle Wh``.

    Attributes:
        P: the covariance after the step.
        A: the block map (``Nb Nz Nz``).
        Wg: the map of the previous packet's used gyro columns (``Gu Nb Nz``).
        Wh: the map of this packet's Hall angles (``M Nb Nz``).
        std: the angles' standard deviations after the step (``K``).
    """

    P: BlockCov
    A: Float[Array, "Nb Nz Nz"]
    Wg: Float[Array, "Gu Nb Nz"]
    Wh: Float[Array, "M Nb Nz"]
    std: Float[Array, " K"]


def converged_map(params: Params, method: str, P: BlockCov, dt: Float[Array, ""]) -> HostMap:
    """The affine map of one regular packet (every reading present), for the streaming filter's
    host path: for the block covariance ``P`` before a step of ``dt``. When ``P`` has
    converged, ``HostMap.P = P`` and every later packet with the same ``dt`` and every reading
    is the same map.
    """
    st = structure(params.robot, method)
    dtype = P.dtype
    robot = params.robot
    inputs = FilterInput(dt.astype(dtype), jnp.zeros(3 * robot.n_links, dtype),
                         jnp.zeros(robot.n_hall, dtype))
    row = block_inputs(params, st, jnp.zeros(3 * robot.n_links, dtype), inputs,
                       in_loop=False)
    P_new, A, Gr, Gh, _ = step_maps(params, st, P, row)
    Wg, Wh = input_weights(Gr, Gh, *reading_maps(params, st, dtype))
    std = block_estimate(st, jnp.zeros(P.shape[:2], dtype), P_new, in_loop=False).angle_std
    return HostMap(P_new, A, Wg, Wh, std)


