"""Offline analysis and tuning without motion capture on the command line (issue 18):
``kckf filter --smooth``, ``kckf evaluate --smooth``, ``kckf fit --loss nll|rmse+nll``."""

from __future__ import annotations

import csv
import json
import os
import shutil

import numpy as np
import pytest
from helpers import default_compile_env

from kckf_jax import FitConfig, filter_sessions, fit, initial_params, load_params, read_session
from kckf_jax.cli import main


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("analysis") / "s1")
    assert main(["simulate", path, "--kind", "cyclic", "--seed", "3", "--duration", "12",
                 "--joints", "x,y,x,y", "--drop-prob", "0.01", "--quiet"]) == 0
    return path


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_filter_smooth_writes_the_smoothed_estimates(session, tmp_path, capsys):
    out = str(tmp_path / "est.csv")
    code, _, err = _run(capsys, "filter", session, "--smooth", "-o", out)
    assert code == 0, err
    with open(out) as f:
        rows = list(csv.DictReader(f))
    cols = {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}
    want = filter_sessions([read_session(session)], "kckf", smooth=True)[0].columns()
    filtered = filter_sessions([read_session(session)], "kckf")[0].columns()
    for name, x in want.items():
        np.testing.assert_allclose(cols[name], x, atol=1e-6)
    assert max(np.abs(cols[k] - filtered[k]).max() for k in want) > 1e-4  # not the filter
    # The smoothed estimates satisfy the constraint phi = sum theta, axis by axis.
    np.testing.assert_allclose(cols["phi_x"], cols["theta1_x"] + cols["theta3_x"], atol=1e-6)
    np.testing.assert_allclose(cols["phi_y"], cols["theta2_y"] + cols["theta4_y"], atol=1e-6)


def test_evaluate_smooth_scores_the_smoother(session, capsys):
    code, out, err = _run(capsys, "evaluate", session, "--method", "kckf", "--method", "gyro",
                          "--json")
    assert code == 0, err
    filtered = json.loads(out)["methods"]
    code, out, err = _run(capsys, "evaluate", session, "--method", "kckf", "--method", "gyro",
                          "--smooth", "--json")
    assert code == 0, err
    smoothed = json.loads(out)["methods"]
    k = smoothed["kckf"]
    assert k["smoothed"] is True and k["path"] == "smoothed"
    assert k["mean_rmse_deg"] < filtered["kckf"]["mean_rmse_deg"]
    assert k["steps_scored"] == filtered["kckf"]["steps_scored"]
    # The NIS from the smoother's forward pass (the filter): one pass, the filter's figures.
    assert k["filter_passes"] == 1 and filtered["kckf"]["filter_passes"] == 1
    assert k["nis"]["mean"] == pytest.approx(filtered["kckf"]["nis"]["mean"], rel=1e-5)
    # A method that is not a Kalman filter is scored as it is, and says so.
    assert "smoothed" not in smoothed["gyro"]
    assert smoothed["gyro"]["mean_rmse_deg"] == filtered["gyro"]["mean_rmse_deg"]


def test_fit_nll_needs_no_motion_capture(session, tmp_path, capsys):
    bare = str(tmp_path / "bare")
    shutil.copytree(session, bare)
    os.remove(os.path.join(bare, "mocap.csv"))
    out = str(tmp_path / "p.json")
    code, _, err = _run(capsys, "fit", bare, "-o", out, "--steps", "3", "--quiet")
    assert code == 2 and "mocap" in err and "--loss nll" in err  # rmse needs truth
    code, stdout, err = _run(capsys, "fit", bare, "-o", out, "--steps", "3", "--loss", "nll",
                             "--quiet")
    assert code == 0, err
    summary = json.loads(stdout)
    assert summary["loss"] == "nll" and np.isfinite(summary["best_nll_nats"])
    assert load_params(out).robot.n_joints == 4


@pytest.mark.parametrize("loss", ["nll", "rmse+nll"])
@pytest.mark.long
def test_the_likelihood_losses_go_down(session, loss):
    s = read_session(session)
    res = fit([s], (), FitConfig(steps=8, loss=loss))
    key = next(k for k in res.history[0] if k.startswith("loss_"))
    losses = [h[key] for h in res.history]
    assert all(np.isfinite(losses)) and losses[-1] < losses[0]
    assert res.unit == {"nll": "nats", "rmse+nll": "deg_plus_nats"}[loss]


def test_fit_config_names_the_losses():
    with pytest.raises(ValueError, match="rmse, nll, rmse\\+nll"):
        FitConfig(loss="likelihood")
    with pytest.raises(ValueError, match="nll_weight: expected a positive number"):
        FitConfig(loss="rmse+nll", nll_weight=0.0)


@pytest.mark.long
def test_rmse_nll_is_the_rmse_plus_the_weighted_likelihood(session):
    """``rmse+nll`` = RMSE (deg) + ``nll_weight`` x NLL (nats per reading), at any weight."""
    from kckf_jax._fitting._fit import make_batch, make_loss

    s = read_session(session)
    params = initial_params([s], FitConfig())
    batch = make_batch([s], params.log_q.dtype)
    rmse = float(make_loss("rmse", params, batch, "kckf", None)(params, batch)) * 180 / np.pi
    nll = float(make_loss("nll", params, batch, "kckf", None)(params, batch))
    for w in (0.1, 2.0):
        both = float(make_loss("rmse+nll", params, batch, "kckf", None, w)(params, batch))
        assert both == pytest.approx(rmse + w * nll, rel=1e-9)


@pytest.mark.long
def test_the_command_keeps_compiled_programs_between_runs(session, tmp_path):
    """``$KCKF_CACHE_DIR``: the second run of a command loads what the first compiled (the
    command as users run it, XLA's default flags; every program kept,
    ``KCKF_CACHE_MIN_COMPILE_S=0``, so that a fast machine's quick compiles are kept too)."""
    import subprocess
    import sys

    env = {k: v for k, v in default_compile_env().items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env["KCKF_CACHE_DIR"] = str(tmp_path / "cache")
    env["KCKF_CACHE_MIN_COMPILE_S"] = "0"
    argv = [sys.executable, "-m", "kckf_jax", "filter", session, "-o", str(tmp_path / "e.csv"),
            "--quiet"]
    r = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert os.listdir(tmp_path / "cache")  # compiled programs written
    env["KCKF_CACHE_DIR"] = ""  # off
    r = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
