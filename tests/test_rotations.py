"""The finite rotations of a serial chain (``kckf_jax._models._rotations``) in JAX: the same
values as in NumPy, differentiable, and to first order the paper's linear model (Eqs. 2 and 14), the
ground a rotation-aware KCKF linearises (issue 35)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kckf_jax import Robot
from kckf_jax._models._rotations import (
    chain_rotation,
    euler_xyz,
    joint_jacobian,
    link_rates,
)


def _split(robot, theta):
    """Each joint's coordinates (its axes in order) from the joint-axis vector."""
    out, j = [], 0
    for axes in robot.joints:
        out.append(theta[..., j:j + len(axes)])
        j += len(axes)
    return out


def _torso(robot, theta, xp):
    phi = euler_xyz(chain_rotation(robot.joints, _split(robot, theta), xp), xp)
    return phi[..., [("x", "y", "z").index(a) for a in robot.torso_axes]]


@pytest.mark.parametrize("spec", ["xyz,xyz,xyz", "x,y,x,y", "xz,y,xyz"])
def test_jax_and_numpy_agree_and_the_torso_jacobian_is_the_papers_sum_at_zero(spec):
    robot = Robot.from_spec(spec)
    rng = np.random.default_rng(1)
    theta = 0.4 * rng.standard_normal(robot.n_joint_axes)
    np.testing.assert_allclose(_torso(robot, jnp.asarray(theta), jnp),
                               _torso(robot, theta, np), atol=1e-13)
    # The constraint's Jacobian (what an EKF linearises), by jacfwd, against central
    # differences at a finite pose, and equal to Eq. 14's sum matrix at the neutral pose.
    jac = jax.jacfwd(lambda th: _torso(robot, th, jnp))
    h = 1e-6
    fd = np.stack([(_torso(robot, theta + h * e, np) - _torso(robot, theta - h * e, np)) / (2 * h)
                   for e in np.eye(robot.n_joint_axes)], axis=1)
    np.testing.assert_allclose(jac(jnp.asarray(theta)), fd, atol=1e-8)
    np.testing.assert_allclose(jac(jnp.zeros(robot.n_joint_axes)), robot.torso_sum, atol=1e-15)


def test_link_rates_are_the_papers_rate_differences_at_the_neutral_pose():
    """At zero angles each link turns at the link below's rate plus its joint's rates (Eq. 2);
    a joint's Jacobian is then the identity on its axes."""
    robot = Robot.from_spec("xyz,xyz")
    rng = np.random.default_rng(2)
    rates = rng.standard_normal(robot.n_joint_axes)
    base = rng.standard_normal(3)
    zero = np.zeros(robot.n_joint_axes)
    w = link_rates(robot.joints, _split(robot, zero), _split(robot, rates), base)
    np.testing.assert_allclose(w[1], base + rates[:3], atol=1e-15)
    np.testing.assert_allclose(w[2], base + rates[:3] + rates[3:], atol=1e-15)
    np.testing.assert_allclose(joint_jacobian(("x", "y", "z"), np.zeros(3)), np.eye(3))
