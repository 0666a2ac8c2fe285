"""The simulator: deterministic, any layout, physically sensible signals."""

from __future__ import annotations

import numpy as np
import pytest

from kckf_jax import (
    Robot,
    SimConfig,
    hall_angle,
    hall_voltage,
    read_session,
    simulate,
    write_session,
)

DEG = np.pi / 180.0


def test_seeded_and_deterministic():
    a = simulate("x,y,x,y", "cyclic", seed=4, duration_s=5.0)
    b = simulate("x,y,x,y", "cyclic", seed=4, duration_s=5.0)
    c = simulate("x,y,x,y", "cyclic", seed=5, duration_s=5.0)
    np.testing.assert_array_equal(a.gyro, b.gyro)
    np.testing.assert_array_equal(a.hall_v, b.hall_v)
    assert not np.allclose(a.gyro, c.gyro)


@pytest.mark.parametrize("spec", ["x", "x,y,x,y", "xyz,xyz,xyz,xyz", "xz,y,xyz"])
@pytest.mark.parametrize("kind", ["cyclic", "static", "human"])
def test_any_layout_and_kind(spec, kind):
    robot = Robot.from_spec(spec)
    s = simulate(robot, kind, seed=1, duration_s=8.0, move_s=4.0)
    assert s.gyro.shape == (800, 3 * robot.n_links) and s.hall_v.shape == (800, robot.n_hall)
    assert np.all(np.isfinite(s.gyro)) and np.all(np.isfinite(s.hall_v))
    assert np.all((s.hall_v >= 0) & (s.hall_v <= 3.3))
    truth = s.truth()
    # The torso truth is the sum of the joint truths (Eq. 14), up to mocap noise.
    phi = truth[:, robot.n_joint_axes:]
    summed = truth[:, :robot.n_joint_axes] @ robot.torso_sum.T
    ok = np.isfinite(phi).all(1)
    assert np.sqrt(np.mean((phi[ok] - summed[ok]) ** 2)) < 0.6 * DEG


def test_gyro_differences_integrate_to_the_joint_angles():
    """Without bias and noise, Eq. 2 integrated reproduces the mocap joint angles."""
    cfg = SimConfig(gyro_noise_density_dps_rthz=0.0, gyro_zero_rate_dps=0.0,
                    gyro_temp_coeff_dps_per_c=0.0, gyro_bias_walk_dps_rts=0.0,
                    gyro_scale_error=0.0, gyro_lsb_dps=1e-9, mocap_noise_deg=0.0)
    robot = Robot.from_spec("x,y,x,y")
    s = simulate(robot, "cyclic", seed=2, duration_s=20.0, config=cfg)
    rates = s.gyro @ robot.rate_map.T
    angles = np.concatenate([[np.zeros(robot.n_angles)],
                             np.cumsum(rates[:-1] * np.diff(s.t)[:, None], axis=0)])
    err = angles - s.truth()
    # Euler integration (Eq. 9) of a ~1 Hz, +-20 deg motion at 100 Hz lags by half a step:
    # an error that oscillates with the rate (about ts/2 * 200 deg/s) but does not accumulate.
    assert np.nanmax(np.abs(err)) < 1.5 * DEG
    assert np.all(np.abs(np.nanmean(err, axis=0)) < 0.1 * DEG)


def test_gyro_bias_is_within_the_datasheet_zero_rate_level():
    s = simulate("x,y", "static", seed=3, duration_s=30.0, move_s=5.0)
    still = s.t > 10.0
    mean_rate = s.gyro[still].mean(axis=0)
    assert np.all(np.abs(mean_rate) < 1.2 * DEG)  # +-1 dps plus warm-up drift
    assert np.std(mean_rate) > 0.05 * DEG  # every gyro has its own offset


def test_hall_noise_is_amplified_on_the_saturated_side():
    """Voltage noise through the curve: a sensor's angle noise grows where |d theta/dV| does."""
    robot = Robot.from_spec("x")
    s = simulate(robot, "cyclic", seed=6, duration_s=60.0)
    true_models = s.extra_meta["simulation"]["true_hall_models"]
    theta = s.truth()[:, 0]
    for m, name in enumerate(robot.hall_names):
        c = true_models[name]
        ang = np.asarray(hall_angle(s.hall_v[:, m], c["a"] * DEG, c["b"], c["c"] * DEG, c["d"],
                                    c["sign"]))
        err = ang - theta
        sat = (theta * c["sign"]) < -8 * DEG  # the flat side of this sensor's curve
        lin = np.abs(theta) < 3 * DEG
        assert np.nanstd(err[sat]) > 2 * np.nanstd(err[lin]), name


def test_hall_voltage_inverts_the_model():
    rng = np.random.default_rng(0)
    ang = rng.uniform(-40, 40, 500) * DEG
    a, b, c, d = 0.07 * DEG, 2.87, 2.22e5 * DEG, 8.43
    for sign in (1, -1):
        v = hall_voltage(ang, a, b, c, d, sign)
        np.testing.assert_allclose(np.asarray(hall_angle(v, a, b, c, d, sign)), ang, atol=1e-10)


def test_hall_voltage_is_the_root_to_rounding_on_the_saturating_side_too():
    """Against plain bisection (200 halvings of [-2, 6] V, float64): the inverse stops at the
    root where Newton reaches the rounding floor (e.g. -60 deg with sign +1, where the next
    step rounds onto the bracket's end) instead of bisecting away from it."""
    ang = np.linspace(-120.0, 120.0, 4001) * DEG
    a, b, c, d = 0.07 * DEG, 2.87, 2.22e5 * DEG, 8.43
    for sign in (1.0, -1.0):
        lo, hi = np.full(ang.shape, -2.0), np.full(ang.shape, 6.0)
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            above = sign * (np.asarray(hall_angle(mid, a, b, c, d, sign)) - ang) >= 0
            lo, hi = np.where(above, lo, mid), np.where(above, mid, hi)
        np.testing.assert_allclose(hall_voltage(ang, a, b, c, d, sign), 0.5 * (lo + hi),
                                   rtol=0, atol=1e-12)


def test_drops_mocap_clock_and_roundtrip(tmp_path):
    s = simulate("x,y,x,y", "human", seed=8, duration_s=10.0, drop_prob=0.05)
    frac = np.isnan(s.hall_v).mean()
    assert 0.03 < frac < 0.07
    assert s.mocap_time_offset_s != 0.0
    assert abs(np.median(np.diff(s.mocap_t)) - 1 / 120) < 1e-9
    truth = s.truth()
    assert np.isnan(truth[0]).all() and np.isnan(truth[-1]).all()  # mocap span is shorter
    write_session(s, tmp_path / "s")
    r = read_session(tmp_path / "s")
    np.testing.assert_array_equal(r.t, s.t)
    np.testing.assert_allclose(r.gyro, s.gyro, rtol=1e-8, equal_nan=True)
    assert r.extra_meta["simulation"]["kind"] == "human"


def test_bad_arguments():
    with pytest.raises(ValueError, match="kind must be one of"):
        simulate("x", "walk")
    with pytest.raises(ValueError, match="duration_s must be positive"):
        simulate("x", duration_s=0)
