"""The fixed-interval (Rauch-Tung-Striebel) smoother of the Kalman methods, over the filter's
own steps.

Offline, the best estimate of an angle uses the readings after it too. The forward pass is the
kernel's ``step`` (``kalman_step_moments``: the same arithmetic, with the predicted moments it
computed on the way); the backward pass is the RTS recursion in the filter's block
coordinates, block by block:

    G_k = P_k|k F' S^-1,   z_k|T = z_k|k + G_k (y_k+1|T - y_k+1|k),
    P_k|T = P_k|k + G_k (P^y_k+1|T - S) G_k'

with ``y = [z, e]`` the predicted state of the next row, ``F = F0 + dt F1`` its map from ``z``
and ``S`` its covariance. For the KCKF the constraint is a perfect measurement at every row
with a time step, so the next row's smoothed ``y`` is ``[z_k+1|T, 0]`` with no variance in
``e``: the smoothed estimates satisfy the constraint too (``phi = sum theta`` by construction
of the block coordinates). A row with no time step (the first, padding) has no constraint
and no process noise, and a coordinate with no variance (a padding joint) none either; their
rows of ``S`` are left out of the solve. A skipped row (its update was not finite) keeps the
state, so its smoothed state is the next one's. ``S`` is factored by a small Cholesky
written out (no LAPACK call, see the deadlock hazard).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._kalman import symmetrise
from ._kernel import (
    Estimate,
    FilterState,
    SensorSeries,
    StepMoments,
    block_estimate,
    check_method,
    init_state,
    kalman_step_moments,
)
from ._model import FILTER_METHODS, structure
from ._params import Params


def filter_moments(params: Params, series: SensorSeries, method: str,
                   state: FilterState | None = None):
    """The forward pass: ``lax.scan`` of ``kalman_step_moments`` over one trial. Returns the
    final state, the filtered block states and covariances per row (``T Nb Nz``, ``T Nb Nz
    Nz``) and the ``StepMoments`` per row."""
    state = init_state(params, method) if state is None else state
    dtype = state.z.dtype
    series = jax.tree_util.tree_map(lambda x: jnp.asarray(x).astype(dtype), series)

    @jax.checkpoint
    def body(carry, row):
        new, _, mom = kalman_step_moments(params, carry, row, method)
        return new, (new.z, new.P, mom)

    final, (zs, Ps, mom) = jax.lax.scan(body, state, series)
    return final, zs, Ps, mom


def _cholesky_solve(S: Float[Array, "n n"], B: Float[Array, "n k"]) -> Float[Array, "n k"]:
    """``S^-1 B`` for a small symmetric positive definite ``S``: its Cholesky factor and two
    triangular solves, written out entry by entry."""
    n = S.shape[0]
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        d = S[j, j] - sum((L[j][k] ** 2 for k in range(j)), jnp.zeros((), S.dtype))
        L[j][j] = jnp.sqrt(jnp.maximum(d, jnp.finfo(S.dtype).tiny))
        for i in range(j + 1, n):
            L[i][j] = (S[i, j] - sum((L[i][k] * L[j][k] for k in range(j)),
                                     jnp.zeros((), S.dtype))) / L[j][j]
    zero = jnp.zeros_like(B[0])
    y = []
    for i in range(n):  # L y = B
        y.append((B[i] - sum((L[i][k] * y[k] for k in range(i)), zero)) / L[i][i])
    x = [None] * n
    for i in reversed(range(n)):  # L' x = y
        x[i] = (y[i] - sum((L[k][i] * x[k] for k in range(i + 1, n)), zero)) / L[i][i]
    return jnp.stack(x)


def _rts_block(st, z_f, P_f, y_pred, S, dt, skipped, z_s, P_s):
    """One block of one backward step: the smoothed ``(z, P)`` of row ``k`` from the filtered
    one (``z_f, P_f``), the next row's predicted moments (``y_pred, S``, ``dt``, ``skipped``)
    and its smoothed one (``z_s, P_s``)."""
    nz, ny = st.n_z, st.n_z + st.n_e
    dtype = z_f.dtype
    F = jnp.asarray(st.F0, dtype) + dt * jnp.asarray(st.F1, dtype)  # (Ny, Nz)
    # Rows of y the next row's update conditioned on: every z coordinate with variance, and
    # the constraint where there was a time step.
    use = jnp.concatenate([jnp.diag(S)[:nz] > 0, jnp.full(st.n_e, dt > 0)])
    S = jnp.where(use[:, None] & use[None, :], S, 0.0) + jnp.diag(jnp.where(use, 0.0, 1.0))
    C = jnp.where(use[None, :], P_f @ F.T, 0.0)  # (Nz, Ny)
    G = _cholesky_solve(S, C.T).T
    y_s = jnp.concatenate([z_s, jnp.zeros(st.n_e, dtype)])
    Py_s = jnp.zeros((ny, ny), dtype).at[:nz, :nz].set(P_s)
    r = jnp.where(use, y_s - y_pred, 0.0)
    z = z_f + G @ r
    D = jnp.where(use[:, None] & use[None, :], Py_s - S, 0.0)
    P = symmetrise(P_f + G @ D @ G.T)
    return jnp.where(skipped, z_s, z), jnp.where(skipped, P_s, P)


def rts(params: Params, method: str, zs, Ps, mom: StepMoments):
    """The backward pass over the forward pass's rows: the smoothed block states and
    covariances per row (the last row's are its filtered ones)."""
    st = structure(params.robot, method)

    def body(carry, row):
        z_s, P_s = carry
        z_f, P_f, y_next, S_next, dt_next, skip_next = row
        z, P = jax.vmap(lambda *a: _rts_block(st, *a))(
            z_f, P_f, y_next, S_next, jnp.broadcast_to(dt_next, z_f.shape[:1]),
            jnp.broadcast_to(skip_next, z_f.shape[:1]), z_s, P_s)
        return (z, P), (z, P)

    rows = (zs[:-1], Ps[:-1], mom.y[1:], mom.S[1:], mom.dt[1:], mom.skipped[1:])
    _, (z_rows, P_rows) = jax.lax.scan(jax.checkpoint(body), (zs[-1], Ps[-1]), rows,
                                       reverse=True)
    return (jnp.concatenate([z_rows, zs[-1:]]), jnp.concatenate([P_rows, Ps[-1:]]))


def _smoothed(params: Params, series: SensorSeries, method: str, state: FilterState | None):
    _, zs, Ps, mom = filter_moments(params, series, method, state)
    z, P = rts(params, method, zs, Ps, mom)
    st = structure(params.robot, method)
    est = jax.vmap(lambda a, b: block_estimate(st, a, b))(z, P)
    return dataclasses.replace(est, skipped=mom.skipped)


def smooth(params: Params, series: SensorSeries, method: str = "kckf",
           state: FilterState | None = None) -> Estimate:
    """The fixed-interval (RTS) smoothed estimates of one recording (``run_filter``'s
    arguments; ``method`` ``"kckf"`` or ``"kf"``): each row's angles, their standard
    deviations and biases given every reading of the recording, before and after it.

    Example:
        >>> robot = Robot.from_spec("x")
        >>> series = SensorSeries(jnp.full(5, 0.01), jnp.zeros((5, 6)), jnp.ones((5, 2)))
        >>> smooth(Params.paper_defaults(robot), series).angles.shape
        (5, 2)
    """
    _check(method)
    est = _smooth_one(params, series, method, state)
    return dataclasses.replace(est, path="smoothed", names=params.robot.angle_names)


def smooth_batch(params: Params, series: SensorSeries, method: str = "kckf") -> Estimate:
    """``smooth`` over a batch of padded trials (leading axis ``B``; ``pad_series``)."""
    _check(method)
    est = _smooth_many(params, series, method)
    return dataclasses.replace(est, path="smoothed", names=params.robot.angle_names)


def _check(method: str) -> None:
    check_method(method)
    if method not in FILTER_METHODS:
        raise ValueError(f"smoothing needs a Kalman filter (kckf or kf), got {method!r}")


@eqx.filter_jit
def _smooth_one(params, series, method, state):
    return _smoothed(params, series, method, state)


@eqx.filter_jit
def _smooth_many(params, series, method):
    return jax.vmap(lambda s: _smoothed(params, s, method, None))(series)


