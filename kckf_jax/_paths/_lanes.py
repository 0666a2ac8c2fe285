"""The filter over rows with the trials as lanes: every state and covariance entry an array
over trials.

A ``vmap`` of the kernel's ``step`` puts the trial axis first, so XLA's CPU loops run over the
tiny block matrices (5 x 5 for the bench robot) one trial at a time. Here the step is
``_lane_step.lane_step``: the same arithmetic written out entry by entry with the trial axis
*last*, so each operation is one loop over the lanes, and the step is a few hundred of them,
which XLA fuses.

The arithmetic is the kernel's: the prediction (Eqs. 3, 9-13), the constraint as a perfect
measurement (KCKF), one Joseph-form scalar update per joint with its fused Hall reading, the
step skipped (state kept) when its update is not finite, a missing gyro reading holding the
last one. Readings are turned into block inputs beforehand for every row at once (the Hall
model, the fusion of each pair, the process noise), so the scan carries only the state. The
reverse pass of the filter and of its innovations is written by hand (``_lanes_adjoint``).
"""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._models._blocks import ProcessNoise, Structure, block_gather, q_blocks
from .._models._chunked_scan import chunked_scan
from .._models._classes import structure
from .._models._kernel import (
    Estimate,
    FilterState,
    SensorSeries,
    block_hall,
)
from .._models._params import Params
from .._readings._prepare import prepare
from ._base import AbstractPath, PathCost, kalman_only
from ._exact_lanes import exact_lanes, exact_lanes_run
from ._lane_step import _apply, _Consts, _tri, _tri_index, lane_step, pack_tape
from ._lanes_adjoint import scan_rows


class LaneInputs(NamedTuple):
    """Every row's inputs to the lanes scans that do not depend on the state, rows first and
    trials last (``lane_inputs``): laid out once for all rows, so the scan carries only the
    state.

    Attributes:
        ts: the time steps (``T, B``).
        noise: the process noise (``T, m1, Nb, B`` each term).
        hb: each block joint's fused Hall reading (``T, m, Nb, B``).
        rb: its variance.
        vb: whether it exists.
        gyro: the gyro readings (``T, G, B``), held where missing.
    """

    ts: Float[Array, "T B"]
    noise: ProcessNoise
    hb: Float[Array, "T m Nb B"]
    rb: Float[Array, "T m Nb B"]
    vb: Bool[Array, "T m Nb B"]
    gyro: Float[Array, "T G B"]


#: The inputs of a no-op row (no time step, every reading missing): one scalar per leaf.
NO_OP_INPUTS = LaneInputs(0.0, ProcessNoise(0.0, 0.0, 0.0), 0.0, 1.0, False, jnp.nan)


def lane_inputs(params: Params, st: Structure, dt: Float[Array, "B T"],
                gyro: Float[Array, "B T G"], hall_v: Float[Array, "B T M"]) -> LaneInputs:
    """Every row's inputs to the lanes scans that do not depend on the state, for all rows and
    trials at once, rows first and trials last: the process noise and each block joint's
    fused Hall reading, its variance and validity (the kernel's ``block_inputs`` terms, every
    row laid out outside the loop)."""
    ts = jnp.moveaxis(dt, 0, 1)
    laid = jax.vmap(jax.vmap(lambda x: block_gather(st, x, in_loop=False)))
    hall = jax.vmap(jax.vmap(lambda v: block_hall(params, st, v, in_loop=False)))

    def lanes(x):  # (T, B, Nb, j) -> (T, j, Nb, B): one lane array per block coordinate
        return jnp.moveaxis(x, (1, 2, 3), (3, 2, 1))

    noise = q_blocks(params.q, params.angle_rw, params.bias_rw, ts[..., None])  # (T, B, K)
    hb, rb, vb = (lanes(x) for x in hall(jnp.moveaxis(hall_v, 0, 1)))
    return LaneInputs(ts, ProcessNoise(*(lanes(laid(n)) for n in noise)), hb, rb, vb,
                      jnp.moveaxis(gyro, (0, 1, 2), (2, 0, 1)))


class LaneState(NamedTuple):
    """The filter's state on every lane, lanes first (``FilterState``'s fields as arrays
    over lanes: ``B Nb Nz``, ``B Nb Nz Nz``, ``B G``)."""

    z: Float[Array, "B Nb Nz"]
    P: Float[Array, "B Nb Nz Nz"]
    hold: Float[Array, "B G"]


class LaneRows(NamedTuple):
    """Per row, what the filter's estimates are read from (``lane_scan``): the block states
    (``T Nz Nb B``), the covariances' upper triangles (``T n_tri Nb B``) and whether the row's
    update was skipped (``T B``)."""

    z: Float[Array, "T Nz Nb B"]
    P: Float[Array, "T X Nb B"]
    skipped: Bool[Array, "T B"]


class LaneInnovations(NamedTuple):
    """Per row, the likelihood's terms (``lane_innovations_scan``): every joint's fused Hall
    innovation, its variance and whether it was used (``T m Nb B`` each)."""

    nu: Float[Array, "T m Nb B"]
    s: Float[Array, "T m Nb B"]
    valid: Bool[Array, "T m Nb B"]


class LaneRowsInnovations(NamedTuple):
    """Per row, ``LaneRows``' fields and ``LaneInnovations``' (``lane_scan_innovations``:
    the estimates and the diagnostics' innovations from one pass, as ``kckf evaluate`` asks)."""

    z: Float[Array, "T Nz Nb B"]
    P: Float[Array, "T X Nb B"]
    skipped: Bool[Array, "T B"]
    nu: Float[Array, "T m Nb B"]
    s: Float[Array, "T m Nb B"]
    valid: Bool[Array, "T m Nb B"]


class LaneMoments(NamedTuple):
    """Per row, the smoother's terms (``lane_moments_scan``): ``LaneRows``' fields and the
    predicted moments of ``y = [z, e]`` before the row's updates (``T Ny Nb B``, and the upper
    triangle of ``S``: ``T n_tri(Ny) Nb B``)."""

    z: Float[Array, "T Nz Nb B"]
    P: Float[Array, "T X Nb B"]
    skipped: Bool[Array, "T B"]
    y: Float[Array, "T Ny Nb B"]
    S: Float[Array, "T Y Nb B"]


class LaneMomentsInnovations(NamedTuple):
    """Per row, ``LaneMoments``' fields and ``LaneInnovations``' (``lane_moments_scan(...,
    innovations=True)``: the smoother's forward pass with the diagnostics' innovations)."""

    z: Float[Array, "T Nz Nb B"]
    P: Float[Array, "T X Nb B"]
    skipped: Bool[Array, "T B"]
    y: Float[Array, "T Ny Nb B"]
    S: Float[Array, "T Y Nb B"]
    nu: Float[Array, "T m Nb B"]
    s: Float[Array, "T m Nb B"]
    valid: Bool[Array, "T m Nb B"]


class LaneRun(NamedTuple):
    """What a lanes scan returns: the final state of every lane, what it kept per row
    (``LaneRows``, ``LaneInnovations`` or ``LaneMoments``, as the scan's name says), and the
    state after ``snapshot_row`` rows where asked (else ``None``)."""

    final: LaneState
    rows: LaneRows | LaneInnovations | LaneMoments
    snapshot: LaneState | None = None


def lane_scan(params: Params, st: Structure, start: LaneState, inputs: LaneInputs,
              remat_chunk: int | None = None, snapshot_row: int | None = None) -> LaneRun:
    """The Kalman filter over ``T`` rows of ``B`` trials, trials as lanes, from ``start``:
    ``LaneRun`` with ``LaneRows``. ``snapshot_row``: also the states after that many rows."""
    return _lane_loop(params, st, start, inputs, LaneRows, remat_chunk, snapshot_row)


def lane_innovations_scan(params: Params, st: Structure, start: LaneState, inputs: LaneInputs,
                          remat_chunk: int | None = None) -> LaneRun:
    """The filter's every fused Hall innovation (the likelihood's terms; no estimates kept):
    ``LaneRun`` with ``LaneInnovations``."""
    return _lane_loop(params, st, start, inputs, LaneInnovations, remat_chunk, None)


def lane_scan_innovations(params: Params, st: Structure, start: LaneState, inputs: LaneInputs,
                          snapshot_row: int | None = None) -> LaneRun:
    """``lane_scan`` and ``lane_innovations_scan`` in one pass (no reverse pass written for
    it: the filter's estimates with their innovations, not a loss): ``LaneRun`` with
    ``LaneRowsInnovations``. ``snapshot_row``: as ``lane_scan``'s."""
    return _lane_loop(params, st, start, inputs, LaneRowsInnovations, None, snapshot_row)


def lane_moments_scan(params: Params, st: Structure, start: LaneState, inputs: LaneInputs,
                      innovations: bool = False) -> LaneRun:
    """The filter with each row's predicted moments (the smoother's forward pass): ``LaneRun``
    with ``LaneMoments`` (``innovations``: ``LaneMomentsInnovations``)."""
    keep = LaneMomentsInnovations if innovations else LaneMoments
    return _lane_loop(params, st, start, inputs, keep, None, None)


def _kept(keep: type, step, x_new, fin, vb):
    """What a row keeps of its step (``keep`` one of the row types above)."""
    nz = step.z.shape[0]
    if keep is LaneInnovations:
        return LaneInnovations(step.nu, step.s, vb & fin)
    if keep is LaneMoments:
        return LaneMoments(x_new[:nz], x_new[nz:], ~fin, step.y, step.S)
    if keep is LaneMomentsInnovations:
        return LaneMomentsInnovations(x_new[:nz], x_new[nz:], ~fin, step.y, step.S, step.nu,
                                      step.s, vb & fin)
    if keep is LaneRowsInnovations:
        return LaneRowsInnovations(x_new[:nz], x_new[nz:], ~fin, step.nu, step.s, vb & fin)
    return LaneRows(x_new[:nz], x_new[nz:], ~fin)


def _lane_loop(params: Params, st: Structure, start: LaneState, inputs: LaneInputs,
               keep: type, remat_chunk: int | None, snapshot_row: int | None) -> LaneRun:
    """The scan the three above share: the kernel's step on lanes over every row, each row
    keeping a ``keep``."""
    robot = params.robot
    z0, P0, hold0 = start
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
    rows = inputs
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

    def body(carry, row: LaneInputs, record=False):
        # The state as one array (z entries, then P's upper triangle; each (Nb, B)) and the
        # held gyro rates. ``record``: also the skipped flags and the updates' terms, for
        # the reverse pass (``_lanes_adjoint``).
        x, hold = carry[:2]
        tsb = jnp.broadcast_to(row.ts, (nb,) + row.ts.shape)
        tape = [] if record else None
        step = lane_step(st, consts, x[:nz], x[nz:], rates_of(hold), row.noise, row.hb,
                         row.rb, row.vb, tsb, tape)
        x_new = jnp.concatenate([step.z, step.P])
        fin = jnp.isfinite(x_new).all(axis=(0, 1))
        x_new = jnp.where(fin, x_new, x)
        hold = jnp.where(fin & jnp.isfinite(row.gyro), row.gyro, hold)
        new = (x_new, hold)
        if snapshot_row is not None:  # the states after row snapshot_row - 1, kept
            i, x_snap, hold_snap = carry[2:]
            take = i == snapshot_row - 1
            new += (i + 1, jnp.where(take, x_new, x_snap), jnp.where(take, hold, hold_snap))
        kept = _kept(keep, step, x_new, fin, row.vb)
        if record:
            return new, (kept, ~fin, pack_tape(tape))
        return new, kept

    x0 = jnp.stack([jnp.moveaxis(z0[:, :, i], 0, 1) for i in range(nz)]
                   + [jnp.moveaxis(P0[:, :, i, j], 0, 1) for i, j in tri])
    hold = jnp.moveaxis(hold0[:, used], 0, 1)
    carry = (x0, hold)
    if snapshot_row is not None:
        carry += (jnp.asarray(0), x0, hold)
    if remat_chunk:
        # No-op rows pad the last chunk: no time step, every reading missing.
        final, out = chunked_scan(body, carry, rows, remat_chunk,
                                  jax.tree_util.tree_leaves(NO_OP_INPUTS))
    elif keep not in (LaneRows, LaneInnovations, LaneMoments) or snapshot_row is not None:
        # Each row recomputed under reverse mode (only the carries saved): the transposed
        # body then runs as one piece (64 x 10,000 bench, float32: gradient 3.7 -> 3.0 s).
        final, out = jax.lax.scan(jax.checkpoint(body), carry, rows)
    else:  # the filter, its innovations or the smoother's forward pass: the reverse pass
        # written by hand (_lanes_adjoint)
        final, out = scan_rows(st, consts, Rm, body, x0, hold, rows)

    def states(x, h) -> LaneState:  # lanes layout -> lanes first
        z = jnp.moveaxis(x[:nz], (0, 1, 2), (2, 1, 0))
        P = jnp.zeros((z0.shape[0], nb, nz, nz), dtype)
        for (i, j), p in zip(tri, x[nz:]):
            p = jnp.moveaxis(p, 0, 1)
            P = P.at[:, :, i, j].set(p).at[:, :, j, i].set(p)
        return LaneState(z, P, hold0.at[:, used].set(jnp.moveaxis(h, 0, 1)))

    snapshot = states(*final[3:]) if snapshot_row is not None else None
    return LaneRun(states(*final[:2]), out, snapshot)


def rows_innovations(rows) -> tuple | None:
    """The innovations a scan's rows kept (``LaneRowsInnovations``,
    ``LaneMomentsInnovations``), lanes first as the sequential path gives them (``(nu, s,
    valid)``, each ``B T Nb m``); ``None`` for rows without them."""
    if not isinstance(rows, (LaneRowsInnovations, LaneMomentsInnovations)):
        return None
    return tuple(jnp.transpose(x, (3, 0, 2, 1)) for x in (rows.nu, rows.s, rows.valid))


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
        remat_chunk: checkpoint the scan in chunks of this many rows under reverse mode, and
            differentiate it with JAX's own transpose of the step. By default (``None``) the
            reverse pass is the hand-written one (``_lanes_adjoint``): it keeps every row's
            state and the updates' gains (39 numbers per block, row and trial for the bench
            robot, float32: 200 MB for 64 x 10,000 rows); the fitting step is 2x faster with it
            (benchmarks/README.md).
        exact: whether ``kckf3d`` takes it (its own step on lanes, ``_exact_lanes``; faster
            than its sequential path from one trial on, and its gradient too, by the
            hand-written reverse pass of ``_exact_adjoint``).
        exact_chunk: ``kckf3d``'s reverse pass in checkpointed chunks of this many rows. That
            pass keeps every row's covariance and gains (2.9 kB a trial-row for
            ``xyz,xyz,xyz``, float32); in chunks, each chunk's forward pass runs again in the
            reverse one and only its rows' are kept at once. ``Auto.for_loss(remat_chunk)``
            (a gradient chunked for memory) sets it. ``remat_chunk`` is the linear
            filters'.
    """

    name: ClassVar[str] = "lanes"
    min_trials: int = eqx.field(static=True, default=12)
    remat_chunk: int | None = eqx.field(static=True, default=None)
    exact: bool = eqx.field(static=True, default=True)
    exact_chunk: int | None = eqx.field(static=True, default=None)

    def applies(self, params: Params, series: SensorSeries, method: str,
                state: FilterState | None = None) -> str | None:
        if exact_lanes(method):  # kckf3d: its own step on lanes (_exact_lanes)
            return None if self.exact else (
                "kckf3d's lanes step is turned off here (Lanes.exact=False)")
        return kalman_only(method)

    def min_trials_for(self, method: str) -> int:
        """The smallest batch ``Auto`` takes this path for: ``min_trials``; for ``kckf3d`` one
        trial (its lanes step is faster than its sequential one at every batch measured, and
        compiles no longer: benchmarks/README.md, "Issue 49")."""
        return 1 if exact_lanes(method) else self.min_trials

    def batch_layout(self, n_trials: int, method: str = "kckf") -> str:
        if exact_lanes(method):  # the smoother and the likelihood of kckf3d: sequential
            return "sequential"
        why = kalman_only(method)
        if why is not None:
            raise ValueError(f"the lanes path does not apply: {why}")
        return "lanes"

    def cost(self, n_trials: int, n_rows: int) -> PathCost:
        """Compile 2.8 s; ``0.5 + 2 / B`` us a trial-row (the lanes fill with trials): fitted to
        ``benchmarks/one_shot.py``, as ``Sequential.cost``."""
        return PathCost(2.8, (0.5 + 2.0 / n_trials) * 1e-6 * n_trials * n_rows)

    def run(self, params: Params, series: SensorSeries, method: str, state: FilterState
            ) -> tuple[FilterState, Estimate]:
        return self._run(params, series, method, state, innovations=False)

    innovations_in_pass: ClassVar[bool] = True

    def run_innovations(self, params: Params, series: SensorSeries, method: str,
                        state: FilterState) -> tuple[FilterState, Estimate]:
        """``run``, the estimate carrying each row's fused Hall innovations from the same
        scan (``Estimate.innovations``: ``(nu, s, valid)``, ``B T Nb m`` as the sequential
        path gives them)."""
        return self._run(params, series, method, state, innovations=True)

    def _run(self, params: Params, series: SensorSeries, method: str, state: FilterState,
             innovations: bool) -> tuple[FilterState, Estimate]:
        dtype = state.z.dtype
        series = prepare(params, series, method, dtype)
        if exact_lanes(method):
            return exact_lanes_run(params, series, state, innovations,
                                   chunk=self.exact_chunk)
        st = structure(params.robot, method)
        start = LaneState(state.z, state.P, state.gyro_hold)
        inputs = lane_inputs(params, st, series.dt, series.gyro, series.hall_v)
        run = (lane_scan_innovations(params, st, start, inputs) if innovations
               else lane_scan(params, st, start, inputs, self.remat_chunk))
        angles, std, bias = lane_estimates(st, run.rows.z, run.rows.P)
        return FilterState(*run.final), Estimate(angles, std, bias,
                                                 jnp.moveaxis(run.rows.skipped, 0, 1),
                                                 innovations=rows_innovations(run.rows))
