"""The RTS smoother on lanes: the forward pass of ``lane_moments_scan`` with its predicted
moments, then the backward pass (``_rts.rts_block``) written out entry by entry with the trial
axis last, as ``_lanes.py`` writes the filter step.

The arithmetic is ``rts_block``'s, in the same order: the rows of the next row's ``y = [z, e]``
the update conditioned on (every z coordinate with variance, the constraint where there was a
time step), ``G = P F' S^-1`` through the same written-out Cholesky, the smoothed mean and the
covariance ``P + G (P^y_s - S) G'`` stored as its upper triangle, a skipped next row passing
its smoothed state through. Equal to the vmapped smoother to rounding (tested).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._models._blocks import Structure
from .._models._kalman import cholesky_solve
from .._models._kernel import Estimate, FilterState, SensorSeries
from .._models._params import Params
from .._readings._prepare import prepare
from ._lane_step import _Consts, _tri
from ._lanes import (
    LaneMoments,
    LaneMomentsInnovations,
    LaneState,
    lane_estimates,
    lane_inputs,
    lane_moments_scan,
    rows_innovations,
)


def lane_rts_step(st: Structure, c: _Consts, z_f, P_f, y_pred, S, ts, skipped, z_s, P_s):
    """One backward step on lanes: the smoothed ``(z, P)`` of a row (``Nz, Nb, B`` and the
    upper triangle ``n_tri(Nz), Nb, B``) from its filtered ones, the next row's predicted
    moments (``y_pred`` ``Ny, Nb, B``, ``S`` upper triangle), time step ``ts`` (``Nb, B``),
    whether it was skipped (``Nb, B``) and its smoothed ``(z_s, P_s)``."""
    nz, ny = st.n_z, st.n_z + st.n_e
    iz, iy = c.index[nz], c.index[ny]
    zero = jnp.zeros_like(ts)
    use = [S[iy[i, i]] > 0 for i in range(nz)] + [ts > 0] * st.n_e
    Sm = jnp.stack([jnp.stack([jnp.where(use[i] & use[j], S[iy[i, j]], 0.0)
                               + (jnp.where(use[i], 0.0, 1.0) if i == j else 0.0)
                               for j in range(ny)]) for i in range(ny)])
    # C = P F' with F = F0 + ts F1 (Ny x Nz), the unused columns zero: C' is (Ny, Nz).
    F0, F1 = c.F0, c.F1
    Ct = []
    for i in range(ny):
        row = []
        for a in range(nz):
            acc = zero
            for b in np.flatnonzero((F0[i] != 0) | (F1[i] != 0)):
                f = float(F0[i, b]) + ts * float(F1[i, b]) if F1[i, b] else float(F0[i, b])
                acc = acc + P_f[iz[a, b]] * f
            row.append(jnp.where(use[i], acc, 0.0))
        Ct.append(jnp.stack(row))
    Gt = cholesky_solve(Sm, jnp.stack(Ct))  # (Ny, Nz): G'
    r = [jnp.where(use[i], (z_s[i] if i < nz else zero) - y_pred[i], 0.0) for i in range(ny)]
    z = jnp.stack([z_f[a] + sum((Gt[i, a] * r[i] for i in range(ny)), zero)
                   for a in range(nz)])

    def d(i, j):  # (P^y_s - S) on the used rows
        ps = P_s[iz[i, j]] if i < nz and j < nz else zero
        return jnp.where(use[i] & use[j], ps - S[iy[i, j]], 0.0)

    D = [[d(i, j) for j in range(ny)] for i in range(ny)]
    GD = [[sum((Gt[i, a] * D[i][j] for i in range(ny)), zero) for j in range(ny)]
          for a in range(nz)]
    P = jnp.stack([P_f[iz[a, b]] + sum((GD[a][j] * Gt[j, b] for j in range(ny)), zero)
                   for a, b in _tri(nz)])
    return jnp.where(skipped, z_s, z), jnp.where(skipped, P_s, P)


def lane_rts(st: Structure, moments: LaneMoments | LaneMomentsInnovations,
             ts_rows: Float[Array, "T B"]):
    """The backward pass over ``lane_moments_scan``'s rows (rows first, trials last): the
    smoothed ``(z, P)`` of every row (the last row's are its filtered ones)."""
    z_rows, P_rows, skipped, y_rows, S_rows = (moments.z, moments.P, moments.skipped,
                                               moments.y, moments.S)
    c = _Consts(st)
    nb = z_rows.shape[2]

    def body(carry, row):
        z_s, P_s = carry
        z_f, P_f, y, S, ts, skip = row
        tsb = jnp.broadcast_to(ts, (nb,) + ts.shape)
        skb = jnp.broadcast_to(skip, (nb,) + skip.shape)
        z, P = lane_rts_step(st, c, z_f, P_f, y, S, tsb, skb, z_s, P_s)
        return (z, P), (z, P)

    rows = (z_rows[:-1], P_rows[:-1], y_rows[1:], S_rows[1:], ts_rows[1:], skipped[1:])
    _, (z, P) = jax.lax.scan(jax.checkpoint(body), (z_rows[-1], P_rows[-1]), rows,
                             reverse=True)
    return jnp.concatenate([z, z_rows[-1:]]), jnp.concatenate([P, P_rows[-1:]])


def lane_smooth(params: Params, st: Structure, series: SensorSeries, state: FilterState,
                innovations: bool = False) -> Estimate:
    """The smoothed angles, their standard deviations and biases of a batch of trials (leading
    axis ``B`` on ``series`` and ``state``), and the skipped rows; ``innovations``: with the
    forward pass's fused Hall innovations (``Estimate.innovations``, ``B T Nb m``)."""
    dtype = state.z.dtype
    series = prepare(params, series, dtype=dtype)  # a linear model: the paper's gyro pairs
    rows = lane_moments_scan(params, st, LaneState(state.z, state.P, state.gyro_hold),
                             lane_inputs(params, st, series.dt, series.gyro,
                                         series.hall_v), innovations).rows
    z, P = lane_rts(st, rows, jnp.moveaxis(series.dt, 0, 1))
    angles, std, bias = lane_estimates(st, z, P)
    return Estimate(angles, std, bias, jnp.moveaxis(rows.skipped, 0, 1),
                    innovations=rows_innovations(rows))
