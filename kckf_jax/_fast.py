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
  filter runs the first ``L = min(T, STEADY_STEPS)`` rows, and the converged map serves every
  later row. If the covariance has not converged by then (relative change above
  ``STEADY_TOL``), a ``lax.cond`` falls back to the sequential filter for the whole recording,
  inside the same compiled function.
* ``"parallel"``: anything (missing readings, uneven time steps, the voltage noise model): the
  covariance phase runs over the whole recording, the mean phase by associative scan. On a CPU
  this is slower than the sequential filter (the covariance phase costs as much, and the
  associative scan's small batched products are slow there); it is the path for accelerators,
  where the mean's sequential dependency is what limits.

Both agree with the sequential filter to 1e-8 rad in float64 (tests/test_fast.py).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

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
from ._model import FILTER_METHODS, block_gather, structure
from ._params import Params

#: Rows the steady path filters in full before it switches to the converged map (the paper's
#: parameters converge to 1e-10 within about 2,600 rows at 100 Hz; 1e-14 within 4,000).
STEADY_STEPS = 4096
#: Relative change of the covariance over its last step below which it counts as converged.
STEADY_TOL = {np.dtype("float64"): 1e-10, np.dtype("float32"): 1e-5}
PATHS = ("auto", "sequential", "steady", "parallel")


def steady_conditions(params: Params, series: SensorSeries, method: str) -> str | None:
    """Why the steady path does not apply to these (concrete) inputs, or None if it does."""
    if method not in FILTER_METHODS:
        return f"method {method!r} is not a Kalman filter"
    if params.hall_noise != "angle":
        return "the voltage noise model makes the Hall noise vary with the data"
    dt = np.asarray(series.dt, np.float64)
    if dt.ndim != 1 or dt.shape[0] < 3:
        return "fewer than three rows"
    if np.max(np.abs(dt[1:] - dt[1])) > 1e-9 or not dt[1] > 0:
        return "the time step is not constant"
    used = np.asarray(params.robot.rate_pairs).ravel()
    if np.isnan(np.asarray(series.gyro)[:, used]).any():
        return "a gyro reading is missing"
    if np.isnan(np.asarray(series.hall_v)).any():
        return "a Hall reading is missing"
    return None


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

        def col(i, which):
            args = list(zeros)
            args[which] = args[which].at[i].set(1.0)
            return lin(*args)[0]

        A = jnp.stack([col(i, 0) for i in range(nz)], axis=1)
        B = jnp.stack([col(i, 1) for i in range(m1)], axis=1)
        C = jnp.stack([col(i, 2) for i in range(m)], axis=1)
        return P_new, A, B, C

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


def _rates_and_readings(params: Params, st, series: SensorSeries, hold0: jax.Array):
    """For rows with every used gyro reading present (the steady path): each row's block
    rates from the previous row and its fused Hall readings, ``(T, P, m + 1)`` and
    ``(T, P, m)``; vectorised over rows, without the general path's forward fill."""
    plus, minus = params.robot.rate_pairs
    prev = jnp.concatenate([hold0[None], series.gyro[:-1]], axis=0)
    rates = jax.vmap(lambda g: block_gather(st, g[plus] - g[minus]))(prev)
    h, _, _ = jax.vmap(lambda v: fused_pairs(*hall_measurements(params, v)))(series.hall_v)
    ji = st.joint_index
    return rates, jnp.where(ji < 0, 0.0, h[:, np.maximum(ji, 0)])


def _covariance_phase(params: Params, st, P0, head):
    """``lax.scan`` of the covariance over the rows of ``head``: per row the new covariance
    and the mean's affine maps ``A`` (``P x Nz x Nz``) and ``BC = [B, C]``."""
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


def _steady_parts(params: Params, series: SensorSeries, method: str, state: FilterState,
                  remat_chunk: int | None = None):
    """The steady path without its fallback: ``(final, estimate, relative covariance change
    at the switch)``. ``series`` must be longer than ``STEADY_STEPS`` rows."""
    T = series.dt.shape[0]
    L = STEADY_STEPS
    st = structure(params.robot, method)
    dtype = state.z.dtype
    series = jax.tree_util.tree_map(lambda x: jnp.asarray(x).astype(dtype), series)
    head = jax.tree_util.tree_map(lambda x: x[:L], series)
    tail = jax.tree_util.tree_map(lambda x: x[L:], series)
    mid, est_head = scan_filter(params, head, method, state, remat_chunk)
    (row0, _) = _inputs(params, st, jax.tree_util.tree_map(lambda x: x[:1], tail),
                        mid.gyro_hold)
    row0 = jax.tree_util.tree_map(lambda x: x[0], row0)
    rates, hb = _rates_and_readings(params, st, tail, mid.gyro_hold)
    held = _last_finite(tail.gyro, mid.gyro_hold)[None]
    P_ss, A, B, C = _maps(params, st, mid.P, row0)
    change = jnp.max(jnp.abs(P_ss - mid.P)) / jnp.max(jnp.abs(P_ss))
    w = jnp.concatenate([rates, hb], axis=2)
    z = _mean_scan(A, jnp.concatenate([B, C], axis=2), w, mid.z, parallel=False)
    # Outputs: angles and biases are linear in z; the covariance (so the std) is constant.
    one = block_estimate(st, z[0], P_ss)
    Tm = jnp.asarray(st.T, dtype)
    xb = jnp.einsum("ij,tpj->tpi", Tm, z)
    m1 = st.m + 1
    bo, so = st.block_of, st.slot_of
    est_tail = Estimate(xb[:, bo, so], jnp.broadcast_to(one.angle_std, (T - L,) +
                                                        one.angle_std.shape),
                        xb[:, bo, m1 + so])
    est = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), est_head, est_tail)
    return FilterState(z[-1], P_ss, held[-1]), est, change


def _tol(dtype) -> float:
    return STEADY_TOL.get(np.dtype(dtype), 1e-5)


def steady_filter(params: Params, series: SensorSeries, method: str = "kckf",
                  state: FilterState | None = None) -> tuple[FilterState, Estimate]:
    """The steady path: the sequential filter for the first ``STEADY_STEPS`` rows (where the
    covariance converges), then the converged affine map for the rest. Falls back to the
    sequential filter for every row (``lax.cond``, same compiled function) when the covariance
    is still moving at that point. Requires what ``steady_conditions`` checks."""
    if state is None:
        state = init_state(params, method)
    if series.dt.shape[0] <= STEADY_STEPS:
        return scan_filter(params, series, method, state)
    final, est, change = _steady_parts(params, series, method, state)
    return jax.lax.cond(change <= _tol(state.z.dtype), lambda: (final, est),
                        lambda: scan_filter(params, series, method, state))


def steady_batch(params: Params, series: SensorSeries, method: str = "kckf",
                 remat_chunk: int | None = None) -> Estimate:
    """The steady path over a batch of regular trials (leading axis): every trial has the same
    time steps, readings and noise, so its covariance is the same; the covariance phase runs
    once for the whole batch, and each trial only applies the affine maps (a scan of two tiny
    products). One fallback decision for the whole batch (a per-trial ``lax.cond`` under
    ``vmap`` would run both branches).

    ``remat_chunk`` applies to the sequential fallback only (``scan_filter``).
    """
    T = series.dt.shape[1]
    state = init_state(params, method)
    dtype = state.z.dtype

    def sequential():
        return jax.vmap(lambda s: scan_filter(params, s, method, state, remat_chunk)[1])(series)

    if T <= STEADY_STEPS:
        return sequential()
    L = STEADY_STEPS
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
    BC = jnp.concatenate([B, C], axis=2)
    std_head = jax.vmap(lambda Pk: block_estimate(st, jnp.zeros(Pk.shape[:2], dtype),
                                                  Pk).angle_std)(Ps)
    std_tail = block_estimate(st, jnp.zeros(P_ss.shape[:2], dtype), P_ss).angle_std
    Tm = jnp.asarray(st.T, dtype)
    m1 = st.m + 1
    bo, so = st.block_of, st.slot_of

    def one(trial):
        r, h = _rates_and_readings(params, st, trial, state.gyro_hold)
        w = jnp.concatenate([r, h], axis=2)
        z_head = _mean_scan(As, BCs, w[:L], state.z, parallel=False)
        z = jnp.concatenate([z_head, _mean_scan(A, BC, w[L:], z_head[-1], parallel=False)])
        xb = jnp.einsum("ij,tpj->tpi", Tm, z)
        return xb[:, bo, so], xb[:, bo, m1 + so]

    angles, bias = jax.vmap(one)(series)
    std = jnp.concatenate([std_head, jnp.broadcast_to(std_tail, (T - L,) + std_tail.shape)])
    est = Estimate(angles, jnp.broadcast_to(std, angles.shape), bias)
    return jax.lax.cond(change <= _tol(dtype), lambda: est, sequential)


def choose_path(params: Params, series: SensorSeries, method: str, path: str = "auto") -> str:
    """The path ``run_filter`` takes: ``path`` itself unless ``"auto"``, which picks
    ``"steady"`` when it applies to these concrete inputs (and the recording is longer than
    ``STEADY_STEPS``), else ``"parallel"`` on an accelerator and ``"sequential"`` on a CPU."""
    if path not in PATHS:
        raise ValueError(f"path must be one of {', '.join(PATHS)}, got {path!r}")
    if path == "steady":
        why = steady_conditions(params, series, method)
        if why is not None:
            raise ValueError(f"path='steady' does not apply: {why}; use path='sequential'")
    if path != "auto":
        return path
    if method not in FILTER_METHODS:
        return "sequential"
    if isinstance(series.dt, jax.core.Tracer):
        return "sequential"
    if series.dt.shape[-1] > STEADY_STEPS and _all_steady(params, series, method):
        return "steady"
    return "parallel" if jax.default_backend() != "cpu" else "sequential"


def _all_steady(params, series, method) -> bool:
    dt = np.asarray(series.dt)
    if dt.ndim == 1:
        return steady_conditions(params, series, method) is None
    return all(steady_conditions(params, jax.tree_util.tree_map(lambda x, b=b: np.asarray(x)[b],
                                                                series), method) is None
               for b in range(dt.shape[0]))


def parallel_filter(params: Params, series: SensorSeries, method: str = "kckf",
                    state: FilterState | None = None) -> tuple[FilterState, Estimate]:
    """The parallel path: covariance phase over every row, mean by an associative scan."""
    if state is None:
        state = init_state(params, method)
    final, est, _ = _two_phase(params, series, method, state, series.dt.shape[0], parallel=True)
    return final, est
