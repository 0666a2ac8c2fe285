"""The lanes filter's hand-written reverse pass (``_paths/_lanes_adjoint.py``) against JAX's
automatic one (``Lanes(remat_chunk=...)`` keeps it) and against finite differences; and the
lanes smoother's gradient, which takes it for its forward pass.

Recorded-like data throughout: jittered time steps, 5 % missing readings per channel, the
voltage noise model, padded trials of uneven length and one overflowing update (a skipped row,
whose cotangents must pass through without the non-finite step's NaN).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_close, leaves

from kckf_jax import (
    Lanes,
    Params,
    Robot,
    SensorSeries,
    filter_batch,
    pad_series,
    simulate,
    smooth_batch,
)
from kckf_jax._models._classes import init_states, structure
from kckf_jax._paths._lanes import LaneMoments, LaneState, _lane_loop, lane_inputs
from kckf_jax._paths._likelihood import hall_nll

AUTOMATIC = Lanes(remat_chunk=40)  # chunked checkpoints: JAX's own transpose of the step


def recorded_like(spec, lengths=((1, 120), (2, 97), (3, 110), (4, 83)), overflow=True):
    robot = Robot.from_spec(spec)
    trials = [simulate(robot, "human", seed=s, duration_s=n / 100.0, drop_prob=0.05)
              for s, n in lengths]
    batch = pad_series([SensorSeries(s.dt(), s.gyro, s.hall_v) for s in trials])
    dt = np.asarray(batch.dt).copy()
    if overflow:
        dt[1, 50] = 1e200  # an overflowing prediction: the row is skipped, the state kept
    batch = SensorSeries(jnp.asarray(dt), batch.gyro, batch.hall_v)
    params = Params.from_physical(robot, hall_models=trials[0].hall_models,
                                  hall_noise="voltage", dtype=jnp.float64)
    return params, batch


def loss(params, batch, path):
    """Every output the estimate has: angles, their standard deviations and the biases."""
    est = filter_batch(params, batch, "kckf", path=path)
    return (jnp.nansum(est.angles**2) + 0.3 * jnp.nansum(est.angle_std)
            + jnp.nansum(jnp.sin(est.bias)))


@pytest.mark.parametrize("spec", ["x,y,x,y", "xz,y,xyz"])
@pytest.mark.long
def test_parameter_gradient_equals_the_automatic_one_float64(spec):
    """Two equal blocks, and three of different sizes (padding joints)."""
    params, batch = recorded_like(spec, overflow=False)
    grad = eqx.filter_jit(eqx.filter_value_and_grad(loss))
    (v0, g0), (v1, g1) = grad(params, batch, Lanes()), grad(params, batch, AUTOMATIC)
    assert float(v0) == pytest.approx(float(v1), rel=1e-10)
    assert_close(g0, g1, 1e-10)


@pytest.mark.long  # a heavy check beside a lighter default one (the default run within 4 min)
def test_a_skipped_row_passes_its_cotangents_through_as_the_sequential_path_does():
    """The overflowing row is skipped; the gradient equals the sequential path's. JAX's own
    transpose of the lanes step spread the skipped step's NaN into every leaf; here only
    ``log_q`` is NaN, on both paths: the row's process noise ``q ts^4 / 4`` itself overflows,
    before any filter runs."""
    params, batch = recorded_like("x,y,x,y")
    assert np.asarray(filter_batch(params, batch, "kckf", path="lanes").skipped)[1, 50]
    grad = eqx.filter_jit(eqx.filter_grad(loss))
    got, ref = grad(params, batch, Lanes()), grad(params, batch, "sequential")
    assert not np.isfinite(np.asarray(got.log_q)).all()
    assert not np.isfinite(np.asarray(ref.log_q)).all()
    finite = lambda g: eqx.tree_at(lambda p: p.log_q, g, jnp.zeros_like(g.log_q))  # noqa: E731
    assert_close(finite(got), finite(ref), 1e-8)


@pytest.mark.long  # a heavy check beside a lighter default one (the default run within 4 min)
def test_gradient_in_the_time_steps_gyro_readings_and_entering_state():
    """Cotangents formed only when asked for: the time steps, the gyro readings (through the
    held rates) and the entering state, held rates included."""
    params, batch = recorded_like("x,y")
    state = init_states(params, "kckf", batch.dt.shape[0])
    state = eqx.tree_at(lambda s: s.gyro_hold, state,
                        jnp.asarray(np.random.default_rng(0).normal(0, 0.1, state.gyro_hold.shape)))
    # gyro3_y (no other gyro measures its rate: Robot.gyro_stand_ins) missing on the first
    # row, so the entering held rate is read.
    batch = SensorSeries(jnp.where(batch.dt > 1.0, 0.01, batch.dt),
                         jnp.asarray(batch.gyro).at[:, 0, 7].set(jnp.nan), batch.hall_v)

    def f(series, state, path):
        _, est = path.run(params, series, "kckf", state)
        return jnp.nansum(est.angles**2) + 0.3 * jnp.nansum(est.angle_std)

    grad = eqx.filter_jit(jax.grad(f, argnums=(0, 1)))
    (s0, x0), (s1, x1) = grad(batch, state, Lanes()), grad(batch, state, AUTOMATIC)
    assert_close((s0.dt, s0.gyro, s0.hall_v), (s1.dt, s1.gyro, s1.hall_v), 1e-10)
    assert_close(x0, x1, 1e-10)
    assert np.abs(np.asarray(s0.dt)).max() > 0 and np.abs(np.asarray(x0.gyro_hold)).max() > 0


def test_parameter_gradient_equals_finite_differences_float64():
    """Central differences along a random direction of the parameters (no autodiff at all)."""
    params, batch = recorded_like("x,y,x,y", overflow=False)
    diff, static = eqx.partition(params, eqx.is_inexact_array)
    rng = np.random.default_rng(1)
    direction = jax.tree_util.tree_map(lambda x: jnp.asarray(rng.normal(size=x.shape)), diff)

    def along(h):
        moved = jax.tree_util.tree_map(lambda x, d: x + h * d, diff, direction)
        return loss(eqx.combine(moved, static), batch, Lanes())

    g = eqx.filter_grad(lambda d: loss(eqx.combine(d, static), batch, Lanes()))(diff)
    exact = sum(float(jnp.vdot(a, b)) for a, b in zip(leaves(g), leaves(direction),
                                                       strict=True))
    h = 1e-5
    fd = (float(along(h)) - float(along(-h))) / (2 * h)
    assert fd == pytest.approx(exact, rel=1e-6)


@pytest.mark.long
def test_float32_gradient_is_as_accurate_as_the_automatic_one():
    """float32's own rounding (about 0.2 % of the largest entry on 120 rows of this data, on
    every path) and no more."""
    params, batch = recorded_like("x,y,x,y", overflow=False)
    p32 = params.astype(jnp.float32)
    b32 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), batch)
    ref = leaves(eqx.filter_grad(loss)(params, batch, Lanes()))

    def error(path):
        got = leaves(eqx.filter_grad(loss)(p32, b32, path))
        return max(float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-30))
                   for a, b in zip(got, ref, strict=True))

    ours, automatic = error(Lanes()), error(AUTOMATIC)
    assert ours < 5e-3 and ours < 1.5 * automatic


@pytest.mark.parametrize("method", ["kckf", "kf"])
@pytest.mark.long
def test_likelihood_gradient_equals_the_sequential_one_float64(method):
    """The likelihood's innovations (``lane_innovations_scan``) take the same reverse
    pass, with the cotangents of every innovation and its variance."""
    params, batch = recorded_like("x,y,x,y", overflow=False)
    grad = eqx.filter_jit(eqx.filter_value_and_grad(
        lambda p, path: hall_nll(p, batch, method, path=path)))
    (v0, g0), (v1, g1) = grad(params, "lanes"), grad(params, "sequential")
    assert float(v0) == pytest.approx(float(v1), rel=1e-11)
    assert_close(g0, g1, 1e-9)
    data = eqx.filter_jit(jax.grad(lambda b, path: hall_nll(params, b, method, path=path)))
    (d0, d1) = data(batch, "lanes"), data(batch, "sequential")  # through the states and held rates
    assert_close((d0.dt, d0.gyro, d0.hall_v), (d1.dt, d1.gyro, d1.hall_v), 1e-9)


def smoothed_loss(params, batch, path, method="kckf"):
    """Every output of the smoothed estimate."""
    est = smooth_batch(params, batch, method, path=path)
    return (jnp.nansum(est.angles**2) + 0.3 * jnp.nansum(est.angle_std)
            + jnp.nansum(jnp.sin(est.bias)))


def moments_loss(params, batch, remat_chunk):
    """Every row the smoother's forward pass keeps (``LaneMoments``: the filtered state and
    covariance, the predicted ``y`` and ``S``), weighted: through the hand-written reverse pass
    (``remat_chunk=None``) or JAX's own (chunked checkpoints)."""
    st = structure(params.robot, "kckf")
    state = init_states(params, "kckf", batch.dt.shape[0])
    inputs = lane_inputs(params, st, batch.dt, batch.gyro, batch.hall_v)
    rows = _lane_loop(params, st, LaneState(state.z, state.P, state.gyro_hold), inputs,
                      LaneMoments, remat_chunk, None).rows
    w = [jnp.cos(jnp.arange(x.size, dtype=x.dtype).reshape(x.shape)) for x in
         (rows.z, rows.P, rows.y, rows.S)]
    return sum(jnp.sum(a * b) for a, b in zip(w, (rows.z, rows.P, rows.y, rows.S)))


@pytest.mark.parametrize("spec", ["x,y,x,y", pytest.param("xz,y,xyz", marks=pytest.mark.long)])
def test_smoothers_forward_pass_gradient_equals_the_automatic_one_float64(spec):
    """The predicted moments' cotangents (``LaneMoments.y``, ``.S``) join the filter's: the
    parameters, the time steps and the gyro readings against JAX's own reverse pass."""
    params, batch = recorded_like(spec, overflow=False)
    grad = eqx.filter_jit(eqx.filter_grad(moments_loss))
    assert_close(grad(params, batch, None), grad(params, batch, 40), 1e-10)
    by_data = jax.jit(jax.grad(lambda b, chunk: moments_loss(params, b, chunk)),
                      static_argnums=1)
    d0, d1 = by_data(batch, None), by_data(batch, 40)
    assert_close((d0.dt, d0.gyro, d0.hall_v), (d1.dt, d1.gyro, d1.hall_v), 1e-10)
    assert np.abs(np.asarray(d0.dt)).max() > 0 and np.abs(np.asarray(d0.gyro)).max() > 0


@pytest.mark.parametrize("method", ["kckf", "kf"])
@pytest.mark.long  # 25-30 s each: the sequential smoother's automatic gradient compiles slowly
def test_smoothed_gradient_equals_the_sequential_one(method):
    """The lanes smoother under reverse mode (the filter's hand-written pass, the gains formed
    for every row at once) against the vmapped sequential smoother's automatic gradient."""
    params, batch = recorded_like("x,y,x,y", overflow=False)
    grad = eqx.filter_jit(eqx.filter_value_and_grad(smoothed_loss))
    (v0, g0), (v1, g1) = (grad(params, batch, "lanes", method),
                          grad(params, batch, "sequential", method))
    assert float(v0) == pytest.approx(float(v1), rel=1e-9)  # the smoothers' own rounding
    assert_close(g0, g1, 1e-8)
    # The data too: the gains' derivative in the time steps, the held gyro rates.
    data = eqx.filter_jit(jax.grad(lambda b, path: smoothed_loss(params, b, path, method)))
    d0, d1 = data(batch, "lanes"), data(batch, "sequential")
    assert_close((d0.dt, d0.gyro, d0.hall_v), (d1.dt, d1.gyro, d1.hall_v), 1e-8)


@pytest.mark.long  # a heavy check beside a lighter default one (the default run within 4 min)
def test_smoothed_gradient_with_a_skipped_row_equals_finite_differences_float64():
    """Central differences of the smoothed loss on lanes along a random direction, with the
    overflowing row skipped. Its non-finite moments reach no derivative (the sequential
    smoother's automatic gradient is NaN in every leaf here); only ``log_q``'s is NaN, as the
    filter's: the row's process noise itself overflows (left out of the direction)."""
    params, batch = recorded_like("x,y,x,y")
    assert np.asarray(smooth_batch(params, batch, path="lanes").skipped)[1, 50]
    diff, static = eqx.partition(params, eqx.is_inexact_array)
    rng = np.random.default_rng(2)
    direction = jax.tree_util.tree_map(lambda x: jnp.asarray(rng.normal(size=x.shape)), diff)
    direction = eqx.tree_at(lambda p: p.log_q, direction, jnp.zeros_like(diff.log_q))
    f = jax.jit(lambda d: smoothed_loss(eqx.combine(d, static), batch, "lanes"))

    def along(h):
        return float(f(jax.tree_util.tree_map(lambda x, d: x + h * d, diff, direction)))

    g = jax.jit(jax.grad(lambda d: smoothed_loss(eqx.combine(d, static), batch, "lanes")))(diff)
    g = eqx.tree_at(lambda p: p.log_q, g, jnp.zeros_like(g.log_q))
    assert all(np.isfinite(np.asarray(x)).all() for x in leaves(g))
    exact = sum(float(jnp.vdot(a, b)) for a, b in zip(leaves(g), leaves(direction),
                                                       strict=True))
    h = 1e-5
    assert (along(h) - along(-h)) / (2 * h) == pytest.approx(exact, rel=1e-6)
