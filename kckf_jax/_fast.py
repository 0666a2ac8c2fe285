"""Faster paths of the same filter: steady-state gains and a parallel-in-time mean.

The Kalman filter's covariance does not depend on the measured values, only on the time steps,
which readings are present and their noise. So a recording can be filtered in two phases:

1. **covariance phase**: ``lax.scan`` of the covariance recursion (the very ``block_update``
   of ``_filter.py``, with the state set to zero). For fixed covariance, time step and masks the
   new estimate is *linear* in (previous estimate, rates, Hall readings), so each step is the
   affine map ``z_k = A_k z_{k-1} + B_k r_k + C_k h_k``; ``jax.linearize`` of that same
   function gives ``A_k, B_k, C_k`` exactly (no second implementation of the filter);
2. **mean phase**: the affine maps applied in turn. On a CPU a ``lax.scan`` of two tiny fused
   products costs tens of nanoseconds a row (the full step, about 35 kernels, costs two
   microseconds); for accelerators the maps are composed with ``jax.lax.associative_scan``
   (``(A2, c2) o (A1, c1) = (A2 A1, A2 c1 + c2)``): parallel in time, no inverse.

Two paths use this:

* ``"steady"``: constant time step, no missing reading and the paper's constant Hall noise
  (``hall_noise="angle"``). Then the covariance converges (to 1e-14 relative within about 4,000
  steps at 100 Hz for the paper's parameters) and the map becomes constant: the sequential
  filter runs the first ``L = HEAD_ROWS[dtype]`` rows, and the converged map serves every
  later row. If the covariance has not converged by then (relative change above
  ``STEADY_TOL``), a ``lax.cond`` falls back to the sequential filter for the whole recording,
  inside the same compiled function. A constant map is applied in chunks of ``CHUNK_ROWS``
  rows, each chunk one matrix product of its raw readings and the state entering it
  (``_chunk_operator``), the entering states solved for in nested groups (``_carries``):
  more arithmetic than a scan of the rows, but in matrix products, which XLA runs at 100-200
  GFLOP/s on a CPU, where a scan pays its loop overhead on every row.
* ``"parallel"``: anything (missing readings, uneven time steps, the voltage noise model): the
  covariance phase runs over the whole recording, the mean phase by associative scan. On a CPU
  this is slower than the sequential filter (the covariance phase costs as much, and the
  associative scan's small batched products are slow there); it is the path for accelerators,
  where the mean's sequential dependency is what limits.

Both agree with the sequential filter to 1e-8 rad in float64 (tests/test_fast.py).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._filter import (
    Estimate,
    FilterState,
    SensorSeries,
    block_estimate,
    block_inputs,
    block_update,
    fused_pairs,
    hall_measurements,
    init_state,
    scan_filter,
)
from ._hall import hall_angle
from ._model import FILTER_METHODS, structure
from ._params import Params

#: Rows the steady path filters in full before it switches to the converged map (the paper's
#: parameters converge to 1e-10 within about 2,600 rows at 100 Hz; 1e-14 within 4,000).
STEADY_STEPS = 4096
#: Rows filtered in full before the switch, per precision (at most ``STEADY_STEPS``): in
#: float32 the covariance reaches its rounding floor (``STEADY_TOL``) within about 1,000
#: rows for the paper's parameters, and switching at 2,048 rows gives the same estimates as
#: at 4,096 (to 1e-7 rad; tests/test_fast.py); float64 needs the longer head for 1e-10.
HEAD_ROWS = {np.dtype("float64"): 4096, np.dtype("float32"): 2048}
#: Relative change of the covariance over its last step below which it counts as converged.
STEADY_TOL = {np.dtype("float64"): 1e-10, np.dtype("float32"): 1e-5}
PATHS = ("auto", "sequential", "steady", "parallel")
#: Filters whose covariance converges on regular data, so that ``"auto"`` may pick the steady
#: path: in the standard KF the torso angle and its bias are unobservable (Eq. 21), their
#: variance grows without bound and the steady path would always fall back.
CONVERGING_METHODS = ("kckf",)


def steady_conditions(params: Params, series: SensorSeries, method: str,
                      readings: bool = True) -> str | None:
    """Why the steady path does not apply to these (concrete) inputs, or None if it does.

    ``series`` may be one recording or a batch (leading axes): a batch must share one
    constant time step, since ``steady_batch`` runs one covariance phase for all of it.
    Traced inputs (inside ``jit``) pass the data checks unchecked: only the static ones
    apply, and the caller vouches for the rest. ``readings=False`` checks the time steps
    only (``plan_path``: the readings are then checked by the steady path itself)."""
    if method not in FILTER_METHODS:
        return f"method {method!r} is not a Kalman filter"
    if params.hall_noise != "angle":
        return "the voltage noise model makes the Hall noise vary with the data"
    if np.ndim(series.dt) < 1 or np.shape(series.dt)[-1] < 3:
        return "fewer than three rows"
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(series)):
        return None  # under jit the values are unknown: the caller vouches for them
    dev, first = (float(x) for x in _dt_regularity(series.dt))
    if not (dev <= 1e-9 and first > 0):  # also false for a NaN step
        return ("the time step is not constant" if np.ndim(series.dt) == 1 else
                "the time step is not one constant shared by every trial")
    if not readings:
        return None
    used = tuple(int(c) for c in np.unique(np.asarray(params.robot.rate_pairs)))
    gyro_nan, hall_nan = (bool(x) for x in _readings_missing(series.gyro, series.hall_v, used))
    if gyro_nan:
        return "a gyro reading is missing"
    if hall_nan:
        return "a Hall reading is missing"
    return None


@jax.jit
def _dt_regularity(dt):
    """On the device, one small transfer back: the largest deviation of a time step (rows
    after the first) from the first trial's second one, and that step."""
    dt = jnp.reshape(dt, (-1, dt.shape[-1]))
    first = dt[0, 1]
    return jnp.max(jnp.abs(dt[:, 1:] - first)), first


@functools.partial(jax.jit, static_argnums=2)
def _readings_missing(gyro, hall_v, used: tuple[int, ...]):
    """Whether a used gyro reading or a Hall reading is missing (a pass over every reading:
    ``plan_path`` leaves this to the steady path itself)."""
    return jnp.isnan(gyro[..., np.asarray(used)]).any(), jnp.isnan(hall_v).any()


def _held_gyro(gyro: jax.Array, hold0: jax.Array) -> jax.Array:
    """Each channel's last finite value at every row (forward fill, ``hold0`` before any)."""
    T = gyro.shape[0]
    ok = jnp.isfinite(gyro)
    idx = jax.lax.cummax(jnp.where(ok, jnp.arange(T)[:, None], -1), axis=0)
    filled = jnp.take_along_axis(gyro, jnp.maximum(idx, 0), axis=0)
    return jnp.where(idx >= 0, filled, hold0[None, :])


def _maps(params: Params, st, P, row_inputs):
    """One covariance step for every block, and the affine maps of the mean (``A, B, C``)."""
    dt, _, noise, _, rb, vb = row_inputs
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

    return jax.vmap(one_block)(P, *noise, rb, vb)


def _inputs(params: Params, st, series: SensorSeries, hold0: jax.Array):
    """Every row's block inputs at once: ``(dt, rates, noise, hb, rb, vb)`` with a leading
    time axis, and the held gyro rates."""
    held = _held_gyro(series.gyro, hold0)
    prev_hold = jnp.concatenate([hold0[None], held[:-1]], axis=0)
    return jax.vmap(lambda g, row: block_inputs(params, st, g, row))(prev_hold, series), held


def _last_finite(gyro: jax.Array, hold0: jax.Array) -> jax.Array:
    """Each channel's last finite value over the rows (``hold0`` where there is none)."""
    T = gyro.shape[0]
    idx = jnp.max(jnp.where(jnp.isfinite(gyro), jnp.arange(T)[:, None], -1), axis=0)
    last = gyro[jnp.maximum(idx, 0), jnp.arange(gyro.shape[1])]
    return jnp.where(idx >= 0, last, hold0)


def _readings_maps(params: Params, st, dtype):
    """The steady path's readings as linear maps of the raw rows: block rates ``r = Jr
    g[used]`` (``P x (m + 1) x Gu``, constant) and fused Hall readings ``h = Jh angles``
    (``P x m x M``; the inverse-variance weights of ``fused_pairs`` for the constant Hall
    noise). Returns ``(used, Jr, Jh)``: ``used`` are the gyro columns the rates read."""
    robot = params.robot
    plus, minus = robot.rate_pairs
    used = np.flatnonzero(np.any(robot.rate_map != 0.0, axis=0))
    col = {int(c): i for i, c in enumerate(used)}
    Jr = np.zeros(st.angle_index.shape + (len(used),))
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

    return used, jnp.asarray(Jr, dtype), jax.jacfwd(readings)(jnp.zeros(M, dtype))


#: Rows per chunk of the steady path's mean: a chunk's estimates are one matrix product of its
#: raw readings and the state entering it (``_chunk_operator``). A longer chunk costs more
#: arithmetic per row (the product is ``L`` rows by ``L`` rows) but fewer carried states;
#: 8 measured fastest of 4, 8 and 16 for the bench and the 3D robot (docs/performance.md).
CHUNK_ROWS = 8
#: The carried states are solved for in groups of this many chunks (``_carries``: the same
#: construction one level up), until at most ``CARRY_SCAN`` remain for a plain scan.
CARRY_GROUP = 16
CARRY_SCAN = 256
#: Trial-rows per block of the steady path's mean: a block's readings and products stay in
#: cache, and estimates are written into the outputs in place.
MEAN_BLOCK = 1 << 16


def _head_rows(dtype) -> int:
    return HEAD_ROWS.get(np.dtype(dtype), STEADY_STEPS)


def _block_rows(trials: int) -> int:
    """Rows per block for ``trials`` trials: a power of two, at least 256."""
    return max(256, 1 << int(np.log2(max(MEAN_BLOCK // trials, 1))))


def _output_map(st) -> np.ndarray:
    """``Tout`` (``2K x P x Nz``): the angles, then the biases, as sums over block states."""
    Tm = np.asarray(st.T)
    K, m1 = len(st.block_of), st.m + 1
    out = np.zeros((2 * K, st.angle_index.shape[0], st.n_z))
    for k, (p, i) in enumerate(zip(st.block_of, st.slot_of)):
        out[k, p], out[K + k, p] = Tm[i], Tm[m1 + i]
    return out


def _chunk_operator(A, Wg, Wh, Tout, L: int):
    """``L`` rows of the converged map as matrices.

    Row ``j`` of the chunk: ``z_j = A z_{j-1} + Wg g_{j-1} + Wh h_j`` (``A`` ``P x Nz x Nz``,
    ``Wg`` ``Gu x P x Nz``, ``Wh`` ``M x P x Nz``; ``g`` the used gyro columns, ``h`` the
    Hall angles). The chunk is entered with the *prediction* ``s = A z_{-1} + Wg g_{-1}``,
    so it needs no reading from before it; then ``z_j = A^j s + sum_{i<=j} A^{j-i} Wh h_i +
    sum_{i<j} A^{j-1-i} Wg g_i``. With ``x`` the chunk's readings row by row (``[g_i, h_i]``,
    flattened) and ``s`` flattened (``q = P Nz``), all as row vectors:

    * the chunk's estimates (``L x 2K``, flattened, ``Tout`` giving them from a state):
      ``[x, s] @ GS``;
    * the prediction entering the next chunk: ``s @ Phi + x @ E`` (``Phi`` is ``A^L``).

    Returns ``(GS, E, Phi)``: ``(L I + q) x (L 2K)``, ``L I x q`` and ``q x q``."""
    P, nz, _ = A.shape
    dtype = A.dtype
    Tout = jnp.asarray(Tout, dtype)

    def mv(X, W):  # (..., P, Nz, Nz) times (..., F, P, Nz) -> (..., F, P, Nz); broadcast
        return sum(X[..., None, :, :, b] * W[..., :, :, b, None] for b in range(nz))

    pw = [jnp.broadcast_to(jnp.eye(nz, dtype=dtype), (P, nz, nz))]
    for _ in range(L):  # A^0 .. A^L, per block (broadcast products: 5 x 5 dots are slow)
        pw.append(_apply(A, pw[-1]))
    pw = jnp.stack(pw)
    Hh = mv(pw, Wh[None])  # A^d Wh, d = 0 .. L
    Hg = mv(pw, Wg[None])  # A^d Wg
    j, i = np.arange(L)[:, None], np.arange(L)[None, :]

    def toeplitz(H, lag):  # (j, i, F, P, Nz): H[j - i - lag] where j - i >= lag, else 0
        d = j - i - lag
        return jnp.where((d >= 0)[:, :, None, None, None], H[np.clip(d, 0, L)], 0.0)

    Z = jnp.concatenate([toeplitz(Hg, 1), toeplitz(Hh, 0)], axis=2)  # (j, i, I, P, Nz)
    n_in = Z.shape[2]
    G = jnp.einsum("jifpa,opa->ifjo", Z, Tout).reshape(L * n_in, -1)
    S = jnp.einsum("jpab,opa->pbjo", pw[:L], Tout).reshape(P * nz, -1)
    # The next chunk's prediction: A z_{L-1} + Wg g_{L-1}, i.e. A^{L-1-i} Wg for g_i and
    # A^{L-i} Wh for h_i.
    back = L - 1 - np.arange(L)
    E = jnp.concatenate([Hg[back], Hh[back + 1]], axis=1).reshape(L * n_in, P * nz)
    # As a right multiplier of the flattened row vector: block diagonal, transposed blocks.
    Phi = jnp.zeros((P, nz, P, nz), dtype).at[np.arange(P), :, np.arange(P), :].set(
        jnp.swapaxes(pw[L], 1, 2)).reshape(P * nz, P * nz)
    return jnp.concatenate([G, S]), E, Phi


def _matrix_powers(Phi, n: int):
    """``Phi^0 .. Phi^n`` stacked."""
    out = [jnp.eye(Phi.shape[0], dtype=Phi.dtype)]
    for _ in range(n):
        out.append(out[-1] @ Phi)
    return jnp.stack(out)


def _carries(Phi, e, s0):
    """The states entering each chunk: ``s_{c+1} = s_c Phi + e_c`` (row vectors) for ``e``
    ``(B, C, q)`` from ``s0`` ``(B, q)``. Returns ``(ss, s_C)``, ``ss`` ``(B, C, q)`` the
    state entering chunk ``c``.

    At most ``CARRY_SCAN`` chunks: a scan. More: in groups of ``n = CARRY_GROUP`` chunks,
    ``s_{gn+j} = t_g Phi^j + sum_{i<j} e_{gn+i} Phi^{j-1-i}``: one matrix product gives every
    group's local part and its end, and the states ``t_g`` entering the groups are the same
    problem with ``Phi^n``, ``n`` times shorter."""
    B, C, q = e.shape
    if C <= CARRY_SCAN:
        def f(s, e_c):
            return sum(s[:, i, None] * Phi[i] for i in range(q)) + e_c, s

        s_end, ss = jax.lax.scan(f, s0, jnp.moveaxis(e, 1, 0))
        return jnp.moveaxis(ss, 0, 1), s_end
    n = CARRY_GROUP
    groups = C // n + 1  # at least one padded chunk, so s_C is some group's local state
    e = jnp.pad(e, ((0, 0), (0, groups * n - C), (0, 0)))
    pw = _matrix_powers(Phi, n)
    i, j = np.arange(n)[:, None], np.arange(n)[None, :]
    local = jnp.where((i < j)[..., None, None], pw[np.clip(j - 1 - i, 0, n)], 0.0)
    local = jnp.transpose(local, (0, 2, 1, 3)).reshape(n * q, n * q)
    end = pw[n - 1 - np.arange(n)].reshape(n * q, q)
    y = e.reshape(B, groups, n * q) @ jnp.concatenate([local, end], axis=1)
    tt, _ = _carries(pw[n], y[..., n * q:], s0)
    ss = y[..., :n * q] + tt @ jnp.transpose(pw[:n], (1, 0, 2)).reshape(q, n * q)
    ss = ss.reshape(B, groups * n, q)
    return ss[:, :C], ss[:, C]


def _apply(A, z):
    """``A z`` for ``A`` ``(P, Nz, Nz)`` and ``z`` ``(P, Nz, B)``, as broadcast products (a
    batched 5 x 5 dot is slower on a CPU)."""
    return sum(A[:, :, j, None] * z[:, j, None, :] for j in range(A.shape[-1]))


@jax.custom_vjp
def _row_scan(As, U, z0):
    """``z_k = A_k z_{k-1} + U_k`` over the rows (``As`` ``(n, P, Nz, Nz)``, ``U`` ``(n, P, Nz,
    B)``, ``z0`` ``(P, Nz, B)``); returns every ``z_k``, ``(n, P, Nz, B)``.

    Reverse mode by hand: the cotangents ``g_k = dZ_k + A_{k+1}^T g_{k+1}`` are one reverse
    scan of the same shape as the forward one, and ``dA_k = g_k z_{k-1}^T`` one product over
    all rows after it. Measured on the 3D robot's head (64 trials x 2,048 rows, float32):
    77 ms for the gradient against 106 ms with JAX's own transpose of the scan."""
    def row(z, r):
        A_k, u = r
        z = _apply(A_k, z) + u
        return z, z

    return jax.lax.scan(row, z0, (As, U))[1]


def _row_scan_fwd(As, U, z0):
    Z = _row_scan(As, U, z0)
    return Z, (As, Z, z0)


def _row_scan_bwd(res, dZ):
    As, Z, z0 = res
    # g_k = dZ_k + A_{k+1}^T g_{k+1}: scan the rows backwards, carrying A_k^T g_k.
    def row(carry, r):
        At_k, dz = r
        g = dz + carry
        return _apply(At_k, g), g

    dz0, G = jax.lax.scan(row, jnp.zeros_like(z0), (jnp.swapaxes(As, 2, 3), dZ), reverse=True)
    Zprev = jnp.concatenate([z0[None], Z[:-1]])
    return jnp.einsum("kpaB,kpbB->kpab", G, Zprev), G, dz0


_row_scan.defvjp(_row_scan_fwd, _row_scan_bwd)


def _chunk_blocks(plan, body, carry, reverse: bool = False):
    """``body(carry, start, m)`` over the chunk rows of ``plan`` in blocks of ``R`` rows (a
    ``fori_loop`` of the full blocks, then the remainder; the other way round, last block
    first, when ``reverse``)."""
    _, n_chunks, L, R, _, _ = plan
    rows = n_chunks * L
    full = rows // R
    if rows % R and reverse:
        carry = body(carry, full * R, rows - full * R)
    if full:
        carry = jax.lax.fori_loop(
            0, full, lambda i, c: body(c, ((full - 1 - i) if reverse else i) * R, R), carry)
    if rows % R and not reverse:
        carry = body(carry, full * R, rows - full * R)
    return carry


def _readings(coeffs, gyro, hall_v, used, start, n):
    """Rows ``start .. start + n`` of the raw readings as the steady map reads them: the used
    gyro columns, then the Hall angles (``B x n x I``)."""
    g = jax.lax.dynamic_slice_in_dim(gyro, start, n, axis=1)[..., list(used)]
    h = jax.lax.dynamic_slice_in_dim(hall_v, start, n, axis=1)
    return jnp.concatenate([g, hall_angle(h, *coeffs)], axis=2)


def _chunk_readings(plan, coeffs, gyro, hall_v, start, m):
    """Rows ``F + start .. F + start + m`` of the readings, as chunks: ``(B, m / L, L I)``."""
    F, _, L, _, used, _ = plan
    x = _readings(coeffs, gyro, hall_v, used, F + start, m)
    return x.reshape(x.shape[0], m // L, -1)


def _chunk_forward(plan, GS, E, Phi, s0, coeffs, gyro, hall_v, outs, keep: bool = False):
    """The converged chunks (``_steady_mean``) in one pass over the readings: per block of
    rows, each chunk's part of the state entering the next (``x @ E``), the states entering
    the block's chunks from the one entering the block (``_carries``), and the estimates
    (``x @ Gx + s @ Gs``), written into ``outs``; the block's readings are read and their Hall
    exponentials computed once, while they are in cache. Returns ``(outs, s_end, ss)``:
    ``ss`` (``B x n_chunks x q``) the state entering every chunk when ``keep`` (the reverse
    mode's residual), else None."""
    F, n_chunks, L, _, _, K = plan
    Bt, q = s0.shape
    n_x = GS.shape[0] - q
    Gx, Gs = GS[:n_x], GS[n_x:]

    def block(carry, start, m):
        outs, s, ss = carry
        x = _chunk_readings(plan, coeffs, gyro, hall_v, start, m)
        s_k, s = _carries(Phi, x @ E, s)
        y = (x @ Gx + s_k @ Gs).reshape(Bt, m, 2 * K)
        outs = tuple(jax.lax.dynamic_update_slice_in_dim(o, y[..., k * K:(k + 1) * K], F + start,
                                                         axis=1) for k, o in enumerate(outs))
        if keep:
            ss = jax.lax.dynamic_update_slice_in_dim(ss, s_k, start // L, axis=1)
        return outs, s, ss

    ss0 = jnp.zeros((Bt, n_chunks, q), s0.dtype) if keep else None
    return _chunk_blocks(plan, block, (outs, s0, ss0))


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _chunk_rows(plan, GS, E, Phi, s0, coeffs, gyro, hall_v, outs):
    """The converged chunks of ``_steady_mean``, with a hand-written reverse mode.

    ``plan = (F, n_chunks, L, R, used, K)``: the chunks start at row ``F``, ``R`` rows per
    block. Returns ``(outs, s_end)``: ``outs`` (angles, biases) with the chunk rows filled in,
    ``s_end`` the prediction entering the row after the last chunk.

    The map is linear in the readings and the entering state, so its reverse mode is the same
    kind of computation run backwards: the cotangents of the entering states follow
    ``a_c = a_{c+1} Phi^T + dss_c`` (``_carries`` with ``Phi^T``, in reverse order), and those of
    the readings and operators are matrix products block by block, the Hall coefficients'
    accumulated block by block while the block is in cache. Symbolic zeros tell which inputs
    are differentiated and which outputs carry a cotangent: a loss on the angles alone skips
    the biases' columns, and the readings' own cotangents (full-size arrays) are formed only
    when something differentiates with respect to the data. Left to JAX (the transposed
    ``fori_loop``s and ``dynamic_update_slice``s), the 3D robot's fitting gradient (64 x
    10,000 rows, float32) took 1.66 s instead of 1.06 s (docs/performance.md)."""
    outs, s_end, _ = _chunk_forward(plan, GS, E, Phi, s0, coeffs, gyro, hall_v, outs)
    return outs, s_end


def _chunk_rows_fwd(plan, GS, E, Phi, s0, coeffs, gyro, hall_v, outs):
    val = jax.tree_util.tree_map(lambda p: p.value, (GS, E, Phi, s0, coeffs, gyro, hall_v, outs))
    perturbed = jax.tree_util.tree_map(lambda p: p.perturbed, (coeffs, gyro, hall_v))
    GS, E, Phi, s0, coeffs, gyro, hall_v, outs = val
    outs, s_end, ss = _chunk_forward(plan, GS, E, Phi, s0, coeffs, gyro, hall_v, outs, keep=True)
    # Which inputs need a cotangent, as pytree structure (residuals hold arrays only).
    need = tuple(() if any(jax.tree_util.tree_leaves(p)) else None for p in perturbed)
    return (outs, s_end), (GS, E, Phi, ss, coeffs, gyro, hall_v, need)


def _is_zero(x) -> bool:
    return isinstance(x, jax.custom_derivatives.SymbolicZero)


def _chunk_rows_bwd(plan, res, ct):
    GS, E, Phi, ss, coeffs, gyro, hall_v, need = res
    want_coeffs, want_gyro, want_hall = (n is not None for n in need)
    want_x = want_gyro or want_hall
    douts, ds_end = ct
    F, n_chunks, L, _, used, K = plan
    Bt, C, q = ss.shape
    n_x = GS.shape[0] - q
    n_in = n_x // L
    Gu = len(used)
    rows = C * L
    dtype = ss.dtype
    # Only the outputs that carry a cotangent: their columns of GS (chunk-row j, output o).
    live = [k for k, o in enumerate(douts) if not _is_zero(o)]
    cols = np.asarray([j * 2 * K + k * K + o for j in range(L) for k in live for o in range(K)],
                      dtype=int)
    GSl = GS[:, cols]
    Gx, Gs = GSl[:n_x], GSl[n_x:]
    ds_end = jnp.zeros((Bt, q), dtype) if _is_zero(ds_end) else ds_end

    # One pass over the blocks, last first. ``a`` is the cotangent of the state entering the
    # chunk after the block: a_c = a_{c+1} Phi^T + dss_c within it (``_carries`` with Phi^T,
    # in reverse order); chunk c's e_c enters s_{c+1}, so its cotangent is a_{c+1}.
    def block(carry, start, m):
        dx, dGS, dE, dPhi, dcoeffs, a = carry
        c0, c = start // L, m // L
        x, readings_vjp = jax.vjp(
            lambda cf: _chunk_readings(plan, cf, gyro, hall_v, start, m), coeffs)
        s_k = jax.lax.dynamic_slice_in_dim(ss, c0, c, axis=1)
        if live:
            dy = jnp.concatenate([jax.lax.dynamic_slice_in_dim(douts[k], F + start, m, axis=1)
                                  for k in live], axis=2).reshape(Bt, c, -1)
            rr, a = _carries(Phi.T, (dy @ Gs.T)[:, ::-1], a)
        else:
            rr, a = _carries(Phi.T, jnp.zeros((Bt, c, q), dtype), a)
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
            dx = jax.lax.dynamic_update_slice_in_dim(dx, dx_k.reshape(Bt, m, n_in), start,
                                                     axis=1)
        return dx, dGS, dE, dPhi, dcoeffs, a

    dx0 = jnp.zeros((Bt, rows, n_in), dtype) if want_x else None
    dx, dGSl, dE, dPhi, dcoeffs, ds0 = _chunk_blocks(
        plan, block, (dx0, jnp.zeros_like(GSl), jnp.zeros_like(E), jnp.zeros_like(Phi),
                      jax.tree_util.tree_map(jnp.zeros_like, coeffs), ds_end), reverse=True)
    dGS = jnp.zeros_like(GS).at[:, cols].set(dGSl)
    dgyro = dhall_v = None
    if want_hall:
        h = jax.lax.dynamic_slice_in_dim(hall_v, F, rows, axis=1)
        _, h_vjp = jax.vjp(lambda h: hall_angle(h, *coeffs), h)
        dhall_v = jax.lax.dynamic_update_slice_in_dim(jnp.zeros_like(hall_v),
                                                      h_vjp(dx[..., Gu:])[0], F, axis=1)
    if want_gyro:
        dgyro = jnp.zeros_like(gyro).at[:, F:F + rows, list(used)].add(dx[..., :Gu])
    # The outputs enter only as buffers whose chunk rows are overwritten.
    douts = tuple(None if _is_zero(o) else jax.lax.dynamic_update_slice_in_dim(
        o, jnp.zeros((Bt, rows, K), o.dtype), F, axis=1) for o in douts)
    return (dGS, dE, dPhi, ds0, dcoeffs if want_coeffs else None, dgyro, dhall_v, douts)


_chunk_rows.defvjp(_chunk_rows_fwd, _chunk_rows_bwd, symbolic_zeros=True)


def _steady_mean(params: Params, st, series: SensorSeries, z0, hold0, maps, head=None,
                 done=None):
    """The mean of the steady path over a batch of trials, chunk by chunk as matrix products.

    Row ``k``: ``z_k = A z_{k-1} + g_{k-1}[used] Wg + hall_angle(V_k) Wh`` with ``(A, B, C)``
    the converged map (``maps``), ``Wg = B Jr`` and ``Wh = C Jh`` (the rate differences and
    the fusion of each Hall pair folded into the map); the first rows use per-row maps
    ``head = (As, Bs, Cs)`` (leading row axis) when given: a scan of those rows, every trial
    at once.

    Chunks of ``L = CHUNK_ROWS`` rows (``_chunk_operator``), one pass over the readings in
    blocks (``_chunk_forward``): per block, each chunk's contribution to the state entering
    the next one (one matrix product of the readings), the states entering the block's
    chunks (``_carries``), and the estimates (one matrix product of the readings and that
    state); the last 1 to ``L`` rows go row by row, which gives the final state. A
    sequential scan of the rows does far less arithmetic but costs XLA's loop overhead per
    row; the matrix products run at 100-200 GFLOP/s here. The converged rows go in blocks of
    ``_block_rows`` rows, so a block's readings stay in cache and estimates are written into
    the outputs in place.

    ``series`` has a leading trial axis ``B``; ``z0`` is ``(B, P, Nz)`` and ``hold0``
    ``(B, G)``. ``done = (angles, biases)`` (``(B, F, K)`` each) are the estimates of the
    first ``F`` rows, already filtered: the mean starts at row ``F`` (with ``z0`` and
    ``hold0`` the state there) and the outputs are filled in after them. Returns ``(angles,
    biases, z_last)``, angles and biases ``(B, T, K)``."""
    dtype = z0.dtype
    used, Jr, Jh = _readings_maps(params, st, dtype)
    Bt, P, nz = z0.shape
    q = P * nz
    T = series.dt.shape[1]
    K = len(st.block_of)
    L = CHUNK_ROWS
    Gu = len(used)
    Tout = _output_map(st)

    def weights(B, C):  # (..., P, nz, m1), (..., P, nz, m) -> (..., Gu, P, nz), (..., M, P, nz)
        return (jnp.einsum("...pij,pjg->...gpi", B, Jr), jnp.einsum("...pij,pjm->...mpi", C, Jh))

    def readings(start, n):  # rows start .. start + n: (B, n, I), used gyro columns first
        return _readings(params.hall_coeffs, series.gyro, series.hall_v, used, start, n)

    def write(outs, y, start):  # y (B, n, 2K): angles then biases
        return tuple(jax.lax.dynamic_update_slice_in_dim(o, y[..., k * K:(k + 1) * K], start,
                                                         axis=1) for k, o in enumerate(outs))

    def entering(A_k, Wg_k, z, g):  # the prediction entering a row: (B, q)
        return (jnp.einsum("pab,Bpb->Bpa", A_k, z)
                + jnp.einsum("Bg,gpa->Bpa", g, Wg_k)).reshape(Bt, q)

    A, B, C = maps
    Wg, Wh = weights(B, C)
    out = jnp.zeros((Bt, T, K), dtype)
    F = 0
    outs = (out, out)
    if done is not None:
        F = done[0].shape[1]
        outs = tuple(jax.lax.dynamic_update_slice_in_dim(out, d, 0, axis=1) for d in done)
    g_prev = hold0[:, used]
    if head is None:
        s = entering(A, Wg, z0, g_prev)
    else:
        As, Wgs, Whs = (head[0],) + weights(head[1], head[2])
        Lh = As.shape[0]
        # Per-row maps: a scan of the rows, every trial at once (trials innermost). Chunk
        # operators would need building per chunk, which costs more than these rows.
        x = jnp.moveaxis(readings(F, Lh), 0, -1)  # (Lh, I, B)
        g = jnp.concatenate([g_prev.T[None], x[:-1, :Gu]])  # each row's previous rates
        U = (jnp.einsum("kfB,kfpa->kpaB", g, Wgs)
             + jnp.einsum("kfB,kfpa->kpaB", x[:, Gu:], Whs))  # (Lh, P, Nz, B)

        Z = _row_scan(As, U, jnp.moveaxis(z0, 0, -1))
        z = Z[-1]
        y = jnp.einsum("kpaB,opa->Bko", Z, jnp.asarray(Tout, dtype))
        outs = write(outs, y, F)
        F = F + Lh
        z0, g_prev = jnp.moveaxis(z, -1, 0), x[-1, :Gu].T
        s = entering(A, Wg, z0, g_prev)
    # The converged rows: C whole chunks, then the last 1 .. L rows one by one.
    n = T - F
    n_chunks = (n - 1) // L
    GS, E, Phi = _chunk_operator(A, Wg, Wh, Tout, L)
    if n_chunks:
        plan = (F, n_chunks, L, _block_rows(Bt), tuple(int(u) for u in used), K)
        outs, s = _chunk_rows(plan, GS, E, Phi, s, params.hall_coeffs, series.gyro,
                              series.hall_v, outs)
        F = F + n_chunks * L
    x = readings(F, T - F)
    z = s.reshape(Bt, P, nz) + jnp.einsum("Bm,mpa->Bpa", x[:, 0, Gu:], Wh)
    zs = [z]
    for k in range(1, T - F):
        z = entering(A, Wg, z, x[:, k - 1, :Gu]).reshape(Bt, P, nz) + jnp.einsum(
            "Bm,mpa->Bpa", x[:, k, Gu:], Wh)
        zs.append(z)
    y = jnp.einsum("kBpa,opa->Bko", jnp.stack(zs), jnp.asarray(Tout, dtype))
    outs = write(outs, y, F)
    return outs[0], outs[1], z


def _covariance_phase(params: Params, st, P0, head):
    """``lax.scan`` of the covariance over the rows of ``head``: per row the new covariance
    and the mean's affine maps ``A`` (``P x Nz x Nz``) and ``BC = [B, C]``."""
    # Rematerialised under reverse mode: storing every intermediate of every row as a
    # residual costs more here than computing the row again (the gradient through this
    # phase, 2,048 rows in float32: bench 67 -> 35 ms, 3D 192 -> 151 ms).
    @jax.checkpoint
    def body(P, row):
        P_new, A, B, C = _maps(params, st, P, row)
        return P_new, (P_new, A, jnp.concatenate([B, C], axis=2))

    return jax.lax.scan(body, P0, head)


def _mean_scan(A, BC, w, z0, parallel: bool):
    """``z_k = A_k z_{k-1} + BC_k w_k`` over the rows of ``w`` (``A``/``BC`` per row, or one
    map for all rows when they lack the time axis). A plain ``lax.scan`` of two tiny fused
    products costs tens of nanoseconds a row on a CPU; ``parallel`` composes the maps with an
    associative scan instead (for accelerators)."""
    const = A.ndim == 3
    if parallel:
        T = w.shape[0]
        As = jnp.broadcast_to(A, (T,) + A.shape) if const else A
        BCs = jnp.broadcast_to(BC, (T,) + BC.shape) if const else BC
        c = jnp.sum(BCs * w[:, :, None, :], axis=3)
        c = c.at[0].add(jnp.sum(As[0] * z0[:, None, :], axis=2))

        def combine(a, b):
            A1, c1 = a
            A2, c2 = b
            return (jnp.einsum("...ij,...jk->...ik", A2, A1),
                    jnp.einsum("...ij,...j->...i", A2, c1) + c2)

        return jax.lax.associative_scan(combine, (As, c))[1]

    def body(z, row):
        A_k, BC_k, w_k = (A, BC, row) if const else row
        z = jnp.sum(A_k * z[:, None, :], axis=2) + jnp.sum(BC_k * w_k[:, None, :], axis=2)
        return z, z

    return jax.lax.scan(body, z0, w if const else (A, BC, w))[1]


def _two_phase(params: Params, series: SensorSeries, method: str, state: FilterState,
               cov_steps: int, parallel: bool = False):
    """Covariance phase over the first ``cov_steps`` rows, then the mean; rows beyond
    ``cov_steps`` reuse the last maps. Also returns the covariance's last relative change
    (the steady path's convergence measure)."""
    st = structure(params.robot, method)
    dtype = state.z.dtype
    series = jax.tree_util.tree_map(lambda x: jnp.asarray(x).astype(dtype), series)
    T = series.dt.shape[0]
    (dt, rates, noise, hb, rb, vb), held = _inputs(params, st, series, state.gyro_hold)
    head = jax.tree_util.tree_map(lambda x: x[:cov_steps], (dt, rates, noise, hb, rb, vb))
    P_last, (Ps, As, BCs) = _covariance_phase(params, st, state.P, head)
    change = (jnp.max(jnp.abs(Ps[-1] - Ps[-2])) / jnp.max(jnp.abs(Ps[-1])) if cov_steps > 1
              else jnp.zeros((), dtype))
    w = jnp.concatenate([rates, hb], axis=2)  # (T, P, m + 1 + m)
    z = _mean_scan(As, BCs, w[:cov_steps], state.z, parallel)
    if cov_steps < T:
        z = jnp.concatenate([z, _mean_scan(As[-1], BCs[-1], w[cov_steps:], z[-1], parallel)])
    est = jax.vmap(lambda zk, Pk: block_estimate(st, zk, Pk))(z[:cov_steps], Ps)
    if cov_steps < T:
        tail = jax.vmap(lambda zk: block_estimate(st, zk, Ps[-1]))(z[cov_steps:])
        est = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), est, tail)
    final = FilterState(z[-1], P_last, held[-1])
    return final, est, change


def _steady_head(params: Params, series: SensorSeries, method: str, state: FilterState,
                 remat_chunk: int | None = None):
    """The steady path's first part: the sequential filter over the first
    ``HEAD_ROWS[dtype]`` rows, the converged map after them and the covariance's relative
    change there (the switch test). Returns ``(series, mid, est_head, (P_ss, A, B, C),
    change)`` with ``series`` cast to the state's dtype."""
    dtype = state.z.dtype
    L = _head_rows(dtype)
    st = structure(params.robot, method)
    series = jax.tree_util.tree_map(lambda x: jnp.asarray(x).astype(dtype), series)
    head = jax.tree_util.tree_map(lambda x: x[:L], series)
    mid, est_head = scan_filter(params, head, method, state, remat_chunk)
    (row0, _) = _inputs(params, st, jax.tree_util.tree_map(lambda x: x[L:L + 1], series),
                        mid.gyro_hold)
    row0 = jax.tree_util.tree_map(lambda x: x[0], row0)
    P_ss, A, B, C = _maps(params, st, mid.P, row0)
    change = jnp.max(jnp.abs(P_ss - mid.P)) / jnp.max(jnp.abs(P_ss))
    return series, mid, est_head, (P_ss, A, B, C), change


def _steady_tail(params: Params, series: SensorSeries, method: str, mid: FilterState,
                 est_head: Estimate, maps) -> tuple[FilterState, Estimate]:
    """The steady path's second part: the converged map over the rows after the head."""
    T = series.dt.shape[0]
    L = est_head.angles.shape[0]
    st = structure(params.robot, method)
    P_ss, A, B, C = maps
    one = jax.tree_util.tree_map(lambda x: x[None], series)
    angles, bias, z = _steady_mean(params, st, one, mid.z[None], mid.gyro_hold[None], (A, B, C),
                                   done=(est_head.angles[None], est_head.bias[None]))
    angles, bias, z = angles[0], bias[0], z[0]
    # The covariance (so the std) is constant from here on.
    std = block_estimate(st, z, P_ss).angle_std
    std = jnp.concatenate([est_head.angle_std, jnp.broadcast_to(std, (T - L,) + std.shape)])
    held = _last_finite(series.gyro[L:], mid.gyro_hold)
    return FilterState(z, P_ss, held), Estimate(angles, std, bias)


def _fallback_chunk(T: int) -> int:
    """Remat chunk (about sqrt(T)) of the sequential fallback inside the steady path's
    ``lax.cond``. Under reverse mode a ``cond`` returns the residuals of both branches (the
    branch not taken fills its own with zeros), so an unchunked fallback made every gradient
    through the steady path allocate and fill the sequential filter's residuals for every
    step: the 3D robot's 64 x 10,000-row gradient took 4.2 s instead of 0.9 s."""
    return max(int(np.ceil(np.sqrt(T))), 1)


def _tol(dtype) -> float:
    return STEADY_TOL.get(np.dtype(dtype), 1e-5)


def steady_filter(params: Params, series: SensorSeries, method: str = "kckf",
                  state: FilterState | None = None) -> tuple[FilterState, Estimate]:
    """The steady path: the sequential filter for the first ``HEAD_ROWS[dtype]`` rows (where
    the covariance converges), then the converged affine map for the rest (``_steady_mean``).
    Recordings of at most ``STEADY_STEPS`` rows take the sequential filter. Falls back to the
    sequential filter for every row (``lax.cond``, same compiled function) when the covariance
    is still moving at that point. Requires what ``steady_conditions`` checks."""
    return steady_filter_checked(params, series, method, state)[:2]


def steady_filter_checked(params: Params, series: SensorSeries, method: str = "kckf",
                          state: FilterState | None = None):
    """``steady_filter`` and whether its result stands: False when the converged map met a
    missing (or overflowing) reading, which the caller must then filter sequentially
    (``plan_path``). True when the sequential branch ran (it handles anything)."""
    if state is None:
        state = init_state(params, method)
    if series.dt.shape[0] <= STEADY_STEPS:
        return scan_filter(params, series, method, state) + (jnp.array(True),)
    return _steady_filter(params, series, method, state)


def _steady_filter(params, series, method, state):
    series, mid, est_head, maps, change = _steady_head(params, series, method, state)
    # The tail runs inside the branch: a branch that only passed on arrays computed before
    # the cond would copy every estimate (a third of the path's time for long recordings).

    def steady():
        final, est = _steady_tail(params, series, method, mid, est_head, maps)
        return final, est, jnp.isfinite(final.z).all()

    def sequential():
        final, est = scan_filter(params, series, method, state,
                                 _fallback_chunk(series.dt.shape[0]))
        return final, est, jnp.array(True)

    return jax.lax.cond(change <= _tol(state.z.dtype), steady, sequential)


def steady_batch(params: Params, series: SensorSeries, method: str = "kckf",
                 remat_chunk: int | None = None) -> Estimate:
    """The steady path over a batch of regular trials (leading axis): every trial has the same
    time steps, readings and noise, so its covariance is the same; the covariance phase runs
    once for the whole batch (the first ``HEAD_ROWS[dtype]`` rows), and the trials only apply
    the affine maps, all at once (``_steady_mean``). One fallback decision for the whole batch
    (a per-trial ``lax.cond`` under ``vmap`` would run both branches).

    ``remat_chunk`` applies to the sequential fallback only (``scan_filter``; default
    ``_fallback_chunk``).
    """
    return steady_batch_checked(params, series, method, remat_chunk)[0]


def steady_batch_checked(params: Params, series: SensorSeries, method: str = "kckf",
                         remat_chunk: int | None = None) -> tuple[Estimate, jax.Array]:
    """``steady_batch`` and whether its result stands (as ``steady_filter_checked``)."""
    T = series.dt.shape[1]
    state = init_state(params, method)
    dtype = state.z.dtype

    def sequential(chunk=remat_chunk or _fallback_chunk(T)):
        return (jax.vmap(lambda s: scan_filter(params, s, method, state, chunk)[1])(series),
                jnp.array(True))

    if T <= STEADY_STEPS:
        return sequential(remat_chunk)
    L = _head_rows(dtype)
    st = structure(params.robot, method)
    series = jax.tree_util.tree_map(lambda x: jnp.asarray(x).astype(dtype), series)
    # Trial 0's time steps, masks and noise stand for every trial's (regular batch).
    (dt, rates, noise, hb, rb, vb), _ = _inputs(
        params, st, jax.tree_util.tree_map(lambda x: x[0, : L + 1], series), state.gyro_hold)
    head = jax.tree_util.tree_map(lambda x: x[:L], (dt, rates, noise, hb, rb, vb))
    P_L, (Ps, As, BCs) = _covariance_phase(params, st, state.P, head)
    row = jax.tree_util.tree_map(lambda x: x[L], (dt, rates, noise, hb, rb, vb))
    P_ss, A, B, C = _maps(params, st, P_L, row)
    change = jnp.max(jnp.abs(P_ss - P_L)) / jnp.max(jnp.abs(P_ss))
    m1 = st.m + 1
    head_maps = (As, BCs[..., :m1], BCs[..., m1:])
    std_head = jax.vmap(lambda Pk: block_estimate(st, jnp.zeros(Pk.shape[:2], dtype),
                                                  Pk).angle_std)(Ps)
    std_tail = block_estimate(st, jnp.zeros(P_ss.shape[:2], dtype), P_ss).angle_std

    Bt = series.dt.shape[0]
    z0 = jnp.broadcast_to(state.z, (Bt,) + state.z.shape)
    hold0 = jnp.broadcast_to(state.gyro_hold, (Bt,) + state.gyro_hold.shape)

    def steady():  # inside the branch, as in steady_filter
        angles, bias, z = _steady_mean(params, st, series, z0, hold0, (A, B, C), head_maps)
        std = jnp.concatenate([std_head, jnp.broadcast_to(std_tail, (T - L,) + std_tail.shape)])
        return Estimate(angles, jnp.broadcast_to(std, angles.shape), bias), jnp.isfinite(z).all()

    return jax.lax.cond(change <= _tol(dtype), steady, sequential)


def choose_path(params: Params, series: SensorSeries, method: str, path: str = "auto") -> str:
    """The path ``run_filter`` takes: ``path`` itself unless ``"auto"``, which picks
    ``"steady"`` when it applies to these concrete inputs, the recording is longer than
    ``STEADY_STEPS`` and the method's covariance converges (``CONVERGING_METHODS``), else
    ``"parallel"`` on an accelerator and ``"sequential"`` on a CPU."""
    if path not in PATHS:
        raise ValueError(f"path must be one of {', '.join(PATHS)}, got {path!r}")
    if path == "steady":
        why = steady_conditions(params, series, method)
        if why is not None:
            raise ValueError(f"path='steady' does not apply: {why}; use path='sequential'")
    if path != "auto":
        return path
    if method not in CONVERGING_METHODS:
        return "sequential"
    if isinstance(series.dt, jax.core.Tracer):
        return "sequential"
    if series.dt.shape[-1] > STEADY_STEPS and _all_steady(params, series, method):
        return "steady"
    return "parallel" if jax.default_backend() != "cpu" else "sequential"


def _all_steady(params, series, method, readings: bool = True) -> bool:
    return steady_conditions(params, series, method, readings) is None


def plan_path(params: Params, series: SensorSeries, method: str,
              path: str = "auto") -> tuple[str, bool]:
    """``(path, verify)`` for ``run_filter`` and ``filter_batch``: ``choose_path`` without
    its pass over every reading. For ``"auto"`` on concrete inputs the readings are not
    checked beforehand (that pass read the whole recording, 10-20 % of the steady path's
    time); ``verify`` then says the caller must run the checked steady path
    (``steady_filter_checked``, ``steady_batch_checked``) and take the sequential path if it
    reports a non-finite state. A missing reading makes the steady path's state NaN from its
    row on: every product of the map propagates it, so the final state shows it."""
    traced = any(isinstance(x, jax.core.Tracer)
                 for x in jax.tree_util.tree_leaves((params, series)))
    if path != "auto" or method not in CONVERGING_METHODS or traced:
        # Under a transformation (grad of a loss, say) the check's outcome is a tracer:
        # check the (concrete) readings beforehand instead.
        return choose_path(params, series, method, path), False
    if series.dt.shape[-1] > STEADY_STEPS and _all_steady(params, series, method, False):
        return "steady", True
    return choose_path(params, series, method, path), False


def parallel_filter(params: Params, series: SensorSeries, method: str = "kckf",
                    state: FilterState | None = None) -> tuple[FilterState, Estimate]:
    """The parallel path: covariance phase over every row, mean by an associative scan."""
    if state is None:
        state = init_state(params, method)
    final, est, _ = _two_phase(params, series, method, state, series.dt.shape[0], parallel=True)
    return final, est


def converged_map(params: Params, method: str, P: Float[Array, "P Nz Nz"],
                  dt: Float[Array, ""]):
    """The steady path's map for one packet at a time (the streaming filter's host path).

    For the block covariance ``P`` before a step of ``dt`` with every reading present,
    returns ``(P_new, A, Wg, Wh, std)``: the covariance after the step, the block map ``A``
    (``P x Nz x Nz``), the input maps on the used gyro columns of the previous packet (``Gu x
    P x Nz``) and on the Hall angles of this one (``M x P x Nz``), and the angles' standard
    deviations. When ``P`` has converged, ``P_new = P`` and every later packet with the same
    ``dt`` and every reading is the affine map ``z -> A z + g Wg + angle Wh``.
    """
    st = structure(params.robot, method)
    dtype = P.dtype
    robot = params.robot
    inputs = SensorSeries(dt.astype(dtype), jnp.zeros(3 * robot.n_links, dtype),
                          jnp.zeros(robot.n_hall, dtype))
    row = block_inputs(params, st, jnp.zeros(3 * robot.n_links, dtype), inputs)
    P_new, A, B, C = _maps(params, st, P, row)
    _, Jr, Jh = _readings_maps(params, st, dtype)
    Wg = jnp.einsum("pij,pjg->gpi", B, Jr)
    Wh = jnp.einsum("pij,pjm->mpi", C, Jh)
    std = block_estimate(st, jnp.zeros(P.shape[:2], dtype), P_new).angle_std
    return P_new, A, Wg, Wh, std
