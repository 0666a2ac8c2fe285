"""The filter step written for lanes: every state and covariance entry an array over trials.

A ``vmap`` of the kernel's ``step`` puts the trial axis first, so XLA's CPU loops run over the
tiny block matrices (5 x 5 for the bench robot) one trial at a time. Here the same arithmetic
is written out entry by entry from the block structure (``_model.Structure``: its constant
matrices decide at trace time which products are zero), with the trial axis *last*: each
operation is one loop over the lanes, and the step is a few hundred of them, which XLA fuses.
The covariance is stored as its upper triangle (symmetric by construction).

The arithmetic is the kernel's: the prediction (Eqs. 3, 9-13), the constraint as a perfect
measurement (KCKF), one Joseph-form scalar update per joint with its fused Hall reading, the
step skipped (state kept) when its update is not finite, a missing gyro reading holding the
last one. Readings are turned into block inputs beforehand for every row at once (the Hall
model, the fusion of each pair, the process noise), so the scan carries only the state.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._kernel import (
    Estimate,
    FilterState,
    SensorSeries,
    chunked_scan,
    fused_pairs,
    hall_measurements,
    plausible,
)
from .._model import Structure, block_gather, q_blocks, structure
from .._params import Params
from ._base import AbstractPath, kalman_only


def _tri(n: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(n) for j in range(i, n)]


def _tri_index(n: int) -> np.ndarray:
    """``(n, n)``: the position of entry ``(i, j)`` in the upper triangle ``_tri(n)``."""
    out = np.zeros((n, n), int)
    for t, (i, j) in enumerate(_tri(n)):
        out[i, j] = out[j, i] = t
    return out


def _apply(C: np.ndarray, x):
    """``C x`` for a constant ``C`` (``a x b``) and lane arrays ``x`` (``b, ...``): the sums of
    its nonzero terms written out (the constants are known at trace time), stacked. On a CPU
    this is several times faster than a broadcast multiply-sum or a small ``dot``."""
    C = np.asarray(C)
    rows = []
    for i in range(C.shape[0]):
        acc = None
        for j in np.flatnonzero(C[i]):
            w = float(C[i, j])
            term = x[j] if w == 1.0 else (-x[j] if w == -1.0 else w * x[j])
            acc = term if acc is None else acc + term
        rows.append(jnp.zeros_like(x[0]) if acc is None else acc)
    return jnp.stack(rows)


class _Consts:
    """The constant matrices of one block step in upper-triangle form (NumPy, built once per
    structure): the prediction ``S = (C0 + ts C1 + ts^2 C2) P + Qa alpha + Qab beta + Qb
    gamma`` and ``y = (F0 + ts F1) z + ts G1 r``, and the index maps of the updates."""

    def __init__(self, st: Structure):
        nz, ny = st.n_z, st.n_z + st.n_e
        iz, iy = _tri_index(nz), _tri_index(ny)
        ty = _tri(ny)
        F0, F1 = np.asarray(st.F0), np.asarray(st.F1)
        C = [np.zeros((len(ty), len(_tri(nz)))) for _ in range(3)]
        for t, (i, j) in enumerate(ty):
            for a in range(nz):
                for b in range(nz):
                    u = iz[a, b]
                    C[0][t, u] += F0[i, a] * F0[j, b]
                    C[1][t, u] += F0[i, a] * F1[j, b] + F1[i, a] * F0[j, b]
                    C[2][t, u] += F1[i, a] * F1[j, b]
        self.C = C
        self.Q = [np.array([[M[k, i, j] for k in range(M.shape[0])] for (i, j) in ty])
                  for M in (st.Qa, st.Qab, st.Qb)]
        self.F0, self.F1, self.G1 = F0, F1, np.asarray(st.G1)
        self.index = {nz: iz, ny: iy}
        self.restrict = np.array([iy[i, j] for (i, j) in _tri(nz)])
        self.rows = {n: np.array([i for i, _ in _tri(n)]) for n in (nz, ny)}
        self.cols = {n: np.array([j for _, j in _tri(n)]) for n in (nz, ny)}


def lane_step(st: Structure, consts: _Consts, z, P, rates, noise, hb, rb, vb, ts,
              innovations: bool = False, moments: bool = False):
    """One block step on lanes: ``z`` (``Nz, Nb, B``), ``P`` (upper triangle, ``n_tri, Nb,
    B``), ``rates`` (``m1, Nb, B``), ``noise = (alpha, beta, gamma)`` (``m1, Nb, B`` each),
    ``hb, rb, vb`` (``m, Nb, B``), ``ts`` (``Nb, B``). Returns the new ``(z, P)`` (the
    kernel's ``block_update``); ``innovations``: also each joint's fused Hall innovation and
    its variance, ``(nu, s)`` (``m, Nb, B`` each; the kernel's ``block_step``); ``moments``:
    also the predicted moments of ``y = [z, e]`` before any update, ``(y, S)`` (``Ny, Nb, B``
    and the upper triangle of ``S``: the smoother's terms), after the innovations if both."""
    c = consts
    nz, ny = st.n_z, st.n_z + st.n_e
    # Predicted mean and covariance (Eqs. 3, 9-13).
    y = _apply(c.F0, z) + ts * _apply(c.F1, z) + ts * _apply(c.G1, rates)
    alpha, beta, gamma = noise
    S = (_apply(c.C[0], P) + ts * (_apply(c.C[1], P) + ts * _apply(c.C[2], P))
         + _apply(c.Q[0], alpha) + _apply(c.Q[1], beta) + _apply(c.Q[2], gamma))
    y, S = jax.lax.optimization_barrier((y, S))
    predicted = (y, S)
    # The constraint e = 0 as a perfect measurement (KCKF), then one update per joint.
    for i in range(st.n_e):
        e = nz + i
        y, S = _update(c, ny, y, S, e, -y[e], jnp.zeros_like(ts), ts > 0)
    z, P = y[:nz], S[c.restrict] if st.n_e else S
    nus, ss = [], []
    for i in range(st.m):
        nus.append(hb[i] - z[i])
        ss.append(P[c.index[nz][i, i]] + rb[i])
        z, P = _update(c, nz, z, P, i, nus[-1], rb[i], vb[i])
    out = (z, P)
    if innovations:
        out += ((jnp.stack(nus), jnp.stack(ss)),)
    if moments:
        out += (predicted,)
    return out


def _update(c: _Consts, n: int, z, P, index: int, innovation, r, valid):
    """The kernel's Joseph-form scalar update (``_kalman.coordinate_update``) on lanes."""
    col = P[c.index[n][:, index]]
    s = col[index] + r
    ok = valid & (s > 0)
    k = jnp.where(ok, col / jnp.where(ok, s, 1.0), 0.0)
    z = z + k * jnp.where(ok, innovation, 0.0)
    a, b = c.rows[n], c.cols[n]
    P = P - k[a] * col[b] - col[a] * k[b] + s * k[a] * k[b]
    return z, P


def row_inputs(params: Params, st: Structure, dt: Float[Array, "T B"],
               hall_v: Float[Array, "T B M"]):
    """Every row's inputs that do not depend on the state, for all rows and trials at once:
    the process noise ``(alpha, beta, gamma)`` (``T m1 Nb B`` each) and each block joint's
    fused Hall reading, its variance and validity (``T m Nb B``)."""
    noise = q_blocks(params.q, params.angle_rw, params.bias_rw, dt[..., None])  # (T, B, K)
    noise = tuple(jnp.moveaxis(jax.vmap(jax.vmap(lambda x: block_gather(st, x)))(n), 1, -1)
                  for n in noise)  # (T, Nb, m1, B)

    def hall_row(v):
        angle, r, valid = hall_measurements(params, v)
        h, rh, ok = fused_pairs(angle, r, valid)
        ji = st.joint_index
        pad = ji < 0
        return (jnp.where(pad, 0.0, h[np.maximum(ji, 0)]),
                jnp.where(pad, 1.0, rh[np.maximum(ji, 0)]),
                jnp.where(pad, False, ok[np.maximum(ji, 0)]))

    hb, rb, vb = (jnp.moveaxis(x, 1, -1) for x in jax.vmap(jax.vmap(hall_row))(hall_v))
    def swap(x):  # (T, Nb, j, B) -> (T, j, Nb, B): one lane array per block coordinate
        return jnp.swapaxes(x, 1, 2)

    return tuple(swap(n) for n in noise), swap(hb), swap(rb), swap(vb)


#: The inputs of a no-op row (no time step, every reading missing), per ``lane_inputs`` leaf in
#: ``tree_leaves`` order: ``ts``, the three noise terms, ``hb``, ``rb``, ``vb``, the gyro.
NO_OP_INPUTS = (0.0, 0.0, 0.0, 0.0, 0.0, 1.0, False, jnp.nan)


def lane_inputs(params: Params, st: Structure, dt: Float[Array, "B T"],
                gyro: Float[Array, "B T G"], hall_v: Float[Array, "B T M"]):
    """Every row's inputs to ``lane_scan``, rows first and trials last: ``(ts (T, B), (alpha,
    beta, gamma), hb, rb, vb, gyro (T, G, B))`` (``row_inputs``' terms)."""
    noise, hb, rb, vb = row_inputs(params, st, jnp.moveaxis(dt, 0, 1),
                                   jnp.moveaxis(hall_v, 0, 1))
    return (jnp.moveaxis(dt, 0, 1), noise, hb, rb, vb,
            jnp.moveaxis(gyro, (0, 1, 2), (2, 0, 1)))


def lane_scan(params: Params, st: Structure, z0: Float[Array, "B Nb Nz"],
              P0: Float[Array, "B Nb Nz Nz"], hold0: Float[Array, "B G"],
              dt: Float[Array, "B T"] | None,
              gyro: Float[Array, "B T G"] | None, hall_v: Float[Array, "B T M"] | None,
              remat_chunk: int | None = None,
              innovations: bool = False, moments: bool = False,
              inputs: tuple | None = None, snapshot_row: int | None = None):
    """The Kalman filter over ``T`` rows of ``B`` trials, trials as lanes.

    Returns ``(zT, PT, holdT, rows)``: the final states (``B`` first, as given) and per row
    ``(z, P upper triangle, skipped)`` with the rows first and trials last:
    ``(T, Nz, Nb, B)``, ``(T, n_tri, Nb, B)``, ``(T, B)``. ``innovations``: ``rows`` is
    ``(nu, s, valid)`` instead (``T, m, Nb, B`` each), every joint's fused Hall innovation,
    its variance and whether it was used (the likelihood's terms; no estimates kept).
    ``moments``: ``rows`` is ``(z, P, skipped, y, S)``, with each row's predicted moments
    (``T, Ny, Nb, B`` and ``T, n_tri(Ny), Nb, B``: ``lane_step``'s), for the smoother.
    ``inputs``: ``lane_inputs(params, st, dt, gyro, hall_v)``, computed beforehand (then
    ``dt``, ``gyro`` and ``hall_v`` are not read). ``snapshot_row``: also return the states
    after that many rows, ``(z, P, hold)`` as the final ones, as a fifth item."""
    robot = params.robot
    dtype = z0.dtype
    nz = st.n_z
    tri = _tri(nz)
    plus, minus = robot.rate_pairs
    # Every gyro channel is held (the final state's hold is the kernel's), the used ones drive.
    used = np.arange(3 * robot.n_links)
    col = {int(c): i for i, c in enumerate(used)}
    # Per block coordinate: which gyro columns make its rate (``rate_map``'s +1 and -1).
    rate_cols = [[(col[int(plus[k])], col[int(minus[k])]) if k >= 0 else None
                  for k in st.angle_index[:, i]] for i in range(st.m + 1)]
    rows = lane_inputs(params, st, dt, gyro, hall_v) if inputs is None else inputs
    nb = st.angle_index.shape[0]

    # The block rates (Eqs. 2, 9, 10) as one constant map of the held gyro columns.
    Rm = np.zeros((st.m + 1, nb, len(used)))
    for i in range(st.m + 1):
        for p, ab in enumerate(rate_cols[i]):
            if ab is not None:
                Rm[i, p, ab[0]] += 1.0
                Rm[i, p, ab[1]] -= 1.0
    Rm = Rm.reshape((st.m + 1) * nb, len(used))

    def rates_of(hold):  # hold (Gu, B) -> (m1, Nb, B)
        return _apply(Rm, hold).reshape((st.m + 1, nb) + hold.shape[1:])

    consts = _Consts(st)

    def body(carry, row):
        # The state as one array (z entries, then P's upper triangle; each (Nb, B)) and the
        # held gyro rates: one output per step.
        x, hold = carry[:2]
        ts, (alpha, beta, gamma), hb_r, rb_r, vb_r, g_r = row
        tsb = jnp.broadcast_to(ts, (nb,) + ts.shape)
        out = lane_step(st, consts, x[:nz], x[nz:], rates_of(hold), (alpha, beta, gamma),
                        hb_r, rb_r, vb_r, tsb, innovations, moments)
        x_new = jnp.concatenate(out[:2])
        fin = jnp.isfinite(x_new).all(axis=(0, 1))
        x_new = jnp.where(fin, x_new, x)
        hold = jnp.where(fin & jnp.isfinite(g_r), g_r, hold)
        new = (x_new, hold)
        if snapshot_row is not None:  # the states after row snapshot_row - 1, kept
            i, x_snap, hold_snap = carry[2:]
            take = i == snapshot_row - 1
            new += (i + 1, jnp.where(take, x_new, x_snap), jnp.where(take, hold, hold_snap))
        if innovations:
            nu, s = out[2]
            return new, (nu, s, vb_r & fin)
        if moments:
            return new, (x_new, ~fin) + out[2]
        return new, (x_new, ~fin)

    x0 = jnp.stack([jnp.moveaxis(z0[:, :, i], 0, 1) for i in range(nz)]
                   + [jnp.moveaxis(P0[:, :, i, j], 0, 1) for i, j in tri])
    hold = jnp.moveaxis(hold0[:, used], 0, 1)
    carry = (x0, hold)
    if snapshot_row is not None:
        carry += (jnp.asarray(0), x0, hold)
    if remat_chunk:
        # No-op rows pad the last chunk: no time step, every reading missing.
        final, out = chunked_scan(body, carry, rows, remat_chunk, NO_OP_INPUTS)
    else:
        # Each row recomputed under reverse mode (only the carries saved): the transposed
        # body then runs as one piece (64 x 10,000 bench, float32: gradient 3.7 -> 3.0 s).
        final, out = jax.lax.scan(jax.checkpoint(body), carry, rows)
    if not innovations:
        xs, skipped = out[:2]
        out = (xs[:, :nz], xs[:, nz:], skipped) + tuple(out[2:])
    def states(x, h):  # lanes layout -> (B, Nb, Nz), (B, Nb, Nz, Nz), (B, G)
        z = jnp.moveaxis(x[:nz], (0, 1, 2), (2, 1, 0))
        P = jnp.zeros((z0.shape[0], nb, nz, nz), dtype)
        for (i, j), p in zip(tri, x[nz:]):
            p = jnp.moveaxis(p, 0, 1)
            P = P.at[:, :, i, j].set(p).at[:, :, j, i].set(p)
        return z, P, hold0.at[:, used].set(jnp.moveaxis(h, 0, 1))

    if snapshot_row is not None:
        return states(*final[:2]) + (out, states(*final[3:]))
    return states(*final[:2]) + (out,)


def lane_estimates(st: Structure, z_rows: Float[Array, "T Nz Nb B"],
                   P_rows: Float[Array, "T X Nb B"]):
    """Angles, their standard deviations and biases (``B T K`` each) from the rows of
    ``lane_scan`` (the kernel's ``block_estimate``, every row at once)."""
    to_x = np.asarray(st.T)
    m1 = st.m + 1
    iz = _tri_index(st.n_z)
    tri = _tri(st.n_z)
    K = len(st.block_of)
    A = np.zeros((K, st.n_z))  # angle k from its block's z
    Bm = np.zeros((K, st.n_z))
    V = np.zeros((K, len(tri)))  # its variance from its block's P
    for k, i in enumerate(st.slot_of):
        A[k], Bm[k] = to_x[i], to_x[m1 + i]
        for a in range(st.n_z):
            for b in range(st.n_z):
                V[k, iz[a, b]] += to_x[i, a] * to_x[i, b]
    rows = np.asarray(st.block_of)

    def per_angle(C, x):  # x (T, n, Nb, B) -> (B, T, K): row k of C on block block_of[k]
        y = _apply(C, jnp.moveaxis(x, 1, 0))  # (K, T, Nb, B)
        y = jnp.take_along_axis(y, jnp.asarray(rows)[:, None, None, None], axis=2)[:, :, 0]
        return jnp.moveaxis(y, (0, 1, 2), (2, 1, 0))

    var = per_angle(V, P_rows)
    return per_angle(A, z_rows), jnp.sqrt(jnp.maximum(var, 0.0)), per_angle(Bm, z_rows)


class Lanes(AbstractPath):
    """Any recording the sequential path accepts, trials as lanes: the kernel's arithmetic
    written entry by entry with the trial axis last (see the module docstring).

    Exact for everything ``Sequential`` computes (irregular time steps, missing readings per
    channel, the voltage noise model, padded trials, skipped updates): the same operations in
    another layout, equal to rounding. It pays from a few trials on (measured in
    benchmarks/README.md); ``Auto`` takes it for batches of at least ``min_trials``.

    Attributes:
        min_trials: ``Auto`` passes it over for fewer trials (one recording: ``Sequential``).
        remat_chunk: checkpoint the scan in chunks of this many rows under reverse mode.
    """

    name: ClassVar[str] = "lanes"
    min_trials: int = eqx.field(static=True, default=12)
    remat_chunk: int | None = eqx.field(static=True, default=None)

    def applies(self, params: Params, series: SensorSeries, method: str,
                state: FilterState | None = None) -> str | None:
        return kalman_only(method)

    def run(self, params: Params, series: SensorSeries, method: str, state: FilterState
            ) -> tuple[FilterState, Estimate]:
        st = structure(params.robot, method)
        dtype = state.z.dtype
        series = plausible(params, jax.tree_util.tree_map(
            lambda x: jnp.asarray(x).astype(dtype), series))
        zT, PT, holdT, (z_rows, P_rows, skipped) = lane_scan(
            params, st, state.z, state.P, state.gyro_hold, series.dt, series.gyro,
            series.hall_v, self.remat_chunk)
        angles, std, bias = lane_estimates(st, z_rows, P_rows)
        return FilterState(zT, PT, holdT), Estimate(angles, std, bias, jnp.moveaxis(skipped, 0,
                                                                                    1))
