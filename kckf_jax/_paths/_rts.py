"""The Rauch-Tung-Striebel backward step of one axis block, in the filter's block coordinates
(``_smooth.py`` says what the smoother is; this module is its arithmetic, shared by the
sequential smoother and the steady one):

    G_k = P_k|k F' S^-1,   z_k|T = z_k|k + G_k (y_k+1|T - y_k+1|k),
    P_k|T = P_k|k + G_k (P^y_k+1|T - S) G_k'

with ``y = [z, e]`` the next row's predicted state, ``F = F0 + dt F1`` its map from ``z`` and
``S`` its covariance. Rows of ``y`` the next row's update did not condition on (a coordinate
with no variance, the constraint at a row with no time step) are left out of the solve; ``S``
is factored by the written-out Cholesky of ``_kalman.cholesky_solve`` (no LAPACK call).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._models._kalman import cholesky_solve, symmetrise


def rts_gain(st, P_f: Float[Array, "Nz Nz"], S: Float[Array, "Ny Ny"], dt: Float[Array, ""],
             F: Float[Array, "Ny Nz"] | None = None
             ) -> tuple[Float[Array, "Nz Ny"], Bool[Array, " Ny"], Float[Array, "Ny Ny"]]:
    """The smoother gain ``G = P F' S^-1`` of one block (its unused columns zero), which rows of
    ``y`` are used, and ``S`` with the unused rows and columns replaced by the identity.
    ``F``: the step's map (default the structure's, ``F0 + dt F1``)."""
    nz = st.n_z
    dtype = P_f.dtype
    if F is None:
        F = jnp.asarray(st.F0, dtype) + dt * jnp.asarray(st.F1, dtype)  # (Ny, Nz)
    # Rows of y the next row's update conditioned on: every z coordinate with variance, and
    # the constraint where there was a time step.
    use = jnp.concatenate([jnp.diag(S)[:nz] > 0, jnp.full(st.n_e, dt > 0)])
    S = jnp.where(use[:, None] & use[None, :], S, 0.0) + jnp.diag(jnp.where(use, 0.0, 1.0))
    C = jnp.where(use[None, :], P_f @ F.T, 0.0)  # (Nz, Ny)
    return cholesky_solve(S, C.T).T, use, S


def rts_covariance(st, P_f, G, use, S, P_s):
    """``P_f + G (P^y_s - S) G'`` on the used rows: the smoothed covariance of one block."""
    nz, ny = st.n_z, st.n_z + st.n_e
    Py_s = jnp.zeros((ny, ny), P_f.dtype).at[:nz, :nz].set(P_s)
    D = jnp.where(use[:, None] & use[None, :], Py_s - S, 0.0)
    return symmetrise(P_f + G @ D @ G.T)


def rts_block(st, z_f, P_f, y_pred, S, dt, skipped, z_s, P_s, F=None):
    """One block of one backward step: the smoothed ``(z, P)`` of row ``k`` from the filtered
    one (``z_f, P_f``), the next row's predicted moments (``y_pred, S``, ``dt``, ``skipped``,
    and its map ``F`` where the step brings one) and its smoothed one (``z_s, P_s``). A skipped
    next row kept the state, so this row's smoothed state is the next one's."""
    G, use, Sm = rts_gain(st, P_f, S, dt, F)
    y_s = jnp.concatenate([z_s, jnp.zeros(st.n_e, z_f.dtype)])
    z = z_f + G @ jnp.where(use, y_s - y_pred, 0.0)
    P = rts_covariance(st, P_f, G, use, Sm, P_s)
    return jnp.where(skipped, z_s, z), jnp.where(skipped, P_s, P)


def rts_rows(st, zs: Float[Array, "R Nb Nz"], Ps: Float[Array, "R Nb Nz Nz"],
             y_next: Float[Array, "R Nb Ny"], S_next: Float[Array, "R Nb Ny Ny"],
             dt_next: Float[Array, " R"], skip_next: Bool[Array, " R"],
             end: tuple[Float[Array, "Nb Nz"], Float[Array, "Nb Nz Nz"]],
             F_next: Float[Array, "R Nb Ny Nz"] | None = None):
    """The backward pass over rows ``R``: each row's filtered moments ``zs, Ps`` and the
    predicted moments of the row after it (``y_next, S_next, dt_next, skip_next``, aligned with
    it, and its maps ``F_next`` where the steps bring them); ``end`` the smoothed ``(z, P)`` of
    the row after the last. Returns the smoothed block states and covariances of every row."""
    def body(carry, row):
        z_s, P_s = carry
        z_f, P_f, y, S, dt, skip, F = row
        z, P = jax.vmap(lambda *a: rts_block(st, *a))(
            z_f, P_f, y, S, jnp.broadcast_to(dt, z_f.shape[:1]),
            jnp.broadcast_to(skip, z_f.shape[:1]), z_s, P_s, F)
        return (z, P), (z, P)

    rows = (zs, Ps, y_next, S_next, dt_next, skip_next, F_next)
    return jax.lax.scan(jax.checkpoint(body), end, rows, reverse=True)[1]
