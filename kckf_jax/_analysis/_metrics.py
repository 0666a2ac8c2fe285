"""Error figures against motion capture (session format, "Error figures")."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .._models._robot import Robot
from .._sessions._session import Session

RAD2DEG = 180.0 / np.pi


def squared_errors(estimate_angles: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-angle sum of squared errors (rad^2) and count over the steps that have truth."""
    err = np.asarray(estimate_angles, np.float64) - truth
    ok = np.isfinite(err)
    return (np.where(ok, err, 0.0) ** 2).sum(axis=0), ok.sum(axis=0)


def estimated_names(robot: Robot, estimate_angles: np.ndarray) -> list[str]:
    """The angles a method estimates (those not NaN everywhere), in ``angle_names`` order."""
    finite = np.isfinite(np.asarray(estimate_angles)).any(axis=0)
    return [n for n, f in zip(robot.angle_names, finite) if f]


def rmse_table(
    sessions: Sequence[Session], estimates: Sequence[np.ndarray], burn_in_s: float = 0.0
) -> dict:
    """RMSE (deg) per angle, pooled over ``sessions`` and per session.

    Args:
        sessions: sessions with motion capture.
        estimates: the matching (T, K) estimated angles, rad (NaN where not estimated).
        burn_in_s: leave out the first seconds of every session.

    Returns:
        ``{"rmse_deg": {name: x}, "mean_rmse_deg": x, "per_session": {key: {name: x}},
        "steps_with_truth": {name: n}, "steps_scored": {name: n}}``: the layout of
        ``kckf evaluate --json`` for one method. An angle the method does not estimate is
        left out; a step with truth but no estimate (NaN) is not scored, and the counts say
        how many steps each RMSE is over.
    """
    robot = sessions[0].robot
    sse = np.zeros(robot.n_angles)
    cnt = np.zeros(robot.n_angles)
    with_truth = np.zeros(robot.n_angles, int)
    per_session = {}
    names = None
    for i, (s, est) in enumerate(zip(sessions, estimates)):
        truth = s.truth()
        if burn_in_s > 0:
            truth = np.where((s.t - s.t[0] < burn_in_s)[:, None], np.nan, truth)
        e2, n = squared_errors(est, truth)
        sse += e2
        cnt += n
        with_truth += np.isfinite(truth).sum(axis=0)
        names = names or estimated_names(robot, est)
        key = s.path or f"session{i + 1}"
        per_session[key] = {
            name: float(np.sqrt(e2[k] / n[k]) * RAD2DEG)
            for k, name in enumerate(robot.angle_names) if name in names and n[k] > 0
        }
    rmse = {name: float(np.sqrt(sse[k] / cnt[k]) * RAD2DEG)
            for k, name in enumerate(robot.angle_names) if name in names and cnt[k] > 0}
    mean = float(np.mean(list(rmse.values()))) if rmse else float("nan")
    names = names or []
    return {"rmse_deg": rmse, "mean_rmse_deg": mean, "per_session": per_session,
            "steps_with_truth": {n: int(with_truth[k]) for k, n in enumerate(robot.angle_names)
                                 if n in names},
            "steps_scored": {n: int(cnt[k]) for k, n in enumerate(robot.angle_names)
                             if n in names}}


def fused_hall_error(params, reference, sessions: Sequence[Session]) -> np.ndarray:
    """Per joint axis, the RMS difference (deg) between the fused Hall reading of ``params``
    and of ``reference`` (e.g. the true curves of a simulation), over the sessions' readings.

    The filter uses each joint's two Hall readings only through their inverse-variance
    weighted mean (``_kernel.fused_pairs``), so this is the part of a Hall calibration that
    matters to it and that fitting can identify: a change of ``a`` against ``b`` (or ``c``
    against ``d``) over the voltages a sensor visits, or an error of one side compensated by
    the other, leaves it unchanged. Both use ``params``' weights.
    """
    import jax
    import jax.numpy as jnp

    from .._models._kernel import fused_pairs, hall_measurements

    def diff(v):
        ang, r, ok = hall_measurements(params, v)
        ang_ref, _, _ = hall_measurements(reference, v)
        h, _, okj = fused_pairs(ang, r, ok)
        h_ref, _, _ = fused_pairs(ang_ref, r, ok)
        return jnp.where(okj, h - h_ref, jnp.nan)

    d = np.concatenate([np.asarray(jax.vmap(diff)(jnp.asarray(s.hall_v, params.log_q.dtype)))
                        for s in sessions])
    return np.sqrt(np.nanmean(d.astype(np.float64) ** 2, axis=0)) * RAD2DEG
