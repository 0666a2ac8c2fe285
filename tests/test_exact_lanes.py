"""``kckf3d`` on lanes (``_paths/_exact_lanes.py``): the exact step written with the trials as
the last axis equals the sequential path's (``exact_step`` under ``vmap``) to float64 rounding,
for every kind of joint, uneven padded trials, missing readings, a skipped update, the
innovations and the final state; its entry-by-entry closed forms equal the ones they restate.
(Against the NumPy reference: tests/test_exact.py, both paths.)"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_params, random_recording
from helpers import series_of as make_series

import kckf_jax as kk
from kckf_jax._models import _exact
from kckf_jax._models._classes import init_states
from kckf_jax._models._exact_entries import joint_rate_entries, torso_entries


@pytest.mark.parametrize("spec", ["xyz,xyz,xyz", "x,y,x,y", "xy,z", "yz,x,xz", "zx,zyx"])
def test_the_entries_are_the_closed_forms(spec):
    """``joint_rate_entries`` and ``torso_jacobian_entries`` (one array per entry, the trials
    last) against ``_exact``'s matrix forms, at large angles, for 5 trials at once."""
    robot = kk.Robot.from_spec(spec)
    model = _exact.exact_model(robot)
    rng = np.random.default_rng(0)
    B = 5
    theta = rng.uniform(-1.2, 1.2, (model.J, B))
    gyro = rng.normal(0, 2.0, (model.G, B))
    for i, (axes, sl) in enumerate(zip(robot.joints, model.joint_slices, strict=True)):
        u, Du, Dg = joint_rate_entries(axes, [jnp.asarray(theta[k]) for k in sl],
                                       list(jnp.asarray(gyro[3 * i:3 * i + 3])),
                                       list(jnp.asarray(gyro[3 * i + 3:3 * i + 6])))
        for b in range(B):
            want = _exact.joint_rate_jacobians(axes, jnp.asarray(theta[list(sl), b]),
                                               jnp.asarray(gyro[3 * i:3 * i + 3, b]),
                                               jnp.asarray(gyro[3 * i + 3:3 * i + 6, b]))
            for got, ref in zip((u, Du, Dg), want):
                got = np.array([[np.broadcast_to(np.asarray(x, float), (B,))[b] for x in row]
                                for row in (got if isinstance(got[0], list) else [got])])
                np.testing.assert_allclose(got.reshape(np.shape(ref)), ref, atol=1e-12)
    _, C = torso_entries(model, [jnp.asarray(theta[k]) for k in range(model.J)])
    for b in range(B):
        _, want = _exact.torso_angles_jacobian(model, jnp.asarray(theta[:, b]))
        got = np.array([[np.broadcast_to(np.asarray(x, float), (B,))[b] for x in row]
                        for row in C])
        np.testing.assert_allclose(got, want, atol=1e-12)


@pytest.mark.parametrize(("seed", "spec", "noise"), [
    pytest.param(0, "xyz,xyz,xyz", "voltage", marks=pytest.mark.long), (1, "x,y,x,y", "angle"),
    (2, "xy,z", "voltage"), pytest.param(3, "yz,x,xz", "angle", marks=pytest.mark.long)])
def test_the_lanes_equal_the_sequential_path(seed, spec, noise):
    """Three uneven trials (padded), irregular steps, 10 % missing readings, random
    parameters, one trial with a 1e100 s step (its noise overflows: the row is skipped):
    the lanes step's estimates, innovations and final state equal the sequential path's to
    1e-12."""
    rng = np.random.default_rng(seed)
    robot = kk.Robot.from_spec(spec)
    params = random_params(rng, robot, hall_noise=noise)
    trials = []
    for T in (50, 80, 65):
        t, gyro, hall_v = random_recording(rng, robot, T=T)
        trials.append(make_series(t, gyro, hall_v))
    big = np.asarray(trials[1].dt).copy()
    big[40] = 1e100  # its process noise overflows
    trials[1] = dataclasses.replace(trials[1], dt=jnp.asarray(big))
    batch = kk.pad_series(trials)
    seq = kk.filter_batch(params, batch, "kckf3d", path="sequential", innovations=True)
    lanes = kk.filter_batch(params, batch, "kckf3d", path="lanes", innovations=True)
    assert (seq.path, lanes.path) == ("sequential", "lanes")
    assert np.asarray(lanes.skipped)[1, 40] and np.asarray(seq.skipped)[1, 40]
    assert np.abs(np.asarray(seq.angles)).max() > 0.1  # angles where the rotations matter
    for name in ("angles", "angle_std", "bias", "skipped"):
        np.testing.assert_allclose(np.asarray(getattr(lanes, name), float),
                                   np.asarray(getattr(seq, name), float), atol=1e-12,
                                   err_msg=name)
    for got, ref in zip(lanes.innovations, seq.innovations):
        np.testing.assert_allclose(np.asarray(got, float), np.asarray(ref, float), atol=1e-12)
    # The final state, from the same screened batch: every leaf to 1e-12.
    state = init_states(params, "kckf3d", 3)
    screened = kk.screened(params, batch, "kckf3d")[0]
    f_l = kk.Lanes().compute(params, screened, "kckf3d", state).final
    f_s = kk.Sequential().compute(params, screened, "kckf3d", state).final
    for a, b in zip(jax.tree_util.tree_leaves(f_l), jax.tree_util.tree_leaves(f_s)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-12)


@pytest.mark.long
def test_float32_recorded_like_walking_stays_stable():
    """Five minutes of exact-rotation walking (recorded-like: jittered stamps, 1 % missing,
    the voltage noise), float32, 4 trials on lanes: finite, the final covariances symmetric
    positive definite, and within 0.05 deg of the float64 run."""
    sessions = [kk.simulate("xyz,xyz,xyz", "walking", seed=i, duration_s=300.0, drop_prob=0.01,
                            kinematics="exact") for i in range(4)]
    out = {}
    for dtype in (np.float32, np.float64):
        est = kk.filter_sessions(sessions, "kckf3d", dtype=dtype)
        assert {e.path for e in est} == {"lanes"}
        out[dtype] = np.stack([e.angles for e in est]).astype(np.float64)
    assert np.isfinite(out[np.float32]).all()
    assert np.degrees(np.abs(out[np.float32] - out[np.float64]).max()) < 0.05
    params = kk.Params.paper_defaults(sessions[0].robot, sessions[0].hall_models,
                                      dtype=jnp.float32)
    batch = kk.pad_series([kk.session_series(s, np.float32) for s in sessions])
    batch = jax.tree_util.tree_map(jnp.asarray, batch)
    final = kk.Lanes().compute(params, kk.screened(params, batch, "kckf3d")[0], "kckf3d",
                               init_states(params, "kckf3d", 4)).final
    P = np.asarray(final.P[:, 0], np.float64)
    np.testing.assert_array_equal(P, np.swapaxes(P, -1, -2))
    assert np.linalg.eigvalsh(P).min() > 0


@pytest.mark.long  # a heavy check beside a lighter default one (the default run within 4 min)
def test_the_packet_step_is_the_step():
    """The stream's and the export's forward-only step of kckf3d (``packet_step``: the entry
    form on one lane) equals the model's step (the matrix form) row by row, float64, random
    parameters and a recording with missing readings: estimates and states to 1e-12."""
    from kckf_jax._models._classes import ExactKCKF

    rng = np.random.default_rng(7)
    robot = kk.Robot.from_spec("xyz,x,zy")
    params = random_params(rng, robot, hall_noise="voltage")
    t, gyro, hall_v = random_recording(rng, robot, T=60)
    rows = kk.prepare(params, make_series(t, gyro, hall_v), "kckf3d")
    model = ExactKCKF()
    a = b = kk.init_state(params, "kckf3d")
    step = jax.jit(model.step)
    packet = jax.jit(model.packet_step)
    for k in range(60):
        row = jax.tree_util.tree_map(lambda x, k=k: x[k], rows)
        a, ea = step(params, a, row)
        b, eb = packet(params, b, row)
        for x, y in zip(jax.tree_util.tree_leaves((a, ea.angles, ea.angle_std, ea.bias)),
                        jax.tree_util.tree_leaves((b, eb.angles, eb.angle_std, eb.bias))):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=1e-12)
