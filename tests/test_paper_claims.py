"""The paper's results, reproduced on simulated sessions (issue 2, "What it must show")."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kckf_jax import (
    Params,
    Robot,
    filter_sessions,
    init_state,
    observability_ranks,
    rmse_table,
    run_filter,
    session_series,
    simulate,
    step,
)

SENSORS = ("gyro", "hall_l", "hall_r")


def test_bench_table1_relations():
    """Cyclic bench tests (x, y, x, y), RMSE pooled over four 60 s sessions: KCKF torso RMSE
    <= 25 % of the standard KF's, and the KCKF's joint RMSE below every single sensor's
    (paper Table 1). (Single sessions vary: where the two end gyros happen to have nearly the
    same zero-rate offset the standard KF's torso barely drifts; see docs/results.md.)"""
    sessions = [simulate("x,y,x,y", "cyclic", seed=seed, duration_s=60.0, drop_prob=0.01)
                for seed in (1, 2, 3, 4)]
    res = {m: rmse_table(sessions, [e.angles for e in filter_sessions(sessions, m)])["rmse_deg"]
           for m in ("kckf", "kf", *SENSORS)}
    s = sessions[0]
    for phi in s.robot.torso_angle_names:
        assert res["kckf"][phi] <= 0.25 * res["kf"][phi], (phi, res["kckf"][phi], res["kf"][phi])
    for name in s.robot.joint_angle_names:
        for m in SENSORS:
            assert res["kckf"][name] < res[m][name], (name, m, res["kckf"][name], res[m][name])


@eqx.filter_jit
def _float32_run(params, series, method):
    """Angles, and whether every block covariance is positive definite after every step (its
    Cholesky factor, in float64, has a positive diagonal: the standard KF's torso variance
    grows to ~1e6 rad^2 in an hour, beside entries of 1e-8)."""

    def body(state, row):
        state, est = step(params, state, row, method)
        P = state.P.astype(jnp.float64)  # (blocks, Nz, Nz); one small factor per block
        low = jnp.min(jnp.stack([jnp.min(jnp.diag(jnp.linalg.cholesky(P[b])))
                                 for b in range(P.shape[0])]))
        return state, (low, est.angles)

    return jax.lax.scan(body, init_state(params, method), series)[1]


def test_one_hour_extended_use():
    """Sec. 4.2 / Fig. 7: movement, then an hour held still. KCKF torso error at the end within
    7 deg while the standard KF drifts away; float32 within 0.05 deg RMSE of float64 over the
    whole hour; the float32 covariance positive definite at every step."""
    s = simulate("x,y,x,y", "static", seed=3, duration_s=3600.0, move_s=60.0)
    truth = s.truth()
    last = np.flatnonzero(np.isfinite(truth).all(axis=1))[-1]
    angles, min_chol = {}, {}
    for dtype in (jnp.float32, jnp.float64):
        params = Params.paper_defaults(s.robot, s.hall_models, dtype=dtype)
        series = session_series(s, dtype)
        for method in ("kckf", "kf"):
            if dtype == jnp.float32:
                low, ang = _float32_run(params, series, method)
                min_chol[method] = np.asarray(low)
            else:
                ang = run_filter(params, series, method)[1].angles
            angles[dtype, method] = np.asarray(ang, np.float64)
    J = s.robot.n_joint_axes
    end_err = np.abs(angles[jnp.float64, "kckf"][last] - truth[last]) * 180 / np.pi
    kf_end = np.abs(angles[jnp.float64, "kf"][last] - truth[last]) * 180 / np.pi
    assert np.all(end_err[J:] < 7.0), end_err
    assert np.all(kf_end[J:] > 50.0), kf_end
    for method in ("kckf", "kf"):
        d = (angles[jnp.float32, method] - angles[jnp.float64, method]) * 180 / np.pi
        assert np.all(np.sqrt(np.mean(d[:, :J] ** 2, axis=0)) < 0.05), method
        assert np.all(np.isfinite(angles[jnp.float32, method]))
        assert min_chol[method].min() > 0, method
    d = (angles[jnp.float32, "kckf"] - angles[jnp.float64, "kckf"]) * 180 / np.pi
    assert np.all(np.sqrt(np.mean(d**2, axis=0)) < 0.05)


@pytest.mark.parametrize(("spec", "lost"), [("x,y,x,y", 4), ("xyz,xyz,xyz,xyz", 6),
                                            ("x,x,x", 2), ("xy,z,xyz", 6)])
def test_observability_ranks_match_the_paper(spec, lost):
    """Eq. 21: the KF loses the torso angle and its bias per axis (N - 6 in 3D); KCKF: N."""
    r = observability_ranks(Robot.from_spec(spec))
    assert r["rank_kckf"] == r["n_states"]
    assert r["rank_kf"] == r["n_states"] - lost
