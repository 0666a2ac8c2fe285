"""The JAX filters against the independent NumPy float64 reference, and their invariants."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import joints_of, random_params, random_recording, random_robot, reference_params
from helpers import series_of as make_series
from reference import reference_baseline, reference_filter

from kckf_jax import (
    METHODS,
    Params,
    Robot,
    filter_batch,
    init_state,
    pad_series,
    prepare_row,
    run_filter,
    step,
)
from kckf_jax._models._blocks import full_state
from kckf_jax._models._classes import structure


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("method", ["kckf", "kf"])
def test_matches_numpy_reference(seed, method):
    """Random robots, parameters, irregular time steps and 10 % missing readings: 1e-6 rad."""
    rng = np.random.default_rng(seed)
    robot = random_robot(rng)
    noise = "voltage" if seed % 2 else "angle"
    params = random_params(rng, robot, hall_noise=noise)
    t, gyro, hall_v = random_recording(rng, robot, T=100)
    ref = reference_filter(joints_of(robot), t, gyro, hall_v, reference_params(params), method)
    final, est = run_filter(params, make_series(t, gyro, hall_v), method)
    np.testing.assert_allclose(est.angles, ref["angles"], atol=1e-6, rtol=0)
    np.testing.assert_allclose(est.bias, ref["bias"], atol=1e-6, rtol=0)
    # The final state and covariance, mapped back to the paper's coordinates.
    x, P = full_state(structure(robot, method), final.z, final.P)
    np.testing.assert_allclose(x, ref["x"][-1], atol=1e-6, rtol=0)
    np.testing.assert_allclose(P, ref["P"][-1], atol=1e-9, rtol=1e-6)


@pytest.mark.parametrize("method", ["gyro", "hall_l", "hall_r"])
def test_baselines_match_reference(method):
    rng = np.random.default_rng(7)
    robot = Robot.from_spec("xy,z,x")
    params = random_params(rng, robot)
    t, gyro, hall_v = random_recording(rng, robot, T=80, missing=0.2)
    ref = reference_baseline(joints_of(robot), t, gyro, hall_v, reference_params(params), method)
    _, est = run_filter(params, make_series(t, gyro, hall_v), method)
    np.testing.assert_allclose(est.angles, ref, atol=1e-9, equal_nan=True)


def _check_invariants(params, series, method):
    robot = params.robot
    st = structure(robot, method)
    state = init_state(params, method)
    D = np.hstack([robot.torso_sum, -np.eye(robot.n_torso_axes)])
    for k in range(series.dt.shape[0]):
        row = jax.tree_util.tree_map(lambda x, k=k: x[k], series)
        state, row = prepare_row(params, state, row, method)  # the row screened alone
        state, est = step(params, state, row, method)
        Pb = np.asarray(state.P, np.float64)
        assert np.all(np.isfinite(Pb)) and np.all(np.isfinite(np.asarray(state.z)))
        np.testing.assert_allclose(Pb, np.swapaxes(Pb, 1, 2), atol=0, rtol=0)
        for Pp in Pb:  # every block, in filter coordinates, without padding joints
            used = np.diag(Pp) > 0
            assert np.linalg.eigvalsh(Pp[np.ix_(used, used)]).min() > 0, f"not PD at step {k}"
        x, _ = full_state(st, state.z, state.P)
        if method == "kckf":
            assert np.max(np.abs(D @ x[: robot.n_angles])) < 1e-5 * (1 + np.abs(x).max())
            ang = np.asarray(est.angles, np.float64)
            np.testing.assert_allclose(
                robot.torso_sum @ ang[: robot.n_joint_axes], ang[robot.n_joint_axes:],
                rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("method", ["kckf", "kf"])
@pytest.mark.long
def test_constraint_and_positive_definite_every_step(dtype, method):
    rng = np.random.default_rng(3)
    robot = Robot.from_spec("xz,y,xyz")
    params = random_params(rng, robot, dtype=dtype)
    t, gyro, hall_v = random_recording(rng, robot, T=60, missing=0.3)
    _check_invariants(params, make_series(t, gyro, hall_v, dtype), method)


@pytest.mark.long
def test_no_nan_from_extreme_finite_inputs():
    """Any finite input (huge rates, rail voltages, tiny and huge dt) leaves the state finite."""
    rng = np.random.default_rng(11)
    robot = Robot.from_spec("x,y,x,y")
    params = Params.paper_defaults(robot, dtype=jnp.float32)
    T = 50
    dt = np.abs(rng.standard_normal(T)) * np.array([1e-6, 1e-3, 0.01, 1.0, 30.0] * 10)
    gyro = rng.standard_normal((T, 15)) * 50.0  # up to thousands of deg/s
    hall_v = rng.choice([0.0, 0.2, 1.0, 1.8, 3.3], (T, 8))
    series = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32),
                                    make_series(np.cumsum(dt), gyro, hall_v, jnp.float32))
    for method in METHODS:
        final, est = run_filter(params, series, method)
        assert np.all(np.isfinite(np.asarray(final.z))), method
        assert np.all(np.isfinite(np.asarray(final.P))), method


@pytest.mark.long
def test_vmap_equals_loop_and_padding_is_a_no_op():
    rng = np.random.default_rng(5)
    robot = Robot.from_spec("x,y,x,y")
    params = random_params(rng, robot)
    trials = [make_series(*random_recording(rng, robot, T=T)) for T in (40, 55, 31)]
    batch = pad_series(trials)
    for method in ("kckf", "kf", "gyro"):
        est = filter_batch(params, batch, method)
        for b, trial in enumerate(trials):
            _, one = run_filter(params, trial, method)
            n = trial.dt.shape[0]
            np.testing.assert_allclose(est.angles[b, :n], one.angles, rtol=1e-12, atol=1e-12)
            # Padding rows repeat the last estimate.
            np.testing.assert_allclose(est.angles[b, n:], np.broadcast_to(
                one.angles[-1], est.angles[b, n:].shape), rtol=1e-12, atol=1e-12)


@pytest.mark.long
def test_jit_equals_eager():
    rng = np.random.default_rng(9)
    robot = Robot.from_spec("xy,x")
    params = random_params(rng, robot)
    series = make_series(*random_recording(rng, robot, T=5))
    _, jitted = run_filter(params, series, "kckf")
    with jax.disable_jit():
        _, eager = run_filter(params, series, "kckf")
    np.testing.assert_allclose(jitted.angles, eager.angles, rtol=1e-10, atol=1e-12)


def test_float32_follows_params_dtype():
    robot = Robot.from_spec("x,y")
    params = Params.paper_defaults(robot, dtype=jnp.float32)
    rng = np.random.default_rng(0)
    series = make_series(*random_recording(rng, robot, T=10), dtype=jnp.float64)
    _, est = run_filter(params, series, "kckf")
    assert est.angles.dtype == jnp.float32


def test_unknown_method_is_a_clear_error():
    params = Params.paper_defaults(Robot.from_spec("x"))
    with pytest.raises(ValueError, match="unknown method 'ukf'.*kckf"):
        init_state(params, "ukf")
