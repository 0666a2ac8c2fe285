"""Evaluation reports: every method's error figures on recorded sessions, as the
``kckf evaluate --json`` document, and the paper's Table 1 layout as text and Markdown.

At the edge with the CLI and the plots: it calls the core (``filter_sessions``,
``rmse_table``) and nothing of the core imports it.
"""

from __future__ import annotations

from collections.abc import Sequence

from ._metrics import rmse_table
from ._params import Params
from ._run import filter_sessions
from ._session import Session

PAPER_TABLE_METHODS = ("gyro", "hall_l", "hall_r", "kf", "kckf")
TABLE_LABELS = {"gyro": "Gyro", "hall_l": "Hall l", "hall_r": "Hall r", "kf": "Std KF",
                "kckf": "KCKF", "kckf_fit": "KCKF fit"}


def evaluate_sessions(sessions: Sequence[Session], methods: Sequence[str],
                      params: Params | None = None, burn_in_s: float = 0.0):
    """RMSE of every method on ``sessions``: the ``kckf evaluate --json`` document (each
    method with the ``"path"`` that computed it) and the estimated angles ``{method: [(T, K)
    per session]}``.

    Raises ``ValueError`` naming the session when one has no motion capture over its sensor
    rows."""
    for s in sessions:
        if not s.has_truth:
            raise ValueError(
                f"{s.path}: no motion capture overlaps the sensors (mocap.csv is needed to "
                "evaluate)"
            )
    out, angles = {}, {}
    for m in methods:
        est = filter_sessions(sessions, m, params)
        angles[m] = [e.angles for e in est]
        out[m] = rmse_table(sessions, angles[m], burn_in_s)
        out[m]["path"] = "+".join(dict.fromkeys(e.path for e in est))
    return {"methods": out, "sessions": [s.path for s in sessions]}, angles


def format_table(results: dict, robot, methods: Sequence[str], title: str = "") -> str:
    """The paper's Table 1 layout: one row per angle, one column per method, RMSE in deg."""
    cols = [m for m in methods if m in results]
    width = 9
    lines = []
    if title:
        lines.append(title)
    lines.append(f"{'angle':<10}" + "".join(f"{TABLE_LABELS.get(m, m):>{width}}" for m in cols))
    for name in robot.angle_names:
        row = f"{name:<10}"
        for m in cols:
            v = results[m]["rmse_deg"].get(name)
            row += f"{'-':>{width}}" if v is None else f"{v:>{width}.2f}"
        lines.append(row)
    lines.append(f"{'mean':<10}" + "".join(
        f"{results[m]['mean_rmse_deg']:>{width}.2f}" for m in cols))
    return "\n".join(lines)


def markdown_table(results: dict, robot, methods: Sequence[str]) -> str:
    """``format_table`` as a Markdown table."""
    cols = [m for m in methods if m in results]
    lines = ["| angle | " + " | ".join(TABLE_LABELS.get(m, m) for m in cols) + " |",
             "| --- |" + " ---: |" * len(cols)]
    for name in robot.angle_names:
        cells = []
        for m in cols:
            v = results[m]["rmse_deg"].get(name)
            cells.append("-" if v is None else f"{v:.2f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append("| mean | " + " | ".join(
        f"{results[m]['mean_rmse_deg']:.2f}" for m in cols) + " |")
    return "\n".join(lines)


def write_estimates(path: str, session: Session, est) -> None:
    """``kckf filter``'s CSV: ``t`` and one column per estimated angle (rad), named as in
    ``mocap.csv``; an angle the method does not estimate is left out, a NaN is an empty cell."""
    import os

    import numpy as np

    robot = session.robot
    names = [n for k, n in enumerate(robot.angle_names) if np.isfinite(est.angles[:, k]).any()]
    cols = [robot.angle_names.index(n) for n in names]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        f.write(",".join(["t", *names]) + "\n")
        for t, row in zip(session.t, est.angles[:, cols]):
            f.write(repr(float(t)) + "," + ",".join(
                "" if not np.isfinite(v) else format(float(v), ".9g") for v in row) + "\n")


def session_name(path: str) -> str:
    """A file-name stem for a session folder: its last two path parts, joined by ``_``."""
    import os

    parts = os.path.normpath(path).split(os.sep)
    return "_".join(parts[-2:]) if len(parts) >= 2 else parts[-1]
