"""The RTS smoother on lanes: the forward pass of ``lane_moments_scan`` with its predicted
moments, then the backward pass (``_rts.rts_block``) written out entry by entry with the trial
axis last, as ``_lanes.py`` writes the filter step.

The arithmetic is ``rts_block``'s, in the same order: the rows of the next row's ``y = [z, e]``
the update conditioned on (every z coordinate with variance, the constraint where there was a
time step), ``G = P F' S^-1`` through the same written-out Cholesky, the smoothed mean and the
covariance ``P + G (P^y_s - S) G'`` stored as its upper triangle, a skipped next row passing
its smoothed state through. Equal to the vmapped smoother to rounding (tested).

Its gradient (a fit of the smoothed estimates) is written by hand, in three pieces: the
forward pass takes the filter's reverse pass (``_lanes_adjoint``, with the predicted moments'
cotangents); the gains, which read only the forward pass, are formed for every row at once and
differentiated as a solve (``_gain_adjoint``); the smoothed mean's linear recursion is
transposed as a recursion of cotangents first row first (``_mean_pass``). The covariance's
recursion is its own scan, which a loss of the angles never runs. Equal to the sequential
smoother's automatic gradient to rounding, and to finite differences
(``tests/test_lanes_adjoint.py``).
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


def lane_rts_gain(st: Structure, c: _Consts, P_f, S, ts):
    """The smoother gains of rows (any trailing lane axes ``L``, every row at once: they read
    only the forward pass): ``G'`` (``Ny, Nz, *L``, the unused rows zero) and which rows of ``y``
    are used (``Ny, *L``), from each row's filtered covariance ``P_f`` (upper triangle,
    ``n_tri(Nz), *L``), the next row's predicted covariance ``S`` (``n_tri(Ny), *L``) and its
    time step ``ts``.

    ``G' = S^-1 C'`` with ``C' = F P`` is differentiated by hand (``_gain_adjoint``)."""
    use = jnp.stack(_used(st, c, S, ts))

    @jax.custom_vjp
    def gain(P_f, S, ts, use):
        return cholesky_solve(*_gain_system(st, c, P_f, S, ts, use))

    def fwd(P_f, S, ts, use):
        Gt = gain(P_f, S, ts, use)
        return Gt, (P_f, S, ts, use, Gt)

    def bwd(res, Gt_bar):
        return _gain_adjoint(st, c, *res, Gt_bar) + (None,)

    gain.defvjp(fwd, bwd)
    return gain(P_f, S, ts, use), use


def _used(st: Structure, c: _Consts, S, ts) -> list:
    """Which rows of ``y`` the next row's update conditioned on: every z coordinate with
    variance, and the constraint where there was a time step."""
    iy = c.index[st.n_z + st.n_e]
    return [S[iy[i, i]] > 0 for i in range(st.n_z)] + [ts > 0] * st.n_e


def _gain_system(st: Structure, c: _Consts, P_f, S, ts, use):
    """``(S, C')`` of the gain's solve, the unused rows of ``S`` replaced by the identity's and
    those of ``C' = F P`` (``F = F0 + ts F1``, ``Ny x Nz``) zero."""
    nz, ny = st.n_z, st.n_z + st.n_e
    iz, iy = c.index[nz], c.index[ny]
    zero = jnp.zeros_like(ts)
    Sm = jnp.stack([jnp.stack([jnp.where(use[i] & use[j], S[iy[i, j]], 0.0)
                               + (jnp.where(use[i], 0.0, 1.0) if i == j else 0.0)
                               for j in range(ny)]) for i in range(ny)])
    Ct = []
    for i in range(ny):
        row = []
        for a in range(nz):
            acc = zero
            for b in _f_cols(c, i):
                acc = acc + P_f[iz[a, b]] * _f(c, i, b, ts)
            row.append(jnp.where(use[i], acc, 0.0))
        Ct.append(jnp.stack(row))
    return Sm, jnp.stack(Ct)


def _f_cols(c: _Consts, i: int):
    """The columns of row ``i`` of ``F = F0 + ts F1`` that are not zero."""
    return [int(b) for b in np.flatnonzero((c.F0[i] != 0) | (c.F1[i] != 0))]


def _f(c: _Consts, i: int, b: int, ts):
    """Entry ``(i, b)`` of ``F = F0 + ts F1``."""
    return float(c.F0[i, b]) + ts * float(c.F1[i, b]) if c.F1[i, b] else float(c.F0[i, b])


def _gain_adjoint(st: Structure, c: _Consts, P_f, S, ts, use, Gt, Gt_bar):
    """The transpose of ``G' = S^-1 C'``: ``W = S^-1 G'_bar`` (one more solve), ``C'_bar = W``
    and ``S_bar = -W G`` on the used rows, then through ``C' = F P`` to ``P``'s upper triangle
    and ``ts``; a symmetric entry's cotangent is the sum of its two places'."""
    nz, ny = st.n_z, st.n_z + st.n_e
    iz, iy = c.index[nz], c.index[ny]
    Sm, _ = _gain_system(st, c, P_f, S, ts, use)
    W = cholesky_solve(Sm, Gt_bar)
    zero = jnp.zeros_like(ts)
    W = [[jnp.where(use[i], W[i, a], 0.0) for a in range(nz)] for i in range(ny)]
    S_bar = [zero for _ in range(len(_tri(ny)))]
    for i in range(ny):
        for j in range(ny):  # Sm_bar[i, j] = -sum_a W[i, a] G'[j, a], used rows and columns
            term = -sum((W[i][a] * Gt[j, a] for a in range(nz)), zero)
            S_bar[iy[i, j]] = S_bar[iy[i, j]] + jnp.where(use[j], term, 0.0)
    P_bar = [zero for _ in range(len(_tri(nz)))]
    ts_bar = zero
    for i in range(ny):
        for b in _f_cols(c, i):
            for a in range(nz):
                P_bar[iz[a, b]] = P_bar[iz[a, b]] + W[i][a] * _f(c, i, b, ts)
                if c.F1[i, b]:
                    ts_bar = ts_bar + W[i][a] * float(c.F1[i, b]) * P_f[iz[a, b]]
    return jnp.stack(P_bar), jnp.stack(S_bar), ts_bar


def lane_rts_mean(st: Structure, z_f, y_pred, Gt, use, skipped, z_s):
    """One backward step of the smoothed mean on lanes: a row's (``Nz, Nb, B``) from its
    filtered one, the next row's predicted mean (``y_pred``, ``Ny, Nb, B``), the gain and used
    rows between them (``lane_rts_gain``), whether the next row was skipped (``Nb, B``) and its
    smoothed mean ``z_s``. Linear in ``z_s``."""
    nz, ny = st.n_z, st.n_z + st.n_e
    zero = jnp.zeros_like(z_f[0])
    r = [jnp.where(use[i], (z_s[i] if i < nz else zero) - y_pred[i], 0.0) for i in range(ny)]
    z = jnp.stack([z_f[a] + sum((Gt[i, a] * r[i] for i in range(ny)), zero)
                   for a in range(nz)])
    return jnp.where(skipped, z_s, z)


def lane_rts_covariance(st: Structure, c: _Consts, P_f, S, Gt, use, skipped, P_s):
    """One backward step of the smoothed covariance on lanes, ``P_f + G (P^y_s - S) G'``
    stored as its upper triangle (``n_tri(Nz), Nb, B``), from the row's filtered one, the next
    row's predicted one (``S``, upper triangle), the gain and used rows, whether the next row
    was skipped and its smoothed one ``P_s``. Linear in ``P_s``."""
    nz, ny = st.n_z, st.n_z + st.n_e
    iz, iy = c.index[nz], c.index[ny]
    zero = jnp.zeros_like(P_f[0])

    def d(i, j):  # (P^y_s - S) on the used rows
        ps = P_s[iz[i, j]] if i < nz and j < nz else zero
        return jnp.where(use[i] & use[j], ps - S[iy[i, j]], 0.0)

    D = [[d(i, j) for j in range(ny)] for i in range(ny)]
    GD = [[sum((Gt[i, a] * D[i][j] for i in range(ny)), zero) for j in range(ny)]
          for a in range(nz)]
    P = jnp.stack([P_f[iz[a, b]] + sum((GD[a][j] * Gt[j, b] for j in range(ny)), zero)
                   for a, b in _tri(nz)])
    return jnp.where(skipped, P_s, P)


def lane_rts(st: Structure, moments: LaneMoments | LaneMomentsInnovations,
             ts_rows: Float[Array, "T B"], gradient: bool = True):
    """The backward pass over ``lane_moments_scan``'s rows (rows first, trials last): the
    smoothed ``(z, P)`` of every row (the last row's are its filtered ones).

    The gains read only the forward pass, so they are formed for every row at once, outside
    the recursion; what is left are two linear recursions, the mean's and the covariance's,
    each its own scan. A loss of the smoothed angles alone never runs the covariance's (XLA
    drops it, and reverse mode transposes only the mean's), and under reverse mode the gains'
    derivative is one vectorised pass, not a step recomputed per row: one ``fit --smooth``
    step costs a small multiple of the filtered fit's (benchmarks/README.md,
    "smooth_fit.py")."""
    z_rows, P_rows, skipped, y_rows, S_rows = (moments.z, moments.P, moments.skipped,
                                               moments.y, moments.S)
    c = _Consts(st)
    nb = z_rows.shape[2]
    if not gradient:  # each row's gain formed in the recursion, one scan
        return _lane_rts_rows(st, c, moments, ts_rows)
    # A skipped next row passes its smoothed state through, whatever its moments (which may
    # not be finite, and would spread NaN into the derivative): they are zeroed, so its gain
    # is zero and finite.
    skip = skipped[1:, None, None]
    y_next = jnp.where(skip, 0.0, y_rows[1:])
    S_next = jnp.where(skip, 0.0, S_rows[1:])
    ts = jnp.where(skip[:, 0], 0.0, jnp.broadcast_to(
        ts_rows[1:, None], (ts_rows.shape[0] - 1, nb) + ts_rows.shape[1:]))
    Gt, use = lane_rts_gain(st, c, jnp.moveaxis(P_rows[:-1], 1, 0), jnp.moveaxis(S_next, 1, 0),
                            ts)
    Gt, use = jnp.moveaxis(Gt, 2, 0), jnp.moveaxis(use, 1, 0)  # rows first
    skb = jnp.broadcast_to(skipped[1:, None], (skipped.shape[0] - 1, nb) + skipped.shape[1:])

    def covariance(P_s, row):
        P = lane_rts_covariance(st, c, *row, P_s)
        return P, P

    z = _mean_pass(st, z_rows[:-1], y_next, Gt, use, skb, z_rows[-1])
    _, P = jax.lax.scan(covariance, P_rows[-1], (P_rows[:-1], S_next, Gt, use, skb),
                        reverse=True)
    return jnp.concatenate([z, z_rows[-1:]]), jnp.concatenate([P, P_rows[-1:]])


def _lane_rts_rows(st: Structure, c: _Consts, moments, ts_rows):
    """``lane_rts`` as one scan, each row's gain formed in its step: the layout without a
    gradient (64 trials x 10,000 rows: 0.63 s, against 0.98 s with the gains formed
    beforehand), the same arithmetic."""
    nb = moments.z.shape[2]

    def body(carry, row):
        z_s, P_s = carry
        z_f, P_f, y, S, ts, skip = row
        tsb = jnp.broadcast_to(ts, (nb,) + ts.shape)
        skb = jnp.broadcast_to(skip, (nb,) + skip.shape)
        use = jnp.stack(_used(st, c, S, tsb))
        Gt = cholesky_solve(*_gain_system(st, c, P_f, S, tsb, use))
        z = lane_rts_mean(st, z_f, y, Gt, use, skb, z_s)
        P = lane_rts_covariance(st, c, P_f, S, Gt, use, skb, P_s)
        return (z, P), (z, P)

    z_rows, P_rows = moments.z, moments.P
    rows = (z_rows[:-1], P_rows[:-1], moments.y[1:], moments.S[1:], ts_rows[1:],
            moments.skipped[1:])
    _, (z, P) = jax.lax.scan(body, (z_rows[-1], P_rows[-1]), rows, reverse=True)
    return jnp.concatenate([z, z_rows[-1:]]), jnp.concatenate([P, P_rows[-1:]])


def _mean_pass(st: Structure, z_f, y_next, Gt, use, skipped, z_last):
    """The smoothed means of rows ``0 .. T-2`` (``lane_rts_mean`` from the last row back:
    ``z_f`` the filtered means, ``y_next``, ``Gt``, ``use`` and ``skipped`` of the row after
    each, ``z_last`` the last row's smoothed mean), with its reverse pass written by hand.

    The recursion is linear in the smoothed mean, so its transpose is a recursion of the
    cotangents the other way (first row first) that needs only the gains: ``zb = z_bar +
    carry``, ``r_bar = G zb`` on the used rows, ``carry' = r_bar[:Nz]`` (or ``zb`` past a
    skipped row). The cotangents of the filtered means, predictions and gains are then formed
    for every row at once, outside the recursion."""
    nz, ny = st.n_z, st.n_z + st.n_e

    @jax.custom_vjp
    def run(z_f, y_next, Gt, z_last, use, skipped):
        def step(z_s, row):
            z = lane_rts_mean(st, *row, z_s)
            return z, z

        return jax.lax.scan(step, z_last, (z_f, y_next, Gt, use, skipped), reverse=True)[1]

    def fwd(z_f, y_next, Gt, z_last, use, skipped):
        z = run(z_f, y_next, Gt, z_last, use, skipped)
        return z, (z, y_next, Gt, z_last, use, skipped)

    def bwd(res, z_bar):
        z, y_next, Gt, z_last, use, skipped = res
        zero = jnp.zeros_like(z_last[0])

        def step(carry, row):  # first row first: the cotangent reaching z_k from row k - 1
            zbar_k, G, u, sk = row
            zb = zbar_k + carry
            r_bar = jnp.stack([jnp.where(u[i] & ~sk, sum((G[i, a] * zb[a] for a in range(nz)),
                                                          zero), 0.0) for i in range(ny)])
            return jnp.where(sk, zb, 0.0) + r_bar[:nz], (zb, r_bar)

        z_last_bar, (zb, r_bar) = jax.lax.scan(step, jnp.zeros_like(z_last),
                                               (z_bar, Gt, use, skipped))
        z_s = jnp.concatenate([z[1:], z_last[None]])
        r = jnp.where(use, jnp.concatenate([z_s, jnp.zeros_like(y_next[:, nz:])], axis=1)
                      - y_next, 0.0)
        kept = ~skipped[:, None]
        Gt_bar = jnp.where(kept[:, None], r[:, :, None] * zb[:, None, :], 0.0)
        return jnp.where(kept, zb, 0.0), -r_bar, Gt_bar, z_last_bar, None, None

    run.defvjp(fwd, bwd)
    return run(z_f, y_next, Gt, z_last, use, skipped)


def lane_smooth(params: Params, st: Structure, series: SensorSeries, state: FilterState,
                innovations: bool = False, gradient: bool = True) -> Estimate:
    """The smoothed angles, their standard deviations and biases of a batch of trials (leading
    axis ``B`` on ``series`` and ``state``), and the skipped rows; ``innovations``: with the
    forward pass's fused Hall innovations (``Estimate.innovations``, ``B T Nb m``).
    ``gradient``: laid out for reverse mode (``lane_rts``); ``False`` for concrete inputs."""
    dtype = state.z.dtype
    series = prepare(params, series, dtype=dtype)  # a linear model: the paper's gyro pairs
    rows = lane_moments_scan(params, st, LaneState(state.z, state.P, state.gyro_hold),
                             lane_inputs(params, st, series.dt, series.gyro,
                                         series.hall_v), innovations).rows
    z, P = lane_rts(st, rows, jnp.moveaxis(series.dt, 0, 1), gradient)
    angles, std, bias = lane_estimates(st, z, P)
    return Estimate(angles, std, bias, jnp.moveaxis(rows.skipped, 0, 1),
                    innovations=rows_innovations(rows))
