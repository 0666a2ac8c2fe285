"""The exact model's Jacobians written from the rotations' closed forms (``_exact.
joint_rate_jacobians``, ``torso_angles_jacobian``; ``_rotations.chain_rotation_axes``,
``euler_xyz_jacobian``) against ``jax.jacfwd`` of the same functions (the model's Jacobians
before issue 49, kept here as the reference), in float64: at random poses up to +-140 deg,
near the torso's Euler singularity, under ``vmap`` and differentiated again; and ``kckf3d``'s
estimates unchanged with the reference in their place."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_params, random_recording
from helpers import series_of as make_series

from kckf_jax import Robot, run_filter, simulate
from kckf_jax._models import _exact
from kckf_jax._models._exact import (
    coordinate_rates,
    exact_model,
    joint_rates_jacobian,
    torso_angles,
    torso_angles_jacobian,
    torso_euler,
)
from kckf_jax._models._rotations import (
    chain_rotation_axes,
    euler_xyz,
    euler_xyz_jacobian,
    joint_rotation,
)

SPECS = ["x,y,z", "x,y,x,y", "xyz,xyz,xyz", "xy,z", "yz,x,xz"]
DEG = np.pi / 180


# ---------------------------------------------------------------- the reference (jacfwd)
def _with_jacobian(f, x):
    jac, value = jax.jacfwd(lambda v: (f(v), f(v)), has_aux=True)(x)
    return value, jac


def reference_joint_rates_jacobian(model, theta, gyro):
    """``joint_rates_jacobian`` as it was: ``jacfwd`` over each joint's coordinates and its two
    links' gyros."""
    g = gyro.reshape(-1, 3)
    dtype = theta.dtype
    us, d_theta, d_gyro = [], [], []
    for i, (axes, sl) in enumerate(zip(model.robot.joints, model.joint_slices, strict=True)):
        m = len(axes)
        th = theta[sl[0]:sl[-1] + 1]

        def f(v, axes=axes, m=m):
            return coordinate_rates(axes, v[:m], v[m + 3:] - joint_rotation(axes, v[:m], jnp).T
                                    @ v[m:m + 3])

        u, D = _with_jacobian(f, jnp.concatenate([th, g[i], g[i + 1]]))
        us.append(u)
        d_theta.append(D[:, :m] if m > 1 else jnp.zeros((1, 1), dtype))
        d_gyro.append(D[:, m:])
    # Assembled independently of the module's concatenations: a block diagonal, and each
    # joint's rows written at its two links' gyro columns.
    Du = jax.scipy.linalg.block_diag(*d_theta)
    Dg = jnp.zeros((Du.shape[0], g.size), dtype)
    row = 0
    for i, d in enumerate(d_gyro):
        Dg = Dg.at[row:row + d.shape[0], 3 * i:3 * i + 6].set(d)
        row += d.shape[0]
    return jnp.concatenate(us), Du, Dg


def reference_torso_angles_jacobian(model, theta):
    """``torso_angles`` and ``jacfwd`` of it."""
    return torso_angles(model, theta), jax.jacfwd(lambda th: torso_angles(model, th))(theta)


# ---------------------------------------------------------------- poses
def _poses(robot, rng, n=6):
    """Random poses: moderate, then large (one-axis joints and a multi-axis joint's outer
    coordinates up to +-140 deg; its middle one, where its Jacobian is singular at +-90 deg,
    up to +-75)."""
    J = robot.n_joint_axes
    middle = np.zeros(J, bool)
    j = 0
    for axes in robot.joints:
        if len(axes) == 3:
            middle[j + 1] = True
        j += len(axes)
    out = [rng.uniform(-40, 40, J) * DEG for _ in range(n // 2)]
    out += [np.where(middle, rng.uniform(-75, 75, J), rng.uniform(-140, 140, J)) * DEG
            for _ in range(n - n // 2)]
    return out


def _near_gimbal_lock(model, rng, gap):
    """A pose whose torso y Euler angle is ``pi/2 - gap`` (Newton's steps from a random pose
    on ``torso_euler``'s y, the smallest change of ``theta``)."""
    th = jnp.asarray(rng.uniform(-30, 30, model.J) * DEG)
    target = np.pi / 2 - gap
    grad = jax.jacfwd(lambda t: torso_euler(model, t)[1])
    for _ in range(60):
        r = target - torso_euler(model, th)[1]
        if abs(float(r)) < 1e-14:
            break
        d = grad(th)
        th = th + d * r / jnp.dot(d, d)
    assert abs(float(torso_euler(model, th)[1]) - target) < 1e-12
    return th


def _close(a, b, tol=1e-10):
    """``a`` and ``b`` within ``tol``, relative to ``b``'s scale where it is above 1 (near
    the singularities the Jacobians' entries grow as ``1 / cos``)."""
    a, b = np.asarray(a), np.asarray(b)
    np.testing.assert_allclose(a, b, atol=tol * max(1.0, np.abs(b).max()), rtol=0)


# ---------------------------------------------------------------- the joints' rates
@pytest.mark.parametrize("spec", SPECS)
def test_joint_rates_jacobians_are_jacfwds(spec):
    robot = Robot.from_spec(spec)
    model = exact_model(robot)
    rng = np.random.default_rng(sum(map(ord, spec)))
    for th in _poses(robot, rng):
        th = jnp.asarray(th)
        g = jnp.asarray(rng.normal(scale=2.0, size=model.G))
        new = joint_rates_jacobian(model, th, g)
        ref = reference_joint_rates_jacobian(model, th, g)
        for a, b in zip(new, ref, strict=True):
            assert a.shape == b.shape and a.dtype == b.dtype
            _close(a, b)
        if all(len(axes) == 1 for axes in robot.joints):
            assert not np.asarray(new[1]).any()  # one-axis joints: no angle dependence


@pytest.mark.parametrize("spec", [pytest.param("xyz,xyz,xyz", marks=pytest.mark.long), "xy,z"])
def test_joint_rates_under_vmap_jit_and_differentiated_again(spec):
    """The closed forms batch, compile, and their own derivatives (the fit's gradient
    differentiates the step, ``F`` included) are ``jacfwd``'s of ``jacfwd``."""
    robot = Robot.from_spec(spec)
    model = exact_model(robot)
    rng = np.random.default_rng(3)
    ths = jnp.asarray(np.stack(_poses(robot, rng, 4)))
    gs = jnp.asarray(rng.normal(size=(4, model.G)))
    batched = jax.jit(jax.vmap(lambda t, g: joint_rates_jacobian(model, t, g)))(ths, gs)
    for k in range(4):
        for a, b in zip(batched, reference_joint_rates_jacobian(model, ths[k], gs[k]),
                        strict=True):
            _close(a[k], b)

    def second(fn):
        return jax.jacfwd(lambda t, g: fn(model, t, g)[1:], argnums=(0, 1))(ths[3], gs[3])

    new, ref = second(joint_rates_jacobian), second(reference_joint_rates_jacobian)
    for a, b in zip(jax.tree_util.tree_leaves(new), jax.tree_util.tree_leaves(ref), strict=True):
        _close(a, b, 1e-9)


# ---------------------------------------------------------------- the torso
@pytest.mark.parametrize("spec", SPECS)
def test_torso_jacobian_is_jacfwds(spec):
    robot = Robot.from_spec(spec)
    model = exact_model(robot)
    rng = np.random.default_rng(7 + sum(map(ord, spec)))
    poses = [jnp.asarray(th) for th in _poses(robot, rng)]
    poses += [_near_gimbal_lock(model, rng, gap) for gap in (0.05, 1e-3)]
    for th in poses:
        phi, C = torso_angles_jacobian(model, th)
        phi_ref, C_ref = reference_torso_angles_jacobian(model, th)
        np.testing.assert_array_equal(phi, phi_ref)  # the same products, the same values
        assert C.shape == C_ref.shape == (robot.n_torso_axes, robot.n_joint_axes)
        _close(C, C_ref)
        # All three Euler angles (a robot's torso axes may be fewer)
        R, S = chain_rotation_axes(robot.joints, [th[sl[0]:sl[-1] + 1]
                                                   for sl in model.joint_slices], jnp)
        _close(euler_xyz_jacobian(R, S, jnp), jax.jacfwd(lambda t: torso_euler(model, t))(th))
        np.testing.assert_array_equal(euler_xyz(R, jnp), torso_euler(model, th))


def test_torso_jacobian_at_the_neutral_pose_is_the_papers_sum():
    robot = Robot.from_spec("xyz,xyz,xyz")
    _, C = torso_angles_jacobian(exact_model(robot), jnp.zeros(robot.n_joint_axes))
    np.testing.assert_array_equal(C, robot.torso_sum)


def test_rotation_helpers_work_in_numpy_on_leading_axes():
    """``_rotations``' functions take ``xp`` and any leading axes; the new ones too."""
    robot = Robot.from_spec("xy,z,xyz")
    rng = np.random.default_rng(5)
    th = rng.uniform(-1, 1, (4, robot.n_joint_axes))
    model = exact_model(robot)
    angles = [th[:, sl[0]:sl[-1] + 1] for sl in model.joint_slices]
    R, S = chain_rotation_axes(robot.joints, angles, np)
    D = euler_xyz_jacobian(R, S, np)
    assert R.shape == (4, 3, 3) and S.shape == (4, 3, 6) and D.shape == (4, 3, 6)
    for k in range(4):
        _close(D[k], jax.jacfwd(lambda t: torso_euler(model, t))(jnp.asarray(th[k])))


# ---------------------------------------------------------------- the filter
@pytest.fixture
def reference_jacobians(monkeypatch):
    """The filter with the ``jacfwd`` Jacobians in place of the closed forms (the compiled
    programs cleared on the way in and out, so that neither is reused for the other)."""
    jax.clear_caches()
    monkeypatch.setattr(_exact, "joint_rates_jacobian", reference_joint_rates_jacobian)
    monkeypatch.setattr(_exact, "torso_angles_jacobian", reference_torso_angles_jacobian)
    yield
    monkeypatch.undo()
    jax.clear_caches()


def _recordings():
    rng = np.random.default_rng(11)
    out = []
    for spec in ("xy,z", "x,y,x,y"):
        robot = Robot.from_spec(spec)
        t, gyro, hall_v = random_recording(rng, robot, T=80)
        out.append((random_params(rng, robot, hall_noise="voltage"),
                    make_series(t, 4 * gyro, hall_v)))  # rates that turn the joints far
    s = simulate("xyz,xyz,xyz", "walking", seed=3, duration_s=2.0, drop_prob=0.01,
                 kinematics="exact")
    from kckf_jax import Params
    out.append((Params.paper_defaults(s.robot, dtype=jnp.float64),
                make_series(s.t, s.gyro, s.hall_v)))
    return out


@pytest.mark.long  # six kckf3d compiles, and the compiled programs cleared twice
def test_filter_estimates_unchanged(request):
    """``kckf3d`` on three robots (one with a two-axis joint, one of three-axis joints on
    exact walking), float64: the closed forms' estimates are the ``jacfwd`` ones to 1e-10."""
    cases = _recordings()
    new = [run_filter(p, s, "kckf3d") for p, s in cases]
    request.getfixturevalue("reference_jacobians")
    ref = [run_filter(p, s, "kckf3d") for p, s in cases]
    for (fa, ea), (fb, eb) in zip(new, ref, strict=True):
        assert np.abs(np.asarray(eb.angles)).max() > 0.3  # poses where the rotations matter
        for name in ("angles", "angle_std", "bias"):
            np.testing.assert_allclose(getattr(ea, name), getattr(eb, name), atol=1e-10,
                                       rtol=0, err_msg=name)
        np.testing.assert_allclose(fa.z, fb.z, atol=1e-10, rtol=0)
        np.testing.assert_allclose(fa.P, fb.P, atol=1e-12, rtol=1e-8)
