"""The faster paths agree with the sequential filter (1e-8 rad in float64) and fall back."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kckf_jax import Params, Robot, _fast, filter_batch, run_filter, simulate
from kckf_jax._fast import STEADY_STEPS, choose_path, steady_conditions
from kckf_jax._filter import SensorSeries


def regular(robot, seed, T, dtype=jnp.float64, kind="cyclic"):
    """A session with an exactly constant time step and no missing reading."""
    s = simulate(robot, kind, seed=seed, duration_s=T / 100.0)
    dt = np.r_[0.0, np.full(T - 1, 0.01)]
    return s, SensorSeries(jnp.asarray(dt, dtype), jnp.asarray(s.gyro, dtype),
                           jnp.asarray(s.hall_v, dtype))


@pytest.mark.parametrize("spec", ["x,y,x,y", "xyz,xyz,xyz,xyz", "xz,y"])
@pytest.mark.parametrize("method", ["kckf", "kf"])
def test_steady_and_parallel_equal_sequential_float64(spec, method):
    robot = Robot.from_spec(spec)
    s, series = regular(robot, 1, STEADY_STEPS + 1500)
    params = Params.paper_defaults(robot, s.hall_models, dtype=jnp.float64)
    # The standard KF's torso variance grows without bound: its steady path falls back.
    assert choose_path(params, series, method) == ("steady" if method == "kckf" else
                                                   "sequential")
    _, ref = run_filter(params, series, method, path="sequential")
    for path in ("steady", "parallel"):
        final, est = run_filter(params, series, method, path=path)
        # Rounding differs from the sequential filter's where the fast branch ran.
        fell_back = method == "kf" and path == "steady"
        assert np.array_equal(np.asarray(est.angles), np.asarray(ref.angles)) == fell_back
        np.testing.assert_allclose(est.angles, ref.angles, atol=1e-8, rtol=0)
        np.testing.assert_allclose(est.bias, ref.bias, atol=1e-8, rtol=0)
        np.testing.assert_allclose(est.angle_std, ref.angle_std, atol=1e-8, rtol=1e-6)


def test_parallel_handles_missing_readings_uneven_steps_and_voltage_noise():
    robot = Robot.from_spec("x,y,x,y")
    s = simulate(robot, "human", seed=4, duration_s=30.0, drop_prob=0.05)
    params = Params.from_physical(robot, hall_models=s.hall_models, hall_noise="voltage",
                                  dtype=jnp.float64)
    series = SensorSeries(jnp.asarray(s.dt()), jnp.asarray(s.gyro), jnp.asarray(s.hall_v))
    assert steady_conditions(params, series, "kckf") is not None
    assert choose_path(params, series, "kckf") == "sequential"
    _, ref = run_filter(params, series, "kckf", path="sequential")
    _, par = run_filter(params, series, "kckf", path="parallel")
    np.testing.assert_allclose(par.angles, ref.angles, atol=1e-8, rtol=0)
    with pytest.raises(ValueError, match="does not apply: the voltage noise model"):
        run_filter(params, series, "kckf", path="steady")


def test_steady_falls_back_when_the_covariance_has_not_converged():
    """Tiny process noise and a huge prior: still moving after STEADY_STEPS rows, so the
    compiled function takes the sequential branch (and the result is the sequential one)."""
    robot = Robot.from_spec("x,y")
    s, series = regular(robot, 2, STEADY_STEPS + 500)
    params = Params.from_physical(robot, q=1e-16, p0_bias=0.5, hall_models=s.hall_models,
                                  dtype=jnp.float64)
    _, ref = run_filter(params, series, "kckf", path="sequential")
    _, est = run_filter(params, series, "kckf", path="steady")
    np.testing.assert_array_equal(np.asarray(est.angles), np.asarray(ref.angles))


def test_batch_steady_equals_sequential_float32_and_grad_is_finite():
    robot = Robot.from_spec("x,y,x,y")
    T = STEADY_STEPS + 300
    trials = [regular(robot, seed, T, jnp.float32)[1] for seed in (5, 6, 7)]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *trials)
    params = Params.paper_defaults(robot, dtype=jnp.float32)
    assert choose_path(params, batch, "kckf") == "steady"
    seq = filter_batch(params, batch, "kckf", path="sequential")
    fast = filter_batch(params, batch, "kckf")
    assert not np.array_equal(np.asarray(fast.angles), np.asarray(seq.angles))
    np.testing.assert_allclose(fast.angles, seq.angles, atol=1e-4, rtol=0)
    grads = eqx.filter_grad(lambda p: jnp.mean(filter_batch(p, batch, "kckf").angles ** 2))(
        params)
    leaves = jax.tree_util.tree_leaves(eqx.filter(grads, eqx.is_inexact_array))
    assert leaves and all(np.isfinite(np.asarray(x)).all() for x in leaves)
    assert any(np.abs(np.asarray(x)).max() > 0 for x in leaves)


def test_steady_blocks_whole_and_partial_float64(monkeypatch):
    """Small blocks: several whole blocks of the head's per-row maps and of the converged
    map, then a partial one, for one recording and for a batch."""
    monkeypatch.setattr(_fast, "MEAN_BLOCK", 512)
    robot = Robot.from_spec("x,y,x,y")
    T = STEADY_STEPS + 1800
    s, series = regular(robot, 3, T)
    params = Params.paper_defaults(robot, s.hall_models, dtype=jnp.float64)
    _, ref = run_filter(params, series, "kckf", path="sequential")
    _, est = run_filter(params, series, "kckf", path="steady")
    assert not np.array_equal(np.asarray(est.angles), np.asarray(ref.angles))
    np.testing.assert_allclose(est.angles, ref.angles, atol=1e-8, rtol=0)
    np.testing.assert_allclose(est.bias, ref.bias, atol=1e-8, rtol=0)
    trials = [regular(robot, seed, T)[1] for seed in (3, 8, 9)]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *trials)
    seq = filter_batch(params, batch, "kckf", path="sequential")
    fast = filter_batch(params, batch, "kckf", path="steady")
    assert not np.array_equal(np.asarray(fast.angles), np.asarray(seq.angles))
    for a, b in ((fast.angles, seq.angles), (fast.bias, seq.bias),
                 (fast.angle_std, seq.angle_std)):
        np.testing.assert_allclose(a, b, atol=1e-8, rtol=0)


def test_steady_chunks_carried_in_groups_float64(monkeypatch):
    """The states entering the chunks solved in nested groups (several levels, a chunk count
    that is no multiple of the group), small blocks, and a row count that leaves a partial
    last chunk: estimates and final state equal the sequential filter's; so does the
    gradient of a loss through the batch path."""
    monkeypatch.setattr(_fast, "MEAN_BLOCK", 512)
    monkeypatch.setattr(_fast, "CARRY_SCAN", 3)
    monkeypatch.setattr(_fast, "CARRY_GROUP", 4)
    robot = Robot.from_spec("xz,y")
    T = STEADY_STEPS + 1805
    s, series = regular(robot, 5, T)
    params = Params.paper_defaults(robot, s.hall_models, dtype=jnp.float64)
    ref_final, ref = run_filter(params, series, "kckf", path="sequential")
    final, est = run_filter(params, series, "kckf", path="steady")
    assert not np.array_equal(np.asarray(est.angles), np.asarray(ref.angles))
    np.testing.assert_allclose(est.angles, ref.angles, atol=1e-8, rtol=0)
    np.testing.assert_allclose(est.bias, ref.bias, atol=1e-8, rtol=0)
    np.testing.assert_allclose(final.z, ref_final.z, atol=1e-8, rtol=0)
    np.testing.assert_allclose(final.P, ref_final.P, atol=1e-12, rtol=0)
    np.testing.assert_array_equal(final.gyro_hold, ref_final.gyro_hold)
    trials = [regular(robot, seed, T)[1] for seed in (5, 6)]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *trials)

    def loss(p, path):
        return jnp.mean(filter_batch(p, batch, "kckf", path=path).angles ** 2)

    (l_seq, g_seq), (l_fast, g_fast) = (
        eqx.filter_value_and_grad(lambda p, path=path: loss(p, path))(params)
        for path in ("sequential", "steady"))
    np.testing.assert_allclose(l_fast, l_seq, rtol=1e-9)
    flat_seq = jax.tree_util.tree_leaves(eqx.filter(g_seq, eqx.is_inexact_array))
    flat_fast = jax.tree_util.tree_leaves(eqx.filter(g_fast, eqx.is_inexact_array))
    for a, b in zip(flat_fast, flat_seq):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9 * float(np.abs(b).max() + 1))

    # Biases in the loss too, and the gradient with respect to the readings themselves: the
    # hand-written reverse mode's other branches (every output live, data cotangents).
    def loss2(p, gyro, hall_v, path):
        est = filter_batch(p, SensorSeries(batch.dt, gyro, hall_v), "kckf", path=path)
        return jnp.mean(est.angles ** 2) + jnp.mean(jnp.sin(3.0 * est.bias))

    g_seq, g_fast = (jax.grad(lambda p, g, h, path=path: loss2(p, g, h, path), argnums=(0, 1, 2))(
        params, batch.gyro, batch.hall_v) for path in ("sequential", "steady"))
    flat_seq = jax.tree_util.tree_leaves(eqx.filter(g_seq, eqx.is_inexact_array))
    flat_fast = jax.tree_util.tree_leaves(eqx.filter(g_fast, eqx.is_inexact_array))
    assert len(flat_fast) == len(flat_seq)
    for a, b in zip(flat_fast, flat_seq):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9 * float(np.abs(b).max() + 1))
    assert np.abs(np.asarray(g_fast[1])).max() > 0 and np.abs(np.asarray(g_fast[2])).max() > 0


def test_batch_with_different_time_steps_is_not_steady():
    """Each trial is regular, but the steps differ: one shared covariance would be wrong."""
    robot = Robot.from_spec("x,y")
    T = STEADY_STEPS + 100
    a, b = regular(robot, 1, T)[1], regular(robot, 2, T)[1]
    b = SensorSeries(b.dt * 2, b.gyro, b.hall_v)
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), a, b)
    params = Params.paper_defaults(robot, dtype=jnp.float64)
    assert "shared by every trial" in steady_conditions(params, batch, "kckf")
    assert choose_path(params, batch, "kckf") == "sequential"
    with pytest.raises(ValueError, match="does not apply"):
        filter_batch(params, batch, "kckf", path="steady")


def test_steady_path_inside_jit():
    """Under jit the data cannot be checked: path='steady' trusts the caller."""
    robot = Robot.from_spec("x,y")
    s, series = regular(robot, 4, STEADY_STEPS + 200)
    params = Params.paper_defaults(robot, s.hall_models, dtype=jnp.float64)
    est = jax.jit(lambda x: run_filter(params, x, "kckf", path="steady")[1].angles)(series)
    _, ref = run_filter(params, series, "kckf", path="sequential")
    np.testing.assert_allclose(est, ref.angles, atol=1e-8, rtol=0)


def test_unknown_path():
    robot = Robot.from_spec("x")
    with pytest.raises(ValueError, match="path must be one of"):
        run_filter(Params.paper_defaults(robot), regular(robot, 1, 10)[1], path="fast")


def test_auto_path_finds_missing_readings_itself():
    """``"auto"`` checks only the time steps beforehand; a missing reading makes the steady
    path's state non-finite, and the call is answered by the sequential filter instead."""
    robot = Robot.from_spec("x,y")
    T = STEADY_STEPS + 300
    params = Params.paper_defaults(robot, dtype=jnp.float64)
    _, series = regular(robot, 11, T)
    hall = np.asarray(series.hall_v).copy()
    hall[T - 100, 1] = np.nan  # after the head: a converged chunk row
    one = SensorSeries(series.dt, series.gyro, jnp.asarray(hall))
    assert _fast.plan_path(params, one, "kckf") == ("steady", True)
    assert choose_path(params, one, "kckf") == "sequential"  # the full check still says so
    _, ref = run_filter(params, one, "kckf", path="sequential")
    _, est = run_filter(params, one, "kckf")
    np.testing.assert_array_equal(np.asarray(est.angles), np.asarray(ref.angles))
    assert np.isfinite(np.asarray(est.angles)).all()
    trials = [regular(robot, seed, T)[1] for seed in (12, 13)]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *trials)
    gyro = np.asarray(batch.gyro).copy()
    used = int(np.asarray(robot.rate_pairs)[0, 0])
    gyro[1, 50, used] = np.nan  # trial 1, inside the head shared by the batch
    batch = SensorSeries(batch.dt, jnp.asarray(gyro), batch.hall_v)
    seq = filter_batch(params, batch, "kckf", path="sequential")
    fast = filter_batch(params, batch, "kckf")
    np.testing.assert_array_equal(np.asarray(fast.angles), np.asarray(seq.angles))
    # The checked path itself does report the missing reading.
    _, ok = jax.jit(lambda b: _fast.steady_batch_checked(params, b, "kckf"))(batch)
    assert not bool(ok)
