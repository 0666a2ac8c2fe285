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
from ._model import FILTER_METHODS, initial_covariance, predicted_moments, structure
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

    ``z`` and ``P`` are the estimate and covariance in the filter's coordinates (for the
    baselines, ``z`` holds the angles and ``P`` is empty); ``gyro_hold`` the last valid rate
    of every gyro channel.
    """

    z: Float[Array, " Nz"]
    P: Float[Array, "Np Np"]  # Np = Nz for the Kalman filters, 0 for the baselines
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
        return FilterState(jnp.zeros(st.n_z, dtype), initial_covariance(st, params), hold)
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
    s = c[index] + r
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


def _kalman_step(params: Params, state: FilterState, inputs: SensorSeries, method: str):
    st = structure(params.robot, method)
    dtype = state.z.dtype
    dt = inputs.dt.astype(dtype)
    # Predict y = [z, e] with the held rates of the previous row (Eqs. 9-13).
    y, S = predicted_moments(st, params, state.z, state.P, state.gyro_hold, dt)
    # KCKF: condition on the perfect measurements e = sum theta - phi = 0 (Eqs. 15-19).
    for i in range(st.n_e):
        e = st.n_z + i
        y, S = _scalar_update(y, S, e, -y[e], jnp.zeros((), dtype), dt > 0)
    z, P = y[: st.n_z], S[: st.n_z, : st.n_z]
    # Hall updates, one sensor at a time (Eqs. 4-5, 8, 20).
    angle, r, valid = hall_measurements(params, inputs.hall_v.astype(dtype))
    for m, j in enumerate(st.hall_index):
        z, P = _scalar_update(z, P, j, angle[m] - z[j], r[m], valid[m])
    P = 0.5 * (P + P.T)
    gyro = inputs.gyro.astype(dtype)
    hold = jnp.where(jnp.isfinite(gyro), gyro, state.gyro_hold)
    T = jnp.asarray(st.T, dtype)
    K = params.robot.n_angles
    Ta = T[:K]
    var = jnp.sum((Ta @ P) * Ta, axis=1)
    est = Estimate(Ta @ z, jnp.sqrt(jnp.maximum(var, 0.0)), T[K:] @ z)
    return FilterState(z, P, hold), est


def _baseline_step(params: Params, state: FilterState, inputs: SensorSeries, method: str):
    robot = params.robot
    dtype = state.z.dtype
    K, J = robot.n_angles, robot.n_joint_axes
    gyro = inputs.gyro.astype(dtype)
    nan_k = jnp.full(K, jnp.nan, dtype)
    if method == "gyro":
        rates = jnp.asarray(robot.rate_map, dtype) @ state.gyro_hold
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


@eqx.filter_jit
def run_filter(
    params: Params, series: SensorSeries, method: str = "kckf", state: FilterState | None = None
) -> tuple[FilterState, Estimate]:
    """Filter a whole recording: ``lax.scan`` of ``step`` over the rows of ``series``.

    Args:
        params: the filter parameters (their dtype sets the computation's precision).
        series: one trial, ``dt`` of shape (T,). Use ``jax.vmap`` over a batch of padded
            trials (``filter_batch`` does it for you).
        method: one of ``METHODS``.
        state: the starting state (default ``init_state(params, method)``).

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
    if state is None:
        state = init_state(params, method)

    def body(carry, row):
        return step(params, carry, row, method)

    return jax.lax.scan(body, state, series)


def filter_batch(params: Params, series: SensorSeries, method: str = "kckf") -> Estimate:
    """``run_filter`` over a batch of trials (leading axis ``B``), padded to one length."""
    _check_method(method)
    return jax.vmap(lambda s: run_filter(params, s, method)[1])(series)


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
