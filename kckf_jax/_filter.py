"""The filters as pure one-step functions, strung together by ``jax.lax.scan``.

``step(params, state, inputs, method) -> (state, estimate)`` is the only implementation of
each method; ``run_filter`` scans it over a recording, ``jax.vmap(run_filter)`` runs many
trials, and the streaming wrapper calls it once per packet.

Methods:

* ``"kckf"``: the Kinematically Constrained KF (paper Sec. 3.2): Hall updates plus the
  forward-kinematics constraint ``sum theta = phi`` as a perfect measurement;
* ``"kf"``: the same filter without the constraint (the paper's "Std KF");
* ``"gyro"``: integrated gyro differences (Eq. 2), from zero (the neutral pose);
* ``"hall_l"``, ``"hall_r"``: one side's Hall sensor alone through Eq. 1 (a missing reading
  holds the last one); they give no torso angle.

Conventions shared with the NumPy reference in ``tests/``:

* ``inputs.dt[k] = t[k] - t[k-1]`` (``dt[0] = 0``: no prediction before the first row);
  timestamps are differenced in float64 before they reach here;
* the gyro rates of row ``k - 1`` drive the prediction from ``k - 1`` to ``k`` (Eq. 9 uses
  ``omega(k)`` to reach ``k + 1``); a missing gyro reading holds that channel's last value;
* a missing Hall reading (NaN) removes only its own measurement row at that step;
* a padded step (``dt = 0``, every reading NaN) leaves the state unchanged.

Numerics (docs/numerics.md): measurements are processed one scalar at a time (``R`` is
diagonal, so this equals the paper's joint update), each with the Joseph form; the constraint
rows are conditioned the same way with zero noise in the coordinates of ``_model.structure``.
There is no matrix inverse or LAPACK call anywhere in a step.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ._hall import hall_angle, hall_slope
from ._model import (
    FILTER_METHODS,
    block_gather,
    initial_covariance,
    predicted_moments,
    q_blocks,
    structure,
)
from ._params import Params

METHODS = ("kckf", "kf", "gyro", "hall_l", "hall_r")


class SensorSeries(eqx.Module):
    """Filter inputs: one step (no leading axis), one trial (``T``) or a batch (``B T``).

    * ``dt``: seconds since the previous row (0 for the first and for padding);
    * ``gyro``: (``G = 3 (n + 1)``) rad/s, flattened ``gyro1_x, gyro1_y, ..., gyro{n+1}_z``;
    * ``hall_v``: (``M``) V, in ``Robot.hall_names`` order. NaN marks a missing reading.
    """

    dt: Float[ArrayLike, "*T"]
    gyro: Float[ArrayLike, "*T G"]
    hall_v: Float[ArrayLike, "*T M"]


class FilterState(eqx.Module):
    """What a filter carries from one step to the next.

    For the Kalman filters ``z`` (``P x Nz``) and ``P`` (``P x Nz x Nz``) are the estimate and
    covariance of every axis block in the filter's coordinates (``_model.Structure``; use
    ``full_state`` for the paper's ``x`` and its covariance). For the baselines ``z`` holds the
    angles and ``P`` is empty. ``gyro_hold`` is the last valid rate of every gyro channel.
    """

    z: Float[Array, "*b Nz"]
    P: Float[Array, "*b Np Np"]
    gyro_hold: Float[Array, " G"]


class Estimate(eqx.Module):
    """Per-step output, in ``Robot.angle_names`` order (joint axes, then torso axes).

    ``angles`` (rad), ``angle_std`` (rad) and ``bias`` (rad/s, joint and torso biases); NaN
    where the method does not estimate a quantity.
    """

    angles: Float[Array, "*T K"]
    angle_std: Float[Array, "*T K"]
    bias: Float[Array, "*T K"]


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")


def init_state(params: Params, method: str = "kckf") -> FilterState:
    """The state before the first row: zero angles and biases, covariance from ``params``."""
    _check_method(method)
    robot = params.robot
    dtype = params.log_q.dtype
    hold = jnp.zeros(3 * robot.n_links, dtype)
    if method in FILTER_METHODS:
        st = structure(robot, method)
        P0 = initial_covariance(st, params)
        return FilterState(jnp.zeros(P0.shape[:2], dtype), P0, hold)
    n = robot.n_angles if method == "gyro" else robot.n_joint_axes
    z0 = jnp.zeros(n, dtype) if method == "gyro" else jnp.full(n, jnp.nan, dtype)
    return FilterState(z0, jnp.zeros((0, 0), dtype), hold)


def _scalar_update(
    z: Float[Array, " N"],
    P: Float[Array, "N N"],
    index: int,
    innovation: Float[Array, ""],
    r: Float[Array, ""],
    valid: Bool[Array, ""],
) -> tuple[Float[Array, " N"], Float[Array, "N N"]]:
    """Condition on ``z[index] + noise(r) = z[index] + innovation``; Joseph form, rank one.

    ``P+ = (I - k e^T) P (I - k e^T)^T + r k k^T = P - k c^T - c k^T + s k k^T`` with
    ``c = P e``, ``s = c[index] + r``, ``k = c / s``. Skipped when ``valid`` is false or the
    innovation variance ``s`` is not positive (e.g. the constraint at ``dt = 0``).
    """
    c = P[:, index]
    return joseph_rank_one(z, P, c, c[index] + r, innovation, valid)


def joseph_rank_one(
    z: Float[Array, " N"],
    P: Float[Array, "N N"],
    c: Float[Array, " N"],
    s: Float[Array, ""],
    innovation: Float[Array, ""],
    valid: Bool[Array, ""],
) -> tuple[Float[Array, " N"], Float[Array, "N N"]]:
    """A scalar measurement update in Joseph form, for any filter of the package.

    For a row ``h`` with noise ``r``: ``c = P h``, ``s = h' c + r``, ``k = c / s`` and
    ``P+ = (I - k h') P (I - k h')' + r k k' = P - k c' - c k' + s k k'``; the estimate moves by
    ``k * innovation``. Skipped (exactly, and with finite gradients) when ``valid`` is false or
    ``s`` is not positive.
    """
    ok = valid & (s > 0)
    k = jnp.where(ok, c / jnp.where(ok, s, 1.0), 0.0)
    z = z + k * jnp.where(ok, innovation, 0.0)
    P = P - jnp.outer(k, c) - jnp.outer(c, k) + s * jnp.outer(k, k)
    return z, P


def hall_measurements(
    params: Params, hall_v: Float[Array, " M"]
) -> tuple[Float[Array, " M"], Float[Array, " M"], Bool[Array, " M"]]:
    """Hall angles (rad, Eq. 1), their noise variances (rad^2) and validity for one row.

    Missing readings are replaced by 0 V *before* the model so that neither the value nor
    its gradient is NaN.
    """
    valid = jnp.isfinite(hall_v)
    v = jnp.where(valid, hall_v, 0.0)
    coeffs = params.hall_coeffs
    angle = hall_angle(v, *coeffs)
    if params.hall_noise == "voltage":
        r = (hall_slope(v, *coeffs) * params.sigma_hall_v) ** 2 + params.sigma_hall**2
    else:
        r = params.sigma_hall**2 * jnp.ones_like(v)
    return angle, r, valid


def fused_pairs(
    angle: Float[Array, " M"], r: Float[Array, " M"], valid: Bool[Array, " M"]
) -> tuple[Float[Array, " J"], Float[Array, " J"], Bool[Array, " J"]]:
    """Combine the ``l`` and ``r`` readings of every joint axis into one measurement.

    Two independent readings of the same angle are equivalent to one at their
    inverse-variance weighted mean with variance ``1 / (1/r_l + 1/r_r)``: the posterior is the
    same as after the paper's two rows (Eqs. 5, 8). A missing reading gets weight 0.
    """
    # A variance floor of 1e-12 rad^2 (6e-5 deg) keeps 1/r finite for a zero noise parameter.
    w = jnp.where(valid, 1.0 / jnp.maximum(r, 1e-12), 0.0).reshape(-1, 2)
    W = jnp.sum(w, axis=1)
    ok = W > 0
    Ws = jnp.where(ok, W, 1.0)
    h = jnp.sum(w * angle.reshape(-1, 2), axis=1) / Ws
    return h, 1.0 / Ws, ok


def block_inputs(params: Params, st, gyro_hold: Float[Array, " G"], inputs: SensorSeries):
    """One row's inputs laid out by axis block (``_model.Structure``).

    Returns ``(dt, rates, noise, hb, rb, vb)``: the time step; the rates of the previous row
    (``P x (m + 1)``, Eqs. 2, 9, 10); the process noise ``(alpha, beta, gamma)`` (Eq. 13,
    each ``P x (m + 1)``); and each block joint's fused Hall reading (rad), its variance and
    whether it exists (``P x m``, Eqs. 1, 5, 8, 20).
    """
    robot = params.robot
    dtype = gyro_hold.dtype
    dt = inputs.dt.astype(dtype)
    plus, minus = robot.rate_pairs
    rates = block_gather(st, gyro_hold[plus] - gyro_hold[minus])
    noise = tuple(block_gather(st, x)
                  for x in q_blocks(params.q, params.angle_rw, params.bias_rw, dt))
    angle, r, valid = hall_measurements(params, inputs.hall_v.astype(dtype))
    h, rh, ok = fused_pairs(angle, r, valid)
    ji = st.joint_index
    pad = ji < 0
    hb = jnp.where(pad, 0.0, h[np.maximum(ji, 0)])
    rb = jnp.where(pad, 1.0, rh[np.maximum(ji, 0)])
    vb = jnp.where(pad, False, ok[np.maximum(ji, 0)])
    return dt, rates, noise, hb, rb, vb


def block_update(st, z, P, rates, alpha, beta, gamma, hb, rb, vb, dt):
    """One axis block's predict and update (the filter's arithmetic, for one block).

    Predict ``y = [z, e]`` (Eqs. 3, 9-13); for the KCKF condition on the perfect measurement
    ``e = sum theta - phi = 0`` (Eqs. 15-19); then one scalar Joseph update per joint with its
    fused Hall reading (Eqs. 4-5, 8, 20). For fixed ``P``, ``dt`` and masks the new ``z`` is
    linear in ``(z, rates, hb)``: the fast paths (``_fast.py``) use exactly that.
    """
    y, S = predicted_moments(st, z, P, rates, (alpha, beta, gamma), dt)
    for i in range(st.n_e):
        e = st.n_z + i
        y, S = _scalar_update(y, S, e, -y[e], jnp.zeros((), z.dtype), dt > 0)
    z, P = y[: st.n_z], S[: st.n_z, : st.n_z]
    for i in range(st.m):
        z, P = _scalar_update(z, P, i, hb[i] - z[i], rb[i], vb[i])
    return z, 0.5 * (P + P.T)


def block_estimate(st, z: Float[Array, "P Nz"], P: Float[Array, "P Nz Nz"]) -> Estimate:
    """Angles, their standard deviations and biases from the block states, in angle order."""
    T = jnp.asarray(st.T, z.dtype)
    m1 = st.m + 1
    xb = jnp.sum(T[None] * z[:, None, :], axis=2)  # (P, 2m + 2): the paper's x per block
    Ta = T[:m1]
    TaP = jnp.sum(Ta[None, :, :, None] * P[:, None, :, :], axis=2)  # (P, m1, Nz)
    var = jnp.sum(TaP * Ta[None], axis=2)
    bo, so = st.block_of, st.slot_of
    return Estimate(xb[bo, so], jnp.sqrt(jnp.maximum(var[bo, so], 0.0)), xb[bo, m1 + so])


def _kalman_step(params: Params, state: FilterState, inputs: SensorSeries, method: str):
    st = structure(params.robot, method)
    dt, rates, noise, hb, rb, vb = block_inputs(params, st, state.gyro_hold, inputs)
    z, P = jax.vmap(lambda *a: block_update(st, *a, dt))(state.z, state.P, rates, *noise, hb,
                                                           rb, vb)
    gyro = inputs.gyro.astype(state.z.dtype)
    hold = jnp.where(jnp.isfinite(gyro), gyro, state.gyro_hold)
    return FilterState(z, P, hold), block_estimate(st, z, P)


def _baseline_step(params: Params, state: FilterState, inputs: SensorSeries, method: str):
    robot = params.robot
    dtype = state.z.dtype
    K, J = robot.n_angles, robot.n_joint_axes
    gyro = inputs.gyro.astype(dtype)
    nan_k = jnp.full(K, jnp.nan, dtype)
    if method == "gyro":
        plus, minus = robot.rate_pairs
        rates = state.gyro_hold[plus] - state.gyro_hold[minus]
        z = state.z + inputs.dt.astype(dtype) * rates
        angles = z
    else:
        angle, _, valid = hall_measurements(params, inputs.hall_v.astype(dtype))
        side = 0 if method == "hall_l" else 1
        z = jnp.where(valid[side::2], angle[side::2], state.z)
        angles = jnp.concatenate([z, jnp.full(K - J, jnp.nan, dtype)])
    hold = jnp.where(jnp.isfinite(gyro), gyro, state.gyro_hold)
    return FilterState(z, state.P, hold), Estimate(angles, nan_k, nan_k)


def step(
    params: Params, state: FilterState, inputs: SensorSeries, method: str = "kckf"
) -> tuple[FilterState, Estimate]:
    """One time step of ``method``: predict from the previous row, then update with this row.

    Pure and jit-friendly (``method`` must be static). ``inputs`` is one row of a
    ``SensorSeries``.
    """
    _check_method(method)
    if method in FILTER_METHODS:
        return _kalman_step(params, state, inputs, method)
    return _baseline_step(params, state, inputs, method)


def scan_filter(
    params: Params, series: SensorSeries, method: str = "kckf",
    state: FilterState | None = None, remat_chunk: int | None = None,
) -> tuple[FilterState, Estimate]:
    """``lax.scan`` of ``step`` over one trial (not jitted: the building block of
    ``run_filter`` and of the fitting loss).

    ``remat_chunk``: split the scan into chunks of this many steps and recompute each chunk's
    intermediate values in the backward pass (``jax.checkpoint``), so a gradient through
    ``T`` steps stores about ``T / remat_chunk + remat_chunk`` states instead of every
    intermediate of every step. The forward result is unchanged.
    """
    _check_method(method)
    if state is None:
        state = init_state(params, method)

    def body(carry, row):
        return step(params, carry, row, method)

    if not remat_chunk:
        return jax.lax.scan(body, state, series)
    T = series.dt.shape[0]
    c = int(remat_chunk)
    n = -(-T // c)
    pad = n * c - T
    # Padding rows (dt = 0, every reading missing) are no-op steps.
    padded = SensorSeries(
        jnp.pad(series.dt, (0, pad)),
        jnp.pad(series.gyro, ((0, pad), (0, 0)), constant_values=jnp.nan),
        jnp.pad(series.hall_v, ((0, pad), (0, 0)), constant_values=jnp.nan),
    )
    chunks = jax.tree_util.tree_map(lambda x: x.reshape((n, c) + x.shape[1:]), padded)

    @jax.checkpoint
    def chunk_body(carry, rows):
        return jax.lax.scan(body, carry, rows)

    final, est = jax.lax.scan(chunk_body, state, chunks)
    est = jax.tree_util.tree_map(lambda x: x.reshape((n * c,) + x.shape[2:])[:T], est)
    return final, est


def run_filter(
    params: Params, series: SensorSeries, method: str = "kckf", state: FilterState | None = None,
    path: str = "auto",
) -> tuple[FilterState, Estimate]:
    """Filter a whole recording: ``lax.scan`` of ``step`` over the rows of ``series``, jitted.

    Args:
        params: the filter parameters (their dtype sets the computation's precision).
        series: one trial, ``dt`` of shape (T,). Use ``filter_batch`` for a batch of padded
            trials (``jax.vmap``).
        method: one of ``METHODS``.
        state: the starting state (default ``init_state(params, method)``).
        path: how to compute it (all give the same estimates; ``docs/performance.md``):
            ``"sequential"`` (the scan of ``step``), ``"steady"`` (constant time step, no
            missing reading, constant Hall noise: the converged gain after the first rows),
            ``"parallel"`` (covariance scan, then the mean by associative scan), or
            ``"auto"`` (default: ``"steady"`` where it applies, else the sequential path on a
            CPU and the parallel path on an accelerator).

    Returns:
        The final state and an ``Estimate`` with a leading time axis.

    Example:
        >>> robot = Robot.from_spec("x,y")
        >>> params = Params.paper_defaults(robot)
        >>> series = SensorSeries(jnp.full(5, 0.01), jnp.zeros((5, 9)), jnp.ones((5, 4)))
        >>> final, est = run_filter(params, series, "kckf")
        >>> est.angles.shape
        (5, 4)
    """
    _check_method(method)
    from ._fast import plan_path

    path, verify = plan_path(params, series, method, path)
    if verify:
        final, est, ok = _run_filter_checked(params, series, method, state)
        if bool(ok):
            return final, est
        path = "sequential"  # a reading is missing: the sequential filter handles it
    return _run_filter(params, series, method, state, path)


@eqx.filter_jit
def _run_filter_checked(params, series, method, state):
    from ._fast import steady_filter_checked

    return steady_filter_checked(params, series, method, state)


@eqx.filter_jit
def _run_filter(params, series, method, state, path):
    if path == "steady":
        from ._fast import steady_filter

        return steady_filter(params, series, method, state)
    if path == "parallel":
        from ._fast import parallel_filter

        return parallel_filter(params, series, method, state)
    return scan_filter(params, series, method, state)


def filter_batch(params: Params, series: SensorSeries, method: str = "kckf",
                 path: str = "auto") -> Estimate:
    """``run_filter`` over a batch of trials (leading axis ``B``), padded to one length."""
    _check_method(method)
    from ._fast import plan_path

    path, verify = plan_path(params, series, method, path)
    if verify:
        est, ok = _filter_batch_checked(params, series, method)
        if bool(ok):
            return est
        path = "sequential"  # a reading is missing: the sequential filter handles it
    return _filter_batch(params, series, method, path)


@eqx.filter_jit
def _filter_batch_checked(params, series, method):
    from ._fast import steady_batch_checked

    return steady_batch_checked(params, series, method)


@eqx.filter_jit
def _filter_batch(params, series, method, path):
    if path == "steady":
        from ._fast import steady_batch

        return steady_batch(params, series, method)
    if path == "parallel":
        from ._fast import parallel_filter

        return jax.vmap(lambda s: parallel_filter(params, s, method)[1])(series)
    return jax.vmap(lambda s: scan_filter(params, s, method)[1])(series)


def pad_series(series: list[SensorSeries], length: int | None = None) -> SensorSeries:
    """Stack trials of uneven length into one batch; padding rows are no-op steps."""
    if not series:
        raise ValueError("pad_series: no trials given")
    T = max(int(np.shape(s.dt)[0]) for s in series) if length is None else length

    def pad(x, fill):
        x = np.asarray(x)
        if x.shape[0] > T:
            raise ValueError(f"pad_series: a trial has {x.shape[0]} rows, more than {T}")
        widths = [(0, T - x.shape[0])] + [(0, 0)] * (x.ndim - 1)
        return np.pad(x, widths, constant_values=fill)

    return SensorSeries(
        dt=np.stack([pad(s.dt, 0.0) for s in series]),
        gyro=np.stack([pad(s.gyro, np.nan) for s in series]),
        hall_v=np.stack([pad(s.hall_v, np.nan) for s in series]),
    )
