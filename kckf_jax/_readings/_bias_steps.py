"""A gyro whose bias steps, seen by a filter that has no gyro pairs: named from the filter's
own bias estimate.

Under the paper's model two gyro channels read the same rate, and the health monitor names
a bias step from their disagreement (``_health``). Under the chain's exact kinematics
(``kckf3d``) no two channels read the same rate, and the filter estimates each channel's
bias (``_exact``): a gyro whose bias steps is absorbed by that estimate, which moves to the
new bias within a few seconds. The estimate is the exact model's reconciliation of the gyros,
the Hall sensors and the chain's forward kinematics, so its moves are what that model says
of the gyros: ``bias_steps`` looks for a step in the joints' estimated rate biases
(``Estimate.bias``): the mean over ``AFTER_S`` starting ``SETTLE_S`` later less the mean over
``BEFORE_S`` before, at least ``MIN_STEP_RAD_S`` and ``WOBBLE_FACTOR`` times the estimate's
own spread within those two windows (which follows the pose where the model's rates are
approximate: a fast three-axis joint at large angles). The change over the joints is then
matched to the gyro channels the joints' rates read (``Robot.rate_map``): the channel, or the
channels the joints cannot tell apart (the two gyros of a one-axis joint whose neighbours turn
about other axes), with the step each would have made.

Measured on 30 s exact-rotation sessions of the simulator (kckf3d, paper defaults; ``x,y,x,y``,
``x,y,z``, ``xyz,xyz,xyz``; walking, human, cyclic; default ranges and 140 deg; seeds 1-3):
the statistic reaches 0.005-0.070 rad/s on clean sessions except ``xyz,xyz,xyz`` cyclic at
140 deg (joints at 14-18 rad/s: 0.07-0.21, where its spread gate holds it), and 0.16-0.23 for
a 0.2 rad/s step of ``gyro3_x`` (docs/faults.md, "A bias step under kckf3d").

NumPy on the host, once per recording, in the report (like ``_drift``): nothing is taken out of
the filter's readings; the estimates already follow the new bias.
"""

from __future__ import annotations

import numpy as np

#: The windows (s): the mean before a time, and the mean after it once the estimate settled.
BEFORE_S, SETTLE_S, AFTER_S = 4.0, 2.0, 4.0
#: The filter's own convergence (s): after the recording starts, and after a gap (a time step
#: over ``GAP_S``, where the filter restarts or predicts), the estimate settles from its prior;
#: no window reaches back into this (the statistic on clean 20 s sessions of ``x,y,z`` cyclic
#: at 140 deg: 0.10-0.15 rad/s at 3-4 s without it).
CONVERGE_S = 5.0
GAP_S = 0.5
#: The smallest step named (rad/s): twice the largest clean value above bar the fast case.
MIN_STEP_RAD_S = 0.1
#: The step must be this many times the estimate's spread within its two windows.
WOBBLE_FACTOR = 1.5
#: The step's time: where the estimate has moved this share of the way.
ONSET_SHARE = 0.25
#: A step must be one gyro's: the best channel leaves at most this share of the change
#: unexplained (a change that no single channel's pattern over the joints makes is the
#: model's, not a gyro's).
MAX_UNEXPLAINED = 0.5


def _window_moments(t, x, lo, hi):
    """Mean and standard deviation of ``x`` (``T x J``, NaN where unknown) over ``[lo, hi)``
    per entry of ``lo``/``hi``."""
    ok = np.isfinite(x)
    v = np.where(ok, x, 0.0)
    zero = np.zeros((1, x.shape[1]))
    c0 = np.concatenate([zero, np.cumsum(ok, axis=0)])
    c1 = np.concatenate([zero, np.cumsum(v, axis=0)])
    c2 = np.concatenate([zero, np.cumsum(v * v, axis=0)])
    i, j = np.searchsorted(t, lo), np.searchsorted(t, hi)
    n = np.maximum(c0[j] - c0[i], 1.0)
    mean = (c1[j] - c1[i]) / n
    var = np.maximum((c2[j] - c2[i]) / n - mean ** 2, 0.0)
    return mean, np.sqrt(var), c0[j] - c0[i]


def bias_steps(session, est) -> list[dict]:
    """The gyro bias steps in ``est`` (an ``Estimate`` of ``session``, whose ``bias`` the
    filter estimated; module docstring): ``[{"t_s", "joints", "change_rad_s", "columns",
    "step_rad_s"}]``: when the estimate had moved a quarter of the way (the filter's lag: about
    a second after the step), the joint axes whose rate bias moved and by how much, and the
    gyro channels that would explain it, each with its own step (rad/s). Empty for a
    recording (or each stretch between gaps) shorter than ``CONVERGE_S`` and the windows, and
    for an estimate without biases."""
    robot = session.robot
    J = robot.n_joint_axes
    t = np.asarray(session.t, np.float64)
    b = np.asarray(est.bias, np.float64)[..., :J]
    span = BEFORE_S + SETTLE_S + AFTER_S
    if b.ndim != 2 or t.size < 2 or not np.isfinite(b).any():
        return []
    # Each row's stretch (rows between gaps): its windows stay inside it, past its start's
    # convergence.
    cut = np.concatenate([[0], np.flatnonzero(np.diff(t) > GAP_S) + 1, [t.size]])
    first = np.repeat(t[cut[:-1]], np.diff(cut))
    last = np.repeat(t[cut[1:] - 1], np.diff(cut))
    grid = np.flatnonzero((t - BEFORE_S >= first + CONVERGE_S)
                          & (t + SETTLE_S + AFTER_S <= last))
    if grid.size == 0:
        return []
    tg = t[grid]
    m0, s0, n0 = _window_moments(t, b, tg - BEFORE_S, tg)
    m1, s1, n1 = _window_moments(t, b, tg + SETTLE_S, tg + SETTLE_S + AFTER_S)
    d = np.where((n0 > 0) & (n1 > 0), m1 - m0, 0.0)
    bar = np.maximum(MIN_STEP_RAD_S, WOBBLE_FACTOR * (s0 + s1))
    hit = np.abs(d) >= bar
    score = np.where(hit, np.abs(d), 0.0).max(axis=1)
    cols = np.asarray(robot.rate_map, np.float64)[:J]
    used = [int(c) for c in robot.used_gyro_index]
    found = []
    while score.max(initial=0.0) > 0.0:
        k = int(np.argmax(score))
        change = d[k]
        moved = np.flatnonzero(hit[k])
        step = _explain(t, b, grid[k], tg[k], m0[k], change, moved, cols, used, robot)
        if step is not None:
            found.append(step)
        score[np.abs(tg - tg[k]) < span] = 0.0  # one step per stretch of the windows
    return sorted(found, key=lambda f: f["t_s"])


def _explain(t, b, row, t_peak, before, change, moved, cols, used, robot) -> dict | None:
    """One step: its onset, the joints it moved and the gyro channels that explain it
    (``None`` where none does: ``MAX_UNEXPLAINED``). ``before``: each joint's mean over the
    window before ``t_peak``."""
    j = moved[np.argmax(np.abs(change[moved]))]
    window = np.flatnonzero((t >= t_peak - BEFORE_S) & (t < t_peak + SETTLE_S + AFTER_S))
    share = (b[window, j] - before[j]) / change[j]
    onset = window[np.flatnonzero(share >= ONSET_SHARE)]
    t_on = float(t[onset[0]] if onset.size else t[row])
    fits = []
    for c in used:
        m = cols[:, c]
        if not m.any():
            continue
        alpha = float(m @ change / (m @ m))
        fits.append((float(np.linalg.norm(change - alpha * m)), c, alpha))
    if not fits:
        return None
    best = min(f[0] for f in fits)
    size = float(np.linalg.norm(change))
    if best > MAX_UNEXPLAINED * size:
        return None
    tol = best + 0.25 * size
    names = robot.gyro_names
    chosen = [(names[c], alpha) for r, c, alpha in fits if r <= tol]
    return {"t_s": round(t_on, 3),
            "joints": [robot.angle_names[i] for i in moved],
            "change_rad_s": [round(float(change[i]), 4) for i in moved],
            "columns": [n for n, _ in chosen],
            "step_rad_s": [round(a, 4) for _, a in chosen]}


def describe_bias_steps(name: str, method: str, steps: list[dict]) -> str:
    """One line for people: the steps ``bias_steps`` found."""
    parts = []
    for s in steps:
        who = " or ".join(f"{c} by {a:+.2f} rad/s" for c, a in zip(s["columns"],
                                                                   s["step_rad_s"]))
        parts.append(f"{who or 'a gyro'} at about {s['t_s']:.1f} s ("
                     + ", ".join(f"{j} {x:+.2f}" for j, x in zip(s["joints"],
                                                               s["change_rad_s"])) + ")")
    return (f"{name}: a gyro's bias stepped ({method}'s bias estimate moved): "
            + "; ".join(parts) + ". The readings are used and the estimate follows the new "
            "bias after a few seconds; check the gyro (temperature, a knock, a reset) "
            "(docs/faults.md, 'A bias step under kckf3d')")
