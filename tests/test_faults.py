"""Faulty and implausible data: one behaviour in the batch filter, the stream and the exported
step, named on stderr and in the JSON, never computed on in silence."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from kckf_jax import (
    Params,
    Robot,
    SensorSeries,
    read_session,
    run_filter,
    simulate,
    write_session,
)
from kckf_jax.cli import main

ROBOT = Robot.from_spec("x,y,x,y")


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _csv(path):
    lines = Path(path).read_text().splitlines()
    return lines[0].split(","), np.array([[float(c) if c else np.nan for c in r.split(",")]
                                          for r in lines[1:]])


# ----------------------------------------------------------------------------- the kernel
@pytest.mark.long
def test_out_of_range_is_missing_and_a_non_finite_update_is_skipped():
    s = simulate(ROBOT, "cyclic", seed=2, duration_s=8.0)
    params = Params.paper_defaults(ROBOT, s.hall_models, dtype=jnp.float64)
    dt = s.dt()
    hall, gyro = s.hall_v.copy(), s.gyro.copy()
    hall[30, 2], gyro[300, 0] = 1e30, -1e30  # finite nonsense
    as_missing_h, as_missing_g = s.hall_v.copy(), s.gyro.copy()
    as_missing_h[30, 2], as_missing_g[300, 0] = np.nan, np.nan
    _, bad = run_filter(params, SensorSeries(dt, gyro, hall))
    _, missing = run_filter(params, SensorSeries(dt, as_missing_g, as_missing_h))
    np.testing.assert_array_equal(np.asarray(bad.angles), np.asarray(missing.angles))
    assert not np.asarray(bad.skipped).any()
    # A time step so long that the prediction overflows: that update is skipped, the state
    # kept (the same on the parallel path), and the filter goes on.
    long = dt.copy()
    long[500] = 1e200
    for path in ("sequential", "parallel"):
        _, est = run_filter(params, SensorSeries(long, s.gyro, s.hall_v), path=path)
        assert np.flatnonzero(np.asarray(est.skipped)).tolist() == [500], path
        np.testing.assert_array_equal(np.asarray(est.angles)[500], np.asarray(est.angles)[499])
        assert np.isfinite(np.asarray(est.angles)).all()


# ----------------------------------------------------------------------------- batch = stream
@pytest.fixture(scope="module")
def faulty(tmp_path_factory):
    """A bench session with one Hall voltage of 1e30 V at row 30 and one gyro rate of
    1e30 rad/s at row 300, and the same session without them."""
    root = tmp_path_factory.mktemp("faulty")
    s = simulate(ROBOT, "cyclic", seed=6, duration_s=25.0)
    write_session(s, root / "clean")
    s.hall_v[30, 2] = 1e30
    s.gyro[300, 0] = 1e30
    write_session(s, root / "bad")
    return root


@pytest.mark.long
def test_filter_and_stream_agree_on_faulty_readings_and_say_so(faulty, tmp_path, capsys):
    est = {}
    for name in ("clean", "bad"):
        code, _, err = _run(capsys, "filter", faulty / name, "-o", tmp_path / f"{name}.csv")
        assert code == 0, err
        est[name] = _csv(tmp_path / f"{name}.csv")[1][:, 1:]
    assert "hall2_y_l out_of_range" in err and "gyro1_x out_of_range" in err
    bad, clean = est["bad"], est["clean"]
    assert np.isfinite(bad).all() and np.abs(bad).max() < np.pi
    # Within a degree of the session without the faults once the filter has recovered.
    assert np.degrees(np.abs(bad - clean)[1000:]).max() < 1.0
    r = subprocess.run([sys.executable, "-m", "kckf_jax", "stream", "--source",
                        f"replay://{faulty / 'bad'}"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    recs = [json.loads(line) for line in r.stdout.splitlines()]
    assert [rec["status"] for rec in recs].count("masked") == 2
    assert "hall2_y_l out_of_range x1" in r.stderr and "gyro1_x out_of_range x1" in r.stderr
    streamed = np.array([[rec[n] for n in ROBOT.angle_names] for rec in recs])
    assert np.abs(streamed - bad).max() <= 1e-4  # float32, both


# ----------------------------------------------------------------------------- a new user
def _user_session(tmp_path, *, t_scale=1.0, mocap_scale=1.0, hole=False):
    """A 200 Hz robot of another layout, mocap at 150 Hz with a 23 ms offset, NaN gyro drops:
    the session a new user writes, with one mistake at a time."""
    robot = Robot.from_spec("xy,z,x")
    s = simulate(robot, "human", seed=3, duration_s=40.0, drop_prob=0.01)
    s.sample_rate_hz = 200.0  # declared; the simulator's rows are 100 Hz: rescale t
    s.t = s.t / 2.0
    s.mocap_t = s.mocap_t / 2.0
    if hole:
        keep = (s.t < 8.0) | (s.t >= 10.0)
        s.t, s.gyro, s.hall_v = s.t[keep], s.gyro[keep], s.hall_v[keep]
    s.t = s.t * t_scale
    s.mocap_t = s.mocap_t * t_scale
    s.mocap = s.mocap * mocap_scale
    s._truth = None
    path = tmp_path / f"user_{t_scale}_{mocap_scale}_{hole}"
    write_session(s, path)
    return path


@pytest.mark.long
def test_timestamps_in_milliseconds_are_refused_unless_accepted(tmp_path, capsys):
    path = _user_session(tmp_path, t_scale=1000.0)
    code, out, err = _run(capsys, "evaluate", path, "--json")
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1
    assert "sensors.csv, column 't'" in err and "sample_rate_hz = 200" in err
    assert "milliseconds" in err and "--accept-implausible" in err
    code, out, err = _run(capsys, "filter", path, "--accept-implausible", "-o",
                          tmp_path / "e.csv")
    assert code == 0, err


def test_mocap_in_degrees_is_refused(tmp_path, capsys):
    path = _user_session(tmp_path, mocap_scale=180.0 / np.pi)
    code, _, err = _run(capsys, "evaluate", path, "--json")
    assert code == 2 and "mocap.csv, column" in err and "beyond 2 pi" in err
    assert "degrees" in err
    with pytest.raises(ValueError, match="beyond 2 pi"):
        read_session(path)
    assert read_session(path, plausible=False).has_truth


@pytest.mark.long
def test_a_hole_in_the_sensor_rows_is_reported_and_handled_as_the_stream_does(tmp_path,
                                                                             capsys):
    path = _user_session(tmp_path, hole=True)
    code, out, err = _run(capsys, "evaluate", path, "--json", "--method", "kckf")
    assert code == 0, err
    doc = json.loads(out)
    (gap,) = doc["gaps"][str(path)]
    # Longer than the default --max-predict (1 s): restarted (docs/faults.md, "Gaps").
    assert gap["length_s"] == pytest.approx(2.0, abs=0.02) and gap["action"] == "restart"
    assert "1 gap(s) in the sensor rows" in err and "(restart)" in err
    s = read_session(path)
    after = (s.t >= 10.0) & (s.t < 15.0)
    truth = s.truth()
    for policy in ("predict", "restart"):
        out_csv = tmp_path / f"{policy}.csv"
        code, _, err = _run(capsys, "filter", path, "--on-gap", policy, "--max-predict", "3",
                            "-o", out_csv)
        assert code == 0 and f"({policy})" in err
        batch = _csv(out_csv)[1][:, 1:]
        r = subprocess.run([sys.executable, "-m", "kckf_jax", "stream", "--source",
                            f"replay://{path}", "--on-gap", policy, "--max-predict", "3"],
                           capture_output=True, text=True, timeout=300)
        recs = [json.loads(line) for line in r.stdout.splitlines()]
        assert [rec.get("gap") for rec in recs if rec["status"] == "gap"] == [policy]
        names = s.robot.angle_names
        streamed = np.array([[rec[n] for n in names] for rec in recs])
        err_batch = np.sqrt(np.nanmean((batch[after] - truth[after]) ** 2))
        err_stream = np.sqrt(np.nanmean((streamed[after] - truth[after]) ** 2))
        assert err_batch <= err_stream + 1e-4, (policy, err_batch, err_stream)


def test_an_rmse_over_fewer_steps_than_have_truth_is_named(tmp_path, capsys):
    s = simulate(ROBOT, "cyclic", seed=8, duration_s=6.0)
    s.hall_v[:200, 0] = np.nan  # hall_l of joint 1 gives nothing for the first 2 s
    path = tmp_path / "late"
    write_session(s, path)
    code, out, err = _run(capsys, "evaluate", path, "--method", "hall_l", "--json")
    assert code == 0
    r = json.loads(out)["methods"]["hall_l"]
    early = int(np.isfinite(read_session(path).truth()[:200, 0]).sum())
    assert early > 0
    assert r["steps_scored"]["theta1_x"] == r["steps_with_truth"]["theta1_x"] - early
    assert "hall_l: RMSE over fewer steps than have truth" in err and "theta1_x" in err


def test_joint_numbers_in_messages_are_one_based(tmp_path, capsys):
    meta = {"format": "kckf-session/1", "joints": [{"axes": ["x"]}, {"axes": ["w"]}],
            "sample_rate_hz": 100}
    os.makedirs(tmp_path / "s")
    (tmp_path / "s" / "meta.json").write_text(json.dumps(meta))
    code, _, err = _run(capsys, "filter", tmp_path / "s", "-o", tmp_path / "e.csv")
    assert code == 2 and "joint 2 (joints[1])" in err and "'w'" in err
