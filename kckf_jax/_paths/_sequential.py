"""The sequential path: ``lax.scan`` of the kernel's ``step`` over every row, ``vmap`` over
trials. It computes anything the filter accepts and is the reference for every other path."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax

from .._kernel import Estimate, FilterState, SensorSeries, scan_filter
from .._params import Params
from ._base import AbstractPath


class Sequential(AbstractPath):
    """The scan of ``step`` (``scan_filter``), trial by trial under ``vmap``.

    Attributes:
        remat_chunk: checkpoint the scan in chunks of this many rows (``scan_filter``): a
            gradient then stores about ``T / remat_chunk + remat_chunk`` states instead of
            every intermediate of every row. ``None``: no checkpointing.
    """

    name: ClassVar[str] = "sequential"
    remat_chunk: int | None = eqx.field(static=True, default=None)

    def applies(self, params: Params, series: SensorSeries, method: str,
                state: FilterState | None = None) -> str | None:
        return None

    def run(self, params: Params, series: SensorSeries, method: str, state: FilterState
            ) -> tuple[FilterState, Estimate]:
        return jax.vmap(lambda s, x: scan_filter(params, s, method, x, self.remat_chunk))(
            series, state)
