"""The filter's kernel: its types and the arithmetic the models' steps share.

The types: ``SensorSeries`` (the readings as recorded), ``FilterInput`` (as the filter uses
them: the only input a step takes; ``_readings._prepare`` makes it), ``FilterState``,
``Estimate``, ``StepMoments``, ``BlockInputs``. The arithmetic: the Hall measurements of a
row, the paper's linear models block by block (``block_inputs``, ``block_step``,
``block_update``, ``block_estimate``) and the exact chain's step laid out as one block
(``exact_parts``). The models (``_classes``: ``KCKF``, ``KF``, ``ExactKCKF``, ``Gyro``,
``HallL``, ``HallR``) own their states and steps and are built on what is here, as every way
of computing the filter (``_paths``), the streaming filter and the exported step are; this
module imports none of them.

Conventions shared with the NumPy reference in ``tests/``:

* ``inputs.dt[k] = t[k] - t[k-1]`` (``dt[0] = 0``: no prediction before the first row);
  timestamps are differenced in float64 before they reach here;
* the gyro rates of row ``k - 1`` drive the prediction from ``k - 1`` to ``k`` (Eq. 9 uses
  ``omega(k)`` to reach ``k + 1``); a missing gyro reading holds that channel's last value;
* a missing Hall reading (NaN) removes only its own measurement row at that step;
* a reading that cannot be a measurement (outside its physical range ``Params.limits``, a
  railed Hall sensor, an angle no joint reaches, a saturated gyro: ``_screen``; a Hall sensor
  isolated over time, a clipped gyro: ``_health``) is treated as missing, and a gyro reading
  missing for a while is taken from a gyro measuring the same rate (``Robot.gyro_stand_ins``)
  where one reads (``_readings._prepare``: the step computes on prepared readings);
* a Kalman step whose new state is not finite is skipped: the state is kept as it was, and
  ``Estimate.skipped`` says so (the streaming filter reports it as ``rejected``);
* a padded step (``dt = 0``, every reading NaN) leaves the state unchanged.

Numerics (docs/numerics.md): measurements are processed one scalar at a time (``R`` is
diagonal, so this equals the paper's joint update), each with the Joseph form
(``_kalman.py``); the constraint rows are conditioned the same way with zero noise in the
coordinates of ``_blocks.structure``. There is no matrix inverse or LAPACK call in a step.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from . import _exact
from ._blocks import (
    ProcessNoise,
    block_gather,
    predicted_moments,
    q_blocks,
    static_take,
)
from ._custom_types import BlockCov, BlockHall, BlockRates, BlockState, BlockValid
from ._exact_entries import entry_estimate, entry_step
from ._hall import hall_angle, hall_slope
from ._kalman import coordinate_update, fused_pairs, symmetrise
from ._params import Params


class SensorSeries(eqx.Module):
    """Filter inputs: one step (no leading axis), one trial (``T``) or a batch (``B T``).

    * ``dt``: seconds since the previous row (0 for the first and for padding);
    * ``gyro``: (``G = 3 (n + 1)``) rad/s, flattened ``gyro1_x, gyro1_y, ..., gyro{n+1}_z``;
    * ``hall_v``: (``M``) V, in ``Robot.hall_names`` order. NaN marks a missing reading.
    """

    dt: Float[ArrayLike, "*T"]
    gyro: Float[ArrayLike, "*T G"]
    hall_v: Float[ArrayLike, "*T M"]


class FilterInput(SensorSeries):
    """The readings as the filter uses them, of one step, one trial or a batch (the fields
    of ``SensorSeries``): judged (every reading the filter does not use is NaN, a gyro missing
    for a while holds its stand-in's reading), in the filter's dtype, and with the learned
    sensor effects taken out. Made by ``_readings._prepare`` alone (``kk.prepare`` for a
    recording or a batch, ``kk.prepare_row`` for a lone row); ``step``, ``scan_filter`` and
    every path compute on it and prepare nothing again."""


def require_input(inputs, where: str) -> None:
    """A clear error where a ``SensorSeries`` reaches the kernel unprepared."""
    if not isinstance(inputs, FilterInput):
        raise TypeError(
            f"{where} takes the readings as the filter uses them (a FilterInput), not a "
            f"{type(inputs).__name__}: prepare them first with kk.prepare(params, series, "
            "method) (a recording or a batch) or kk.prepare_row(params, state, row, method) "
            "(a lone row)")


class FilterState(eqx.Module):
    """What a filter carries from one step to the next.

    For the Kalman filters ``z`` (``Nb x Nz``) and ``P`` (``Nb x Nz x Nz``) are the estimate and
    covariance of every axis block in the filter's coordinates (``_model.Structure``; use
    ``full_state`` for the paper's ``x`` and its covariance). For the baselines ``z`` holds the
    angles and ``P`` is empty. ``gyro_hold`` is the last valid rate of every gyro channel.
    The paths carry a batch of states, one per trial (a leading axis on every leaf).
    """

    z: Float[Array, "*b Nz"]
    P: Float[Array, "*b Np Np"]
    gyro_hold: Float[Array, "*B G"]


class Estimate(eqx.Module):
    """Per-step output, in ``Robot.angle_names`` order (joint axes, then torso axes).

    ``angles`` (rad), ``angle_std`` (rad) and ``bias`` (rad/s, joint and torso biases); NaN
    where the method does not estimate a quantity. ``skipped``: the steps whose update was not
    finite and left the state as it was (``None`` where nothing computed it). ``path``
    (static) names the computation that produced it (``"sequential"``, ``"steady"``, ...;
    ``None`` for a bare ``step`` or ``scan_filter``): every path gives the same estimates, to
    rounding. ``names`` (static, set by ``run_filter`` and friends) are the angles' names:
    ``columns()`` gives the estimates keyed by them. ``faults`` (set by ``run_filter``,
    ``filter_batch`` and ``filter_sessions``): per row and reading (``Robot.gyro_names`` then
    ``Robot.hall_names``) why the filter did not use it, a code of ``_screen.FAULT_KINDS``
    (0: used or missing); ``kk.fault_stretches`` names them by column and time.
    ``innovations``: the fused Hall innovations ``(nu, var, valid)`` per row (``*T Nb m``)
    where the caller asked for them (``filter_batch(..., innovations=True)``) and the path
    computed them in the same pass (``AbstractPath.innovations_in_pass``); else ``None``.
    """

    angles: Float[ArrayLike, "*T K"]
    angle_std: Float[ArrayLike, "*T K"]
    bias: Float[ArrayLike, "*T K"]
    skipped: Bool[ArrayLike, "*T"] | None = None
    faults: Int[ArrayLike, "*T C"] | None = None
    innovations: tuple | None = None
    path: str | None = eqx.field(static=True, default=None)
    names: tuple[str, ...] | None = eqx.field(static=True, default=None)

    def columns(self, what: str = "angles") -> dict[str, np.ndarray]:
        """The estimated ``what`` (``"angles"``, ``"angle_std"`` or ``"bias"``) as NumPy columns
        keyed by angle name (``Robot.angle_names``); an angle the method does not estimate (NaN
        throughout) is left out. Needs ``names`` (set by ``run_filter``, ``filter_batch`` and
        ``filter_sessions``).

        Example:
            >>> robot = Robot.from_spec("x")
            >>> series = SensorSeries(jnp.full(3, 0.01), jnp.zeros((3, 6)), jnp.ones((3, 2)))
            >>> sorted(run_filter(Params.paper_defaults(robot), series)[1].columns())
            ['phi_x', 'theta1_x']
        """
        if self.names is None:
            raise ValueError("Estimate.columns: this estimate has no names; use one from "
                             "run_filter, filter_batch or filter_sessions")
        values = np.asarray(getattr(self, what))
        return {n: values[..., k] for k, n in enumerate(self.names)
                if np.isfinite(values[..., k]).any()}


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


class BlockInputs(NamedTuple):
    """One row's inputs laid out by axis block (``block_inputs``; any leading axes where
    every row is laid out at once).

    Attributes:
        dt: the time step (s).
        rates: the rates of the previous row (``Nb x m1``, Eqs. 2, 9, 10).
        noise: the process noise (Eq. 13), each term ``Nb x m1``.
        hb: each block joint's fused Hall reading (rad, ``Nb x m``; Eqs. 1, 5, 8, 20).
        rb: its variance.
        vb: whether it exists.
    """

    dt: Float[Array, ""]
    rates: BlockRates
    noise: ProcessNoise
    hb: BlockHall
    rb: BlockHall
    vb: BlockValid


def block_inputs(params: Params, st, gyro_hold: Float[Array, " G"], inputs: FilterInput,
                 in_loop: bool = True) -> BlockInputs:
    """One row's inputs laid out by axis block (``_model.Structure``). ``in_loop``: whether
    the row is taken inside a loop (``_blocks.static_take``)."""
    robot = params.robot
    dtype = gyro_hold.dtype
    dt = inputs.dt.astype(dtype)
    plus, minus = robot.rate_pairs

    def take(x, idx):
        return static_take(x, idx, in_loop=in_loop)

    rates = block_gather(st, take(gyro_hold, plus) - take(gyro_hold, minus), in_loop)
    noise = ProcessNoise(*(block_gather(st, x, in_loop)
                           for x in q_blocks(params.q, params.angle_rw, params.bias_rw, dt)))
    return BlockInputs(dt, rates, noise, *block_hall(params, st, inputs.hall_v.astype(dtype),
                                                     in_loop))


def block_hall(params: Params, st, hall_v: Float[Array, " M"], in_loop: bool = True
               ) -> tuple[BlockHall, BlockHall, BlockValid]:
    """One row's Hall voltages as each block joint's fused reading (rad), its variance and
    whether it exists (``Nb x m``; a padding joint: 0, 1 and ``False``; Eqs. 1, 5, 8, 20).
    ``in_loop``: as ``block_inputs``."""
    angle, r, valid = hall_measurements(params, hall_v)
    h, rh, ok = fused_pairs(angle, r, valid)
    ji = st.joint_index
    pad = ji < 0
    at = np.maximum(ji, 0)

    def take(x):
        return static_take(x, at, in_loop=in_loop)

    return (jnp.where(pad, 0.0, take(h)), jnp.where(pad, 1.0, take(rh)),
            jnp.where(pad, False, take(ok)))


def block_step(
    st,
    z: Float[Array, " Nz"],
    P: Float[Array, "Nz Nz"],
    rates: Float[Array, " m1"],
    alpha: Float[Array, " m1"],
    beta: Float[Array, " m1"],
    gamma: Float[Array, " m1"],
    hb: Float[Array, " m"],
    rb: Float[Array, " m"],
    vb: Bool[Array, " m"],
    dt: Float[Array, ""],
) -> tuple[Float[Array, " Nz"], Float[Array, "Nz Nz"], Float[Array, " Ny"], Float[Array, "Ny Ny"],
           Float[Array, " m"], Float[Array, " m"]]:
    """``block_update`` with what happened on the way: returns ``(z, P, y, S, nu, s)``, the new
    state, the predicted moments of ``y = [z, e]`` (before any update: the smoother's
    ``x_{k|k-1}``) and each joint's fused Hall innovation ``nu`` and its variance ``s`` (the
    likelihood's and NIS's terms; where ``vb`` is false they are not used)."""
    y_pred, S_pred = predicted_moments(st, z, P, rates, (alpha, beta, gamma), dt)
    y, S = y_pred, S_pred
    for i in range(st.n_e):
        e = st.n_z + i
        y, S = coordinate_update(y, S, e, -y[e], jnp.zeros((), z.dtype), dt > 0)
    z, P = y[: st.n_z], S[: st.n_z, : st.n_z]
    nus, ss = [], []
    for i in range(st.m):
        nus.append(hb[i] - z[i])
        ss.append(P[i, i] + rb[i])
        z, P = coordinate_update(z, P, i, nus[-1], rb[i], vb[i])
    zero = jnp.zeros((0,), z.dtype)
    nu = jnp.stack(nus) if nus else zero
    s = jnp.stack(ss) if ss else zero
    return z, symmetrise(P), y_pred, S_pred, nu, s


def block_update(
    st,
    z: Float[Array, " Nz"],
    P: Float[Array, "Nz Nz"],
    rates: Float[Array, " m1"],
    alpha: Float[Array, " m1"],
    beta: Float[Array, " m1"],
    gamma: Float[Array, " m1"],
    hb: Float[Array, " m"],
    rb: Float[Array, " m"],
    vb: Bool[Array, " m"],
    dt: Float[Array, ""],
) -> tuple[Float[Array, " Nz"], Float[Array, "Nz Nz"]]:
    """One axis block's predict and update (the filter's arithmetic, for one block).

    Predict ``y = [z, e]`` (Eqs. 3, 9-13); for the KCKF condition on the perfect measurement
    ``e = sum theta - phi = 0`` (Eqs. 15-19); then one scalar Joseph update per joint with its
    fused Hall reading (Eqs. 4-5, 8, 20). For fixed ``P``, ``dt`` and masks the new ``z`` is
    linear in ``(z, rates, hb)``: the steady and parallel paths (``_paths``) use exactly that.
    """
    return block_step(st, z, P, rates, alpha, beta, gamma, hb, rb, vb, dt)[:2]


def block_estimate(st, z: BlockState, P: BlockCov, in_loop: bool = True) -> Estimate:
    """Angles, their standard deviations and biases from the block states, in angle order
    (``in_loop``: as ``block_inputs``)."""
    T = jnp.asarray(st.T, z.dtype)
    m1 = st.m + 1
    xb = jnp.sum(T[None] * z[:, None, :], axis=2)  # (P, 2m + 2): the paper's x per block
    Ta = T[:m1]
    TaP = jnp.sum(Ta[None, :, :, None] * P[:, None, :, :], axis=2)  # (P, m1, Nz)
    var = jnp.sum(TaP * Ta[None], axis=2)
    bo, so = np.asarray(st.block_of), np.asarray(st.slot_of)
    ncol = xb.shape[1]

    def take(x, idx):
        return static_take(x, idx, in_loop=in_loop)

    angle = take(xb.reshape(-1), bo * ncol + so)
    bias = take(xb.reshape(-1), bo * ncol + m1 + so)
    std = jnp.sqrt(jnp.maximum(take(var.reshape(-1), bo * var.shape[1] + so), 0.0))
    return Estimate(angle, std, bias)


class StepMoments(eqx.Module):
    """What a Kalman step computed on the way (``kalman_step_moments``), per block: the
    predicted moments of ``y = [z, e]`` (``y``, ``S``), each joint's fused Hall innovation
    and its variance (``nu``, ``s``) and whether that reading was used (``valid``), the time
    step and whether the update was skipped. The smoother and the likelihood read them."""

    y: Float[Array, "*T Nb Ny"]
    S: Float[Array, "*T Nb Ny Ny"]
    nu: Float[Array, "*T Nb m"]
    s: Float[Array, "*T Nb m"]
    valid: Bool[Array, "*T Nb m"]
    dt: Float[Array, "*T"]
    skipped: Bool[Array, "*T"]
    #: The Jacobian of ``y`` in the previous row's ``z`` (``kckf3d``, whose model depends on
    #: the state); ``None`` for the linear methods, whose map is ``Structure``'s.
    F: Float[Array, "*T Nb Ny Nz"] | None = None


def exact_parts(params: Params, state: FilterState, inputs: FilterInput,
                entries: bool = False):
    """One ``kckf3d`` step (``_exact.exact_step``) laid out as one block (``Nb = 1``);
    ``entries``: computed entry by entry on one lane (``_exact_entries.entry_step``: the
    stream's forward-only step; its ``S`` and ``F`` are not formed, ``None``)."""
    dtype = state.z.dtype
    model = _exact.exact_model(params.robot)
    dt = inputs.dt.astype(dtype)
    noise = ProcessNoise(*q_blocks(params.q, params.angle_rw, params.bias_rw, dt))
    bias_q, bias_rw2, _ = _exact.gyro_bias_noise(model, params.q, params.bias_rw, params.p0_bias)
    h, rh, vh = fused_pairs(*hall_measurements(params, inputs.hall_v.astype(dtype)))
    if entries:
        q = _exact.process_noise_diagonal(model, noise[0], bias_q, bias_rw2, dt)
        z, P, nu, s = (x[..., 0] for x in entry_step(
            model, state.z[0][:, None], state.P[0][..., None], state.gyro_hold[:, None],
            dt[None], h[:, None], rh[:, None], vh[:, None], q[:, None]))
        return z[None], P[None], None, None, None, nu[None], s[None], vh[None], dt
    z, P, y, S, F, nu, s = _exact.exact_step(model, state.z[0], state.P[0], state.gyro_hold,
                                             noise, bias_q, bias_rw2, h, rh, vh, dt)
    return z[None], P[None], y[None], S[None], F[None], nu[None], s[None], vh[None], dt


def exact_block_estimate(robot, z: BlockState, P: BlockCov, entries: bool = False
                         ) -> Estimate:
    """``kckf3d``'s estimate from its one-block state (``_exact.exact_estimate``; ``entries``:
    entry by entry on one lane, ``_exact_entries.entry_estimate``)."""
    model = _exact.exact_model(robot)
    if entries:
        return Estimate(*(x[..., 0] for x in entry_estimate(model, z[0][:, None],
                                                            P[0][..., None])))
    return Estimate(*_exact.exact_estimate(model, z[0], P[0]))
