"""The steady path: the converged filter as one constant affine map.

On a regular recording (constant time step, every reading present) with the paper's constant
Hall noise (``hall_noise="angle"``) the covariance converges, to 1e-14 relative within about
4,000 rows at 100 Hz for the paper's parameters, and the filter becomes the constant map
``z_k = A z_{k-1} + Wg g_{k-1} + Wh h_k``. The path runs the covariance recursion over the
first ``head_rows`` rows once for every trial of the batch (``covariance_phase``; the trials
share it, since it depends only on the time steps and the noise), applies those rows' own maps
to every trial at once (``row_scan``), and serves every later row with the converged map, in
chunks of matrix products (``chunk_rows``).

``applies`` checks everything beforehand, on concrete inputs: the method and noise model, the
length, the one regularity check (``regular_step``) and the one convergence check
(``converges``: the covariance's relative change after the head, below ``tol``). ``run`` then
has no branch and no fallback.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._models._blocks import Structure
from .._models._classes import init_state, model_of, structure
from .._models._kernel import (
    BlockInputs,
    Estimate,
    FilterInput,
    FilterState,
    SensorSeries,
    block_estimate,
    block_update,
)
from .._models._params import Params
from .._readings._prepare import prepare
from ._affine import (
    StepMaps,
    covariance_phase,
    innovation_maps,
    input_weights,
    last_finite,
    output_map,
    read_innovations,
    reading_maps,
    series_inputs,
    step_maps,
)
from ._base import (
    AbstractPath,
    SmootherLayout,
    is_traced,
    kalman_only,
    regular_step,
    relative_change,
)
from ._chunks import ChunkInputs, ChunkPlan, chunk_operator, chunk_rows, raw_readings
from ._row_scan import RowMaps, row_scan


class SteadyForm(NamedTuple):
    """What the steady path computes once for a regular batch (``Steady._form``): the head
    rows' own maps and covariances (``form.head``, a leading row axis), the converged map
    after them (``form.map``) and the first converged row's block inputs (``form.first``:
    its time step and noise stand for every later row's) and trial 0's inputs of the head
    rows and that first converged row (``form.rows``, a leading row axis: ``n_head + 1``)."""

    head: StepMaps
    map: StepMaps
    first: BlockInputs
    rows: BlockInputs


class Steady(AbstractPath):
    """The converged filter's constant map after the first rows (see the module docstring).

    Attributes (defaults measured in docs/performance.md):
        min_rows: recordings of at most this many rows take another path.
        head_rows_float32, head_rows_float64: rows filtered with their own maps before the
            converged one takes over (at most ``min_rows``). The paper's parameters converge to
            1e-10 within about 2,600 rows at 100 Hz and 1e-14 within 4,000; in float32 the
            covariance reaches its rounding floor within about 1,000 rows, and switching at
            2,048 gives the same estimates as at 4,096 to 1e-7 rad.
        tol_float32, tol_float64: the covariance's relative change over one step after the
            head below which it counts as converged.
        chunk_rows: rows per chunk of the converged map (8 measured fastest of 4, 8 and 16
            for the bench and the 3D robot).
        carry_group, carry_scan: the chunks' entering states are solved for in groups of
            ``carry_group`` chunks, until at most ``carry_scan`` remain for a plain scan.
        mean_block: trial-rows per block of the pass over the readings (kept in cache).
    """

    name: ClassVar[str] = "steady"
    min_rows: int = eqx.field(static=True, default=4096)
    head_rows_float32: int = eqx.field(static=True, default=2048)
    head_rows_float64: int = eqx.field(static=True, default=4096)
    tol_float32: float = eqx.field(static=True, default=1e-5)
    tol_float64: float = eqx.field(static=True, default=1e-10)
    chunk_rows: int = eqx.field(static=True, default=8)
    carry_group: int = eqx.field(static=True, default=16)
    carry_scan: int = eqx.field(static=True, default=256)
    mean_block: int = eqx.field(static=True, default=1 << 16)

    def __check_init__(self):
        for name in ("head_rows_float32", "head_rows_float64"):
            if not 2 <= getattr(self, name) <= self.min_rows:
                raise ValueError(f"Steady.{name}: expected 2 .. min_rows ({self.min_rows}), "
                                 f"got {getattr(self, name)}")
        if self.chunk_rows < 1 or self.carry_group < 2 or self.carry_scan < 1:
            raise ValueError("Steady: chunk_rows and carry_scan must be >= 1, carry_group >= 2")

    def head_rows(self, dtype) -> int:
        return self.head_rows_float64 if np.dtype(dtype) == np.float64 else self.head_rows_float32

    def tol(self, dtype) -> float:
        return self.tol_float64 if np.dtype(dtype) == np.float64 else self.tol_float32

    def model_reason(self, params: Params, method: str) -> str | None:
        """Why the filter itself (whatever the data) never becomes a constant map, or None."""
        why = kalman_only(method)
        if why is not None:
            return why
        unobservable = model_of(method).unobservable
        if unobservable is not None:
            return f"{unobservable}: its covariance never converges"
        if params.hall_noise != "angle":
            return "the voltage noise model makes the Hall noise vary with the data"
        return None

    def applies(self, params: Params, series: SensorSeries, method: str,
                state: FilterState | None = None) -> str | None:
        why = self.model_reason(params, method)
        if why is not None:
            return why
        T = np.shape(series.dt)[-1] if np.ndim(series.dt) else 0
        if T <= self.min_rows:
            return f"{T} rows, not more than {self.min_rows}"
        step_s, why = regular_step(params, series)
        if why is not None:
            return why
        if step_s is None or is_traced(params, state):
            return None  # traced: the caller vouches for the data and the convergence
        P0 = (init_state(params, method) if state is None else state).P
        P0 = P0 if P0.ndim == 3 else P0[0]
        return self.converges(params, method, step_s, P0)

    def smoother_layout(self, params: Params, series: SensorSeries, method: str
                        ) -> SmootherLayout:
        """``"steady"``: the smoother's backward pass a constant map too (``SteadySmoother``
        with these constants, which says why where it does not apply; under a caller's trace
        the caller vouches, as for the filter)."""
        return SmootherLayout("steady", self)

    def recheck(self, params: Params, method: str, step_s: float | None) -> str | None:
        """The covariance must still converge with the new parameters (``converges``)."""
        if step_s is None or is_traced(params):
            return None
        return self.converges(params, method, step_s, init_state(params, method).P)

    def converges(self, params: Params, method: str, step_s: float,
                  P0: Float[Array, "Nb Nz Nz"]) -> str | None:
        """The one convergence check: ``None`` when the covariance of a regular recording with
        time step ``step_s``, started at ``P0``, has converged after the head (its relative
        change over the next step at most ``tol``), else why not."""
        dtype = P0.dtype
        n = self.head_rows(dtype)
        P_n, P_next = _head_covariance(params, method, P0, jnp.asarray(step_s, dtype), n)
        change = float(relative_change(P_n, P_next))
        tol = self.tol(dtype)
        if not change <= tol:
            return (f"the covariance has not converged after {n} rows (relative change "
                    f"{change:.1e}, tolerance {tol:.0e})")
        return None

    def run(self, params: Params, series: SensorSeries, method: str, state: FilterState
            ) -> tuple[FilterState, Estimate]:
        return self._run(params, series, method, state, innovations=False)

    innovations_in_pass: ClassVar[bool] = True

    def run_innovations(self, params: Params, series: SensorSeries, method: str,
                        state: FilterState) -> tuple[FilterState, Estimate]:
        """``run``, the estimate carrying every row's fused Hall innovations
        (``Estimate.innovations``: ``(nu, s, valid)``, ``B T Nb m``), read back from the new
        joint angles the pass computes (``_affine.innovation_maps``): the head rows' own
        maps, then the converged row's for every later row."""
        return self._run(params, series, method, state, innovations=True)

    def _run(self, params: Params, series: SensorSeries, method: str, state: FilterState,
             innovations: bool) -> tuple[FilterState, Estimate]:
        dtype = state.z.dtype
        n_head = self.head_rows(dtype)
        st = structure(params.robot, method)
        series = prepare(params, series, method, dtype)
        T = series.dt.shape[1]
        form = self._form(params, st, series, state)
        Ps, ok, P_ss = form.head.P, form.head.ok, form.map.P
        zeros = jnp.zeros(P_ss.shape[:2], dtype)
        std_head = jax.vmap(lambda Pk: block_estimate(st, zeros, Pk, False).angle_std)(Ps)
        std_tail = block_estimate(st, zeros, P_ss, False).angle_std
        angles, bias, z = self._mean(params, st, series, state.z, state.gyro_hold, form)
        std = jnp.concatenate([std_head, jnp.broadcast_to(std_tail, (T - n_head,)
                                                          + std_tail.shape)])
        # Regular data never skip a row (the convergence check ran these rows' covariance).
        skipped = jnp.broadcast_to(jnp.concatenate([~ok, jnp.zeros(T - n_head, bool)]),
                                   angles.shape[:2])
        est = Estimate(angles, jnp.broadcast_to(std, angles.shape), bias, skipped)
        if innovations:
            index = np.asarray(st.angle_index)[:, : st.m]  # the joints' new angles: z[:m]
            joints = jnp.where(index >= 0, angles[..., np.maximum(index, 0)], 0.0)
            est = dataclasses.replace(est, innovations=self._innovations(
                params, st, series, state, form, joints))
        held = jax.vmap(last_finite)(series.gyro, state.gyro_hold)
        return FilterState(z, jnp.broadcast_to(P_ss, state.P.shape), held), est

    def _form(self, params: Params, st: Structure, series: SensorSeries, state: FilterState
             ) -> SteadyForm:
        """The covariance phase over the head rows and the converged map after them, from
        trial 0's rows (a regular batch: its time steps, masks and noise stand for every
        trial's)."""
        n_head = self.head_rows(state.z.dtype)
        trial0 = jax.tree_util.tree_map(lambda x: x[0, : n_head + 1], series)
        rows, _ = series_inputs(params, st, trial0, state.gyro_hold[0])
        head = jax.tree_util.tree_map(lambda x: x[:n_head], rows)
        P_head, head_maps = covariance_phase(params, st, state.P[0], head)
        last = jax.tree_util.tree_map(lambda x: x[n_head], rows)
        return SteadyForm(head_maps, step_maps(params, st, P_head, last), last, rows)

    def _innovations(self, params: Params, st: Structure, series: SensorSeries,
                     state: FilterState, form: SteadyForm, joints: Float[Array, "B T Nb m"]
                     ) -> tuple[Float[Array, "B T Nb m"], Float[Array, "B T Nb m"],
                                Bool[Array, "B T Nb m"]]:
        """``(nu, s, valid)`` of every row from its new joint angles (``joints``: each block's
        ``z[:m]``, 0 at a padding joint): each head row by its entering covariance, every
        converged row by the head's last (``innovation_maps``). The steady smoother's forward
        pass reads them the same way."""
        n_head = form.head.A.shape[0]
        T = series.dt.shape[1]
        P_in = jnp.concatenate([state.P[:1], form.head.P])  # entering rows 0 .. n_head
        maps = jax.tree_util.tree_map(
            lambda x: jnp.concatenate([x[:n_head], jnp.broadcast_to(
                x[n_head], (T - n_head,) + x.shape[1:])]), innovation_maps(st, P_in, form.rows))
        ok = jnp.concatenate([form.head.ok, jnp.ones(T - n_head, bool)])
        return read_innovations(params, st, maps, series.hall_v, joints, ok)

    def _mean(self, params: Params, st: Structure, series: SensorSeries,
             z0: Float[Array, "B Nb Nz"], hold0: Float[Array, "B G"], form: SteadyForm
             ) -> tuple[Float[Array, "B T K"], Float[Array, "B T K"], Float[Array, "B Nb Nz"]]:
        """The angles and biases of every row of a batch of trials, and the last row's block
        state (``_affine_rows`` with the angles' and biases' output map)."""
        out_map = output_map(st)
        K = len(st.block_of)
        outs, z = self._affine_rows(params, st, series, z0, hold0, form, out_map, K)
        return outs[0], outs[1], z

    def _block_states(self, params: Params, st: Structure, series: SensorSeries,
                     z0: Float[Array, "B Nb Nz"], hold0: Float[Array, "B G"], form: SteadyForm
                     ) -> Float[Array, "B T Nb Nz"]:
        """Every row's block state (the smoother's filtered means): ``_affine_rows`` with every
        block coordinate an output (two halves, padded to even)."""
        n_trials, nb, nz = z0.shape
        q = nb * nz
        K = -(-q // 2)
        out_map = np.eye(2 * K, q).reshape(2 * K, nb, nz)
        outs, _ = self._affine_rows(params, st, series, z0, hold0, form, out_map, K)
        zs = jnp.concatenate(outs, axis=-1)[..., :q]
        return zs.reshape(n_trials, series.dt.shape[1], nb, nz)

    def _affine_rows(self, params: Params, st: Structure, series: SensorSeries,
                     z0: Float[Array, "B Nb Nz"], hold0: Float[Array, "B G"], form: SteadyForm,
                     out_map: np.ndarray, K: int
                     ) -> tuple[tuple[Float[Array, "B T K"], Float[Array, "B T K"]],
                                Float[Array, "B Nb Nz"]]:
        """The mean over a batch of trials, read through ``out_map`` (``2K`` outputs, two
        halves of ``K``): the head rows' own maps (``form.head``), then the converged map
        (``form.map``).

        Row ``k``: ``z_k = A z_{k-1} + g_{k-1}[used] Wg + hall_angle(V_k) Wh`` (``Wg, Wh`` from
        ``input_weights``). The head is a scan of its rows, every trial at once (trials
        innermost: chunk operators would need building per row, which costs more than these
        rows). The converged rows go as whole chunks (``chunk_rows``), then the last 1 to
        ``chunk_rows`` rows one by one, which gives the final state. Returns the two halves of
        the outputs and the last row's block state."""
        dtype = z0.dtype
        robot = params.robot
        Jr, Jh = reading_maps(params, st, dtype)
        used = tuple(int(u) for u in robot.used_gyro_index)
        n_trials, nb, nz = z0.shape
        q = nb * nz
        T = series.dt.shape[1]
        L = self.chunk_rows
        Gu = len(used)
        out_map_j = jnp.asarray(out_map, dtype)
        coeffs = params.hall_coeffs

        def readings(first, n):  # rows first .. first + n: (B, n, I), used gyro columns first
            return raw_readings(coeffs, series.gyro, series.hall_v, used, first, n)

        def write(outs, y, first):  # y (B, n, 2K): angles then biases
            return tuple(jax.lax.dynamic_update_slice_in_dim(o, y[..., k * K:(k + 1) * K],
                                                             first, axis=1)
                         for k, o in enumerate(outs))

        def entering(A_k, Wg_k, z, g):  # the prediction entering a row: (B, Nq)
            return (jnp.einsum("pab,Bpb->Bpa", A_k, z)
                    + jnp.einsum("Bg,gpa->Bpa", g, Wg_k)).reshape(n_trials, q)

        A = form.map.A
        Wg, Wh = input_weights(form.map.Gr, form.map.Gh, Jr, Jh)
        out = jnp.zeros((n_trials, T, K), dtype)
        outs = (out, out)
        As = form.head.A
        Wgs, Whs = input_weights(form.head.Gr, form.head.Gh, Jr, Jh)
        n_head = As.shape[0]
        x = jnp.moveaxis(readings(0, n_head), 0, -1)  # (n_head, I, B)
        g = jnp.concatenate([hold0[:, list(used)].T[None], x[:-1, :Gu]])  # previous rates
        U = (jnp.einsum("kfB,kfpa->kpaB", g, Wgs)
             + jnp.einsum("kfB,kfpa->kpaB", x[:, Gu:], Whs))  # (n_head, Nb, Nz, B)
        Z = row_scan(RowMaps(As, U, jnp.moveaxis(z0, 0, -1)))
        outs = write(outs, jnp.einsum("kpaB,opa->Bko", Z, out_map_j), 0)
        z, g_prev = jnp.moveaxis(Z[-1], -1, 0), x[-1, :Gu].T
        s = entering(A, Wg, z, g_prev)
        # The converged rows: whole chunks, then the last 1 .. L rows one by one.
        first = n_head
        n_chunks = (T - first - 1) // L
        GS, E, Phi = chunk_operator(A, Wg, Wh, out_map, L)
        if n_chunks:
            plan = ChunkPlan(start=first, n_chunks=n_chunks, chunk_rows=L,
                             block_rows=self._block_rows(n_trials), used=used, n_angles=K,
                             carry_group=self.carry_group, carry_scan=self.carry_scan)
            outs, s = chunk_rows(plan, ChunkInputs(GS, E, Phi, s, coeffs, series.gyro,
                                                    series.hall_v, outs))
            first = first + n_chunks * L
        x = readings(first, T - first)
        z = s.reshape(n_trials, nb, nz) + jnp.einsum("Bm,mpa->Bpa", x[:, 0, Gu:], Wh)
        zs = [z]
        for k in range(1, T - first):
            z = entering(A, Wg, z, x[:, k - 1, :Gu]).reshape(n_trials, nb, nz) + jnp.einsum(
                "Bm,mpa->Bpa", x[:, k, Gu:], Wh)
            zs.append(z)
        outs = write(outs, jnp.einsum("kBpa,opa->Bko", jnp.stack(zs), out_map_j), first)
        return outs, z

    def _block_rows(self, n_trials: int) -> int:
        """Rows per block of the converged rows' pass, for ``n_trials`` trials: a power of two,
        at least 256 (``mean_block`` trial-rows)."""
        return max(256, 1 << int(np.log2(max(self.mean_block // n_trials, 1))))


@eqx.filter_jit
def _head_covariance(params: Params, method: str, P0: Float[Array, "Nb Nz Nz"],
                     step_s: Float[Array, ""], n: int
                     ) -> tuple[Float[Array, "Nb Nz Nz"], Float[Array, "Nb Nz Nz"]]:
    """The covariance of a regular recording with time step ``step_s`` after ``n`` rows and
    after ``n + 1`` (the first row has ``dt = 0``, as every recording's), started at ``P0``:
    the same block updates as every path's (``block_update``), with every reading present."""
    st = structure(params.robot, method)
    dtype = P0.dtype
    robot = params.robot
    series = FilterInput(jnp.full(n + 1, step_s, dtype).at[0].set(0.0),
                         jnp.zeros((n + 1, 3 * robot.n_links), dtype),
                         jnp.zeros((n + 1, robot.n_hall), dtype))
    rows, _ = series_inputs(params, st, series, jnp.zeros(3 * robot.n_links, dtype))
    zero = jnp.zeros(st.n_z, dtype)

    def body(P, row):
        P = jax.vmap(lambda *a: block_update(st, zero, *a, row.dt)[1])(
            P, row.rates, *row.noise, row.hb, row.rb, row.vb)
        return P, None

    P_n, _ = jax.lax.scan(body, P0, jax.tree_util.tree_map(lambda x: x[:n], rows))
    P_next, _ = body(P_n, jax.tree_util.tree_map(lambda x: x[n], rows))
    return P_n, P_next
