"""The arm exoskeleton + IMU experiment: the exoskeleton alone against the fused estimate,
scored against simulated optical tracking (docs/other_filters.md)."""

from __future__ import annotations

import time
from dataclasses import asdict

import jax
import jax.numpy as jnp
import numpy as np

from ._filter import ArmImuParams, arm_imu_series, pad_arm_imu, run_arm_imu
from ._sim import (
    DEG,
    ArmSimConfig,
    draw_exoskeleton,
    matrix_to_rotvec,
    remove_gyro_bias,
    rotation_angle,
    rotvec_to_matrix,
    simulate_arm_trial,
)


def _latest(t_src: np.ndarray, t_at: np.ndarray) -> np.ndarray:
    """Index of the last ``t_src`` at or before each ``t_at`` (-1 if none)."""
    return np.searchsorted(t_src, t_at, side="right") - 1


def _interpolate(t_src, pos, rot, t_at):
    """Pose at ``t_at`` by linear interpolation of position and of rotation (slerp)."""
    i = np.clip(np.searchsorted(t_src, t_at) - 1, 0, len(t_src) - 2)
    s = np.clip((t_at - t_src[i]) / (t_src[i + 1] - t_src[i]), 0.0, 1.0)[:, None]
    p = (1 - s) * pos[i] + s * pos[i + 1]
    step = matrix_to_rotvec(np.swapaxes(rot[i], -1, -2) @ rot[i + 1])
    return p, rot[i] @ rotvec_to_matrix(s * step)


def _scores(pos, rot, ots_pos, ots_rot):
    """Squared position errors (m^2) and squared rotation angles (rad^2) per sample."""
    e_pos = np.sum((pos - ots_pos) ** 2, axis=-1)
    e_rot = rotation_angle(np.swapaxes(rot, -1, -2) @ ots_rot) ** 2
    return e_pos, e_rot


def _rmse(scores: list) -> dict:
    pos = np.concatenate([s[0] for s in scores])
    rot = np.concatenate([s[1] for s in scores])
    return {"position_mm": float(1e3 * np.sqrt(np.mean(pos))),
            "orientation_deg": float(np.sqrt(np.mean(rot)) / DEG)}


def arm_imu_experiment(
    seed: int = 0, n_trials: int = 4, duration_s: float = 20.0,
    params: ArmImuParams | None = None, dtype=None,
) -> dict:
    """The exoskeleton alone against the fused estimate, scored against optical tracking.

    One simulated exoskeleton (its manufacturing errors drawn from ``seed``) with an MTi,
    ``n_trials`` reaching trials of ``duration_s`` each (1 s at rest, then movements), filtered
    together (``jax.vmap`` of the jitted scan). The gyro bias is removed with a no-rotation
    estimate over the first 0.9 s (``remove_gyro_bias``).

    Scoring, at every tracking sample after the exoskeleton's first reading (pooled over the
    trials): Euclidean position error and the rotation angle between the estimated and tracked
    orientation. The headline ``"rmse"`` is **real time**: each system's latest output at the
    tracking instant, what a tele-operation loop has then (the exoskeleton gives a pose every
    10 ms, the filter after every exoskeleton or IMU sample). ``details["interpolated"]``
    scores both outputs interpolated to the tracking instants instead (linear and slerp; no
    advantage from the IMU's higher rate), and ``details["exoskeleton_manufacturing_only"]``
    the exoskeleton with exact encoders and no deflection: the slow, configuration-dependent
    error that acceleration and turn rate cannot observe, a floor for the fused estimate.

    Measured for ``seed=0`` (defaults; docs/other_filters.md): in real time the fused RMSE is
    42 % below the exoskeleton's in position (1.45 against 2.51 mm) and 58 % below it in
    orientation (0.197 against 0.473 deg). Interpolated, the orientation gain is 27 % and the
    position gain 1 %: the position gain comes from the fused pose being current between the
    exoskeleton's 100 Hz samples, while the exoskeleton's remaining error is below the
    frequencies at which the accelerometer can be trusted.

    Args:
        seed: seed of the whole experiment (``numpy.random.default_rng``).
        n_trials: number of trials.
        duration_s: length of each trial, s (at least 2).
        params: filter parameters (default ``ArmImuParams.paper_defaults`` with the IMU's
            nominal mount).
        dtype: computation dtype (default: JAX's default float).

    Returns:
        ``{"rmse": {"exoskeleton": {"position_mm", "orientation_deg"}, "fused": {...}},
        "details": {...}}``.

    Example:
        >>> r = arm_imu_experiment(seed=0, n_trials=1, duration_s=3.0)
        >>> sorted(r["rmse"]["fused"])
        ['orientation_deg', 'position_mm']
    """
    start = time.perf_counter()
    if duration_s < 2.0 or n_trials < 1:
        raise ValueError(f"arm_imu_experiment: need n_trials >= 1 and duration_s >= 2, got "
                         f"{n_trials} and {duration_s}")
    cfg = ArmSimConfig(duration_s=float(duration_s))
    rng = np.random.default_rng(seed)
    exo = draw_exoskeleton(rng, cfg)
    trials = [simulate_arm_trial(rng, cfg, exo) for _ in range(int(n_trials))]
    dtype = jnp.asarray(0.0).dtype if dtype is None else jnp.dtype(dtype)
    if params is None:
        params = ArmImuParams.from_physical(imu_mount=trials[0].imu_mount, dtype=dtype)
    params = params.astype(dtype)
    merged = [arm_imu_series(tr.t_exo, tr.exo_pos, tr.exo_rot, tr.t_imu, tr.imu_acc,
                             remove_gyro_bias(tr.t_imu, tr.imu_gyro, cfg.rest_s - 0.1))
              for tr in trials]
    batch = pad_arm_imu([m[3] for m in merged])
    batch = jax.tree_util.tree_map(lambda x: np.asarray(x, dtype), batch)
    est = jax.vmap(lambda s: run_arm_imu(params, s)[1])(batch)
    est_pos = np.asarray(est.pos, np.float64)
    est_rot = np.asarray(est.rot, np.float64)

    scores = {k: [] for k in ("exo", "fused", "exo_interp", "fused_interp", "manufacturing")}
    per_trial = []
    for i, (tr, (t_rows, *_)) in enumerate(zip(trials, merged)):
        use = tr.t_ots >= tr.t_exo[0]
        t_at, ots_pos, ots_rot = tr.t_ots[use], tr.ots_pos[use], tr.ots_rot[use]
        e, f = _latest(tr.t_exo, t_at), _latest(t_rows, t_at)
        pos_i, rot_i = est_pos[i, : len(t_rows)], est_rot[i, : len(t_rows)]
        now = {
            "exo": _scores(tr.exo_pos[e], tr.exo_rot[e], ots_pos, ots_rot),
            "fused": _scores(pos_i[f], rot_i[f], ots_pos, ots_rot),
            "exo_interp": _scores(*_interpolate(tr.t_exo, tr.exo_pos, tr.exo_rot, t_at),
                                  ots_pos, ots_rot),
            "fused_interp": _scores(*_interpolate(t_rows, pos_i, rot_i, t_at),
                                    ots_pos, ots_rot),
            "manufacturing": _scores(tr.geom_pos[use], tr.geom_rot[use], ots_pos, ots_rot),
        }
        for k, v in now.items():
            scores[k].append(v)
        per_trial.append({"exoskeleton": _rmse([now["exo"]]), "fused": _rmse([now["fused"]])})

    rmse = {"exoskeleton": _rmse(scores["exo"]), "fused": _rmse(scores["fused"])}
    details = {
        "reduction_percent": {
            k: 100.0 * (1 - rmse["fused"][k] / rmse["exoskeleton"][k]) for k in rmse["fused"]},
        "interpolated": {"exoskeleton": _rmse(scores["exo_interp"]),
                         "fused": _rmse(scores["fused_interp"])},
        "exoskeleton_manufacturing_only": _rmse(scores["manufacturing"]),
        "per_trial": per_trial,
        "n_trials": int(n_trials), "duration_s": float(duration_s), "seed": int(seed),
        "dtype": str(jnp.dtype(dtype)),
        "config": asdict(cfg),
        "wall_s": time.perf_counter() - start,
    }
    return {"rmse": rmse, "details": details}
