"""The rotation-aware KCKF (``kckf3d``) against its independent NumPy reference, against the
linear KCKF at small angles, on exact-rotation data, and the paths' answers for it (what else
it works with: ``test_exact_uses.py``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import joints_of, random_params, random_recording, reference_params
from helpers import series_of as make_series
from reference_exact import Exact, reference_exact_filter

from kckf_jax import (
    Auto,
    Lanes,
    Params,
    Robot,
    Segments,
    choose_path,
    filter_batch,
    filter_sessions,
    pad_series,
    rmse_table,
    run_filter,
    simulate,
)
from kckf_jax._models._hall import hall_voltage
from kckf_jax._models._rotations import link_rates


@pytest.mark.parametrize("path", ["sequential", "lanes"])
@pytest.mark.parametrize(("seed", "spec", "noise"), [
    (0, "xyz,xyz,xyz", "angle"), (1, "x,y,x,y", "voltage"), (2, "xy,z", "angle"),
    (3, "yz,x,xz", "voltage")])
@pytest.mark.long
def test_matches_numpy_reference(seed, spec, noise, path):
    """Irregular time steps, 10 % missing readings, random parameters: 1e-8 rad, on the
    sequential path and on kckf3d's own lanes step (``_exact_lanes``)."""
    rng = np.random.default_rng(seed)
    robot = Robot.from_spec(spec)
    params = random_params(rng, robot, hall_noise=noise)
    t, gyro, hall_v = random_recording(rng, robot, T=60)
    ref = reference_exact_filter(joints_of(robot), t, gyro, hall_v, reference_params(params))
    final, est = run_filter(params, make_series(t, gyro, hall_v), "kckf3d", path=path)
    assert est.path == path
    assert np.abs(ref["angles"]).max() > 0.1  # angles where the rotations matter
    np.testing.assert_allclose(est.angles, ref["angles"], atol=1e-8, rtol=0)
    np.testing.assert_allclose(est.bias, ref["bias"], atol=1e-8, rtol=0)
    np.testing.assert_allclose(final.z[0], ref["z"], atol=1e-8, rtol=0)
    np.testing.assert_allclose(final.P[0], ref["P"], atol=1e-12, rtol=1e-6)


def _small_motion(robot, eps, T=600, seed=0):
    """Noise-free readings of a chain moving by ``eps`` rad from rest at the neutral pose
    (exact kinematics): joint angles, gyros from the exact link rates, Hall voltages through
    Eq. 1's inverse at the paper's curve."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) * 0.01
    f = rng.uniform(0.3, 1.2, (robot.n_joint_axes, 1))
    ph = np.zeros((robot.n_joint_axes, 1))  # every joint starts where the filters do
    theta = (eps * np.sin(2 * np.pi * f * t + ph)).T
    rate = (eps * 2 * np.pi * f * np.cos(2 * np.pi * f * t + ph)).T
    base = eps * np.stack([np.sin(t), np.sin(1.3 * t), np.sin(0.7 * t)], 1)
    model = Exact(joints_of(robot))
    gyro = np.concatenate(link_rates(robot.joints, [theta[:, s] for s in model.sl],
                                     [rate[:, s] for s in model.sl], base), axis=1)
    params = Params.paper_defaults(robot, dtype=jnp.float64)
    a, b, c, d, sign = (np.asarray(x) for x in params.hall_coeffs)
    deg = np.degrees(theta[:, robot.hall_joint_axis])
    hall_v = hall_voltage(deg, np.degrees(a), b, np.degrees(c), d, sign)
    return params, make_series(t, gyro, hall_v)


@pytest.mark.parametrize("spec", ["xyz,xyz,xyz", "x,y,x,y", "xy,z"])
def test_model_is_the_papers_to_first_order(spec):
    """The joints' rates (Eq. 2) and the torso angles (Eq. 14) of the exact model differ from
    the paper's by the square of the motion: angles and rates 10x smaller, about 100x
    closer."""
    from kckf_jax._models._exact import exact_model, joint_rates_jacobian, torso_angles

    robot = Robot.from_spec(spec)
    model = exact_model(robot)
    rng = np.random.default_rng(1)
    th0, g0 = rng.normal(size=robot.n_joint_axes), rng.normal(size=3 * robot.n_links)
    gaps = []
    for eps in (0.02, 0.002):
        th, g = jnp.asarray(eps * th0), jnp.asarray(eps * g0)
        u = joint_rates_jacobian(model, th, g)[0]
        paper_rates = (robot.rate_map @ np.asarray(g))[: robot.n_joint_axes]
        gaps.append(max(np.abs(u - paper_rates).max(),
                        np.abs(torso_angles(model, th) - robot.torso_sum @ np.asarray(th)).max()))
    assert gaps[0] / gaps[1] > 80, gaps


@pytest.mark.parametrize("spec", ["xyz,xyz,xyz", "x,y,x,y", "x,x"])
@pytest.mark.long
def test_close_to_the_linear_kckf_at_small_angles(spec):
    """At small angles (0.1 deg) the two filters' estimates differ by under 2.5 % of the motion,
    and 10x larger motion does not widen the gap by more than the square. Their models agree
    to first order (above); what remains at the smallest motion is their bias models (the
    paper's one per angle, ``kckf3d``'s one per gyro channel), whose gains weigh a step's
    integration error differently (on one-axis joints, whose rates the two models share,
    exactly in proportion to the motion); at 1 deg of 3-axis motion the linear model's own
    error dominates (its estimate 14 % of the motion off the truth, ``kckf3d``'s 4 %)."""
    robot = Robot.from_spec(spec)
    gaps = []
    for eps in (0.02, 0.002):
        params, series = _small_motion(robot, eps)
        lin = np.asarray(run_filter(params, series, "kckf")[1].angles)
        ex = np.asarray(run_filter(params, series, "kckf3d")[1].angles)
        assert np.abs(lin).max() > 0.5 * eps
        gaps.append(np.abs(ex - lin).max())
    assert gaps[1] < 0.025 * 0.002 and gaps[0] / gaps[1] > 7, gaps


def test_one_axis_joints_have_the_papers_rates_at_any_angle():
    """A one-axis joint turns its child about its own axis only, so its rate is its two
    links' gyro difference about that axis (Eq. 2) whatever the angles: the paper's, with
    no dependence on the pose."""
    from kckf_jax._models._exact import exact_model, joint_rates_jacobian

    robot = Robot.from_spec("x,y,x,y")
    rng = np.random.default_rng(4)
    th = jnp.asarray(rng.uniform(-1.2, 1.2, robot.n_joint_axes))
    g = jnp.asarray(rng.normal(size=3 * robot.n_links))
    u, Du, Dg = joint_rates_jacobian(exact_model(robot), th, g)
    W = robot.rate_map[: robot.n_joint_axes]
    np.testing.assert_allclose(u, W @ np.asarray(g), atol=1e-12)
    np.testing.assert_allclose(Dg, W, atol=1e-12)
    assert not np.asarray(Du).any()


@pytest.fixture(scope="module")
def walking():
    return [simulate("xyz,xyz,xyz", "walking", seed=s, duration_s=20.0, drop_prob=0.01,
                     kinematics="exact") for s in (5, 6)]


def test_exact_data_the_exact_filter_wins_and_torso_is_the_chain(walking):
    """On exact-rotation walking sessions the exact filter beats the linear one, and its
    torso angles are the Euler angles of its joints' chain at every row."""
    params = Params.paper_defaults(walking[0].robot)
    lin = rmse_table(walking, [e.angles for e in filter_sessions(walking, "kckf", params)])
    est = filter_sessions(walking, "kckf3d", params)
    ex = rmse_table(walking, [e.angles for e in est])
    assert ex["mean_rmse_deg"] < 0.7 * lin["mean_rmse_deg"], (ex, lin)
    model = Exact(joints_of(walking[0].robot))
    a = np.asarray(est[0].angles, np.float64)
    for k in range(0, a.shape[0], 97):
        np.testing.assert_allclose(a[k, 9:], model.torso_angles(a[k, :9]), atol=2e-5)


@pytest.mark.long
def test_paths_say_why_not_and_the_batch_runs_on_lanes(walking):
    """``Auto`` takes kckf3d's own lanes step from one trial on; the paths that precompute
    the linear filters' maps say why not; a fitting loss's policy takes the lanes too, in
    chunks when the gradient is chunked for memory."""
    params = Params.paper_defaults(walking[0].robot, dtype=jnp.float64)
    series = pad_series([make_series(s.t[:400], s.gyro[:400], s.hall_v[:400])
                         for s in walking] * 6)
    choice = choose_path(params, series, "kckf3d", Auto())
    assert choice.path.name == "lanes"
    assert "depend on the state" in choice.passed_over["steady"], choice.passed_over
    assert "depend on the state" in Segments().applies(params, series, "kckf3d")
    one_trial = jax.tree_util.tree_map(lambda x: x[:1], series)
    assert choose_path(params, one_trial, "kckf3d", Auto()).path.name == "lanes"
    # A gradient takes the lanes (their reverse pass is written by hand, _exact_adjoint);
    # one chunked for memory runs that pass in chunks.
    assert choose_path(params, series, "kckf3d", Auto().for_loss()).path == Lanes(min_trials=1)
    assert choose_path(params, series, "kckf3d", Auto().for_loss(100)).path == Lanes(
        exact_chunk=100)
    validation = choose_path(params, series, "kckf3d", Auto().for_loss(gradient=False))
    assert validation.path.name == "lanes"  # no gradient: the faster forward pass
    with pytest.raises(ValueError, match="lanes.* does not apply: kckf3d's lanes step"):
        filter_batch(params, series, "kckf3d", Lanes(exact=False))
    one = run_filter(params, jax.tree_util.tree_map(lambda x: x[1], series), "kckf3d",
                     path="sequential")[1]
    batch = filter_batch(params, series, "kckf3d")
    assert batch.path == "lanes"
    np.testing.assert_allclose(batch.angles[1], one.angles, atol=1e-12)
