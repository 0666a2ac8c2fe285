"""Kalman helpers shared by every filter of the package (the KCKF, the arm + IMU filter and the
Markovian filter): one scalar measurement update in Joseph form, in three spellings, and the
symmetrisation that follows a step.

Every filter of the package processes its measurements one scalar row at a time (``R`` is
diagonal, so this equals the joint update) and needs no matrix inverse or LAPACK call.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

#: ``cholesky_solve``'s diagonal loading below double precision, in units of ``n eps`` of each
#: diagonal entry: the rounding an ``n x n`` matrix's entries carry, with a margin. Measured on
#: the docstring's fitted ``kckf3d``: 1 still diverges, 4 and 8 hold (0.0003 rad from float64);
#: 8 moves the paper's ``x,y,x,y`` steady smoother by 1.1e-4 rad against float64, 4 by less
#: than 1e-4 (``tests/test_smooth_paths.py``).
SOLVE_JITTER = 4.0


def joseph_rank_one(
    z: Float[Array, " N"],
    P: Float[Array, "N N"],
    c: Float[Array, " N"],
    s: Float[Array, ""],
    innovation: Float[Array, ""],
    valid: Bool[Array, ""],
) -> tuple[Float[Array, " N"], Float[Array, "N N"]]:
    """A scalar measurement update in Joseph form.

    For a row ``h`` with noise ``r``: ``c = P h``, ``s = h' c + r``, ``k = c / s`` and
    ``P+ = (I - k h') P (I - k h')' + r k k' = P - k c' - c k' + s k k'``; the estimate moves by
    ``k * innovation``. Skipped (exactly, and with finite gradients) when ``valid`` is false or
    ``s`` is not positive (e.g. a perfect measurement at a zero time step).
    """
    ok = valid & (s > 0)
    k = jnp.where(ok, c / jnp.where(ok, s, 1.0), 0.0)
    z = z + k * jnp.where(ok, innovation, 0.0)
    P = P - jnp.outer(k, c) - jnp.outer(c, k) + s * jnp.outer(k, k)
    return z, P


def coordinate_update(
    z: Float[Array, " N"],
    P: Float[Array, "N N"],
    index: int,
    innovation: Float[Array, ""],
    r: Float[Array, ""],
    valid: Bool[Array, ""],
) -> tuple[Float[Array, " N"], Float[Array, "N N"]]:
    """Condition on a measurement of one coordinate, ``z[index] + noise(r)``, whose innovation
    (measured minus ``z[index]``) is given: ``joseph_rank_one`` with ``h = e_index``."""
    c = P[:, index]
    return joseph_rank_one(z, P, c, c[index] + r, innovation, valid)


def row_update(
    z: Float[Array, " N"],
    P: Float[Array, "N N"],
    h: Float[Array, " N"],
    y: Float[Array, ""],
    r: Float[Array, ""],
    valid: Bool[Array, ""],
) -> tuple[Float[Array, " N"], Float[Array, "N N"]]:
    """Condition on ``y = h' z + noise(r)``: ``joseph_rank_one`` with ``c = P h``."""
    c = P @ h
    return joseph_rank_one(z, P, c, h @ c + r, y - h @ z, valid)


def symmetrise(P: Float[Array, "*b N N"]) -> Float[Array, "*b N N"]:
    """``(P + P') / 2``: removes the rounding asymmetry the updates leave."""
    return 0.5 * (P + jnp.swapaxes(P, -1, -2))


def cholesky_solve(S: Float[Array, "n n *L"], B: Float[Array, "n k *L"]) -> Float[Array, "n k *L"]:
    """``S^-1 B`` for a small symmetric positive definite ``S``: its Cholesky factor and two
    triangular solves, written out entry by entry (no LAPACK call, see the deadlock hazard).
    Trailing lane axes ``L`` (the smoother's trials) are carried through every entry.

    Below double precision each diagonal entry of ``S`` is loaded by ``SOLVE_JITTER n eps`` of
    itself: a direction whose variance is within the rounding of its coordinates' (two nearly
    equal coordinates' difference) is not trusted beyond it. The smoother's ``S`` spans more
    than float32 resolves where a fit leaves little process noise (a fitted ``x,y,x,y``
    ``kckf3d``: eigenvalues 1.3e-7 to 0.06, the weakest 6 % off in float32), and its gains
    along such a direction, near 1 over thousands of rows, let the rounding grow: smoothed
    angles 23 deg off float64's, or infinite. Float64 is solved as it is."""
    n = S.shape[0]
    if jnp.finfo(S.dtype).bits < 64:
        load = 1.0 + SOLVE_JITTER * n * float(jnp.finfo(S.dtype).eps)
        S = jnp.where(jnp.eye(n, dtype=bool).reshape((n, n) + (1,) * (S.ndim - 2)), S * load, S)
    zero_s = jnp.zeros_like(S[0, 0])
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        d = S[j, j] - sum((L[j][k] ** 2 for k in range(j)), zero_s)
        L[j][j] = jnp.sqrt(jnp.maximum(d, jnp.finfo(S.dtype).tiny))
        for i in range(j + 1, n):
            L[i][j] = (S[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), zero_s)) / L[j][j]
    zero = jnp.zeros_like(B[0])
    y = []
    for i in range(n):  # L y = B
        y.append((B[i] - sum((L[i][k] * y[k] for k in range(i)), zero)) / L[i][i])
    x = [None] * n
    for i in reversed(range(n)):  # L' x = y
        x[i] = (y[i] - sum((L[k][i] * x[k] for k in range(i + 1, n)), zero)) / L[i][i]
    return jnp.stack(x)


def fused_pairs(
    angle: Float[Array, " M"], r: Float[Array, " M"], valid: Bool[Array, " M"]
) -> tuple[Float[Array, " J"], Float[Array, " J"], Bool[Array, " J"]]:
    """Combine the ``l`` and ``r`` readings of every joint axis into one measurement.

    Two independent readings of the same angle are equivalent to one at their
    inverse-variance weighted mean with variance ``1 / (1/r_l + 1/r_r)``: the posterior is the
    same as after the paper's two rows (Eqs. 5, 8). A missing reading gets weight 0.
    """
    # A variance floor of 1e-12 rad^2 (6e-5 deg) keeps 1/r finite for a zero noise parameter.
    w = jnp.where(valid, 1.0 / jnp.maximum(r, 1e-12), 0.0).reshape(-1, 2)
    W = jnp.sum(w, axis=1)
    ok = W > 0
    Ws = jnp.where(ok, W, 1.0)
    h = jnp.sum(w * angle.reshape(-1, 2), axis=1) / Ws
    return h, 1.0 / Ws, ok
