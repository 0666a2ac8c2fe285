"""``Auto``: the policy that picks a path, once, on concrete inputs, with reasons a user can read
(as ``lineax.AutoLinearSolver`` picks a solver)."""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import jax
import numpy as np

from .._kernel import Estimate, FilterState, SensorSeries
from .._params import Params
from ._base import AbstractPath, is_traced
from ._lanes import Lanes
from ._parallel import Parallel
from ._segments import Segments
from ._sequential import Sequential
from ._steady import Steady


class PathChoice(NamedTuple):
    """The path ``Auto`` picked, and why each faster one was passed over (``{name: reason}``)."""

    path: AbstractPath
    passed_over: dict[str, str]


class Auto(AbstractPath):
    """The fastest path that applies: ``Steady`` on a regular recording whose covariance
    converges; else, for a Kalman filter, ``Lanes`` for a batch of at least
    ``lanes.min_trials`` trials; else ``Segments`` for recordings long enough to cut into
    ``segments.min_segments`` segments (``segments=None``: never); else ``Parallel`` on an
    accelerator and ``Sequential`` on a CPU.

    The choice is made on concrete inputs before anything is traced (``run_filter``,
    ``filter_batch``, ``filter_sessions`` and the fitting loss all resolve ``Auto`` first).
    Inside a transformation (``jit``, ``grad``, ``vmap`` of the caller's) the data cannot be
    checked, so ``Auto`` takes the path that needs no check (``Sequential``) and says so in
    ``passed_over``; pass a path explicitly to vouch for the data instead.

    Attributes:
        steady: the ``Steady`` path to try (its constants).
        lanes: the ``Lanes`` path to try (its constants).
        segments: the ``Segments`` path to try (its constants), or ``None``.
        sequential: the ``Sequential`` path to fall back on (its remat chunk).
    """

    name: ClassVar[str] = "auto"
    steady: Steady = Steady()
    lanes: Lanes = Lanes()
    segments: Segments | None = Segments()
    sequential: Sequential = Sequential()

    def select(self, params: Params, series: SensorSeries, method: str,
               state: FilterState | None = None) -> PathChoice:
        """The path for these inputs, and why each faster one does not apply."""
        passed: dict[str, str] = {}
        if is_traced(params, series, state):
            passed["steady"] = "the inputs are traced (inside jit or grad): not checked"
        else:
            why = self.steady.applies(params, series, method, state)
            if why is None:
                return PathChoice(self.steady, passed)
            passed["steady"] = why
        n_trials = np.shape(series.dt)[0] if np.ndim(series.dt) > 1 else 1
        why = self.lanes.applies(params, series, method, state)
        if why is None and n_trials >= self.lanes.min_trials:
            return PathChoice(self.lanes, passed)
        passed["lanes"] = why or (f"{n_trials} trial(s), fewer than {self.lanes.min_trials}: "
                                  "lanes pay for batches")
        if self.segments is None:
            passed["segments"] = "not offered here"
        else:
            why = self.segments.applies(params, series, method, state) or self.segments.pays(
                series, _dtype(params, state))
            if why is None:
                return PathChoice(self.segments, passed)
            passed["segments"] = why
        if jax.default_backend() != "cpu" and Parallel().applies(params, series, method) is None:
            return PathChoice(Parallel(), passed)
        passed["parallel"] = "slower than the sequential path on a CPU"
        return PathChoice(self.sequential, passed)

    def applies(self, params: Params, series: SensorSeries, method: str,
                state: FilterState | None = None) -> str | None:
        return None

    def run(self, params: Params, series: SensorSeries, method: str, state: FilterState
            ) -> tuple[FilterState, Estimate]:
        return self.select(params, series, method, state).path.run(params, series, method,
                                                                   state)


def _dtype(params: Params, state: FilterState | None):
    """The computation's precision: the entering state's, else the parameters'."""
    return state.z.dtype if state is not None else params.log_q.dtype
