"""Shared test helpers: parameter conversion for the NumPy reference and random problems."""

from __future__ import annotations

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kckf_jax import Params, Robot, SensorSeries, SessionError, read_session
from kckf_jax._readings import _health

DEG = np.pi / 180


def reference_params(params: Params) -> dict:
    """The physical values of ``params`` as the plain dict ``tests/reference.py`` takes."""
    a, b, c, d, sign = (np.asarray(x, dtype=np.float64) for x in params.hall_coeffs)
    out = {k: np.asarray(getattr(params, k), dtype=np.float64)
           for k in ("q", "angle_rw", "bias_rw", "sigma_hall", "sigma_hall_v", "p0_angle",
                     "p0_bias")}
    out.update(a=a, b=b, c=c, d=d, sign=sign, hall_noise=params.hall_noise,
               hall_v_range=params.limits.hall_v, gyro_range_rad_s=params.limits.gyro_rad_s,
               joint_range_rad=params.limits.joint_range_rad,
               health={k: getattr(_health, k) for k in (
                   "CLIP_REPEATS", "CLIP_MIN_RAD_S", "HOLD_S", "RESTART_S", "MOTION_FRACTION",
                   "MOTION_FLOOR_RAD", "ROUGH_TAU_S", "ROUGH_HIGH", "ROUGH_LOW", "STUCK_S",
                   "STUCK_MOVE_RAD", "READMIT_S", "REF_TAU_S", "PAIR_FAST_S", "PAIR_SLOW_S",
                   "BIAS_STEP_RAD_S", "CM_FAST_S", "CM_SLOW_S", "BIAS_EVIDENCE_RAD",
                   "PAIR_SPREAD_S", "SPREAD_FACTOR", "MONITOR_MIN_SIGMA_V")}
               if params.faults.isolates else None)
    return out


def joints_of(robot: Robot) -> list[list[str]]:
    return [list(axes) for axes in robot.joints]


def random_robot(rng: np.random.Generator, max_joints: int = 4) -> Robot:
    n = int(rng.integers(1, max_joints + 1))
    joints = []
    for _ in range(n):
        axes = tuple(a for a in "xyz" if rng.random() < 0.5)
        joints.append(axes or (str(rng.choice(list("xyz"))),))
    return Robot(tuple(joints))


def random_params(rng: np.random.Generator, robot: Robot, hall_noise: str = "angle",
                  dtype=jnp.float64) -> Params:
    """Random but sensible parameters, Hall coefficients scattered around the paper's."""
    K, M = robot.n_angles, robot.n_hall
    models = {
        name: {"a": 0.07 * np.exp(0.1 * rng.standard_normal()),
               "b": 2.87 * np.exp(0.02 * rng.standard_normal()),
               "c": 2.22e5 * np.exp(0.1 * rng.standard_normal()),
               "d": 8.43 * np.exp(0.02 * rng.standard_normal()),
               "sign": s, "unit": "deg"}
        for name, s in zip(robot.hall_names, robot.hall_side_sign)
    }
    return Params.from_physical(
        robot,
        q=DEG**2 * np.exp(rng.uniform(-3, 3, K)),
        angle_rw=DEG * np.exp(rng.uniform(-4, 0, K)),
        bias_rw=0.1 * DEG * np.exp(rng.uniform(-3, 0, K)),
        sigma_hall=DEG * rng.uniform(1, 5, M),
        sigma_hall_v=rng.uniform(0.005, 0.05, M),
        p0_angle=DEG * rng.uniform(5, 40, K),
        p0_bias=DEG * rng.uniform(0.2, 2, K),
        hall_models=models, hall_noise=hall_noise, dtype=dtype,
    )


def random_recording(rng: np.random.Generator, robot: Robot, T: int = 120,
                     missing: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Timestamps, gyro rates and Hall voltages that follow the kinematic chain, with NaNs.

    Irregular time steps (5-15 ms); link rates are the base rate plus the rates of the joints
    below (so the constraint is consistent with the data); Hall voltages near the middle of
    the curve with noise.
    """
    t = np.cumsum(rng.uniform(0.005, 0.015, T)) - 0.01
    J = robot.n_joint_axes
    rates = 0.5 * rng.standard_normal((T, J))
    link = np.repeat(0.2 * rng.standard_normal((T, 1, 3)), robot.n_links, axis=1)
    for j, (i, a) in enumerate(robot.joint_axes):
        link[:, i:, "xyz".index(a)] += rates[:, j:j + 1]
    gyro = link.reshape(T, -1) + 0.01 + 0.002 * rng.standard_normal((T, 3 * robot.n_links))
    hall_v = rng.uniform(1.1, 1.9, (T, robot.n_hall))
    gyro[rng.random(gyro.shape) < missing] = np.nan
    hall_v[rng.random(hall_v.shape) < missing] = np.nan
    return t, gyro, hall_v


def series_of(t, gyro, hall_v, dtype=jnp.float64) -> SensorSeries:
    dt = np.diff(np.asarray(t, np.float64), prepend=t[0])
    return SensorSeries(jnp.asarray(dt, dtype), jnp.asarray(gyro, dtype),
                        jnp.asarray(hall_v, dtype))


def default_compile_env() -> dict[str, str]:
    """The environment for a subprocess that runs far more than it compiles (the demo, the
    one-hour run, the notebooks, a long fit): XLA's flags as the suite was started, without
    the compile flags that conftest.py gives every other process of the tests."""
    env = dict(os.environ)
    env.pop("KCKF_TEST_COMPILE_FLAGS", None)
    env["XLA_FLAGS"] = env.pop("KCKF_TEST_XLA_FLAGS", "")
    if not env["XLA_FLAGS"]:
        del env["XLA_FLAGS"]
    return env


def error_of(folder, **kwargs) -> str:
    """``read_session``'s refusal of ``folder``: a ``SessionError`` of one line."""
    with pytest.raises(SessionError) as info:
        read_session(folder, **kwargs)
    message = str(info.value)
    assert "\n" not in message, message
    return message


def leaves(tree) -> list:
    """The floating-point array leaves of a pytree (a gradient of ``Params``), in order."""
    return jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_inexact_array))


def assert_close(got, ref, rtol: float) -> None:
    """Every leaf of ``got`` finite and within ``rtol`` of the largest entry of ``ref``'s
    leaf (gradients: relative to the leaf's scale, not entry by entry)."""
    for a, b in zip(leaves(got), leaves(ref), strict=True):
        a, b = np.asarray(a), np.asarray(b)
        scale = np.max(np.abs(b)) if b.size else 0.0
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale + 1e-300)
