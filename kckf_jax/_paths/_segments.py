"""The segments path: one long recording cut into segments that run side by side as lanes.

A single recording leaves the lanes layout (``_lanes.py``) nothing to put in its lanes, and a
sequential scan is bound by XLA's cost per loop iteration (about 0.9 us per row here with each
loop one kernel, ``_cpu_loops``; 2.6 us without; on a GPU far more). But
the filter forgets where it started: from the initial state, its estimates and covariance
meet those of a filter that has run from the first row within a few thousand rows (measured
on recorded-like bench sessions, float64: the state within 4e-8 after 4,096 rows and 4e-14
after 8,192; in float32 the two meet float32's own rounding, about 1e-6, after 3,072). So
each segment first runs ``warmup`` rows before its own from the initial state, in the same
lanes as the others, and then its own rows from there: every segment in one lane, the whole
recording in one scan of ``T / S + warmup`` iterations. The warm-up reads the inputs already
computed for the segment before (one lane over), so nothing is computed twice but the scan.

That is only exact if every warm-up has converged, so the path checks it: at each segment's
first row the warmed-up state (mean, covariance and gyro hold) must equal the state the
segment before it reached there, to ``atol`` (``segment_check``). Where a check fails
(a long stretch with missing readings, say, during which the filter cannot forget), a repair
pass runs every segment's own rows again, each entering where the one before it ended (the
first segments enter as before): a segment whose predecessor was right is now exactly right,
and the pass is checked the same way (every segment must end where it ended in the pass
before, so that the next one entered right). One pass costs ``T / S`` iterations, about two
thirds of the first (``T / S + warmup``), where the sequential path costs ``T``. Only where
the repairs fail too is the recording filtered by the sequential path, and ``run_filter`` and
``filter_batch`` say so (``Estimate.path`` is ``"sequential"``). From the host
(``Segments.compute``) each pass is a program of its own, so that a recording whose check
passes compiles no repair; under a caller's ``jit``, ``Segments.run`` has every pass in one
program (each repair and the sequential fallback in a ``lax.cond``).
"""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool

from .._models._classes import model_of, structure
from .._models._kernel import Estimate, FilterState, SensorSeries
from .._models._params import Params
from .._readings._prepare import prepare
from ._base import AbstractPath, PathCost, PathRun, is_traced, kalman_only
from ._lanes import (
    NO_OP_INPUTS,
    LaneRows,
    LaneRowsInnovations,
    LaneState,
    lane_estimates,
    lane_inputs,
    lane_scan,
    lane_scan_innovations,
    rows_innovations,
)
from ._sequential import Sequential


class Segments(AbstractPath):
    """One or a few long recordings, each cut into segments that run as lanes, every segment
    warmed up over the rows before it, and checked (see the module docstring).

    Exact for everything ``Sequential`` computes (irregular time steps, missing readings per
    channel, the voltage noise model, padded trials, skipped updates) wherever the check
    passes, at once or after a repair pass; where it fails after ``repairs`` passes, ``run``
    computes the sequential path's result instead (and ``run_checked`` says so).

    Attributes:
        lanes: about how many lanes (trials x segments) to fill.
        warmup_float32, warmup_float64: the rows each segment runs before its own.
        min_segments: ``Auto`` takes this path when each trial makes at least this many
            segments (at least ``warmup`` rows each).
        atol_float32, atol_float64: the check's bound on the mean (rad, rad/s) and, relative
            to ``sqrt(P_ii P_jj)``, on the covariance (float32: the accuracy asked of every
            path against the sequential one; float64: 1e-11).
        repairs: how many repair passes to try when the check fails, before the
            sequential path (0: none).
        gap_fraction: ``Auto`` passes this path over for rows with a stretch at least this
            fraction of a warm-up long in which some joint has no Hall reading (``pays``).
    """

    name: ClassVar[str] = "segments"
    lanes: int = eqx.field(static=True, default=64)
    warmup_float32: int = eqx.field(static=True, default=3072)
    warmup_float64: int = eqx.field(static=True, default=8192)
    min_segments: int = eqx.field(static=True, default=4)
    atol_float32: float = eqx.field(static=True, default=1e-5)
    atol_float64: float = eqx.field(static=True, default=1e-11)
    repairs: int = eqx.field(static=True, default=2)
    gap_fraction: float = eqx.field(static=True, default=0.5)

    def warmup(self, dtype) -> int:
        return self.warmup_float64 if jnp.dtype(dtype) == jnp.float64 else self.warmup_float32

    def atol(self, dtype) -> float:
        return self.atol_float64 if jnp.dtype(dtype) == jnp.float64 else self.atol_float32

    def segments_of(self, n_trials: int, n_rows: int, dtype) -> int:
        """How many segments each of ``n_trials`` trials of ``n_rows`` rows is cut into."""
        per_trial = max(1, self.lanes // max(n_trials, 1))
        return int(max(1, min(per_trial, n_rows // max(self.warmup(dtype), 1))))

    def applies(self, params: Params, series: SensorSeries, method: str,
                state: FilterState | None = None) -> str | None:
        unobservable = model_of(method).unobservable
        if unobservable is not None:
            return f"{unobservable}: it never forgets where it started, so no warm-up converges"
        return kalman_only(method)

    def pays(self, series: SensorSeries, dtype) -> str | None:
        """Why ``Auto`` should not take this path for ``series`` (or ``None``): too few
        segments, or (concrete rows) a stretch in which some joint has no Hall reading that
        is at least ``gap_fraction`` of a warm-up long, across which the warm-ups cannot
        forget where they started, so the check would fail and the repair passes cost more
        than the sequential path (``benchmarks/one_shot.py``, an hour with a 100 s dropout:
        6.47 s for the first call and 0.61 s for the next against 2.20 and 0.45 s; gaps of
        1,000 float32 rows anywhere passed the check at once, of 3,000 failed)."""
        shape = np.shape(series.dt)
        B, T = (shape[0], shape[1]) if len(shape) > 1 else (1, shape[0])
        n = self.segments_of(B, T, dtype)
        W = self.warmup(dtype)
        if n < self.min_segments:
            return (f"{T} rows make {n} segment(s) of {W} rows or more, "
                    f"fewer than {self.min_segments}")
        if not is_traced(series):
            gap, at = _longest_joint_gap(series.hall_v)
            if gap >= self.gap_fraction * W:
                return (f"some joint has no Hall reading for {gap} rows (from row {at}), "
                        f"{self.gap_fraction:g} of a {W}-row warm-up or more: the warm-ups "
                        "across it would not converge, and repairing them costs more than "
                        "the sequential path")
        return None

    #: From the host, its passes keep the innovations too (``compute``).
    innovations_in_pass: ClassVar[bool] = True

    def cost(self, n_trials: int, n_rows: int) -> PathCost:
        """Compile 3.0 s (the first pass; a repair compiles another); 0.7 us a row: fitted to
        ``benchmarks/one_shot.py``, as ``Sequential.cost``."""
        return PathCost(3.0, 0.7e-6 * n_trials * n_rows)

    def run(self, params: Params, series: SensorSeries, method: str, state: FilterState
            ) -> tuple[FilterState, Estimate]:
        final, est, ok = self.run_checked(params, series, method, state)
        return jax.lax.cond(ok, lambda: (final, est),
                            lambda: Sequential().run(params, series, method, state))

    def compute(self, params: Params, series: SensorSeries, method: str,
                state: FilterState, innovations: bool = False) -> PathRun:
        """From the host: the first pass, then repair passes while the check fails, each pass a
        program of its own (a recording whose check passes compiles no repair; a failed one
        compiles one and runs it up to ``repairs`` times), then, where they fail too, the
        sequential path (``PathRun.path`` says which ran). Under a caller's trace: ``run``.
        ``innovations``: each pass's scan also keeps the fused Hall innovations
        (``lane_scan_innovations``), so the estimate carries them from the pass that passed
        the check (or from the sequential path's); none under a caller's trace."""
        if is_traced(params, series, state):
            return super().compute(params, series, method, state)
        last = None
        for _ in range(self.repairs + 1):
            final, est, last = _one_pass(self, params, series, method, state, last,
                                         innovations)
            if bool(last.ok):
                return PathRun(final, est, self)
        return Sequential().compute(params, series, method, state, innovations)

    def run_checked(self, params: Params, series: SensorSeries, method: str,
                    state: FilterState) -> tuple[FilterState, Estimate, Bool[Array, ""]]:
        """The segmented filter and whether every segment's check passed (if not, the
        estimates are not the sequential path's: use ``run``, which falls back). The first
        pass and every repair pass (each in a ``lax.cond``) in one program, for a caller's
        ``jit``; from the host ``compute`` runs ``_run_pass`` instead, each pass a program of
        its own, so that a recording whose check passes compiles no
        repair (one recorded-like hour: 2.95 -> 1.75 s of compiling)."""
        last = self._run_pass(params, series, method, state)[2]
        B, T = jnp.shape(series.dt)
        for _ in range(self.repairs if self.segments_of(B, T, state.z.dtype) > 1 else 0):
            last = jax.lax.cond(last.ok, lambda p: p,
                                lambda p: self._run_pass(params, series, method, state, p)[2],
                                last)
        return self._result(params, series, method, state, last) + (last.ok,)

    def _run_pass(self, params: Params, series: SensorSeries, method: str, state: FilterState,
                 last: SegmentPass | None = None, innovations: bool = False
                 ) -> tuple[FilterState, Estimate, SegmentPass]:
        """One pass over the segments: the first (``last`` is ``None``: every segment warmed
        up from the entering state) or a repair (every segment's own rows again, entering
        where the one before it ended in ``last``: the first enters as before). A segment
        whose predecessor was right is now right; if every segment ends where it ended in
        ``last``, every one entered where the sequential filter was. Returns the pass's final
        state and estimates, and the ``SegmentPass`` a repair would start from, its check in
        ``ok``. ``innovations``: the estimates carry each row's fused Hall innovations from
        the same scan."""
        st = structure(params.robot, method)
        scan = lane_scan_innovations if innovations else lane_scan
        dtype = state.z.dtype
        series = prepare(params, series, method, dtype)
        B, T, S, W, L = self._layout(series, dtype)

        def padded(x, fill):  # (B, T, ...) -> (B, S * L, ...): no-op rows at the end
            return jnp.pad(x, [(0, 0), (0, S * L - T)] + [(0, 0)] * (x.ndim - 2),
                           constant_values=fill)

        fills = (0.0, jnp.nan, jnp.nan)
        rows = [padded(x, f) for x, f in zip((series.dt, series.gyro, series.hall_v), fills)]
        own = lane_inputs(params, st, *(x.reshape((B * S, L) + x.shape[2:]) for x in rows))
        first = np.arange(B * S) % S == 0  # the lanes that hold a trial's first segment
        if last is None:
            start = LaneState(*(jnp.repeat(x, S, axis=0)
                                for x in (state.z, state.P, state.gyro_hold)))
            inputs = own
            if W:
                # Segment s first runs the last W rows of segment s - 1 (W <= L): the same
                # inputs, one lane over, in the same scan; the first segment of a trial runs W
                # no-op rows, which leave its entering state exactly as it was.
                def warm(x, fill):
                    w = jnp.where(first, fill, jnp.roll(x[L - W:], 1, axis=-1))
                    return jnp.concatenate([w, x])

                inputs = jax.tree_util.tree_map(warm, own, NO_OP_INPUTS)
            run = scan(params, st, start, inputs, snapshot_row=W)
            rows_out = jax.tree_util.tree_map(lambda x: x[W:], run.rows)
            entered = run.snapshot
        else:
            entered = LaneState(*(jnp.where(_lanes_first(first, e), e, jnp.roll(x, 1, axis=0))
                                  for e, x in zip(last.entered, last.ended)))
            run = scan(params, st, entered, own)
            rows_out = run.rows
        this = SegmentPass(run.final, entered, rows_out,
                           segment_check(entered, run.final, B, S, self.atol(dtype)))
        return self._result(params, series, method, state, this) + (this,)

    def _layout(self, series: SensorSeries, dtype) -> tuple[int, int, int, int, int]:
        """``(B, T, S, W, L)``: trials, rows, segments per trial, warm-up rows, rows per
        segment."""
        B, T = jnp.shape(series.dt)
        S = self.segments_of(B, T, dtype)
        return B, T, S, self.warmup(dtype) if S > 1 else 0, -(-T // S)

    def _result(self, params: Params, series: SensorSeries, method: str, state: FilterState,
                this: SegmentPass) -> tuple[FilterState, Estimate]:
        """The final state and estimates of a pass, trials first."""
        st = structure(params.robot, method)
        B, T, S, _, L = self._layout(series, state.z.dtype)
        angles, std, bias = lane_estimates(st, this.rows.z, this.rows.P)

        def trials(x):  # (B * S, L, ...) -> (B, T, ...)
            return x.reshape((B, S * L) + x.shape[2:])[:, :T]

        innovations = rows_innovations(this.rows)  # (lanes, L, Nb, m) each, or None
        if innovations is not None:
            innovations = tuple(trials(x) for x in innovations)
        est = Estimate(trials(angles), trials(std), trials(bias),
                       trials(jnp.moveaxis(this.rows.skipped, 0, 1)), innovations=innovations)
        return FilterState(*(_split(x, B, S)[:, -1] for x in this.ended)), est


@eqx.filter_jit
def _one_pass(path: Segments, params, series, method, state, last, innovations=False):
    final, est, this = path._run_pass(params, series, method, state, last, innovations)
    return final, est, this._replace(rows=None)


class SegmentPass(NamedTuple):
    """One pass of ``Segments._run_pass`` over every lane (trials x segments): what a repair
    pass starts from and what the estimates are read from.

    Attributes:
        ended: every lane's state after its own rows (lanes first).
        entered: every lane's state entering its own rows.
        rows: per row what the estimates are read from (``lane_scan``'s; with the
            innovations, ``lane_scan_innovations``'), or ``None`` where a caller no longer
            needs them.
        ok: whether every segment entered where the one before it ended
            (``segment_check``).
    """

    ended: LaneState
    entered: LaneState
    rows: LaneRows | LaneRowsInnovations | None
    ok: Bool[Array, ""]


def _split(x, B: int, S: int):
    return x.reshape((B, S) + x.shape[1:])


def _lanes_first(first, x):
    """``first`` (one flag per lane) shaped to broadcast against ``x`` (lanes first)."""
    return first.reshape((-1,) + (1,) * (x.ndim - 1))


def _longest_joint_gap(hall_v) -> tuple[int, int]:
    """The longest run of rows in which some joint has neither of its two Hall readings
    (columns in pairs, as ``fused_pairs`` reads them), over every trial, and the row it
    starts at. On the host (NumPy): an hour of 8 columns takes about 5 ms, where a program of
    its own compiled 0.3 s per shape."""
    h = np.asarray(hall_v)
    missing = ~np.isfinite(h.reshape((-1,) + h.shape[-2:]))
    lost = np.zeros(missing.shape[:2], bool)
    for j in range(0, missing.shape[-1], 2):  # pair by pair (NumPy's reductions over a
        lost |= missing[..., j] & missing[..., j + 1]  # trailing axis of 2 took 30 ms here)
    if not lost.any():
        return 0, 0
    T = missing.shape[1]
    rows = np.arange(T)
    last_ok = np.maximum.accumulate(np.where(lost, -1, rows[None, :]), axis=1)
    run = np.where(lost, rows[None, :] - last_ok, 0)  # rows lost so far in this stretch
    flat = int(np.argmax(run))
    longest = int(run.reshape(-1)[flat])
    return longest, flat % T - longest + 1


def segment_check(entered: LaneState, ended: LaneState, B: int, S: int, atol: float
                  ) -> Bool[Array, ""]:
    """Whether every segment started where the one before it ended: ``entered`` and
    ``ended`` are the lanes' ``(z, P, hold)`` (``B S`` lanes, a trial's segments in order);
    the entering state of segment ``s >= 1`` against the final state of segment ``s - 1``:
    the mean to ``atol``, the covariance to ``atol sqrt(P_ii P_jj)``, the gyro hold
    exactly."""
    (z_in, P_in, hold_in), (z_out, P_out, hold_out) = (
        tuple(_split(x, B, S) for x in xs) for xs in (entered, ended))
    if S < 2:
        return jnp.asarray(True)
    zi, zo = z_in[:, 1:], z_out[:, :-1]
    Pi, Po = P_in[:, 1:], P_out[:, :-1]
    d = jnp.sqrt(jnp.abs(jnp.diagonal(Po, axis1=-2, axis2=-1)))
    scale = d[..., :, None] * d[..., None, :]
    mean_ok = jnp.all(jnp.abs(zi - zo) <= atol)
    cov_ok = jnp.all(jnp.abs(Pi - Po) <= atol * scale)
    hold_ok = jnp.all(hold_in[:, 1:] == hold_out[:, :-1])
    return mean_ok & cov_ok & hold_ok

