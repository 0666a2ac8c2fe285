"""A constant affine map applied to many rows as matrix products, with its reverse mode by hand.

The steady path's converged rows: ``z_j = A z_{j-1} + Wg g_{j-1} + Wh h_j`` with one map for
every row. A sequential scan of the rows does little arithmetic but pays XLA's loop overhead
on every row (about a microsecond on a CPU); here the rows go in chunks of ``chunk_rows``,
each chunk's estimates one matrix product of its raw readings and the state entering it
(``chunk_operator``), and the states entering the chunks are solved for in nested groups
(``carries``), also matrix products, which XLA runs at 100-200 GFLOP/s on a CPU.

``chunk_rows`` makes one pass over the readings in blocks of ``ChunkPlan.block_rows`` rows, so
a block's readings stay in cache and the Hall exponentials are computed once; its reverse mode
(``_chunk_rows_bwd``) is the same kind of computation run backwards.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._models._hall import hall_angle
from ._affine import apply_blocks
from ._reverse import if_perturbed, is_perturbed


@dataclass(frozen=True)
class ChunkPlan:
    """How ``chunk_rows`` covers the converged rows (static: part of the compiled program).

    Attributes:
        start: the first row of the first chunk.
        n_chunks: whole chunks, ``chunk_rows`` rows each.
        chunk_rows: rows per chunk.
        block_rows: rows per block of the one pass over the readings (a multiple of
            ``chunk_rows``).
        used: the gyro columns the map reads (``Robot.used_gyro_index``).
        n_angles: ``K``, angles per output row (the outputs are angles, then biases).
        carry_group: chunks per group when solving for the entering states (``carries``).
        carry_scan: at most this many entering states are left to a plain scan.
    """

    start: int
    n_chunks: int
    chunk_rows: int
    block_rows: int
    used: tuple[int, ...]
    n_angles: int
    carry_group: int
    carry_scan: int


def chunk_operator(A: Float[Array, "Nb Nz Nz"], Wg: Float[Array, "Gu Nb Nz"],
                   Wh: Float[Array, "M Nb Nz"], out_map: np.ndarray, L: int
                   ) -> tuple[Float[Array, "X O"], Float[Array, "Y Nq"], Float[Array, "Nq Nq"]]:
    """``L`` rows of the converged map as matrices.

    Row ``j`` of the chunk: ``z_j = A z_{j-1} + Wg g_{j-1} + Wh h_j`` (``g`` the used gyro
    columns, ``h`` the Hall angles). The chunk is entered with the *prediction* ``s = A z_{-1}
    + Wg g_{-1}``, so it needs no reading from before it; then ``z_j = A^j s + sum_{i<=j}
    A^{j-i} Wh h_i + sum_{i<j} A^{j-1-i} Wg g_i``. With ``x`` the chunk's readings row by row
    (``[g_i, h_i]``, flattened) and ``s`` flattened (``Nq = Nb Nz``), all as row vectors:

    * the chunk's estimates (``L x 2K``, flattened, ``out_map`` giving them from a state):
      ``[x, s] @ GS``;
    * the prediction entering the next chunk: ``s @ Phi + x @ E`` (``Phi`` is ``A^L``).

    Returns ``(GS, E, Phi)``: ``(L I + Nq) x (L 2K)``, ``L I x Nq`` and ``Nq x Nq``."""
    nb, nz, _ = A.shape
    dtype = A.dtype
    out_map = jnp.asarray(out_map, dtype)

    def mv(X, W):  # (..., Nb, Nz, Nz) times (..., F, Nb, Nz) -> (..., F, Nb, Nz); broadcast
        return sum(X[..., None, :, :, b] * W[..., :, :, b, None] for b in range(nz))

    pw = [jnp.broadcast_to(jnp.eye(nz, dtype=dtype), (nb, nz, nz))]
    for _ in range(L):  # A^0 .. A^L, per block (broadcast products: 5 x 5 dots are slow)
        pw.append(apply_blocks(A, pw[-1]))
    pw = jnp.stack(pw)
    Hh = mv(pw, Wh[None])  # A^d Wh, d = 0 .. L
    Hg = mv(pw, Wg[None])  # A^d Wg
    j, i = np.arange(L)[:, None], np.arange(L)[None, :]

    def toeplitz(H, lag):  # (j, i, F, Nb, Nz): H[j - i - lag] where j - i >= lag, else 0
        d = j - i - lag
        return jnp.where((d >= 0)[:, :, None, None, None], H[np.clip(d, 0, L)], 0.0)

    Z = jnp.concatenate([toeplitz(Hg, 1), toeplitz(Hh, 0)], axis=2)  # (j, i, I, Nb, Nz)
    n_in = Z.shape[2]
    G = jnp.einsum("jifpa,opa->ifjo", Z, out_map).reshape(L * n_in, -1)
    S = jnp.einsum("jpab,opa->pbjo", pw[:L], out_map).reshape(nb * nz, -1)
    # The next chunk's prediction: A z_{L-1} + Wg g_{L-1}, i.e. A^{L-1-i} Wg for g_i and
    # A^{L-i} Wh for h_i.
    back = L - 1 - np.arange(L)
    E = jnp.concatenate([Hg[back], Hh[back + 1]], axis=1).reshape(L * n_in, nb * nz)
    # As a right multiplier of the flattened row vector: block diagonal, transposed blocks.
    Phi = jnp.zeros((nb, nz, nb, nz), dtype).at[np.arange(nb), :, np.arange(nb), :].set(
        jnp.swapaxes(pw[L], 1, 2)).reshape(nb * nz, nb * nz)
    return jnp.concatenate([G, S]), E, Phi


def _matrix_powers(Phi: Float[Array, "Nq Nq"], n: int) -> Float[Array, "R Nq Nq"]:
    """``Phi^0 .. Phi^n`` stacked."""
    out = [jnp.eye(Phi.shape[0], dtype=Phi.dtype)]
    for _ in range(n):
        out.append(out[-1] @ Phi)
    return jnp.stack(out)


def carries(Phi: Float[Array, "Nq Nq"], e: Float[Array, "B C Nq"], s0: Float[Array, "B Nq"],
            group: int, scan_below: int) -> tuple[Float[Array, "B C Nq"], Float[Array, "B Nq"]]:
    """The states entering each chunk: ``s_{c+1} = s_c Phi + e_c`` (row vectors) from ``s0``.
    Returns ``(ss, s_C)``, ``ss[:, c]`` the state entering chunk ``c``.

    At most ``scan_below`` chunks: a scan. More: in groups of ``n = group`` chunks,
    ``s_{gn+j} = t_g Phi^j + sum_{i<j} e_{gn+i} Phi^{j-1-i}``: one matrix product gives every
    group's local part and its end, and the states ``t_g`` entering the groups are the same
    problem with ``Phi^n``, ``n`` times shorter."""
    n_trials, n_chunks, q = e.shape
    if n_chunks <= scan_below:
        def f(s, e_c):
            return sum(s[:, i, None] * Phi[i] for i in range(q)) + e_c, s

        s_end, ss = jax.lax.scan(f, s0, jnp.moveaxis(e, 1, 0))
        return jnp.moveaxis(ss, 0, 1), s_end
    n = group
    groups = n_chunks // n + 1  # at least one padded chunk, so s_C is some group's local state
    e = jnp.pad(e, ((0, 0), (0, groups * n - n_chunks), (0, 0)))
    pw = _matrix_powers(Phi, n)
    i, j = np.arange(n)[:, None], np.arange(n)[None, :]
    local = jnp.where((i < j)[..., None, None], pw[np.clip(j - 1 - i, 0, n)], 0.0)
    local = jnp.transpose(local, (0, 2, 1, 3)).reshape(n * q, n * q)
    end = pw[n - 1 - np.arange(n)].reshape(n * q, q)
    y = e.reshape(n_trials, groups, n * q) @ jnp.concatenate([local, end], axis=1)
    tt, _ = carries(pw[n], y[..., n * q:], s0, group, scan_below)
    ss = y[..., :n * q] + tt @ jnp.transpose(pw[:n], (1, 0, 2)).reshape(q, n * q)
    ss = ss.reshape(n_trials, groups * n, q)
    return ss[:, :n_chunks], ss[:, n_chunks]


def _over_blocks(plan: ChunkPlan, body, carry, reverse: bool = False):
    """``body(carry, first, rows)`` over the chunk rows of ``plan`` in blocks of
    ``plan.block_rows`` rows (a ``fori_loop`` of the full blocks, then the remainder; the other
    way round, last block first, when ``reverse``)."""
    R = plan.block_rows
    rows = plan.n_chunks * plan.chunk_rows
    full = rows // R
    if rows % R and reverse:
        carry = body(carry, full * R, rows - full * R)
    if full:
        carry = jax.lax.fori_loop(
            0, full, lambda i, c: body(c, ((full - 1 - i) if reverse else i) * R, R), carry)
    if rows % R and not reverse:
        carry = body(carry, full * R, rows - full * R)
    return carry


def raw_readings(coeffs, gyro: Float[Array, "B T G"], hall_v: Float[Array, "B T M"],
                 used: tuple[int, ...], first, n: int) -> Float[Array, "B R I"]:
    """Rows ``first .. first + n`` of the raw readings as the steady map reads them: the used
    gyro columns, then the Hall angles (``coeffs`` is ``Params.hall_coeffs``, rad)."""
    g = jax.lax.dynamic_slice_in_dim(gyro, first, n, axis=1)[..., list(used)]
    h = jax.lax.dynamic_slice_in_dim(hall_v, first, n, axis=1)
    return jnp.concatenate([g, hall_angle(h, *coeffs)], axis=2)


def _chunk_readings(plan: ChunkPlan, coeffs, gyro: Float[Array, "B T G"],
                    hall_v: Float[Array, "B T M"], first, n: int) -> Float[Array, "B C Y"]:
    """Chunk rows ``first .. first + n`` (counted from ``plan.start``) as chunks:
    ``(B, n / chunk_rows, chunk_rows I)``."""
    x = raw_readings(coeffs, gyro, hall_v, plan.used, plan.start + first, n)
    return x.reshape(x.shape[0], n // plan.chunk_rows, -1)


def _chunk_forward(plan: ChunkPlan, GS: Float[Array, "X O"], E: Float[Array, "Y Nq"],
                   Phi: Float[Array, "Nq Nq"], s0: Float[Array, "B Nq"], coeffs,
                   gyro: Float[Array, "B T G"], hall_v: Float[Array, "B T M"], outs,
                   keep: bool = False):
    """The chunks in one pass over the readings: per block of rows, each chunk's part of the
    state entering the next (``x @ E``), the states entering the block's chunks from the one
    entering the block (``carries``), and the estimates (``x @ Gx + s @ Gs``), written into
    ``outs``. Returns ``(outs, s_end, ss)``: ``ss`` (``B x n_chunks x Nq``) the state entering
    every chunk when ``keep`` (the reverse mode's residual), else None."""
    K = plan.n_angles
    n_trials, q = s0.shape
    n_x = GS.shape[0] - q
    Gx, Gs = GS[:n_x], GS[n_x:]

    def block(carry, first, n):
        outs, s, ss = carry
        x = _chunk_readings(plan, coeffs, gyro, hall_v, first, n)
        s_k, s = carries(Phi, x @ E, s, plan.carry_group, plan.carry_scan)
        y = (x @ Gx + s_k @ Gs).reshape(n_trials, n, 2 * K)
        outs = tuple(jax.lax.dynamic_update_slice_in_dim(
            o, y[..., k * K:(k + 1) * K], plan.start + first, axis=1) for k, o in enumerate(outs))
        if keep:
            ss = jax.lax.dynamic_update_slice_in_dim(ss, s_k, first // plan.chunk_rows, axis=1)
        return outs, s, ss

    ss0 = jnp.zeros((n_trials, plan.n_chunks, q), s0.dtype) if keep else None
    return _over_blocks(plan, block, (outs, s0, ss0))


class ChunkInputs(NamedTuple):
    """What ``chunk_rows`` maps, and is differentiated with respect to: the chunk operators
    ``GS``, ``E``, ``Phi`` (``chunk_operator``), the prediction entering the first chunk
    ``s0``, the Hall coefficients, the readings and the output buffers (angles, biases)."""

    GS: Float[Array, "X O"]
    E: Float[Array, "Y Nq"]
    Phi: Float[Array, "Nq Nq"]
    s0: Float[Array, "B Nq"]
    coeffs: tuple
    gyro: Float[Array, "B T G"]
    hall_v: Float[Array, "B T M"]
    outs: tuple[Float[Array, "B T K"], Float[Array, "B T K"]]


def chunk_rows(plan: ChunkPlan, inputs: ChunkInputs
               ) -> tuple[tuple[Float[Array, "B T K"], Float[Array, "B T K"]],
                          Float[Array, "B Nq"]]:
    """The converged rows of ``plan``: ``inputs.outs`` (angles, biases) with the chunk rows
    filled in, and the prediction entering the row after the last chunk.

    The map is linear in the readings and the entering state, so its reverse mode is the same
    kind of computation run backwards (``eqx.filter_custom_vjp``): the cotangents of the
    entering states follow ``a_c = a_{c+1} Phi^T + dss_c`` (``carries`` with ``Phi^T``, in
    reverse order), and those of the readings and operators are matrix products block by
    block, the Hall coefficients' accumulated block by block while the block is in cache.
    Which inputs are perturbed and which outputs carry a cotangent decide what is formed: a
    loss on the angles alone skips the biases' columns, and the readings' own cotangents
    (full-size arrays) are formed only when something differentiates with respect to the
    data. Left to JAX (the transposed ``fori_loop``s and ``dynamic_update_slice``s), the 3D
    robot's fitting gradient (64 x 10,000 rows, float32) took 1.66 s instead of 1.06 s
    (docs/performance.md)."""
    return _chunk_rows(inputs, plan)


@eqx.filter_custom_vjp
def _chunk_rows(inputs: ChunkInputs, plan: ChunkPlan):
    outs, s_end, _ = _chunk_forward(plan, *inputs)
    return outs, s_end


@_chunk_rows.def_fwd
def _chunk_rows_fwd(perturbed: ChunkInputs, inputs: ChunkInputs, plan: ChunkPlan):
    outs, s_end, ss = _chunk_forward(plan, *inputs, keep=True)
    return (outs, s_end), ss


@_chunk_rows.def_bwd
def _chunk_rows_bwd(ss, ct, perturbed: ChunkInputs, inputs: ChunkInputs, plan: ChunkPlan):
    GS, E, Phi, _, coeffs, gyro, hall_v, _ = inputs
    want_coeffs, want_gyro, want_hall = (is_perturbed(p) for p in (
        perturbed.coeffs, perturbed.gyro, perturbed.hall_v))
    want_x = want_gyro or want_hall
    douts, ds_end = ct  # None: not differentiated
    L, K, start = plan.chunk_rows, plan.n_angles, plan.start
    n_trials, n_chunks, q = ss.shape
    n_x = GS.shape[0] - q
    n_in = n_x // L
    Gu = len(plan.used)
    rows = n_chunks * L
    dtype = ss.dtype
    # Only the outputs that carry a cotangent: their columns of GS (chunk-row j, output o).
    live = [k for k, o in enumerate(douts) if o is not None]
    cols = np.asarray([j * 2 * K + k * K + o for j in range(L) for k in live for o in range(K)],
                      dtype=int)
    GSl = GS[:, cols]
    Gx, Gs = GSl[:n_x], GSl[n_x:]
    ds_end = jnp.zeros((n_trials, q), dtype) if ds_end is None else ds_end
    PhiT = Phi.T

    # One pass over the blocks, last first. ``a`` is the cotangent of the state entering the
    # chunk after the block: a_c = a_{c+1} Phi^T + dss_c within it (``carries`` with Phi^T,
    # in reverse order); chunk c's e_c enters s_{c+1}, so its cotangent is a_{c+1}.
    def block(carry, first, n):
        dx, dGS, dE, dPhi, dcoeffs, a = carry
        c0, c = first // L, n // L
        x, readings_vjp = jax.vjp(
            lambda cf: _chunk_readings(plan, cf, gyro, hall_v, first, n), coeffs)
        s_k = jax.lax.dynamic_slice_in_dim(ss, c0, c, axis=1)
        if live:
            dy = jnp.concatenate([jax.lax.dynamic_slice_in_dim(douts[k], start + first, n,
                                                               axis=1)
                                  for k in live], axis=2).reshape(n_trials, c, -1)
            rr, a = carries(PhiT, (dy @ Gs.T)[:, ::-1], a, plan.carry_group, plan.carry_scan)
        else:
            rr, a = carries(PhiT, jnp.zeros((n_trials, c, q), dtype), a, plan.carry_group,
                            plan.carry_scan)
        de = rr[:, ::-1]
        dx_k = de @ E.T
        if live:
            dx_k = dx_k + dy @ Gx.T
            dGS = dGS + jnp.concatenate([jnp.einsum("Bci,Bco->io", x, dy),
                                         jnp.einsum("Bcq,Bco->qo", s_k, dy)])
        dE = dE + jnp.einsum("Bci,Bcq->iq", x, de)
        dPhi = dPhi + jnp.einsum("Bcq,Bcr->qr", s_k, de)
        if want_coeffs:
            dcoeffs = jax.tree_util.tree_map(jnp.add, dcoeffs, readings_vjp(dx_k)[0])
        if want_x:
            dx = jax.lax.dynamic_update_slice_in_dim(dx, dx_k.reshape(n_trials, n, n_in), first,
                                                     axis=1)
        return dx, dGS, dE, dPhi, dcoeffs, a

    dx0 = jnp.zeros((n_trials, rows, n_in), dtype) if want_x else None
    dx, dGSl, dE, dPhi, dcoeffs, ds0 = _over_blocks(
        plan, block, (dx0, jnp.zeros_like(GSl), jnp.zeros_like(E), jnp.zeros_like(Phi),
                      jax.tree_util.tree_map(jnp.zeros_like, coeffs), ds_end), reverse=True)
    dGS = jnp.zeros_like(GS).at[:, cols].set(dGSl)
    dgyro = dhall_v = None
    if want_hall:
        h = jax.lax.dynamic_slice_in_dim(hall_v, start, rows, axis=1)
        _, h_vjp = jax.vjp(lambda h: hall_angle(h, *coeffs), h)
        dhall_v = jax.lax.dynamic_update_slice_in_dim(jnp.zeros_like(hall_v),
                                                      h_vjp(dx[..., Gu:])[0], start, axis=1)
    if want_gyro:
        dgyro = jnp.zeros_like(gyro).at[:, start:start + rows, list(plan.used)].add(dx[..., :Gu])
    # The outputs enter only as buffers whose chunk rows are overwritten.
    douts = tuple(None if o is None else jax.lax.dynamic_update_slice_in_dim(
        o, jnp.zeros((n_trials, rows, K), o.dtype), start, axis=1) for o in douts)

    return ChunkInputs(if_perturbed(dGS, perturbed.GS), if_perturbed(dE, perturbed.E),
                       if_perturbed(dPhi, perturbed.Phi), if_perturbed(ds0, perturbed.s0),
                       dcoeffs if want_coeffs else None, dgyro, dhall_v,
                       tuple(if_perturbed(d, p) for d, p in zip(douts, perturbed.outs)))
