"""Batches of recordings: trials padded to one length (``pad_series``, ``pad_trials``)."""

from __future__ import annotations

import dataclasses

import numpy as np

from .._models._kernel import SensorSeries


def pad_trials(series: list, length: int | None = None, what: str = "pad_series"):
    """Stack trials of uneven length (any series module with a ``dt`` field: ``SensorSeries``,
    ``filters.ArmImuSeries``) into one batch: ``dt`` padded with 0, every other field with
    NaN (missing), so padding rows are no-op steps. ``length``: the padded length (default
    the longest trial's)."""
    if not series:
        raise ValueError(f"{what}: no trials given")
    T = max(int(np.shape(s.dt)[0]) for s in series) if length is None else length

    def pad(x, fill):
        x = np.asarray(x)
        if x.shape[0] > T:
            raise ValueError(f"{what}: a trial has {x.shape[0]} rows, more than {T}")
        return np.pad(x, [(0, T - x.shape[0])] + [(0, 0)] * (x.ndim - 1), constant_values=fill)

    names = [f.name for f in dataclasses.fields(series[0]) if not f.metadata.get("static")]
    return type(series[0])(**{n: np.stack([pad(getattr(s, n), 0.0 if n == "dt" else np.nan)
                                           for s in series]) for n in names})


def pad_series(series: list[SensorSeries], length: int | None = None) -> SensorSeries:
    """Stack trials of uneven length into one batch; padding rows are no-op steps.

    Example:
        >>> trials = [SensorSeries(np.full(n, 0.01), np.zeros((n, 6)), np.ones((n, 2)))
        ...           for n in (3, 5)]
        >>> pad_series(trials).hall_v.shape
        (2, 5, 2)
    """
    return pad_trials(series, length, "pad_series")
