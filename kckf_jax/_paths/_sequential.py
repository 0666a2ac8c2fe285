"""The sequential path: ``lax.scan`` of the kernel's ``step`` over every row, ``vmap`` over
trials. It computes anything the filter accepts and is the reference for every other path."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax

from .._models._classes import scan_filter
from .._models._kernel import Estimate, FilterState, SensorSeries
from .._models._params import Params
from .._readings._prepare import prepare
from ._base import AbstractPath, PathCost


class Sequential(AbstractPath):
    """The scan of ``step`` (``scan_filter``), trial by trial under ``vmap``.

    Attributes:
        remat_chunk: checkpoint the scan in chunks of this many rows (``scan_filter``): a
            gradient then stores about ``T / remat_chunk + remat_chunk`` states instead of
            every intermediate of every row. ``None``: no checkpointing.
    """

    name: ClassVar[str] = "sequential"
    remat_chunk: int | None = eqx.field(static=True, default=None)

    def cost(self, n_trials: int, n_rows: int) -> PathCost:
        """Compile 1.5 s (one recording) or 2.0 s (a vmapped batch); 1.1 us a row for one
        trial, each trial costing more in a larger batch (``1 + (B - 1) / 18`` times): fitted
        to ``benchmarks/one_shot.py`` (its figures: benchmarks/README.md, "one_shot.py")."""
        per_row = 1.1e-6 * (1 + (n_trials - 1) / 18)
        return PathCost(1.5 if n_trials == 1 else 2.0, per_row * n_trials * n_rows)

    def applies(self, params: Params, series: SensorSeries, method: str,
                state: FilterState | None = None) -> str | None:
        return None

    def run(self, params: Params, series: SensorSeries, method: str, state: FilterState
            ) -> tuple[FilterState, Estimate]:
        series = prepare(params, series, method)
        return jax.vmap(lambda s, x: scan_filter(params, s, method, x, self.remat_chunk))(
            series, state)

    innovations_in_pass: ClassVar[bool] = True

    def run_innovations(self, params: Params, series: SensorSeries, method: str,
                        state: FilterState) -> tuple[FilterState, Estimate]:
        series = prepare(params, series, method)
        return jax.vmap(lambda s, x: scan_filter(params, s, method, x, self.remat_chunk,
                                                 innovations=True))(series, state)
