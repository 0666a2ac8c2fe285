"""The simulator's sensor effects (docs/simulator.md, "Sensor effects"): each off by default and
then changing nothing; on, each is the physical definition the docs give, with its true values
in ``meta.json``'s ``simulation.effects``."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from kckf_jax import Robot, SimConfig, hall_angle, read_session, simulate, write_session
from kckf_jax.cli import main

DEG = np.pi / 180.0
ROBOT = Robot.from_spec("x,y")
# The Hall readings without noise, wander or a coarse ADC, and the truth without noise and so
# dense that interpolating it onto the sensor times costs no more than 0.002 deg (at 120 Hz:
# 0.02 deg): what a sensor sees is then read back from its voltage through its true curve.
CLEAN_HALL = dict(hall_v_noise=0.0, hall_v_wander=0.0, adc_bits=24, mocap_noise_deg=0.0,
                  mocap_rate_hz=4000.0)


# --------------------------------------------------------------------------- effects off
def _canon(x):
    """Floats to 9 significant digits, so that the fingerprint does not hang on the last bit."""
    if isinstance(x, float):
        return float(f"{x:.9g}")
    if isinstance(x, dict):
        return {k: _canon(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_canon(v) for v in x]
    return x


def _fingerprint(s) -> str:
    """SHA-256 of a session's arrays (rounded to 1e-9) and of its meta without the effects
    record."""
    h = hashlib.sha256()
    for a in (s.t, s.gyro, s.hall_v, s.mocap_t, s.mocap, [s.mocap_time_offset_s]):
        h.update((np.round(np.asarray(a, dtype=np.float64), 9) + 0.0).tobytes())
    meta = json.loads(json.dumps(s.extra_meta))
    meta["simulation"].pop("effects")
    h.update(json.dumps(_canon(meta), sort_keys=True).encode())
    return h.hexdigest()


# Recorded from the simulator before the effects existed (the commit before them, b66b95e).
BEFORE_EFFECTS = {
    "cyclic": (dict(robot="x,y,x,y", kind="cyclic", seed=1, duration_s=20.0, drop_prob=0.01),
               "ddb746a99e7f297f185cb531e4afad1f4fe86a7f674cd298325167cc50cdab1e"),
    "human": (dict(robot="x,y,x,y", kind="human", seed=2, duration_s=20.0, device_seed=5),
              "9f274bf4370f82077137d632c0e61be89c1402ea0ace0f142a3f960cd35c8e77"),
    "walking_exact": (dict(robot="xyz,xyz", kind="walking", seed=3, duration_s=10.0,
                           kinematics="exact"),
                      "db9599fe01a0b5e1c96dc03f6de66cd2210889d5a9f9c2bcbfa560e180463169"),
}


@pytest.mark.parametrize("case", sorted(BEFORE_EFFECTS))
def test_effects_off_is_the_simulator_before_them(case):
    kwargs, digest = BEFORE_EFFECTS[case]
    s = simulate(**kwargs)
    assert _fingerprint(s) == digest
    sim = s.extra_meta["simulation"]
    assert list(sim["effects"]) == ["gyro_scale"]  # the gyro scales alone, always recorded
    assert not {"hall_play_deg", "hall_curve_deg", "mocap_sync_error_s"} & set(sim["config"])


# --------------------------------------------------------------------------- play and curve
def _seen_deg(s, robot: Robot) -> np.ndarray:
    """(T, M) the angle each Hall sensor saw, deg: its voltage through its true Eq. 1 curve."""
    models = s.extra_meta["simulation"]["true_hall_models"]
    cols = [models[n] for n in robot.hall_names]
    a, b, c, d, sign = (np.array([m[k] for m in cols], dtype=float)
                        for k in ("a", "b", "c", "d", "sign"))
    return np.asarray(hall_angle(s.hall_v, a * DEG, b, c * DEG, d, sign)) / DEG


def _play(angle: np.ndarray, h: np.ndarray) -> np.ndarray:
    """The play operator written out: p_k = clip(p_{k-1}, a_k - h, a_k + h), p_0 = a_0."""
    p = np.empty_like(angle)
    p[0] = angle[0]
    for k in range(1, len(angle)):
        p[k] = np.clip(p[k - 1], angle[k] - h, angle[k] + h)
    return p


def _legendre_deviation(angle_deg, p2, p3):
    u = angle_deg / 30.0
    return np.polynomial.legendre.legval(u, np.array([np.zeros_like(p2), 0 * p2, p2, p3]),
                                         tensor=False)


@pytest.mark.parametrize("play, curve", [(1.0, 0.0), (0.0, 0.8), (1.0, 0.8)])
def test_play_and_curve_are_what_the_sensors_see(play, curve):
    """The sensor sees the joint through the play, then through its curve's deviation."""
    s = simulate(ROBOT, "cyclic", seed=4, duration_s=20.0,
                 config=SimConfig(**CLEAN_HALL, hall_play_deg=play, hall_curve_deg=curve))
    effects = s.extra_meta["simulation"]["effects"]
    names = ROBOT.hall_names
    assert ("hall_play_deg" in effects) == (play > 0)
    assert ("hall_curve_deg" in effects) == (curve > 0)
    per_axis = effects.get("hall_play_deg", {})  # one per joint axis: both sensors see it
    axes = s.robot.angle_names[:s.robot.n_joint_axes]
    h = np.array([per_axis.get(axes[j], 0.0) for j in s.robot.hall_joint_axis])
    p2, p3 = (np.array([effects["hall_curve_deg"][n][k] if curve else 0.0 for n in names])
              for k in ("p2", "p3"))
    if play:
        assert np.all((h >= 0.75 * play) & (h <= 1.25 * play)) and np.ptp(h) > 0
    theta = s.truth()[:, ROBOT.hall_joint_axis] / DEG  # (T, M) the joint each sensor is on
    ok = np.isfinite(theta).all(axis=1)
    first = np.argmax(ok)  # the session is still and neutral here: the play holds nothing
    assert ok[first:np.flatnonzero(ok)[-1] + 1].all()
    theta = theta[ok]
    seen = _seen_deg(s, ROBOT)[ok]
    p = _play(theta, h)
    expected = p + _legendre_deviation(p, p2, p3)
    assert np.max(np.abs(seen - expected)) < 0.01
    assert np.max(np.abs(seen - theta)) > 0.5 * max(play, curve)  # the effect is there
    if play and not curve:
        # A steady motion (one way for the last 0.2 s and by more than the play's width):
        # the sensor reads theta - h sign(rate).
        n = 20
        step = np.diff(theta, axis=0)
        one_way = np.array([np.all(step[k - n:k] > 0, axis=0) | np.all(step[k - n:k] < 0,
                                                                        axis=0)
                            for k in range(n, len(step) + 1)])
        moved = np.abs(theta[n:] - theta[:-n]) > 2 * h
        steady = one_way & moved
        assert steady.mean() > 0.2
        lag = (seen - theta)[n:]
        want = -h * np.sign(theta[n:] - theta[:-n])
        np.testing.assert_allclose(lag[steady], np.broadcast_to(want, lag.shape)[steady],
                                   atol=0.01)


def test_curve_coefficients_have_the_stated_rms():
    s = simulate("x,y,x,y", "human", seed=1, duration_s=5.0, config=SimConfig(hall_curve_deg=0.7))
    curve = s.extra_meta["simulation"]["effects"]["hall_curve_deg"]
    p2 = np.array([c["p2"] for c in curve.values()])
    p3 = np.array([c["p3"] for c in curve.values()])
    np.testing.assert_allclose(np.sqrt(p2**2 / 5 + p3**2 / 7), 0.7, rtol=1e-12)
    u = np.linspace(-1, 1, 200_001)  # the same RMS taken numerically over +-30 deg
    dev = _legendre_deviation(30.0 * u[:, None], p2, p3)
    np.testing.assert_allclose(np.sqrt(np.trapezoid(dev**2, u, axis=0) / 2), 0.7, rtol=1e-6)
    assert np.ptp(np.arctan2(p3 / np.sqrt(7), p2 / np.sqrt(5))) > 0.1  # each sensor its own


def test_effect_values_belong_to_the_device():
    cfg = SimConfig(hall_play_deg=1.0, hall_curve_deg=0.5)

    def effects(seed, device_seed, config=cfg):
        s = simulate(ROBOT, "cyclic", seed=seed, duration_s=2.0, config=config,
                     device_seed=device_seed)
        return s.extra_meta["simulation"]["effects"]

    a, b, c = effects(1, 9), effects(2, 9), effects(2, 10)
    assert a == b and a["hall_play_deg"] != c["hall_play_deg"]
    assert a["hall_curve_deg"] != c["hall_curve_deg"]
    # One effect's values do not move when the other is turned off.
    alone = effects(1, 9, SimConfig(hall_curve_deg=0.5))
    assert alone["hall_curve_deg"] == a["hall_curve_deg"] and "hall_play_deg" not in alone


# --------------------------------------------------------------------------- sync error
def test_sync_error_shifts_the_aligned_truth(tmp_path):
    """meta.json's offset is wrong by eps: after alignment the motion capture shows at t the
    robot at t - eps, so a perfect estimate minus that truth is about eps * rate."""
    eps = 0.05
    cfg = dict(mocap_noise_deg=0.0)
    s0 = simulate("x,y,x,y", "cyclic", seed=2, duration_s=20.0, config=SimConfig(**cfg))
    s1 = simulate("x,y,x,y", "cyclic", seed=2, duration_s=20.0,
                  config=SimConfig(**cfg, mocap_sync_error_s=eps))
    for k in ("t", "gyro", "hall_v", "mocap_t", "mocap"):
        np.testing.assert_array_equal(getattr(s1, k), getattr(s0, k))
    assert s1.mocap_time_offset_s == pytest.approx(s0.mocap_time_offset_s + eps, abs=1e-15)
    write_session(s1, tmp_path / "s")
    r = read_session(tmp_path / "s")
    assert r.extra_meta["simulation"]["effects"]["mocap_sync_error_s"] == eps
    t, true, aligned = r.t, s0.truth(), r.truth()
    have = np.isfinite(true).all(1)
    tt = t[have]
    ok = np.isfinite(aligned).all(1) & (t - eps >= tt[0]) & (t + eps <= tt[-1])

    def shifted(dt):
        return np.stack([np.interp(t[ok] + dt, tt, true[have, k])
                         for k in range(true.shape[1])], 1)

    assert np.max(np.abs(aligned[ok] - shifted(-eps))) < 0.05 * DEG
    assert np.max(np.abs(aligned[ok] - shifted(+eps))) > 2 * DEG  # the sign matters
    rate = np.gradient(true[have], tt, axis=0)[ok[have]]
    err = (true[ok] - aligned[ok]).ravel()
    slope = np.dot(err, rate.ravel()) / np.dot(rate.ravel(), rate.ravel())
    assert slope == pytest.approx(eps, rel=0.05)  # a finite difference, not a derivative


# --------------------------------------------------------------------------- gyro scales
def test_gyro_scales_are_recorded_per_column():
    clean = dict(gyro_noise_density_dps_rthz=0.0, gyro_zero_rate_dps=0.0,
                 gyro_temp_coeff_dps_per_c=0.0, gyro_bias_walk_dps_rts=0.0, gyro_lsb_dps=1e-9)
    ideal = simulate(ROBOT, "cyclic", seed=3, duration_s=5.0,
                     config=SimConfig(**clean, gyro_scale_error=0.0))
    s = simulate(ROBOT, "cyclic", seed=3, duration_s=5.0, config=SimConfig(**clean))
    scale = s.extra_meta["simulation"]["effects"]["gyro_scale"]
    assert list(scale) == list(ROBOT.gyro_names)
    sc = np.array(list(scale.values()))
    assert 0.003 < np.std(sc) < 0.03  # 1 % (normal) per axis
    moving = np.abs(ideal.gyro) > 0.05
    expected = (1 + sc) * ideal.gyro
    np.testing.assert_allclose(s.gyro[moving], expected[moving], rtol=1e-6)


def test_every_effect_round_trips_through_meta_json(tmp_path):
    cfg = SimConfig(hall_play_deg=0.5, hall_curve_deg=1.0, mocap_sync_error_s=-0.02)
    s = simulate("xyz", "walking", seed=5, duration_s=3.0, config=cfg)
    write_session(s, tmp_path / "s")
    sim = read_session(tmp_path / "s").extra_meta["simulation"]
    assert sim["effects"] == s.extra_meta["simulation"]["effects"]
    assert list(sim["effects"]) == ["hall_play_deg", "hall_curve_deg", "mocap_sync_error_s",
                                    "gyro_scale"]
    assert {k: sim["config"][k] for k in ("hall_play_deg", "hall_curve_deg",
                                          "mocap_sync_error_s")} == {
        "hall_play_deg": 0.5, "hall_curve_deg": 1.0, "mocap_sync_error_s": -0.02}
    assert SimConfig(**sim["config"]) == cfg


@pytest.mark.parametrize("field, value", [("hall_play_deg", -1.0), ("hall_curve_deg", np.inf),
                                          ("mocap_sync_error_s", np.nan)])
def test_bad_effect_sizes_are_refused(field, value):
    with pytest.raises(ValueError, match=f"config.{field} must be a finite number"):
        simulate("x", duration_s=1.0, config=SimConfig(**{field: value}))


# --------------------------------------------------------------------------- the command
def test_cli_writes_the_effects(tmp_path, capsys):
    out = tmp_path / "s"
    code = main(["simulate", str(out), "--seed", "2", "--duration", "5", "--joints", "x,y",
                 "--effect", "play=1.5", "--effect", "curve=0.5", "--effect", "sync=-0.03"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "effects: play=1.5 curve=0.5 sync=-0.03" in err
    meta = json.loads((out / "meta.json").read_text())
    effects = meta["simulation"]["effects"]
    assert effects["mocap_sync_error_s"] == -0.03
    assert set(effects["hall_curve_deg"]) == set(ROBOT.hall_names)
    assert set(effects["hall_play_deg"]) == set(ROBOT.angle_names[:ROBOT.n_joint_axes])
    expected = simulate(ROBOT, "cyclic", seed=2, duration_s=5.0, config=SimConfig(
        hall_play_deg=1.5, hall_curve_deg=0.5, mocap_sync_error_s=-0.03))
    assert effects == expected.extra_meta["simulation"]["effects"]
    assert meta["mocap_time_offset_s"] == expected.mocap_time_offset_s
    np.testing.assert_allclose(read_session(out).hall_v, expected.hall_v, rtol=1e-8)


@pytest.mark.parametrize("specs, message", [
    (["wobble=1"], "--effect 'wobble=1': unknown name 'wobble'; expected one of play, curve, "
                   "sync, delay, mount, soft"),
    (["play"], "--effect 'play': expected NAME=SIZE, e.g. play=1"),
    (["curve=abc"], "--effect 'curve=abc': size 'abc' is not a number"),
    (["play=-1"], "--effect 'play=-1': the size must be a finite number >= 0"),
    (["sync=nan"], "--effect 'sync=nan': the size must be a finite number"),
    (["play=1", "play=2"], "--effect 'play=2': play is given twice"),
])
def test_cli_bad_effect_is_one_line_and_exit_2(tmp_path, capsys, specs, message):
    out = tmp_path / "s"
    args = [x for spec in specs for x in ("--effect", spec)]
    code = main(["simulate", str(out), "--duration", "2", *args])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1 and lines[0] == f"kckf simulate: error: {message}", captured.err
    assert not out.exists()


def test_gyro_delay_reads_the_rate_late():
    """``gyro_delay_s``: the reading at t_k is the rate at t_k - d, the draws unchanged."""
    d = 0.004
    quiet = SimConfig(gyro_noise_density_dps_rthz=0.0)  # white noise is not delayed
    base = simulate(ROBOT, "cyclic", seed=2, duration_s=6.0, config=quiet)
    late = simulate(ROBOT, "cyclic", seed=2, duration_s=6.0,
                    config=SimConfig(gyro_noise_density_dps_rthz=0.0, gyro_delay_s=d))
    assert late.extra_meta["simulation"]["effects"]["gyro_delay_s"] == d
    np.testing.assert_array_equal(late.hall_v, base.hall_v)
    moved = np.stack([np.interp(base.t - d, base.t, base.gyro[:, i])
                      for i in range(base.gyro.shape[1])], axis=1)
    lsb = SimConfig().gyro_lsb_dps * np.pi / 180
    rows = slice(50, None)  # after the first rows (before the start: the first sample's rate)
    err = np.abs(late.gyro[rows] - moved[rows])
    assert np.max(err) < 3 * lsb  # rounding of both to the LSB, and interpolating twice
    assert np.max(np.abs(late.gyro[rows] - base.gyro[rows])) > 20 * lsb  # the delay shows
