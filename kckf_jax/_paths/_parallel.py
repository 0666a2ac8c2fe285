"""The parallel path: the covariance recursion over every row, then the mean as an associative
scan of the rows' affine maps (parallel in time: for accelerators, where the mean's sequential
dependency is what limits).

It computes anything the filter accepts (missing readings, uneven time steps, the voltage noise
model). On a CPU it is slower than the sequential path: the covariance phase costs as much, and
the associative scan's small batched products are slow there.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._models._classes import structure
from .._models._kernel import Estimate, FilterInput, FilterState, SensorSeries, block_estimate
from .._models._params import Params
from .._readings._prepare import prepare
from ._affine import covariance_phase, innovation_maps, read_innovations, series_inputs
from ._base import AbstractPath, kalman_only


class Parallel(AbstractPath):
    """Covariance phase, then the mean by ``jax.lax.associative_scan``:
    ``(A2, c2) o (A1, c1) = (A2 A1, A2 c1 + c2)``, no inverse."""

    name: ClassVar[str] = "parallel"

    def applies(self, params: Params, series: SensorSeries, method: str,
                state: FilterState | None = None) -> str | None:
        return kalman_only(method)

    def run(self, params: Params, series: SensorSeries, method: str, state: FilterState
            ) -> tuple[FilterState, Estimate]:
        return jax.vmap(lambda s, x: _one_trial(params, s, method, x))(series, state)

    innovations_in_pass: ClassVar[bool] = True

    def run_innovations(self, params: Params, series: SensorSeries, method: str,
                        state: FilterState) -> tuple[FilterState, Estimate]:
        """``run``, the estimate carrying every row's fused Hall innovations
        (``Estimate.innovations``: ``(nu, s, valid)``, ``B T Nb m``), read back from each
        row's new state by its entering covariance (``_affine.innovation_maps``)."""
        return jax.vmap(lambda s, x: _one_trial(params, s, method, x, True))(series, state)


def _one_trial(params: Params, series: SensorSeries, method: str, state: FilterState,
               innovations: bool = False) -> tuple[FilterState, Estimate]:
    st = structure(params.robot, method)
    dtype = state.z.dtype
    series = prepare(params, series, method, dtype)
    rows, _ = series_inputs(params, st, series, state.gyro_hold)
    P_last, maps = covariance_phase(params, st, state.P, rows)
    Ps, As, ok = maps.P, maps.A, maps.ok
    # A skipped row keeps the whole state, its gyro hold included: the rates of the rows after
    # it come from the holds without its readings (the covariance does not depend on them).
    kept = FilterInput(series.dt, jnp.where(ok[:, None], series.gyro, jnp.nan), series.hall_v)
    kept_rows, held = series_inputs(params, st, kept, state.gyro_hold)
    # c_k = Gr_k r_k + Gh_k h_k, with the entering state folded into the first row.
    c = (jnp.einsum("kpaj,kpj->kpa", maps.Gr, kept_rows.rates)
         + jnp.einsum("kpaj,kpj->kpa", maps.Gh, kept_rows.hb))
    c = c.at[0].add(jnp.einsum("pab,pb->pa", As[0], state.z))
    z = _compose(As, c)
    est = dataclasses.replace(jax.vmap(lambda zk, Pk: block_estimate(st, zk, Pk, False))(z, Ps),
                              skipped=~ok)
    if innovations:
        P_in = jnp.concatenate([state.P[None], Ps[:-1]])
        est = dataclasses.replace(est, innovations=read_innovations(
            params, st, innovation_maps(st, P_in, rows), series.hall_v, z[..., : st.m], ok))
    return FilterState(z[-1], P_last, held[-1]), est


def _compose(As: Float[Array, "T Nb Nz Nz"], c: Float[Array, "T Nb Nz"]
             ) -> Float[Array, "T Nb Nz"]:
    """Every ``z_k`` of ``z_k = A_k z_{k-1} + c_k`` (``z_{-1} = 0``) by associative scan."""
    def combine(a, b):
        A1, c1 = a
        A2, c2 = b
        return (jnp.einsum("...ij,...jk->...ik", A2, A1),
                jnp.einsum("...ij,...j->...i", A2, c1) + c2)

    return jax.lax.associative_scan(combine, (As, c))[1]
