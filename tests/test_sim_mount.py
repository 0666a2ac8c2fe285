"""Gyros as worn in the simulator (``_sessions/_sim_mount.py``; docs/simulator.md, "Sensor
effects"): each board's tilt on its link and its soft mount, off by default and then changing
nothing, and on, the physical definitions the docs give, checked against independent
arithmetic (a rotation applied by hand; the spring's steady-state response in closed form and
a fine Runge-Kutta integration)."""

from __future__ import annotations

import numpy as np
import pytest

from kckf_jax import SimConfig, simulate
from kckf_jax._sessions._sim_mount import rotation_matrices, soft_mount_rates
from kckf_jax._sessions._simulate import parse_effects
from kckf_jax.cli import main

DEG = np.pi / 180.0
# Gyros that read the rate alone: no bias, noise, scale error or coarse step.
IDEAL_GYRO = dict(gyro_noise_density_dps_rthz=0.0, gyro_zero_rate_dps=0.0,
                  gyro_temp_coeff_dps_per_c=0.0, gyro_bias_walk_dps_rts=0.0,
                  gyro_scale_error=0.0, gyro_lsb_dps=1e-9)


@pytest.mark.parametrize("kinematics", ["linear", "exact"])
def test_a_tilted_board_reads_the_links_rate_in_its_own_frame(kinematics):
    plain = simulate("x,y,z", "walking", seed=4, duration_s=5.0, kinematics=kinematics,
                     config=SimConfig(**IDEAL_GYRO))
    tilted = simulate("x,y,z", "walking", seed=4, duration_s=5.0, kinematics=kinematics,
                      config=SimConfig(**IDEAL_GYRO, gyro_mount_deg=12.0))
    tilt = tilted.extra_meta["simulation"]["effects"]["gyro_mount_deg"]
    v = np.array([tilt[f"gyro{i + 1}"] for i in range(4)]) * DEG
    angles = np.linalg.norm(v, axis=1) / DEG
    assert np.all((angles >= 6.0) & (angles <= 12.0))  # 12 x U(0.5, 1)
    # R' omega by hand: R from the recorded rotation vector (Rodrigues), the link's rate as
    # the untilted board read it.
    for i in range(4):
        k, a = v[i] / np.linalg.norm(v[i]), np.linalg.norm(v[i])
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        R = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
        want = plain.gyro[:, 3 * i:3 * i + 3] @ R
        np.testing.assert_allclose(tilted.gyro[:, 3 * i:3 * i + 3], want, atol=1e-8)
    # Nothing else moved: the Hall sensors and the truth are the plain session's.
    np.testing.assert_array_equal(tilted.hall_v, plain.hall_v)
    np.testing.assert_array_equal(tilted.mocap, plain.mocap)


def test_rotation_matrices_are_rotations():
    v = np.random.default_rng(0).normal(0, 0.3, (5, 3))
    R = rotation_matrices(v)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.einsum("lij,lj->li", R, v), v, atol=1e-12)  # the axis stays


def test_the_soft_mount_is_the_damped_spring_driven_by_the_links_acceleration():
    """A link turning as ``A sin(2 pi f0 t)``: after the transient the board's rate against
    it has the closed-form steady-state amplitude, and the whole response is a fine RK4
    integration of the same equation."""
    f0, A, fn, zeta = 3.0, 2.0, 8.0, 0.3
    t = np.arange(0, 4.0, 1e-3)
    omega = A * np.sin(2 * np.pi * f0 * t)
    rate, phi = soft_mount_rates(t, omega[:, None, None] * np.ones((1, 1, 3)), np.array([fn]),
                                 zeta)
    w, s = 2 * np.pi * fn, 2j * np.pi * f0
    gain = abs(-s**2 / (s**2 + 2 * zeta * w * s + w**2))  # phi' / omega
    late = t > 2.0
    assert np.max(np.abs(rate[late, 0, 0])) == pytest.approx(A * gain, rel=0.01)

    def f(x, time):  # RK4 of phi'' = -2 zeta w phi' - w^2 phi - alpha(t), alpha exact
        alpha = A * 2 * np.pi * f0 * np.cos(2 * np.pi * f0 * time)
        return np.array([x[1], -2 * zeta * w * x[1] - w**2 * x[0] - alpha])

    x, h, ref = np.zeros(2), 1e-4, []
    for k in range(len(t)):
        ref.append(x.copy())
        for j in range(10):
            tk = t[k] + j * h
            k1 = f(x, tk)
            k2 = f(x + h / 2 * k1, tk + h / 2)
            k3 = f(x + h / 2 * k2, tk + h / 2)
            k4 = f(x + h * k3, tk + h)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    ref = np.array(ref)
    scale = np.max(np.abs(ref[:, 1]))
    assert np.max(np.abs(rate[:, 0, 0] - ref[:, 1])) < 0.03 * scale
    assert np.max(np.abs(phi[:, 0, 0] - ref[:, 0])) < 0.03 * np.max(np.abs(ref[:, 0]))


def test_a_soft_mount_adds_its_wobble_and_records_it():
    plain = simulate("x,y", "walking", seed=2, duration_s=10.0, config=SimConfig(**IDEAL_GYRO))
    soft = simulate("x,y", "walking", seed=2, duration_s=10.0,
                    config=SimConfig(**IDEAL_GYRO, soft_mount_hz=6.0))
    rec = soft.extra_meta["simulation"]["effects"]["soft_mount"]
    assert rec["damping_ratio"] == 0.3
    assert all(4.8 <= f <= 7.2 for f in rec["natural_frequency_hz"].values())
    assert all(0 < x < 5 for x in rec["rms_wobble_deg"].values())
    diff = soft.gyro - plain.gyro
    assert 0 < np.sqrt(np.mean(diff**2)) < 0.5 * np.sqrt(np.mean(plain.gyro**2))
    # Its mean over the session is about zero: the board swings about its rest on the link.
    assert np.all(np.abs(diff.mean(axis=0)) < 0.01)


def test_effects_named_on_the_command_line_and_refused_when_unphysical(tmp_path):
    assert parse_effects(["mount=10", "soft=8"]) == {"gyro_mount_deg": 10.0,
                                                      "soft_mount_hz": 8.0}
    with pytest.raises(ValueError, match="damping"):
        simulate("x", duration_s=1.0, config=SimConfig(soft_mount_hz=5.0,
                                                       soft_mount_damping=1.5))
    with pytest.raises(ValueError, match="half the sample rate"):
        simulate("x", duration_s=1.0, config=SimConfig(soft_mount_hz=45.0))
    with pytest.raises(ValueError, match=">= 0"):
        parse_effects(["mount=-1"])
    assert main(["simulate", str(tmp_path / "s"), "--duration", "2", "--joints", "x,y",
                 "--effect", "mount=8", "--effect", "soft=10", "--quiet"]) == 0


# ------------------------------------------------------------- the start from the gyros alone
@pytest.mark.parametrize("spec", ["x,y,z", "x,y,x,y"])
def test_the_boards_between_two_hinges_are_found_from_the_gyros_alone(spec):
    """``estimate_mounting`` (the hinges' axes as the boards see them, Seel's constraint, then
    Kabsch): a board with a hinge on each side within 1 deg of its tilt; an end board, which
    sees one hinge, no farther from it than it was; no hinge, no change. Recorded-like gyros
    (noise, biases, 1 % dropped readings), exact walking, tilts of 5-10 deg."""
    from kckf_jax import estimate_mounting

    sessions = [simulate(spec, "walking", seed=k, duration_s=40.0, device_seed=7,
                         kinematics="exact", drop_prob=0.01,
                         config=SimConfig(gyro_mount_deg=10.0)) for k in (1, 2)]
    truth = np.array(list(sessions[0].extra_meta["simulation"]["effects"]["gyro_mount_deg"]
                          .values()))
    got, by = estimate_mounting(sessions[0].robot, sessions)
    err = np.linalg.norm(got - truth, axis=1)
    assert [len(b) for b in by] == [1] + [2] * (len(truth) - 2) + [1]
    assert np.all(err[1:-1] < 1.0)
    assert np.all(err[[0, -1]] < np.linalg.norm(truth[[0, -1]], axis=1))
    none, by_none = estimate_mounting(sessions[0].robot.from_spec("xyz,xyz"), [])
    assert not np.any(none) and by_none == [[], [], []]


def test_kabsch_and_the_smallest_rotation():
    from kckf_jax._fitting._mounting import board_rotation

    v = np.array([0.1, -0.2, 0.05])
    R = rotation_matrices(v)
    e = list(np.eye(3))
    seen = [R.T @ x for x in e[:2]]  # the board sees R' e
    np.testing.assert_allclose(board_rotation(seen, e[:2]), v, atol=1e-12)
    one = board_rotation(seen[:1], e[:1])  # one direction: the smallest rotation onto it
    np.testing.assert_allclose(rotation_matrices(one) @ seen[0], e[0], atol=1e-12)
    assert abs(one[0]) < 1e-12  # no turn about the direction itself


def _hinge_axis_errors_deg(joints: str, got_deg: np.ndarray, want_deg: np.ndarray) -> list:
    """Each one-axis joint's axis as each of its two boards sees it (``R' e``), under the
    learned against the true rotations, deg."""
    out = []
    for i, axis in enumerate(joints.split(",")):
        e = np.eye(3)["xyz".index(axis)]
        for b in (i, i + 1):
            Rg, Rw = rotation_matrices(np.radians(got_deg[b])), rotation_matrices(
                np.radians(want_deg[b]))
            out.append(np.degrees(np.arccos(np.clip((Rg.T @ e) @ (Rw.T @ e), -1.0, 1.0))))
    return out


@pytest.mark.long  # two fits of 150 steps (about 35 s)
def test_the_mounting_is_learned_with_the_scale_not_in_its_place():
    """A soft mount reads a cycle at ``f`` about ``(f / f_n)^2`` (1.1 % at 0.85 Hz on 8 Hz)
    high, and a board turned ``d`` off a hinge reads its rate ``cos d`` of itself: learned
    alone, the mounting turns about 9 deg off to stand in for that scale (docs/fitting.md).
    With ``gyro_scale`` learned beside it each hinge axis is found to 2 deg, and the held-out
    error is lower."""
    import jax.numpy as jnp

    import kckf_jax as kk

    def one(seed):
        return simulate("x,y,z", "cyclic", seed=seed, duration_s=20.0, device_seed=7,
                        kinematics="exact", drop_prob=0.01,
                        config=SimConfig(gyro_mount_deg=10.0, soft_mount_hz=8.0))

    train, val = [one(701), one(702)], [one(703)]
    truth = np.array(list(train[0].extra_meta["simulation"]["effects"]["gyro_mount_deg"]
                          .values()))
    errs, loss = {}, {}
    for learn in (("gyro_mounting",), ("gyro_mounting", "gyro_scale")):
        cfg = kk.FitConfig(steps=150, method="kckf3d", learn=learn, patience=1000)
        res = kk.fit(train, val, cfg, dtype=jnp.float32)
        errs[learn[-1]] = _hinge_axis_errors_deg(
            "x,y,z", np.asarray(res.params.effects.mounting, np.float64), truth)
        loss[learn[-1]] = res.best_loss_deg
    assert max(errs["gyro_scale"]) < 2.0, errs  # 1.54 deg at worst when written
    assert max(errs["gyro_mounting"]) > 3 * max(errs["gyro_scale"]), errs  # 9.9 deg
    assert loss["gyro_scale"] < loss["gyro_mounting"], loss  # 0.286 against 0.310 deg
