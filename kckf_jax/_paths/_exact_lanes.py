"""``kckf3d`` on lanes: its step (``_models/_exact_entries``, written entry by entry for any
trailing lane axes) run over a batch with the trials as the last axis, as ``_lanes.py`` runs
the linear KCKF's.

The sequential path runs the one-trial step under ``vmap``: every trial's 3 x 3 rotations and
21 x 21 covariance become small arrays of their own. Here each entry of the state and of the
covariance is one array over the trials, and every operation an elementwise one over them.
Each row also gives its angles' variances (the torso's through the chain's Jacobian at the
new state) and its Hall innovations; the angles and biases are read from the kept states
afterwards, the rows and trials as lanes (``entry_estimate``). The same estimates as the
sequential path to rounding (tests/test_exact_lanes.py). Its reverse pass is written by hand
(``_exact_adjoint``: a fitting step of 64 x 10,000 rows half the sequential path's), so a
fitting loss takes it too (``Auto.for_loss``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._models import _exact
from .._models._blocks import q_blocks
from .._models._chunked_scan import chunked_scan
from .._models._classes import ExactKCKF, model_of
from .._models._exact_entries import angle_variances, entry_estimate, entry_step
from .._models._kalman import fused_pairs
from .._models._kernel import Estimate, FilterInput, FilterState, hall_measurements
from .._models._params import Params
from ._exact_adjoint import exact_scan_rows


def exact_lanes(method: str) -> bool:
    """Whether ``method``'s lanes step is this module's (``kckf3d``) rather than the linear
    filters' (``_lanes``)."""
    return isinstance(model_of(method), ExactKCKF)


# ---------------------------------------------------------------------------- the scan
class ExactLaneInputs(NamedTuple):
    """Every row's inputs, rows first and trials last: the time step (``T B``), the gyro row
    (``T G B``; NaN where missing), each joint coordinate's fused Hall reading, its variance
    and whether it exists (``T J B``), and the process noise's diagonal (``T Nz B``)."""

    ts: Float[Array, "T B"]
    gyro: Float[Array, "T G B"]
    h: Float[Array, "T J B"]
    rh: Float[Array, "T J B"]
    vh: Bool[Array, "T J B"]
    q: Float[Array, "T Nz B"]


class ExactLaneRows(NamedTuple):
    """What each row keeps: the new state (``T Nz B``), its angles' variances (``T K B``), the
    Hall innovations, their variances and use (``T J B``) and whether the row was skipped."""

    z: Float[Array, "T Nz B"]
    var: Float[Array, "T K B"]
    nu: Float[Array, "T J B"]
    s: Float[Array, "T J B"]
    valid: Bool[Array, "T J B"]
    skipped: Bool[Array, "T B"]


def exact_lane_inputs(params: Params, model: _exact.ExactModel, series: FilterInput
                      ) -> ExactLaneInputs:
    """The rows of a batch (``series`` prepared, leading axis ``B``) laid out for the scan."""
    dtype = params.log_q.dtype
    angle, r, valid = jax.vmap(jax.vmap(lambda v: hall_measurements(params, v)))(
        series.hall_v.astype(dtype))
    h, rh, vh = jax.vmap(jax.vmap(fused_pairs))(angle, r, valid)
    dt = series.dt.astype(dtype)
    alpha = q_blocks(params.q, params.angle_rw, params.bias_rw, dt[..., None])[0]
    bias_q, bias_rw2, _ = _exact.gyro_bias_noise(model, params.q, params.bias_rw,
                                                 params.p0_bias)
    q = _exact.process_noise_diagonal(model, alpha, bias_q, bias_rw2, dt)

    def lanes(x):  # (B, T, ...) -> (T, ..., B)
        return jnp.moveaxis(x, 0, -1)

    return ExactLaneInputs(lanes(dt), lanes(series.gyro.astype(dtype)), lanes(h), lanes(rh),
                           lanes(vh), lanes(q))


def exact_lane_scan(model: _exact.ExactModel, z0: Float[Array, "B Nz"],
                    P0: Float[Array, "B Nz Nz"], hold0: Float[Array, "B G"],
                    inputs: ExactLaneInputs, by_hand: bool = True, chunk: int | None = None
                    ) -> tuple[tuple, ExactLaneRows]:
    """The filter over every row, trials as lanes: the final ``(z, P, hold)`` (lanes first)
    and the rows' ``ExactLaneRows``. Its reverse pass is the hand-written one
    (``_exact_adjoint``), which keeps every row's covariance; with ``chunk``, in checkpointed
    chunks of that many rows (each chunk's forward pass run again in the reverse one, and
    only its rows' covariances kept at once). ``by_hand=False``: JAX's own, each row
    recomputed (the tests' reference)."""

    def body(carry, row: ExactLaneInputs, record: bool = False):
        z, P, hold = carry
        tape = [] if record else None
        zn, Pn, nu, s = entry_step(model, z, P, hold, row.ts, row.h, row.rh, row.vh, row.q,
                                   tape=tape)
        fin = jnp.isfinite(zn).all(axis=0) & jnp.isfinite(Pn).all(axis=(0, 1))
        zn = jnp.where(fin[None], zn, z)
        Pn = jnp.where(fin[None, None], Pn, P)
        hold = jnp.where(fin[None] & jnp.isfinite(row.gyro), row.gyro, hold)
        kept = ExactLaneRows(zn, angle_variances(model, zn, Pn), nu, s, row.vh & fin[None],
                             ~fin)
        if record:
            return (zn, Pn, hold), (kept, (jnp.stack([k for k, _ in tape]),
                                           jnp.stack([w for _, w in tape])))
        return (zn, Pn, hold), kept

    carry = (jnp.moveaxis(z0, 0, -1), jnp.moveaxis(P0, 0, -1), jnp.moveaxis(hold0, 0, -1))
    if by_hand and chunk:
        # No-op rows pad the last chunk: no time step, no process noise, no reading.
        fill = jax.tree_util.tree_leaves(ExactLaneInputs(0.0, jnp.nan, 0.0, 1.0, False, 0.0))
        (z, P, hold), rows = chunked_scan(
            lambda c, r: exact_scan_rows(model, body, *c, r), carry, inputs, chunk, fill,
            per_row=False)
    elif by_hand:
        (z, P, hold), rows = exact_scan_rows(model, body, *carry, inputs)
    else:
        (z, P, hold), rows = jax.lax.scan(jax.checkpoint(body), carry, inputs)
    return (jnp.moveaxis(z, -1, 0), jnp.moveaxis(P, -1, 0), jnp.moveaxis(hold, -1, 0)), rows


def exact_lanes_run(params: Params, series: FilterInput, state: FilterState,
                    innovations: bool = False, by_hand: bool = True,
                    chunk: int | None = None) -> tuple[FilterState, Estimate]:
    """``kckf3d`` over a prepared batch (leading axis ``B``) from ``state`` (one block):
    the final state and the estimates (``B T K``), with the innovations where asked
    (``B T 1 J``, as the sequential path gives them). ``by_hand``, ``chunk``:
    ``exact_lane_scan``'s."""
    model = _exact.exact_model(params.robot)
    inputs = exact_lane_inputs(params, model, series)
    (z, P, hold), rows = exact_lane_scan(model, state.z[:, 0], state.P[:, 0],
                                         state.gyro_hold, inputs, by_hand, chunk)
    # The angles and biases of every row at once, the rows and trials as lanes (their
    # variances came from the scan: the covariances are not kept).
    zs = jnp.moveaxis(rows.z, 0, 1)  # (Nz, T, B)
    zeros = jnp.zeros((model.n_z, model.n_z) + zs.shape[1:], zs.dtype)
    angles, _, bias = (jnp.moveaxis(x, (0, 1, 2), (2, 1, 0))
                       for x in entry_estimate(model, zs, zeros))
    std = jnp.sqrt(jnp.maximum(jnp.moveaxis(rows.var, -1, 0), 0.0))
    innov = None
    if innovations:
        innov = tuple(jnp.moveaxis(x, -1, 0)[:, :, None] for x in (rows.nu, rows.s,
                                                                   rows.valid))
    est = Estimate(angles, std, bias, jnp.moveaxis(rows.skipped, -1, 0), innovations=innov)
    return FilterState(z[:, None], P[:, None], hold), est


__all__ = ["exact_lane_inputs", "exact_lane_scan", "exact_lanes", "exact_lanes_run"]
