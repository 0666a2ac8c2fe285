"""The steady smoother: the RTS backward pass of the steady filter as a constant map too.

Where ``Steady`` applies (a regular recording, the constant Hall noise, the covariance
converged after the head), every row after the head has the same filtered covariance
``P_ss`` and the same predicted one ``S_ss``, so the smoother gain ``G = P_ss F' S_ss^-1`` is
one constant (``_rts.rts_gain``) and the backward mean is the constant affine recursion

    z_k|T = G_z z_k+1|T + (z_k|k - G y_k+1|k)

(``G_z`` the gain's columns on ``z``: the constraint's smoothed value is 0). The smoothed
covariance does not depend on the data: from ``P_ss`` at the last row it converges backward to
a fixed point, which ``applies`` checks within ``tail_rows`` rows of the end, as ``Steady``
checks the forward one. So: the filtered means of every row from ``Steady``'s own chunked map
(``Steady._block_states``), the backward mean over the converged rows in chunks of matrix
products (``reverse_affine``), the covariance recursion over the last ``tail_rows`` rows only,
and the head rows, whose covariances still change, with the general backward step
(``_rts.rts_rows``). The same estimates as the sequential smoother, to rounding (tested).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._models._blocks import predicted_moments
from .._models._classes import init_state, structure
from .._models._kernel import Estimate, FilterInput, FilterState, SensorSeries, block_estimate
from .._models._params import Params
from .._readings._prepare import prepare
from ._affine import output_map, reading_maps, series_inputs, step_maps
from ._base import is_traced, regular_step, relative_change
from ._rts import rts_covariance, rts_gain, rts_rows
from ._steady import Steady, _head_covariance

#: Rows per chunk of the backward mean (16 measured faster than 8 and 32 on the bench hour).
CHUNK_ROWS = 16


def reverse_affine(M: Float[Array, "Nb Nz Nz"], w: Float[Array, "B N Nb Nz"],
                   x_end: Float[Array, "B Nb Nz"], L: int = CHUNK_ROWS
                   ) -> Float[Array, "B N Nb Nz"]:
    """Every ``x_k`` of ``x_k = M x_k+1 + w_k`` (``k = N - 1 .. 0``, ``x_N = x_end``), per block,
    for a constant ``M``: in chunks of ``L`` rows, each one matrix product of its inputs with
    the powers of ``M``, and a scan over the chunks for the states entering them."""
    n_trials, N, nb, nz = w.shape
    dtype = w.dtype
    v = w[:, ::-1]  # forward order: x'_j = M x'_j-1 + v_j, x'_-1 = x_end
    C = -(-N // L)
    v = jnp.pad(v, ((0, 0), (0, C * L - N), (0, 0), (0, 0)))
    pw = [jnp.broadcast_to(jnp.eye(nz, dtype=dtype), (nb, nz, nz))]
    for _ in range(L):
        pw.append(jnp.einsum("pab,pbc->pac", M, pw[-1]))
    pw = jnp.stack(pw)  # (L + 1, Nb, Nz, Nz): M^0 .. M^L
    j, i = np.arange(L)[:, None], np.arange(L)[None, :]
    Phi = jnp.where((j >= i)[:, :, None, None, None], pw[np.clip(j - i, 0, L)], 0.0)
    # Per block one product: (B C, L Nz) @ (L Nz, L Nz).
    V = v.reshape(n_trials * C, L, nb, nz)
    Op = jnp.transpose(Phi, (2, 1, 4, 0, 3)).reshape(nb, L * nz, L * nz)  # (p, i b, j a)
    Y = jnp.einsum("xpk,pkl->xpl", jnp.transpose(V, (0, 2, 1, 3)).reshape(-1, nb, L * nz), Op)
    Y = Y.reshape(n_trials, C, nb, L, nz).transpose(1, 0, 3, 2, 4)  # (C, B, L, Nb, Nz)

    def chunk(s, y):  # s: the state before the chunk (B, Nb, Nz)
        return jnp.einsum("pab,Bpb->Bpa", pw[L], s) + y[:, -1], s

    _, S = jax.lax.scan(chunk, x_end, Y)  # (C, B, Nb, Nz): entering states
    X = Y + jnp.einsum("jpab,cBpb->cBjpa", pw[1:], S)
    X = jnp.moveaxis(X, 1, 0).reshape(n_trials, C * L, nb, nz)[:, :N]
    return X[:, ::-1]


class SteadySmoother(eqx.Module):
    """The smoother where ``steady`` applies and the smoothed covariance converges within
    ``tail_rows(dtype)`` rows of the end (see the module docstring; in float64 the smoothed
    covariance of the paper's parameters changes by 5e-9 relative 2,048 rows before the end,
    so float64 takes 4,096 as the forward head does)."""

    steady: Steady = Steady()
    tail_rows_float32: int = eqx.field(static=True, default=2048)
    tail_rows_float64: int = eqx.field(static=True, default=4096)

    def tail_rows(self, dtype) -> int:
        return self.tail_rows_float64 if np.dtype(dtype) == np.float64 else self.tail_rows_float32

    def applies(self, params: Params, series: SensorSeries, method: str,
                state: FilterState | None = None) -> str | None:
        """``None`` when this smoother computes ``series``, else why not (concrete inputs)."""
        why = self.steady.applies(params, series, method, state)
        if why is not None:
            return why
        if is_traced(params, series, state):
            return "the inputs are traced (inside jit or grad): not checked"
        step_s, _ = regular_step(params, series)
        P0 = (init_state(params, method) if state is None else state).P
        P0 = P0 if P0.ndim == 3 else P0[0]
        dtype = P0.dtype
        T = np.shape(series.dt)[-1]
        n = self.tail_rows(dtype)
        if T - 1 - self.steady.head_rows(dtype) <= n:
            return None  # the backward covariance is recursed over every converged row
        change = float(_tail_change(params, method, P0, jnp.asarray(step_s, dtype),
                                    self.steady.head_rows(dtype), n))
        tol = self.steady.tol(dtype)
        if not change <= tol:
            return (f"the smoothed covariance has not converged {n} rows before the end "
                    f"(relative change {change:.1e}, tolerance {tol:.0e})")
        return None

    def run(self, params: Params, series: SensorSeries, method: str, state: FilterState,
            innovations: bool = False) -> Estimate:
        """The smoothed angles, their standard deviations and biases of a regular batch, and
        the skipped rows (``state`` with a leading trial axis). ``innovations``: the estimate
        also carries the forward pass's fused Hall innovations (``Steady.run_innovations``'
        form)."""
        steady = self.steady
        dtype = state.z.dtype
        n_head = steady.head_rows(dtype)
        st = structure(params.robot, method)
        series = prepare(params, series, method, dtype)
        n_trials, T = series.dt.shape
        nz = st.n_z
        # The forward pass: Steady.run's covariances and maps, every row's block state.
        form = steady._form(params, st, series, state)
        Ps, ok, P_ss = form.head.P, form.head.ok, form.map.P
        Z = steady._block_states(params, st, series, state.z, state.gyro_hold,
                                 form)  # (B, T, Nb, Nz)
        ts, noise = form.first.dt, form.first.noise  # every row after the first: the same
        # The predicted mean of the row after each row: F z_k + ts G1 r_k+1 (r from row k's
        # gyro: every reading present), per trial.
        Jr, _ = reading_maps(params, st, dtype)
        used = np.asarray(params.robot.used_gyro_index)
        rates = jnp.einsum("pig,Btg->Btpi", Jr, series.gyro[:, :-1, used])  # (B, T-1, Nb, m1)
        F = jnp.asarray(st.F0, dtype) + ts * jnp.asarray(st.F1, dtype)
        G1 = jnp.asarray(st.G1, dtype)
        y_next = (jnp.einsum("ya,Btpa->Btpy", F, Z[:, :-1])
                  + ts * jnp.einsum("yi,Btpi->Btpy", G1, rates))  # (B, T-1, Nb, Ny)

        gain = _converged_gain(st, P_ss, noise, ts)
        G_ss = gain[0]
        # The converged rows k = n_head .. T-2, backward from the last row's filtered state.
        w = Z[:, n_head:-1] - jnp.einsum("pay,Btpy->Btpa", G_ss, y_next[:, n_head:])
        Zs_mid = reverse_affine(G_ss[:, :, :nz], w, Z[:, -1])
        # Their covariance: the recursion over the last rows, then its fixed point.
        n_mid = T - 1 - n_head
        n_tail = min(self.tail_rows(dtype), n_mid)
        P_inf, P_tail = _covariance_tail(st, P_ss, gain, n_tail)  # last row first
        # The head rows: their own gains, entered from the first converged row's smoothing.
        S_head = jax.vmap(lambda P: _predicted_cov(st, P, noise, ts))(Ps)
        # (The carry P_inf is the first converged row's: the fixed point, or the tail's last.)
        z_first = Zs_mid[:, 0] if n_mid else Z[:, -1]
        skip_next = jnp.concatenate([~ok[1:], jnp.zeros(1, bool)])
        Zs_head, Ps_head = jax.vmap(lambda zs, yn, zf: rts_rows(
            st, zs, Ps, yn, S_head, jnp.full(n_head, ts), skip_next, (zf, P_inf)))(
            Z[:, :n_head], y_next[:, :n_head], z_first)
        Zs = jnp.concatenate([Zs_head, Zs_mid, Z[:, -1:]], axis=1)
        # Outputs: angles and biases from every smoothed state; the standard deviations from
        # the head's covariances, the fixed point, the tail's and the last row's.
        out = jnp.asarray(output_map(st), dtype)
        K = len(st.block_of)
        y = jnp.einsum("Btpa,opa->Bto", Zs, out)
        zeros = jnp.zeros(P_ss.shape[:2], dtype)

        def std_of(P):
            return block_estimate(st, zeros, P, False).angle_std

        std_head = jax.vmap(lambda Ps_b: jax.vmap(std_of)(Ps_b))(Ps_head)  # (B, n_head, K)
        std_tail = jax.vmap(std_of)(P_tail[::-1])
        std_mid = jnp.broadcast_to(std_of(P_inf), (n_mid - n_tail, K))
        std = jnp.concatenate([std_mid, std_tail, std_of(P_ss)[None]])
        std = jnp.concatenate([std_head, jnp.broadcast_to(std, (n_trials,) + std.shape)],
                              axis=1)
        skipped = jnp.broadcast_to(jnp.concatenate([~ok, jnp.zeros(T - n_head, bool)]),
                                   (n_trials, T))
        innov = (steady._innovations(params, st, series, state, form, Z[..., : st.m])
                 if innovations else None)
        return Estimate(y[..., :K], std, y[..., K:], skipped, innovations=innov)


def _predicted_cov(st, P: Float[Array, "Nb Nz Nz"], noise, ts) -> Float[Array, "Nb Ny Ny"]:
    """Each block's predicted covariance of the next row's ``y`` from this row's ``P``, with
    that row's process noise ``(alpha, beta, gamma)`` and time step ``ts``."""
    dtype = P.dtype
    zero = jnp.zeros(st.m + 1, dtype)
    return jax.vmap(lambda Pb, a, b, c: predicted_moments(
        st, jnp.zeros(st.n_z, dtype), Pb, zero, (a, b, c), ts)[1])(P, *noise)


def _converged_gain(st, P_ss: Float[Array, "Nb Nz Nz"], noise, ts):
    """The constant smoother gain of the converged rows (``_rts.rts_gain`` per block): ``(G,
    use, S)``, from the converged covariance ``P_ss`` and the rows' noise and time step."""
    S_ss = _predicted_cov(st, P_ss, noise, ts)
    return jax.vmap(lambda P, S: rts_gain(st, P, S, ts))(P_ss, S_ss)


def _covariance_tail(st, P_ss: Float[Array, "Nb Nz Nz"], gain, n: int):
    """The smoothed covariance backward from the last row (``P_ss``) over ``n`` converged rows
    with the constant ``gain``: ``(the last one reached, every one, last row first)``."""
    G, use, Sm = gain

    def cov_row(P_s, _):
        P = jax.vmap(lambda *a: rts_covariance(st, *a))(P_ss, G, use, Sm, P_s)
        return P, P

    return jax.lax.scan(cov_row, P_ss, None, length=n)


@eqx.filter_jit
def _tail_change(params: Params, method: str, P0: Float[Array, "Nb Nz Nz"],
                 step_s: Float[Array, ""], n_head: int, n: int) -> Float[Array, ""]:
    """The smoothed covariance's relative change over one row, ``n`` rows before the end of a
    regular recording whose filter converged after ``n_head`` rows (every reading present)."""
    st = structure(params.robot, method)
    dtype = P0.dtype
    P_head, _ = _head_covariance(params, method, P0, step_s, n_head)
    series = FilterInput(jnp.full(2, step_s, dtype), jnp.zeros((2, 3 * params.robot.n_links),
                                                               dtype),
                         jnp.zeros((2, params.robot.n_hall), dtype))
    rows, _ = series_inputs(params, st, series, jnp.zeros(3 * params.robot.n_links, dtype))
    last = jax.tree_util.tree_map(lambda x: x[1], rows)
    P_ss = step_maps(params, st, P_head, last).P
    gain = _converged_gain(st, P_ss, last.noise, step_s)
    _, P_rows = _covariance_tail(st, P_ss, gain, n + 1)
    return relative_change(P_rows[n - 1], P_rows[n])
