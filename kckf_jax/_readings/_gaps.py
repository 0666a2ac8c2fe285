"""Holes in the sensor rows: one policy for the batch filter, the fit and the stream.

A time step longer than ``gap_s`` is a *gap* (a dropped stretch of packets, a paused logger).
The filter either predicts across it (``"predict"``: the covariance grows with the time, and
the next readings pull the estimate back) or starts again from its initial state at the first
row after it (``"restart"``); a gap longer than ``max_predict_s`` always restarts. Every
command reports the gaps it found and what it did (stderr, and the JSON of ``kckf evaluate``).

Predicting holds the last gyro rates across the gap, which describes a worn robot's motion for
a fraction of a second, not for minutes: on a 60 s bench session (``kckf simulate --kind
cyclic --seed 1``, paper defaults, float32) whose sensor rows stop for a while halfway,
predicting across 2 s scored 8.7 deg mean RMSE and across 10 min 1,670 deg (estimates to
7,818 deg, the covariance losing definiteness), where restarting scored 1.44 deg for every
length (clean: 1.41). So by default only gaps up to ``DEFAULT_MAX_PREDICT_S`` are predicted
across, and the filter starts again after any longer one (docs/faults.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ON_GAP = ("predict", "restart")
#: The longest gap predicted across by default (s): a quarter to a half of a gait cycle.
DEFAULT_MAX_PREDICT_S = 1.0


@dataclass(frozen=True)
class GapPolicy:
    """What counts as a gap, and what the filter does across one.

    Attributes:
        gap_s: a time step longer than this (s) is a gap.
        on_gap: ``"predict"`` (step across it) or ``"restart"`` (start again after it).
        max_predict_s: a gap longer than this restarts even with ``on_gap="predict"``;
            ``None`` (default): ``DEFAULT_MAX_PREDICT_S``, or ``gap_s`` where that is longer
            (every gap then restarts).
    """

    gap_s: float = 0.5
    on_gap: str = "predict"
    max_predict_s: float | None = None

    def __post_init__(self):
        if self.on_gap not in ON_GAP:
            raise ValueError(f"on_gap must be 'predict' or 'restart', got {self.on_gap!r}")
        if not self.gap_s > 0:
            raise ValueError(f"gap_s must be positive, got {self.gap_s}")
        if self.max_predict_s is None:
            object.__setattr__(self, "max_predict_s", max(DEFAULT_MAX_PREDICT_S, self.gap_s))
        if not self.max_predict_s >= self.gap_s:
            raise ValueError(f"max_predict_s must be at least gap_s, got {self.max_predict_s}")

    def action(self, dt: float) -> str | None:
        """``None`` for an ordinary step, else what the filter does: ``"predict"`` or
        ``"restart"``."""
        if not dt > self.gap_s:
            return None
        return "predict" if self.on_gap == "predict" and dt <= self.max_predict_s else "restart"


@dataclass(frozen=True)
class Gap:
    """One hole: the first row after it, its length (s), its start (s, the last row before
    it) and what the filter did."""

    row: int
    length_s: float
    t_s: float
    action: str

    def to_json(self) -> dict:
        return {"t_s": self.t_s, "length_s": self.length_s, "row": self.row,
                "action": self.action}


def find_gaps(t: np.ndarray, policy: GapPolicy) -> list[Gap]:
    """Every gap of the timestamps ``t`` (s) under ``policy``."""
    t = np.asarray(t, np.float64)
    rows = np.flatnonzero(np.diff(t) > policy.gap_s) + 1
    return [Gap(int(k), float(t[k] - t[k - 1]), float(t[k - 1]), policy.action(t[k] - t[k - 1]))
            for k in rows]


def segments(n_rows: int, gaps: list[Gap]) -> list[tuple[int, int]]:
    """``[(start, stop), ...]``: the stretches filtered from a fresh state (split at every gap
    that restarts)."""
    cuts = [g.row for g in gaps if g.action == "restart"]
    edges = [0, *cuts, n_rows]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:])]


def describe(name: str, gaps: list[Gap]) -> str | None:
    """One line for people about ``gaps``, or None."""
    if not gaps:
        return None
    parts = [f"{g.length_s:.3g} s at t = {g.t_s:.6g} s ({g.action})" for g in gaps[:4]]
    more = f" and {len(gaps) - 4} more" if len(gaps) > 4 else ""
    return (f"{name}: {len(gaps)} gap(s) in the sensor rows: " + ", ".join(parts) + more
            + " (--gap, --on-gap)")
