"""``kckf3d``'s lanes filter, its hand-written reverse pass (``_paths/_exact_adjoint.py``)
against JAX's own (``exact_lanes_run(by_hand=False)``: each row recomputed and transposed by
JAX), in checkpointed chunks, and against finite differences, in float64.

Recorded-like exact-rotation data throughout: jittered time steps, 5 % missing readings per
channel, the voltage noise model, padded trials of uneven length; every sensor effect on, so
the gyro readings are differentiated too; and one overflowing row (skipped: its cotangents
must pass through without the non-finite step's NaN).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_close, leaves

from kckf_jax import Lanes, Params, Robot, SensorSeries, filter_batch, pad_series, simulate
from kckf_jax._models._classes import init_states
from kckf_jax._models._effects import EFFECTS, SensorEffects
from kckf_jax._paths._exact_lanes import exact_lanes_run
from kckf_jax._readings._prepare import prepare


def recorded_like(spec, overflow=False):
    robot = Robot.from_spec(spec)
    trials = [simulate(robot, "human", seed=s, duration_s=n / 100.0, drop_prob=0.05,
                       kinematics="exact") for s, n in ((1, 60), (2, 47), (3, 55))]
    batch = pad_series([SensorSeries(s.dt(), s.gyro, s.hall_v) for s in trials])
    dt = np.asarray(batch.dt).copy()
    if overflow:
        dt[1, 20] = 1e200  # an overflowing prediction: the row is skipped, the state kept
    batch = SensorSeries(jnp.asarray(dt), batch.gyro, batch.hall_v)
    rng = np.random.default_rng(0)
    G, J, M = 3 * robot.n_links, robot.n_joint_axes, robot.n_hall
    effects = SensorEffects(jnp.asarray(2.0), jnp.asarray(0.5),
                            jnp.asarray(rng.uniform(-1, 1, G)),
                            jnp.asarray(rng.uniform(0.8, 1.2, J)),
                            jnp.asarray(rng.uniform(-0.5, 0.5, (M, 2))),
                            jnp.asarray(rng.uniform(-5, 5, (robot.n_links, 3))),
                            on=EFFECTS)
    params = Params.from_physical(robot, hall_models=trials[0].hall_models,
                                  hall_noise="voltage", dtype=jnp.float64)
    return params.with_effects(EFFECTS, effects), batch


def run(params, batch, by_hand=True, chunk=None):
    """``Lanes``' run of ``kckf3d``: its reverse pass by hand (optionally in chunks) or, with
    ``by_hand=False``, JAX's own (each row recomputed and transposed)."""
    prepared = prepare(params, batch, "kckf3d", jnp.float64)
    state = init_states(params, "kckf3d", batch.dt.shape[0])
    return exact_lanes_run(params, prepared, state, True, by_hand, chunk)


def loss(params, batch, by_hand=True, chunk=None):
    """Every output the estimate has: angles, their standard deviations and the biases."""
    est = run(params, batch, by_hand, chunk)[1]
    return (jnp.nansum(est.angles**2) + 0.3 * jnp.nansum(est.angle_std)
            + jnp.nansum(jnp.sin(est.bias)))


@pytest.mark.parametrize("spec", ["x,y,x,y", pytest.param("xz,y,xyz", marks=pytest.mark.long)])
def test_parameter_gradient_equals_the_automatic_one(spec):
    """One-axis joints (constant entries), and joints of two and three axes; and the
    filter's gradient (``Lanes``, as a fitting loss takes it) is this one."""
    params, batch = recorded_like(spec)
    grad = eqx.filter_jit(eqx.filter_value_and_grad(loss))
    (v0, g0), (v1, g1) = grad(params, batch), grad(params, batch, False)
    assert float(v0) == pytest.approx(float(v1), rel=1e-12)
    assert_close(g0, g1, 1e-9)
    assert max(np.max(np.abs(np.asarray(x))) for x in leaves(g0.effects)) > 0

    def through_lanes(p):
        est = filter_batch(p, batch, "kckf3d", path=Lanes(min_trials=1))
        return (jnp.nansum(est.angles**2) + 0.3 * jnp.nansum(est.angle_std)
                + jnp.nansum(jnp.sin(est.bias)))

    # Two compiled programs, the same arithmetic in another order: 2e-12 of the leaf's scale
    # measured on xz,y,xyz once the monitor's noise floor changed the program around it.
    assert_close(eqx.filter_jit(eqx.filter_grad(through_lanes))(params), g0, 1e-11)


@pytest.mark.long  # the default run checks the parameters' gradient (x,y,x,y) above
def test_data_gradient_and_the_innovations_equal_the_automatic_ones():
    """The cotangents of the time steps, gyro readings and Hall voltages, through the
    estimate, every row's innovations and their variances (the likelihood's) and the final
    state; and the same in checkpointed chunks (``Lanes.exact_chunk``; 25 rows, the last
    chunk padded)."""
    params, batch = recorded_like("xy,z")

    def total(series, by_hand, chunk=None):
        final, est = run(params, series, by_hand, chunk)
        nu, s, valid = est.innovations
        return (jnp.nansum(est.angles**2) + 0.3 * jnp.nansum(est.angle_std)
                + jnp.sum(jnp.where(valid, nu**2 / s + jnp.log(s), 0.0))
                + jnp.sum(final.z**2) + jnp.sum(final.P))

    grads = [jax.jit(jax.value_and_grad(lambda x, a=a: total(x, *a)))(batch)
             for a in ((True,), (False,), (True, 25))]
    (v0, g0), (v1, g1), (v2, g2) = grads
    assert float(v0) == pytest.approx(float(v1), rel=1e-12)
    assert float(v2) == pytest.approx(float(v0), rel=1e-12)
    for a, b, c in zip(leaves(g0), leaves(g1), leaves(g2), strict=True):
        a, b, c = np.asarray(a), np.asarray(b), np.asarray(c)
        scale = np.max(np.abs(b))
        assert scale > 0
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * scale)
        np.testing.assert_allclose(c, a, rtol=0, atol=1e-12 * scale)


@pytest.mark.long
def test_a_skipped_row_passes_its_cotangents_through():
    """JAX's own gradient through an overflowing row is NaN; the hand-written one is NaN
    only in ``log_q``, whose row's process noise itself overflows (as for the linear KCKF's),
    and equals central finite differences in the others."""
    params, batch = recorded_like("x,y,x,y", overflow=True)
    plain = params.with_effects(())
    g = eqx.filter_jit(eqx.filter_grad(loss))(plain, batch)
    assert not np.all(np.isfinite(np.asarray(g.log_q)))
    auto = eqx.filter_jit(eqx.filter_grad(loss))(plain, batch, False)
    assert not np.isfinite(np.asarray(auto.log_hall_d)).all()
    f = jax.jit(lambda p: loss(p, batch))
    for name in ("log_hall_d", "log_p0_bias", "log_sigma_hall_v"):
        x = np.asarray(getattr(plain, name))
        got = np.asarray(getattr(g, name))
        for i in range(0, x.size, 3):
            h = 1e-6
            up, down = x.copy(), x.copy()
            up[i] += h
            down[i] -= h
            fd = (float(f(eqx.tree_at(lambda p, n=name: getattr(p, n), plain, jnp.asarray(up))))
                  - float(f(eqx.tree_at(lambda p, n=name: getattr(p, n), plain,
                                        jnp.asarray(down))))) / (2 * h)
            assert got[i] == pytest.approx(fd, rel=1e-6, abs=1e-8), (name, i)
