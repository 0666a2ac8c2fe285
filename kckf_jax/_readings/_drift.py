"""A Hall sensor drifting slowly from its partner: named, with its size.

The health monitor sees fast changes (noise, a stuck reading, a step): its reference follows
both Hall sensors of a joint axis with a 0.5 s time constant, so an offset that grows over
minutes (a sensor warming up, a magnet creeping in its mount) passes it. The two sensors of
a joint axis measure one angle under any kinematics, so their difference moves only by their
noise and by how their curves disagree, which depends on the angle, not on the time. A drift
is that difference changing with time: ``hall_drift`` fits the difference of the two angles
(Eq. 1, readings the filter did not use left out) by least squares on a constant, the time
and the joint's angle and its square (the curves' disagreement), and names a pair whose time
term moves it by ``MIN_DRIFT_DEG`` or more over the recording. Which of the two drifts is
not said: the gyros cannot tell a slow offset (two gyros' relative bias drifts by degrees a
minute), and the filter's estimate follows the pair's mean (tried: the residual of each
sensor against the bench KCKF's estimate named the wrong sensor of hall1_x on 3 of 4 seeds).

NumPy on the host, once per recording, in the report (``data_faults``); nothing is taken out
of the filter's readings: a slow drift is a finding for the user (recalibrate, refit), not a
decision row by row.
"""

from __future__ import annotations

import numpy as np

from .._models._hall import DEG, hall_angle_np
from ._stats import least_squares

#: The pair's difference must move this far over the recording (deg). Clean simulated pairs
#: (linear and exact; x,y,x,y cyclic and human, x,y,z and xyz,xyz,xyz walking; 4 seeds each,
#: 60 s): at most 1.51 deg; 0.25 V over a minute on the bench robot: 9.9-17.8 deg.
MIN_DRIFT_DEG = 3.0
#: The recording must be this long (s) for a trend to be told from the motion.
MIN_SPAN_S = 10.0
def _angles(session, params, codes) -> np.ndarray:
    """Every Hall reading's angle (``T x M``, rad; NaN where missing or not used)."""
    robot = session.robot
    v = np.asarray(session.hall_v, np.float64)
    if codes is not None:
        v = np.where(np.asarray(codes)[:, 3 * robot.n_links:] > 0, np.nan, v)
    return hall_angle_np(v, params.hall_coeffs)


def _trend(t, y, theta) -> float:
    """The change over ``t``'s span of ``y``'s least-squares time term (regressors: 1, time,
    ``theta``, ``theta^2``)."""
    span = t[-1] - t[0]
    u = (t - t[0]) / span - 0.5
    X = np.stack([np.ones_like(t), u, theta, theta ** 2], axis=1)
    coef, _ = least_squares(X, y)
    return float(coef[1])


def hall_drift(session, params, codes=None) -> list[dict]:
    """The joint axes whose two Hall sensors drift apart over the recording (module
    docstring): ``[{"columns": [l, r], "drift_deg"}]`` (``drift_deg``: the change of the
    angle of ``l`` less that of ``r`` over the recording). ``codes``: the recording's fault
    codes (``Estimate.faults``; those readings left out)."""
    t = np.asarray(session.t, np.float64)
    if t.size < 2 or t[-1] - t[0] < MIN_SPAN_S:
        return []
    robot = session.robot
    ang = _angles(session, params, codes)
    names = robot.hall_names
    out = []
    for j in range(robot.n_joint_axes):
        a, b = ang[:, 2 * j], ang[:, 2 * j + 1]
        ok = np.isfinite(a) & np.isfinite(b)
        if ok.sum() < 100 or t[ok][-1] - t[ok][0] < MIN_SPAN_S:
            continue
        mid = 0.5 * (a[ok] + b[ok])
        drift = _trend(t[ok], a[ok] - b[ok], mid)
        if abs(drift) < MIN_DRIFT_DEG * DEG:
            continue
        out.append({"columns": [names[2 * j], names[2 * j + 1]],
                    "drift_deg": round(drift / DEG, 2)})
    return out


def describe_drift(name: str, pairs: list[dict]) -> str:
    """One line for people: the pairs ``hall_drift`` found."""
    parts = [f"{a} less {b} moves by {p['drift_deg']:+.1f} deg over the recording"
             for p in pairs for a, b in [p["columns"]]]
    return (f"{name}: a Hall sensor drifts slowly from its partner: " + "; ".join(parts)
            + " (which of the two, neither the gyros nor the filter can tell). The readings "
            "are used; recalibrate the sensors' curves or refit (docs/faults.md, 'Slow "
            "drift')")
