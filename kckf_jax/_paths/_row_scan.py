"""A scan of per-row affine maps over a batch of trials, with its reverse mode by hand.

``z_k = A_k z_{k-1} + U_k``: the steady path's first rows (its head), where every row has its
own map but every trial the same one, so the trials ride along as the last axis.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._affine import apply_blocks


class RowMaps(NamedTuple):
    """The affine maps of ``row_scan``: ``z_k = A_k z_{k-1} + U_k``, ``z_{-1} = z0``."""

    As: Float[Array, "R Nb Nz Nz"]
    U: Float[Array, "R Nb Nz B"]
    z0: Float[Array, "Nb Nz B"]


def row_scan(maps: RowMaps) -> Float[Array, "R Nb Nz B"]:
    """``z_k = A_k z_{k-1} + U_k`` over the rows; returns every ``z_k``.

    Reverse mode by hand (``eqx.filter_custom_vjp``): the cotangents ``g_k = dZ_k + A_{k+1}^T
    g_{k+1}`` are one reverse scan of the same shape as the forward one, and ``dA_k = g_k
    z_{k-1}^T`` one product over all rows after it. Measured on the 3D robot's head (64 trials
    x 2,048 rows, float32): 77 ms for the gradient against 106 ms with JAX's own transpose of
    the scan."""
    return _row_scan(maps)


def _forward(maps: RowMaps):
    def row(z, r):
        A_k, u = r
        z = apply_blocks(A_k, z) + u
        return z, z

    return jax.lax.scan(row, maps.z0, (maps.As, maps.U))[1]


@eqx.filter_custom_vjp
def _row_scan(maps: RowMaps):
    return _forward(maps)


@_row_scan.def_fwd
def _row_scan_fwd(perturbed, maps: RowMaps):
    Z = _forward(maps)
    return Z, Z


@_row_scan.def_bwd
def _row_scan_bwd(Z, dZ, perturbed, maps: RowMaps):
    As, z0 = maps.As, maps.z0
    if dZ is None:
        dZ = jnp.zeros_like(Z)

    # g_k = dZ_k + A_{k+1}^T g_{k+1}: scan the rows backwards, carrying A_k^T g_k.
    def row(carry, r):
        At_k, dz = r
        g = dz + carry
        return apply_blocks(At_k, g), g

    dz0, G = jax.lax.scan(row, jnp.zeros_like(z0), (jnp.swapaxes(As, 2, 3), dZ), reverse=True)
    dA = None
    if perturbed.As:
        Zprev = jnp.concatenate([z0[None], Z[:-1]])
        dA = jnp.einsum("kpaB,kpbB->kpab", G, Zprev)
    return RowMaps(dA, G if perturbed.U else None, dz0 if perturbed.z0 else None)
