"""The smoother's fast paths (trials as lanes; the steady smoother's constant backward map)
against the sequential smoother, which ``test_smooth.py`` checks against the NumPy RTS
smoother, and the NumPy smoother itself on a short trial."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import joints_of, random_params, random_recording, reference_params
from helpers import series_of as make_series
from reference import reference_smoother

from kckf_jax import Params, Robot, SensorSeries, pad_series, simulate, smooth, smooth_batch
from kckf_jax._paths._smooth import _smooth_path


def _close(a, b, atol):
    for f in ("angles", "angle_std", "bias"):
        np.testing.assert_allclose(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)),
                                   atol=atol, rtol=0, err_msg=f)


@pytest.mark.parametrize("method", ["kckf", "kf"])
def test_lanes_smoother_equals_sequential_and_numpy(method):
    """Irregular steps, 10 % missing readings, the voltage noise model, padded trials and a
    skipped row (a time step so long that the prediction overflows)."""
    rng = np.random.default_rng(7)
    robot = Robot.from_spec("xz,y")  # an x block of two joints, a z block of one (padded)
    params = random_params(rng, robot, hall_noise="voltage")
    recs = [random_recording(rng, robot, T=T) for T in (60, 45, 80)]
    series = [make_series(*r) for r in recs]
    series[1] = SensorSeries(series[1].dt.at[20].set(1e300), series[1].gyro, series[1].hall_v)
    batch = pad_series(series)
    seq = smooth_batch(params, batch, method, path="sequential")
    lanes = smooth_batch(params, batch, method, path="lanes")
    assert (seq.path, lanes.path) == ("smoothed", "smoothed:lanes")
    _close(lanes, seq, 1e-9)
    np.testing.assert_array_equal(lanes.skipped, seq.skipped)
    assert np.asarray(lanes.skipped)[1, 20] and np.isfinite(np.asarray(lanes.angles)).all()
    ref = reference_smoother(joints_of(robot), *recs[0], reference_params(params), method)
    np.testing.assert_allclose(lanes.angles[0, :60], ref["angles"], atol=1e-8, rtol=0)
    # Auto takes lanes from Lanes.min_trials trials on, as the filter does.
    assert _smooth_path(params, pad_series(series * 4), method, "auto").name == "lanes"
    assert _smooth_path(params, batch, method, "auto").name == "sequential"


@pytest.mark.long
def test_lanes_smoother_gradient_equals_sequential():
    rng = np.random.default_rng(3)
    robot = Robot.from_spec("x,y")
    params = random_params(rng, robot, hall_noise="voltage")
    batch = pad_series([make_series(*random_recording(rng, robot, T=T)) for T in (30, 22)])
    diff, static = eqx.partition(params, eqx.is_inexact_array)

    def loss(d, path):
        est = smooth_batch(eqx.combine(d, static), batch, path=path)
        return jnp.nanmean(est.angles ** 2) + jnp.nanmean(est.angle_std)

    g_seq = jax.grad(loss)(diff, "sequential")
    g_lanes = jax.grad(loss)(diff, "lanes")
    for a, b in zip(jax.tree_util.tree_leaves(g_seq), jax.tree_util.tree_leaves(g_lanes)):
        assert np.isfinite(np.asarray(b)).all()
        np.testing.assert_allclose(b, a, atol=1e-10, rtol=1e-7)


def _regular(robot, seed, rows, dtype=np.float64):
    s = simulate(robot, "human", seed=seed, duration_s=rows / 100.0, drop_prob=0.0)
    dt = np.full(rows, 0.01)
    dt[0] = 0.0
    return SensorSeries(jnp.asarray(dt, dtype), jnp.asarray(s.gyro[:rows], dtype),
                        jnp.asarray(s.hall_v[:rows], dtype))


@pytest.mark.parametrize("spec,rows", [("x,y,x,y", 9000), ("xz,y", 4500), ("x,y", 4097)])
@pytest.mark.long
def test_steady_smoother_equals_sequential(spec, rows):
    """Past the filter's head (4,096 rows in float64) the steady smoother's backward map is
    constant; 9,000 rows also reach the smoothed covariance's fixed point (4,096 rows before
    the end), 4,097 rows leave one converged row."""
    robot = Robot.from_spec(spec)
    params = Params.paper_defaults(robot, dtype=jnp.float64)
    one = _regular(robot, 1, rows)
    seq = smooth(params, one, path="sequential")
    if spec == "x,y,x,y":  # a batch of two regular trials (each against its own sequential)
        two = jax.tree_util.tree_map(lambda *x: jnp.stack(x), one, _regular(robot, 2, rows))
        batch = smooth_batch(params, two)
        assert batch.path == "smoothed:steady"
        _close(jax.tree_util.tree_map(lambda x: x[1], batch),
               smooth(params, jax.tree_util.tree_map(lambda x: x[1], two), path="sequential"),
               1e-9)
        est = jax.tree_util.tree_map(lambda x: x[0], batch)
    else:
        est = smooth(params, one)
        assert est.path == "smoothed:steady"
    _close(est, seq, 1e-9)
    a = np.asarray(est.angles)  # the constraint holds for the smoothed estimates too
    np.testing.assert_allclose(a[:, robot.n_joint_axes:],
                               a[:, :robot.n_joint_axes] @ robot.torso_sum.T, atol=1e-12)
    if spec == "x,y":  # differentiable: the steady path's gradient is the sequential one's
        diff, static = eqx.partition(params, eqx.is_inexact_array)

        def loss(d, path):
            est = smooth(eqx.combine(d, static), one, path=path)
            return jnp.mean(est.angles ** 2) + jnp.mean(est.angle_std)

        g_seq, g_steady = (jax.jit(jax.grad(loss), static_argnums=1)(diff, p)
                           for p in ("sequential", "steady"))
        for a, b in zip(jax.tree_util.tree_leaves(g_seq), jax.tree_util.tree_leaves(g_steady)):
            np.testing.assert_allclose(b, a, atol=1e-12, rtol=1e-8)
    if spec == "x,y,x,y":  # float32
        p32 = params.astype(jnp.float32)
        s32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), one)
        e32 = smooth(p32, s32)
        assert e32.path == "smoothed:steady"
        assert np.abs(np.asarray(e32.angles, np.float64) - np.asarray(seq.angles)).max() < 1e-4
        assert (np.asarray(e32.angle_std) > 0).all()


def test_steady_smoother_says_why_it_does_not_apply():
    robot = Robot.from_spec("x,y")
    params = Params.paper_defaults(robot, dtype=jnp.float64)
    one = _regular(robot, 1, 5000)
    jittered = SensorSeries(one.dt.at[100].set(0.011), one.gyro, one.hall_v)
    with pytest.raises(ValueError, match="the steady path does not apply: the time step is not"):
        smooth(params, jittered, path="steady")
    assert smooth(params, jittered).path == "smoothed"
    with pytest.raises(ValueError, match="unknown path"):
        smooth_batch(params, jax.tree_util.tree_map(lambda x: x[None], one), path="fast")


@pytest.mark.long
def test_the_policy_lays_out_the_smoother_with_its_own_constants_and_checks_once(monkeypatch):
    """``Auto``'s ``Steady`` constants reach the steady smoother, whose check ``Auto`` ran
    (once: the smoother does not run it again); an explicit ``Steady`` is checked by the
    smoother."""
    from kckf_jax import Auto, Steady
    from kckf_jax._paths._steady_smooth import SteadySmoother

    robot = Robot.from_spec("x,y")
    params = Params.paper_defaults(robot, dtype=jnp.float64)
    one = jax.tree_util.tree_map(lambda x: x[None], _regular(robot, 1, 5000))
    mine = Steady(head_rows_float64=3000)
    layout = _smooth_path(params, one, "kckf", Auto(steady=mine))
    assert (layout.name, layout.steady, layout.checked) == ("steady", mine, True)
    explicit = _smooth_path(params, one, "kckf", mine)
    assert (explicit.name, explicit.steady, explicit.checked) == ("steady", mine, False)
    calls, seen = [], []
    applies, run = SteadySmoother.applies, SteadySmoother.run
    monkeypatch.setattr(SteadySmoother, "applies",
                        lambda self, *a, **k: calls.append(1) or applies(self, *a, **k))
    monkeypatch.setattr(SteadySmoother, "run",
                        lambda self, *a, **k: seen.append(self.steady) or run(self, *a, **k))
    est = smooth_batch(params, one, path=Auto(steady=mine))
    assert est.path == "smoothed:steady" and len(calls) == 1 and seen == [mine]
    _close(est, smooth_batch(params, one, path="sequential"), 1e-9)
