"""A gyro bias step under ``kckf3d`` (``kk.bias_steps``): named from the filter's own bias
estimate, with the gyro channels that explain it, and never on a clean recording (issue 45,
item 3: ``kckf3d`` has no gyro pairs for the health monitor to compare)."""

from __future__ import annotations

import dataclasses
import json
import types

import numpy as np
import pytest

import kckf_jax as kk
from kckf_jax._readings._bias_steps import MIN_STEP_RAD_S
from kckf_jax.cli import main


def _estimate(robot, t, steps=(), wobble=0.01, seed=0):
    """A bias estimate as a filter gives one: a slow wander per joint axis, and each step
    ``(joint axis, t_s, size)`` reached over 2 s (the filter's lag)."""
    rng = np.random.default_rng(seed)
    K = len(robot.angle_names)
    bias = 0.02 * np.cumsum(rng.standard_normal((t.size, K)), axis=0) / np.sqrt(t.size)
    bias += wobble * np.sin(2 * np.pi * 0.8 * t)[:, None] + 0.005 * rng.standard_normal(
        (t.size, K))
    for j, t_s, size in steps:
        bias[:, j] += size * np.clip((t - t_s) / 2.0, 0.0, 1.0)
    return types.SimpleNamespace(bias=bias)


def _session(spec, duration=30.0, rate=100.0):
    robot = kk.Robot.from_spec(spec)
    return types.SimpleNamespace(robot=robot, t=np.arange(0.0, duration, 1.0 / rate))


def test_a_clean_wander_is_not_a_step():
    s = _session("x,y,x,y")
    for seed in range(5):
        assert kk.bias_steps(s, _estimate(s.robot, s.t, seed=seed)) == [], seed
    # A wobble with the pose as large as the step bar is not a step either.
    assert kk.bias_steps(s, _estimate(s.robot, s.t, wobble=MIN_STEP_RAD_S)) == []


def test_a_one_axis_joint_names_both_of_its_gyros():
    s = _session("x,y,x,y")
    j = s.robot.angle_names.index("theta3_x")
    (step,) = kk.bias_steps(s, _estimate(s.robot, s.t, [(j, 15.0, -0.2)]))
    # theta3_x's rate is gyro4_x less gyro3_x: either one's step explains it.
    assert step["columns"] == ["gyro3_x", "gyro4_x"]
    assert step["step_rad_s"] == pytest.approx([0.2, -0.2], abs=0.02)
    assert step["joints"] == ["theta3_x"]
    assert 15.0 <= step["t_s"] <= 16.0  # a quarter of the way: half a second in


def test_a_three_axis_chain_names_the_one_gyro():
    s = _session("xyz,xyz,xyz")
    names = s.robot.angle_names
    steps = [(names.index("theta1_y"), 12.0, 0.15), (names.index("theta2_y"), 12.0, -0.15)]
    (step,) = kk.bias_steps(s, _estimate(s.robot, s.t, steps))
    assert step["columns"] == ["gyro2_y"]  # the link between the two joints
    assert step["step_rad_s"] == pytest.approx([0.15], abs=0.02)


def test_a_change_no_single_gyro_makes_is_not_named():
    s = _session("x,y,x,y")
    names = s.robot.angle_names
    steps = [(names.index("theta1_x"), 15.0, 0.2), (names.index("theta2_y"), 15.0, 0.2)]
    assert kk.bias_steps(s, _estimate(s.robot, s.t, steps)) == []


def test_two_steps_apart_are_both_named_and_short_recordings_none():
    s = _session("x,y,x,y", duration=60.0)
    names = s.robot.angle_names
    steps = [(names.index("theta1_x"), 15.0, 0.2), (names.index("theta4_y"), 40.0, -0.3)]
    found = kk.bias_steps(s, _estimate(s.robot, s.t, steps))
    assert [f["joints"] for f in found] == [["theta1_x"], ["theta4_y"]]
    short = _session("x,y,x,y", duration=8.0)
    assert kk.bias_steps(short, _estimate(short.robot, short.t, [(0, 3.0, 0.5)])) == []


def test_the_filters_convergence_and_gaps_are_not_steps():
    s = _session("x,y,x,y", duration=40.0)
    j = s.robot.angle_names.index("theta1_x")
    # The estimate settling from its prior in the first seconds.
    assert kk.bias_steps(s, _estimate(s.robot, s.t, [(j, 1.0, 0.3)])) == []
    # A jump across a gap (the filter restarted there), and its settling after it.
    t = np.concatenate([s.t[s.t < 15.0], s.t[s.t >= 17.0]])
    gap = types.SimpleNamespace(robot=s.robot, t=t)
    est = _estimate(s.robot, t, [(j, 17.0, 0.3)])
    assert kk.bias_steps(gap, est) == []
    # The same jump without the gap is a step.
    assert [f["joints"] for f in kk.bias_steps(
        types.SimpleNamespace(robot=s.robot, t=s.t), _estimate(s.robot, s.t, [(j, 17.0, 0.3)])
    )] == [["theta1_x"]]


def test_kckf3d_names_a_bias_step_it_absorbs(tmp_path, capsys):
    s = kk.simulate("x,y,z", "walking", 1, 30.0, kinematics="exact", device_seed=1)
    assert kk.bias_steps(s, kk.filter_sessions([s], "kckf3d")[0]) == []
    bad = kk.inject_faults(s, [kk.Fault.parse("bias_step:gyro3_z@15=0.2")])
    kk.write_session(bad, tmp_path / "s")
    assert main(["evaluate", str(tmp_path / "s"), "--method", "kckf3d", "--json"]) == 0
    out = capsys.readouterr()
    (step,) = json.loads(out.out)["bias_steps"][str(tmp_path / "s")]
    assert "gyro3_z" in step["columns"]
    assert step["step_rad_s"][step["columns"].index("gyro3_z")] == pytest.approx(0.2, abs=0.04)
    assert 15.0 <= step["t_s"] <= 17.5
    assert "a gyro's bias stepped" in out.err
    # Under ``off`` the monitor's findings are not made, this one included; kckf names its own
    # (from the gyro pairs, ``_health``) and this finding is not made for it.
    for extra in (["--method", "kckf3d", "--faults", "off"], ["--method", "kckf"]):
        assert main(["evaluate", str(tmp_path / "s"), "--json", *extra]) == 0
        assert json.loads(capsys.readouterr().out).get("bias_steps", {}) == {}, extra


@pytest.mark.long
@pytest.mark.parametrize("joints,kind,reach", [("x,y,x,y", "walking", 140.0),
                                               ("xyz,xyz,xyz", "human", 140.0),
                                               ("x,y,z", "cyclic", None)])
def test_exact_sessions_clean_and_stepped(joints, kind, reach):
    cfg = kk.SimConfig() if reach is None else dataclasses.replace(kk.SimConfig(),
                                                                   motion_range_deg=reach)
    channel = "gyro3_z" if joints == "x,y,z" else "gyro3_x"
    for seed in (2, 3):
        s = kk.simulate(joints, kind, seed, 30.0, config=cfg, kinematics="exact",
                        device_seed=seed)
        assert kk.bias_steps(s, kk.filter_sessions([s], "kckf3d")[0]) == [], seed
        bad = kk.inject_faults(s, [kk.Fault.parse(f"bias_step:{channel}@15=0.2")])
        found = kk.bias_steps(bad, kk.filter_sessions([bad], "kckf3d")[0])
        assert [channel in f["columns"] for f in found] == [True], (seed, found)
