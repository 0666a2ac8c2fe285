"""Where the data leave the paper's linear model: gyro pairs that do not read the same rate.

Under the paper's first-order model the gyros about one axis on links that no joint about that
axis separates read the same rate (``Robot.gyro_stand_ins``): the health monitor compares
them to find a gyro whose bias steps, and a missing gyro takes its pair's reading. Under the
chain's exact rotations they do not: a link's rate turned by the joints between (``w_hi =
R^T w_lo``, ``_rotations``) mixes the other axes' rates into this one, so across an x joint
at 100 deg ``gyro2_y`` reads mostly ``gyro1_z``. That disagreement is not a fault: it lasts
as long as the pose and follows it. ``model_mismatch`` finds it from the data (NumPy, on the
host, once per session): per pair, the pair's difference (averaged over ``SMOOTH_S``)
against what the exact rotations predict from the lower link's gyros and the joints' Hall
angles (``R^T w_lo - w_lo`` about the pair's axis). A pair whose difference wanders by more
than ``MIN_SPREAD_RAD_S`` (95th percentile of its distance from its median) and follows the
prediction (correlation at least ``MIN_CORR``, slope within ``SLOPE_RANGE``) is named once,
with its size and the remedy (``--method kckf3d``); its readings stay in use. A bias step
does not follow the pose (its correlation with the prediction is low), so it is not taken
for the model's approximation.
``kckf3d`` models the rotations: nothing to say.
"""

from __future__ import annotations

import numpy as np

from .._models._classes import AbstractModel, exact_kinematics
from .._models._hall import DEG, hall_angle_np
from .._models._robot import AXES
from .._models._rotations import joint_rotation
from ._screen import screen
from ._stats import hold_last, moving_mean

SMOOTH_S = 0.25  # the pair's difference averaged over this (the monitor's fast average)
MIN_SPREAD_RAD_S = 0.05  # the monitor's bias-step size: a smaller wander changes nothing
MIN_CORR = 0.5  # the difference follows the exact rotations' prediction at least this well
# ... at about its scale: on linear data at large angles and rates the gyros' scale errors
# (1 %) correlate with the prediction too, at a slope of a few hundredths.
SLOPE_RANGE = (0.5, 2.0)


def joint_angles_from_hall(session, params, codes=None) -> np.ndarray:
    """Each joint axis's angle (``T x J``, rad): the mean of its Hall sensors' angles through
    their curves (Eq. 1, ``params``), readings the screen leaves out skipped, holes held (NaN
    throughout for a joint axis without a reading). ``codes``: the session's fault codes
    where a filter already judged it (``Estimate.faults``, ``G + M`` per row), so its Hall
    readings are not screened again."""
    robot = session.robot
    hall_v = np.asarray(session.hall_v, np.float64)
    if codes is None:
        v = screen(params, np.asarray(session.gyro, np.float64), hall_v, np).hall_v
    else:
        v = np.where(np.asarray(codes)[:, 3 * robot.n_links:] > 0, np.nan, hall_v)
    ang = hall_angle_np(v, params.hall_coeffs)
    J = robot.n_joint_axes
    pair = ang.reshape(len(ang), J, 2)
    ok = np.isfinite(pair)
    with np.errstate(invalid="ignore"):
        theta = np.where(ok.any(-1), np.nansum(pair, -1) / np.maximum(ok.sum(-1), 1), np.nan)
    return np.stack([hold_last(theta[:, j]) if np.isfinite(theta[:, j]).any() else theta[:, j]
                     for j in range(J)], axis=1)


def model_mismatch(session, method: str | AbstractModel = "kckf", params=None, codes=None
                   ) -> list[dict]:
    """The paper's gyro pairs that the data show do not read the same rate, following the
    pose (module docstring): ``[{"columns": [a, b], "axis", "spread_rad_s", "corr",
    "joints", "max_angle_deg"}]``, empty where the model holds or for ``kckf3d``.
    ``params``: the Hall curves (default: the session's paper defaults); ``codes``: as
    ``joint_angles_from_hall``'s."""
    if exact_kinematics(method):
        return []
    from .._models._params import Params

    robot = session.robot
    if params is None:
        params = Params.paper_defaults(robot, session.hall_models, limits=session.limits)
    theta = joint_angles_from_hall(session, params, codes)
    gyro = np.asarray(session.gyro, np.float64)
    t = np.asarray(session.t, np.float64)
    n = max(1, int(round(SMOOTH_S / max(np.median(np.diff(t)), 1e-6)))) if t.size > 1 else 1
    names = robot.gyro_names
    used = set(int(i) for i in robot.used_gyro_index)
    axis_start = np.concatenate([[0], np.cumsum([len(a) for a in robot.joints])])
    out, seen = [], set()
    for c, mates in enumerate(robot.gyro_stand_ins):
        if c not in used or not mates:
            continue
        m = mates[0]
        key = tuple(sorted((c, m)))
        if key in seen:
            continue
        seen.add(key)
        lo, hi = sorted((c // 3, m // 3))
        ax = c % 3
        if not all(np.isfinite(gyro[:, 3 * lo + k]).any() for k in range(3)):
            continue  # a rate of the lower link never read
        w_lo = np.stack([hold_last(gyro[:, 3 * lo + k]) for k in range(3)], axis=1)
        R = np.broadcast_to(np.eye(3), (t.size, 3, 3))
        for j in range(lo, hi):  # joint j joins links j and j + 1
            R = R @ joint_rotation(robot.joints[j], theta[:, axis_start[j]:axis_start[j + 1]])
        predicted = np.einsum("tji,tj->ti", R, w_lo)[:, ax] - w_lo[:, ax]
        upper, lower = (c, m) if c // 3 == hi else (m, c)
        d = moving_mean(gyro[:, upper] - gyro[:, lower], n)
        p = moving_mean(predicted, n)
        ok = np.isfinite(d) & np.isfinite(p)
        if ok.sum() < 10:
            continue
        spread = float(np.percentile(np.abs(d[ok] - np.median(d[ok])), 95))
        if spread < MIN_SPREAD_RAD_S or np.std(p[ok]) == 0 or np.std(d[ok]) == 0:
            continue
        corr = float(np.corrcoef(d[ok], p[ok])[0, 1])
        dc, pc = d[ok] - d[ok].mean(), p[ok] - p[ok].mean()
        slope = float(dc @ pc / (pc @ pc))
        if corr < MIN_CORR or not SLOPE_RANGE[0] <= slope <= SLOPE_RANGE[1]:
            continue
        between = list(range(axis_start[lo], axis_start[hi]))
        out.append({"columns": [names[lower], names[upper]], "axis": AXES[ax],
                    "spread_rad_s": round(spread, 4), "corr": round(corr, 3),
                    "slope": round(slope, 3),
                    "joints": [robot.angle_names[k] for k in between],
                    "max_angle_deg": round(float(np.nanmax(np.abs(theta[:, between])) / DEG),
                                           1)})
    return out


def describe_mismatch(name: str, pairs: list[dict]) -> str:
    """One line for people: the pairs ``model_mismatch`` found, their size and the remedy."""
    parts = [f"{a} and {b} differ by up to {p['spread_rad_s']:.2f} rad/s following "
             f"{', '.join(p['joints'])} (up to {p['max_angle_deg']:.0f} deg; r "
             f"{p['corr']:.2f} with the exact rotations)"
             for p in pairs for a, b in [p["columns"]]]
    return (f"{name}: the paper's linear model does not hold at these angles: "
            + "; ".join(parts) + ". The readings are used (a disagreement that follows the "
            "pose is the model's approximation, not a fault); --method kckf3d models the "
            "rotations exactly (docs/faults.md)")
