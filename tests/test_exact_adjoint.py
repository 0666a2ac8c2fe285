"""``kckf3d``'s lanes filter, its hand-written reverse pass (``_paths/_exact_adjoint.py``)
against JAX's own (``Lanes(remat_chunk=...)`` keeps it: each row recomputed and transposed by
JAX) and against finite differences, in float64.

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

from kckf_jax import Lanes, Params, Robot, SensorSeries, filter_batch, pad_series, simulate
from kckf_jax._models._classes import init_states
from kckf_jax._models._effects import EFFECTS, SensorEffects
from kckf_jax._paths._exact_lanes import exact_lanes_run
from kckf_jax._readings._prepare import prepare

AUTOMATIC = Lanes(remat_chunk=40)  # JAX's own transpose of the step, each row recomputed


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


def loss(params, batch, path):
    """Every output the estimate has: angles, their standard deviations and the biases."""
    est = filter_batch(params, batch, "kckf3d", path=path)
    return (jnp.nansum(est.angles**2) + 0.3 * jnp.nansum(est.angle_std)
            + jnp.nansum(jnp.sin(est.bias)))


def leaves(tree):
    return jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_inexact_array))


def assert_close(got, ref, rtol):
    for a, b in zip(leaves(got), leaves(ref), strict=True):
        a, b = np.asarray(a), np.asarray(b)
        scale = np.max(np.abs(b)) if b.size else 0.0
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale + 1e-300)


@pytest.mark.parametrize("spec", ["x,y,x,y", pytest.param("xz,y,xyz", marks=pytest.mark.long)])
def test_parameter_gradient_equals_the_automatic_one(spec):
    """One-axis joints (constant entries), and joints of two and three axes."""
    params, batch = recorded_like(spec)
    grad = eqx.filter_jit(eqx.filter_value_and_grad(loss))
    (v0, g0), (v1, g1) = grad(params, batch, Lanes()), grad(params, batch, AUTOMATIC)
    assert float(v0) == pytest.approx(float(v1), rel=1e-12)
    assert_close(g0, g1, 1e-9)
    assert max(np.max(np.abs(np.asarray(x))) for x in leaves(g0.effects)) > 0


def test_data_gradient_and_the_innovations_equal_the_automatic_ones():
    """The cotangents of the time steps, gyro readings and Hall voltages, through the
    estimate and through every row's innovations and their variances (the likelihood's)."""
    params, batch = recorded_like("xy,z")

    def total(series, by_hand):
        prepared = prepare(params, series, "kckf3d", jnp.float64)
        B = series.dt.shape[0]
        state = init_states(params, "kckf3d", B)
        final, est = exact_lanes_run(params, prepared, state, True, by_hand)
        nu, s, valid = est.innovations
        return (jnp.nansum(est.angles**2) + 0.3 * jnp.nansum(est.angle_std)
                + jnp.sum(jnp.where(valid, nu**2 / s + jnp.log(s), 0.0))
                + jnp.sum(final.z**2) + jnp.sum(final.P))

    g0, g1 = (jax.jit(jax.grad(lambda x, b=b: total(x, b)))(batch) for b in (True, False))
    for a, b in zip(leaves(g0), leaves(g1), strict=True):
        a, b = np.asarray(a), np.asarray(b)
        scale = np.max(np.abs(b))
        assert scale > 0
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * scale)


@pytest.mark.long
def test_a_skipped_row_passes_its_cotangents_through():
    """JAX's own gradient through an overflowing row is NaN in every leaf; the hand-written
    one is NaN only in ``log_q``, whose row's process noise itself overflows (as for the
    linear KCKF's), and equals central finite differences in the others."""
    params, batch = recorded_like("x,y,x,y", overflow=True)
    plain = params.with_effects(())
    g = eqx.filter_jit(eqx.filter_grad(loss))(plain, batch, Lanes())
    assert not np.all(np.isfinite(np.asarray(g.log_q)))
    auto = eqx.filter_jit(eqx.filter_grad(loss))(plain, batch, AUTOMATIC)
    assert not np.isfinite(np.asarray(auto.log_hall_d)).all()
    f = jax.jit(lambda p: loss(p, batch, Lanes()))
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
