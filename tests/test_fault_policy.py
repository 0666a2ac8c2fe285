"""What the health monitor's findings do (``--faults isolate|report|off``), and the monitor on
data that is not the paper's linear model (issue 45): exact rotations at large angles are
the model's approximation, named once, never isolated."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest
from helpers import joints_of, random_params, random_recording, random_robot, reference_params
from helpers import series_of as make_series
from reference import reference_filter

import kckf_jax as kk
from kckf_jax import FaultPolicy, Params, Robot
from kckf_jax._readings._screen import SCREEN_KINDS
from kckf_jax.cli import main

BENCH = Robot.from_spec("x,y,x,y")
NAMES = BENCH.gyro_names + BENCH.hall_names


def test_the_policy_is_one_object_with_a_clear_error():
    assert FaultPolicy.of(None) == FaultPolicy("isolate")
    assert FaultPolicy.of("report") == FaultPolicy("report")
    with pytest.raises(ValueError, match="FaultPolicy.mode: expected one of"):
        FaultPolicy("ignore")
    with pytest.raises(ValueError, match="FaultPolicy.mode"):
        kk.FitConfig(faults="skip")
    p = Params.paper_defaults(BENCH).with_faults("off")
    assert p.faults == FaultPolicy("off") and p.astype(np.float64).faults == p.faults
    assert "faults" not in kk.params_to_dict(p)  # a setting of the run, not a fitted value


@pytest.mark.parametrize("seed", [0, 1, 3])
def test_off_is_the_filter_without_the_monitor(seed):
    """``off``: every reading the screen lets through, as before the monitor (the NumPy
    reference without its health rules), float64, 1e-9 rad; on random data whose roughness
    the monitor does judge."""
    assert jax.config.jax_enable_x64  # conftest.py
    rng = np.random.default_rng(seed)
    robot = random_robot(rng)
    params = random_params(rng, robot, hall_noise="voltage").with_faults("off")
    t, gyro, hall_v = random_recording(rng, robot, T=100)
    ref = reference_filter(joints_of(robot), t, gyro, hall_v, reference_params(params), "kckf")
    _, est = kk.run_filter(params, make_series(t, gyro, hall_v), "kckf")
    np.testing.assert_allclose(est.angles, ref["angles"], atol=1e-9, rtol=0)


@pytest.fixture(scope="module")
def faulty():
    s = kk.simulate(BENCH, "cyclic", seed=2, duration_s=40.0, device_seed=2)
    return kk.inject_faults(s, [kk.Fault.parse(x) for x in (
        "noise:hall2_y_r@10-12=0.5", "bias_step:gyro3_x@20=0.2", "disconnect:hall4_y_l@30-33")])


def test_report_names_what_isolate_takes_out_and_changes_no_estimate(faulty):
    est = {f: kk.filter_sessions([faulty], faults=f)[0] for f in ("isolate", "report", "off")}
    np.testing.assert_array_equal(est["report"].angles, est["off"].angles)
    np.testing.assert_array_equal(est["report"].faults, est["isolate"].faults)
    assert not np.array_equal(est["isolate"].angles, est["off"].angles)
    kinds = {f["kind"] for f in kk.fault_stretches(faulty.t, est["off"].faults, NAMES)}
    assert kinds and kinds <= set(SCREEN_KINDS)  # off: the plausibility screen alone


@pytest.mark.parametrize("policy", ["report", "off"])
def test_the_stream_and_the_batch_filter_follow_one_policy(faulty, policy):
    params = Params.paper_defaults(BENCH, faulty.hall_models).with_faults(policy)
    est = kk.filter_sessions([faulty], params=params)[0]
    sf = kk.StreamingFilter(params)
    parser = kk.PacketParser(BENCH, params=params)
    out = []
    for k in range(faulty.n_steps):
        pkt = parser.check(kk.Packet(float(faulty.t[k]), faulty.gyro[k].copy(),
                                     faulty.hall_v[k].copy(), "ok"))
        rec = sf.push(pkt)
        out.append([rec.get(n, np.nan) for n in BENCH.angle_names])
    np.testing.assert_allclose(np.array(out), np.asarray(est.angles), atol=1e-4)


def test_evaluate_takes_faults_and_says_what_report_keeps(faulty, tmp_path, capsys):
    kk.write_session(faulty, tmp_path / "s")
    assert main(["evaluate", str(tmp_path / "s"), "--faults", "report", "--json"]) == 0
    out = capsys.readouterr()
    doc = json.loads(out.out)
    assert doc["fault_policy"] == "report"
    assert "judged faulty, still used (--faults report" in out.err
    assert "railed" in out.err and "faulty reading(s) not used" in out.err
    assert main(["evaluate", str(tmp_path / "s"), "--faults", "off", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert {f["kind"] for f in doc["faults"][str(tmp_path / "s")]} <= set(SCREEN_KINDS)


@pytest.mark.parametrize("joints,kind", [("x,y,x,y", "walking"), ("x,y,z", "human"),
                                         ("xyz,xyz,xyz", "walking")])
@pytest.mark.long
def test_exact_rotations_at_large_angles_are_not_faults(joints, kind):
    """Clean exact-rotation sessions, joints to 120 deg: the linear KCKF's monitor isolates
    no sensor for more than a moment (before: gyro2_y and gyro3_y bias_step for most of the
    session) and costs at most 2 % against ``off``; the pairs' disagreement is named as the
    model's approximation. kckf3d, which has no pairs, isolates nothing."""
    cfg = dataclasses.replace(kk.SimConfig(), motion_range_deg=120.0)
    s = kk.simulate(joints, kind, seed=4, duration_s=30.0, config=cfg, kinematics="exact")
    names = s.robot.gyro_names + s.robot.hall_names
    for method in ("kckf", "kckf3d"):
        iso, off = (kk.filter_sessions([s], method, faults=f)[0] for f in ("isolate", "off"))
        found = [f for f in kk.fault_stretches(s.t, iso.faults, names)
                 if f["kind"] not in SCREEN_KINDS]
        if method == "kckf3d":
            assert not found, found
        assert all(f["to_s"] - f["from_s"] <= 2.0 for f in found), found
        assert sum(f["count"] for f in found) <= 0.02 * s.n_steps, found
        r_iso, r_off = (kk.rmse_table([s], [e.angles])["mean_rmse_deg"] for e in (iso, off))
        assert r_iso <= 1.02 * r_off, (method, r_iso, r_off)
    pairs = kk.model_mismatch(s, "kckf")
    if any(s.robot.gyro_stand_ins):  # the paper's pairs, across joints of other axes
        assert pairs and all(p["corr"] >= 0.5 for p in pairs), pairs
    assert kk.model_mismatch(s, "kckf3d") == []


@pytest.mark.parametrize("joints,kind", [("x,y,z", "walking"), ("x,y,x,y", "cyclic")])
def test_linear_data_at_large_angles_is_no_mismatch(joints, kind):
    """The linear simulator's pairs read one rate: no mismatch at 140 deg either (its gyros'
    1 % scale errors correlate with the exact rotations' prediction, at a slope far below
    the 0.5 the rule asks)."""
    cfg = dataclasses.replace(kk.SimConfig(), motion_range_deg=140.0)
    for seed in (1, 2):
        assert kk.model_mismatch(kk.simulate(joints, kind, seed, 20.0, config=cfg), "kckf") == []


def test_a_bias_step_does_not_pass_for_the_model():
    """A real bias step on a linear session is a fault, not a mismatch: the pair's
    difference does not follow the exact rotations' prediction."""
    s = kk.simulate(BENCH, "cyclic", seed=3, duration_s=40.0, device_seed=3)
    bad = kk.inject_faults(s, [kk.Fault.parse("bias_step:gyro3_x@20=0.2")])
    assert kk.model_mismatch(bad, "kckf") == []
    assert kk.model_mismatch(s, "kckf") == []


@pytest.mark.long
def test_a_fitted_small_voltage_noise_calls_no_healthy_sensor_noisy():
    """A fit shrinks ``sigma_hall_v`` where the gyros' model misses (boards tilted 10 deg, not
    modelled: 0.005 V on the z joint against a true 0.03 V, issue 50). The monitor judges
    against at least the default noise (``_health.MONITOR_MIN_SIGMA_V``): judged against
    0.005 V both healthy sensors of a joint were isolated for the whole session (0.70 -> 37
    deg). Half a volt of noise on one sensor is still found with the same parameters."""
    cfg = dataclasses.replace(kk.SimConfig(), gyro_mount_deg=10.0)
    robot = Robot.from_spec("x,y,z")
    p = Params.from_physical(robot, sigma_hall_v=0.005)
    names = robot.gyro_names + robot.hall_names
    clean = kk.simulate(robot, "walking", seed=3, duration_s=20.0, device_seed=7, config=cfg,
                        kinematics="exact", drop_prob=0.01)
    iso, off = (kk.filter_sessions([clean], "kckf3d", p, faults=f)[0]
                for f in ("isolate", "off"))
    assert kk.fault_stretches(clean.t, iso.faults, names) == []
    np.testing.assert_array_equal(iso.angles, off.angles)
    fault = kk.Fault.parse("noise:hall3_z_l@8-12=0.5")
    noisy = kk.simulate(robot, "walking", seed=3, duration_s=20.0, device_seed=7, config=cfg,
                        kinematics="exact", drop_prob=0.01, faults=[fault])
    found = kk.fault_stretches(noisy.t, kk.filter_sessions([noisy], "kckf3d", p)[0].faults,
                               names)
    assert {f["column"] for f in found} == {"hall3_z_l"}, found  # railed too, by the screen
    (stretch,) = [f for f in found if f["kind"] == "noisy"]
    assert 8.0 <= stretch["from_s"] <= 8.5 and stretch["to_s"] <= 13.0, found  # + READMIT_S
