"""``Auto``: the policy that picks a path, once, on concrete inputs, with reasons a user can read
(as ``lineax.AutoLinearSolver`` picks a solver)."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import numpy as np

from .._models._kernel import Estimate, FilterState, SensorSeries
from .._models._params import Params
from ._base import AbstractPath, PathChoice, PathRun, SmootherLayout, is_traced, kalman_only
from ._exact_lanes import exact_lanes
from ._lanes import Lanes
from ._parallel import Parallel
from ._segments import Segments
from ._sequential import Sequential
from ._steady import Steady
from ._steady_smooth import SteadySmoother


class Auto(AbstractPath):
    """The fastest path that applies (for ``runs`` runs: the soonest done, compile
    included): any of ``before`` that applies, in order; then
    ``Steady`` on a regular recording whose covariance converges; else, for a Kalman filter,
    ``Lanes`` for a batch of at least ``lanes.min_trials`` trials; else ``Segments`` for
    recordings long enough to cut into ``segments.min_segments`` segments (``segments=None``:
    never); else ``Parallel`` on an accelerator and ``Sequential`` on a CPU.

    The choice is made on concrete inputs before anything is traced (``run_filter``,
    ``filter_batch``, ``filter_sessions`` and the fitting loss all resolve ``Auto`` first).
    Inside a transformation of the caller's (``jit``, ``grad``, ``vmap``) the values cannot be
    checked: ``Auto`` passes ``Steady`` over (its checks need them) and decides on shapes
    alone: ``Lanes`` for a batch of ``lanes.min_trials`` trials or more, ``Segments`` for a
    recording long enough (its check then runs inside the program, each repair and the
    sequential fallback in a ``lax.cond``), else ``Sequential``; ``passed_over`` says so. Pass
    a path explicitly to vouch for the data instead.

    The same policy lays out the smoother and the likelihood (``batch_layout``,
    ``smoother_layout``), so ``Auto(lanes=Lanes(min_trials=4))`` moves all three;
    ``for_loss`` is the policy a fitting loss uses.

    Attributes:
        steady: the ``Steady`` path to try (its constants).
        lanes: the ``Lanes`` path to try (its constants).
        segments: the ``Segments`` path to try (its constants), or ``None``.
        sequential: the ``Sequential`` path to fall back on (its remat chunk).
        before: paths of the caller's to try first, in order (a path added by
            ``docs/performance.md``'s recipe: no line of this class changes).
        runs: how many times the caller runs the chosen program on these shapes, when it
            knows (the ``kckf`` command filters a recording once: ``1``). Then the lanes and
            segments paths are taken only where their compile plus ``runs`` runs is
            estimated shorter than the sequential path's (``AbstractPath.cost``, measured:
            for one run an hour takes the sequential path, 1.9 s against 3.3 s, and 12
            trials of 10,000 rows too, 2.3 s against 3.1 s; 64 trials take lanes, 3.3 s
            against 5.1 s). ``None`` (default, as for a fit or a program run many times):
            by run time alone.
    """

    name: ClassVar[str] = "auto"
    steady: Steady = Steady()
    lanes: Lanes = Lanes()
    segments: Segments | None = Segments()
    sequential: Sequential = Sequential()
    before: tuple[AbstractPath, ...] = ()
    runs: int | None = eqx.field(static=True, default=None)

    def for_loss(self, remat_chunk: int | None = None, gradient: bool = True) -> Auto:
        """The policy for a fitting loss: not ``Segments`` (its warm-ups cut each segment's
        dependence on the rows before it, which the values' check vouches for but a gradient
        would not see); ``Sequential(remat_chunk)`` to fall back on; and, for a gradient
        (``gradient``; a validation loss is not one) not chunked for memory
        (``remat_chunk=None``), ``Lanes`` from one trial on.

        Its hand-written reverse pass (``_lanes_adjoint``) makes the lanes gradient faster
        than the sequential path's at every batch measured, where a filter run once is done
        sooner on the sequential path below ``Lanes.min_trials`` (the lanes program compiles
        longer; docs/performance.md; the figures: benchmarks/README.md, "Measurements behind
        the paths' choices"); ``kckf3d``'s lanes step has its own (``_exact_adjoint``). It
        keeps every row's state and gains (about 1.1 kB per trial-step with the rows' inputs
        for the linear KCKF), so a gradient the sequential path would chunk for memory keeps
        ``lanes`` as it is; ``kckf3d``'s keeps its whole covariance per row (2.9 kB a
        trial-row for ``xyz,xyz,xyz``), so such a gradient runs its pass in checkpointed
        chunks of ``remat_chunk`` rows (``Lanes.exact_chunk``)."""
        lanes = Lanes(min_trials=1) if gradient and remat_chunk is None else self.lanes
        if gradient and remat_chunk is not None:
            lanes = dataclasses.replace(lanes, exact_chunk=remat_chunk)
        return Auto(steady=self.steady, lanes=lanes, segments=None,
                    sequential=Sequential(remat_chunk), before=self.before)

    def batch_layout(self, n_trials: int, method: str = "kckf") -> str:
        """``"lanes"`` for ``lanes.min_trials`` trials or more of a method the lanes compute,
        else ``"sequential"``."""
        return ("lanes" if n_trials >= self.lanes.min_trials and kalman_only(method) is None
                else "sequential")

    def smoother_layout(self, params: Params, series: SensorSeries, method: str
                        ) -> SmootherLayout:
        """``"steady"`` where the steady smoother applies (concrete inputs; checked here, once),
        else ``batch_layout``'s."""
        if not is_traced(params, series):
            if SteadySmoother(steady=self.steady).applies(params, series, method) is None:
                return SmootherLayout("steady", self.steady, checked=True)
        return SmootherLayout(self.batch_layout(int(np.shape(series.dt)[0]), method))

    def choose(self, params: Params, series: SensorSeries, method: str,
               state: FilterState | None = None) -> PathChoice:
        return self.select(params, series, method, state)

    def select(self, params: Params, series: SensorSeries, method: str,
               state: FilterState | None = None) -> PathChoice:
        """The path for these inputs, and why each faster one does not apply."""
        passed: dict[str, str] = {}
        for path in self.before:
            why = path.applies(params, series, method, state)
            if why is None:
                return PathChoice(path, passed)
            passed[path.name] = why
        if is_traced(params, series, state):
            passed["steady"] = "the inputs are traced (inside jit or grad): not checked"
        else:
            why = self.steady.applies(params, series, method, state)
            if why is None:
                return PathChoice(self.steady, passed)
            passed["steady"] = why
        n_trials = np.shape(series.dt)[0] if np.ndim(series.dt) > 1 else 1
        n_rows = int(np.shape(series.dt)[-1])
        why = self.lanes.applies(params, series, method, state)
        least = self.lanes.min_trials_for(method)
        if why is None and n_trials >= least:
            # (kckf3d's lanes step costs less than its sequential one from one trial on, and
            # compiles no longer: no compile to weigh; the costs are the linear filters')
            why = None if exact_lanes(method) else self._outweighed(self.lanes, n_trials, n_rows)
            if why is None:
                return PathChoice(self.lanes, passed)
        passed["lanes"] = why or (f"{n_trials} trial(s), fewer than {least}: "
                                  "lanes pay for batches")
        if self.segments is None:
            passed["segments"] = "not offered here"
        else:
            why = (self.segments.applies(params, series, method, state)
                   or self._outweighed(self.segments, n_trials, n_rows)
                   or self.segments.pays(series, _dtype(params, state)))
            if why is None:
                return PathChoice(self.segments, passed)
            passed["segments"] = why
        if jax.default_backend() != "cpu" and Parallel().applies(params, series, method) is None:
            return PathChoice(Parallel(), passed)
        passed["parallel"] = "slower than the sequential path on a CPU"
        return PathChoice(self.sequential, passed)

    def _outweighed(self, path: AbstractPath, n_trials: int, n_rows: int) -> str | None:
        """With ``runs`` set: why ``path``'s compile outweighs what it saves over the
        sequential path in ``runs`` runs (estimated, ``AbstractPath.cost``), or ``None``."""
        if self.runs is None:
            return None
        fast, slow = path.cost(n_trials, n_rows), self.sequential.cost(n_trials, n_rows)
        if fast is None or slow is None or fast.total(self.runs) <= slow.total(self.runs):
            return None
        return (f"for {self.runs} run(s) its compile costs more than it saves: about "
                f"{fast.total(self.runs):.2f} s against {slow.total(self.runs):.2f} s "
                "sequential (compile and run, estimated)")

    def applies(self, params: Params, series: SensorSeries, method: str,
                state: FilterState | None = None) -> str | None:
        return None

    def run(self, params: Params, series: SensorSeries, method: str, state: FilterState
            ) -> tuple[FilterState, Estimate]:
        return self.select(params, series, method, state).path.run(params, series, method,
                                                                   state)

    def compute(self, params: Params, series: SensorSeries, method: str,
                state: FilterState, innovations: bool = False) -> PathRun:
        return self.select(params, series, method, state).path.compute(params, series,
                                                                       method, state,
                                                                       innovations)


def _dtype(params: Params, state: FilterState | None):
    """The computation's precision: the entering state's, else the parameters'."""
    return state.z.dtype if state is not None else params.log_q.dtype
