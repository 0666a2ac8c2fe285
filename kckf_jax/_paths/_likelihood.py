"""The likelihood of the Hall readings, and the consistency figures built from the same
innovations.

The filter's innovations are the readings it did not predict: for each joint axis, the fused
reading of its two Hall sensors minus the predicted angle, with variance ``s`` (the
``StepMoments`` of the kernel's step). The two sensors of a joint read the same angle, so
their readings are equivalent to their fused mean and their difference, which is independent
of the state; and a voltage is read, not an angle, so the density of the voltage has Eq. 1's
slope as a factor. The negative log-likelihood of every Hall voltage given the earlier ones is
therefore

    sum over fused readings  1/2 log(2 pi s) + nu^2 / (2 s)
  + sum over complete pairs  1/2 log(2 pi v) + d^2 / (2 v)     (d = h_l - h_r, v = r_l + r_r)
  - sum over readings        log |d theta / d V|

(missing readings left out), and it needs no motion capture: the training objective of
dynamax and cuthbert, here for the constrained filter and learned sensor curves.

The innovations of a batch come from the lanes path's scan (``_paths/_lanes.py``, trials as
lanes: the fast machinery of the RMSE loss on recorded-like data), those of one trial or a few
from the kernel's step (``_smooth.filter_moments``); the two are the same arithmetic.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._models._classes import AbstractModel, init_states, structure
from .._models._hall import hall_slope
from .._models._kernel import SensorSeries, hall_measurements
from .._models._params import Params
from .._readings._prepare import prepare
from .._readings._stats import chi2_quantile
from . import AbstractPath, as_path
from ._lanes import LaneState, lane_innovations_scan, lane_inputs
from ._smooth import filter_moments


def _pair_terms(params: Params, hall_v: Float[Array, "*B T M"]):
    """The state-free terms: each complete pair's difference term and each reading's slope
    (``-log |d theta / d V|``), summed, and the number of readings."""
    dtype = params.log_q.dtype
    v = jnp.asarray(hall_v, dtype)
    angle, r, valid = jax.vmap(lambda row: hall_measurements(params, row))(
        v.reshape(-1, v.shape[-1]))
    pair_ok = valid[:, 0::2] & valid[:, 1::2]
    d = jnp.where(pair_ok, angle[:, 0::2] - angle[:, 1::2], 0.0)
    var = jnp.where(pair_ok, r[:, 0::2] + r[:, 1::2], 1.0)
    pairs = jnp.where(pair_ok, 0.5 * jnp.log(2 * math.pi * var) + 0.5 * d**2 / var, 0.0)
    slope = jnp.abs(hall_slope(jnp.where(valid, v.reshape(-1, v.shape[-1]), 0.0),
                               *params.hall_coeffs))
    # The floor keeps the log finite at a flat stretch of a fitted curve.
    jac = jnp.where(valid, -jnp.log(jnp.maximum(slope, jnp.finfo(dtype).tiny)), 0.0)
    return jnp.sum(pairs) + jnp.sum(jac), jnp.sum(valid)


def innovations(params: Params, series: SensorSeries, method: str = "kckf"):
    """Every fused Hall innovation of one trial: ``(nu, s, valid)``, each ``T x Nb x m``."""
    _, _, _, mom = filter_moments(params, series, method)
    return mom.nu, mom.s, mom.valid


def lane_innovations(params: Params, batch: SensorSeries, method: str = "kckf",
                     remat_chunk: int | None = None):
    """Every fused Hall innovation of a batch (``B T``) from the lanes path's scan:
    ``LaneInnovations`` ``(nu, s, valid)``, each ``T x m x Nb x B`` (``innovations``' terms,
    another layout)."""
    st = structure(params.robot, method)
    state = init_states(params, method, jnp.shape(batch.dt)[0])
    dtype = state.z.dtype
    series = prepare(params, batch, method, dtype)
    run = lane_innovations_scan(params, st, LaneState(state.z, state.P, state.gyro_hold),
                                lane_inputs(params, st, series.dt, series.gyro, series.hall_v),
                                remat_chunk)
    return run.rows


def hall_nll(params: Params, series: SensorSeries, method: str | AbstractModel = "kckf",
             path: str | AbstractPath = "auto") -> Float[Array, ""]:
    """The negative log-likelihood (nats) of every Hall voltage of ``series`` (one trial ``T``
    or a batch ``B T``) given the earlier ones, per reading (the module docstring).
    ``path`` lays out the innovations' scan (``AbstractPath.batch_layout``: ``"lanes"``, or
    a ``vmap`` of the one-trial scan; ``"auto"``: lanes for a batch of at least
    ``Lanes.min_trials`` trials); the same value either way, to rounding."""
    batch = jax.tree_util.tree_map(jnp.asarray, series)
    if batch.dt.ndim == 1:
        batch = jax.tree_util.tree_map(lambda x: x[None], batch)
    # Prepared once (``_prepare.prepare``: the readings the filter uses), for both kinds of term.
    batch = prepare(params, batch, method, params.log_q.dtype)
    if as_path(path).batch_layout(batch.dt.shape[0], method) == "lanes":
        nu, s, valid = lane_innovations(params, batch, method)
    else:
        nu, s, valid = jax.vmap(lambda x: innovations(params, x, method))(batch)
    s_safe = jnp.where(valid, s, 1.0)
    fused = jnp.where(valid, 0.5 * jnp.log(2 * math.pi * s_safe) + 0.5 * nu**2 / s_safe, 0.0)
    rest, n = _pair_terms(params, batch.hall_v)
    return (jnp.sum(fused) + rest) / jnp.maximum(n, 1)


def chi2_interval(n: int, dof: int = 1) -> tuple[float, float]:
    """The 95 % interval of the mean of ``n`` independent chi-square variables of ``dof``
    degrees of freedom each (Wilson and Hilferty's approximation of the quantiles of
    ``chi2(n dof) / n``)."""
    k = max(int(n) * dof, 1)
    lo, hi = (chi2_quantile(k, z) / max(int(n), 1) for z in (-1.959963984540054,
                                                             1.959963984540054))
    return lo, hi


def consistency(terms: np.ndarray, independent: bool = True) -> dict:
    """``{"mean", "lo95", "hi95", "count"}`` of normalised squared errors (each chi-square
    with one degree of freedom for a consistent filter).

    The interval is that of the mean of ``count`` independent terms: right for the
    innovations (a consistent filter's are white), too narrow for the estimation errors of
    successive rows, which are correlated; ``independent=False`` leaves it out (``None``)."""
    x = np.asarray(terms, np.float64)
    x = x[np.isfinite(x)]
    lo, hi = chi2_interval(x.size) if independent else (None, None)
    return {"mean": float(x.mean()) if x.size else float("nan"), "lo95": lo, "hi95": hi,
            "count": int(x.size)}
