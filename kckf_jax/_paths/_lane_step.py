"""One filter step on lanes (every state and covariance entry an array over trials), and its
adjoint.

The step is the kernel's arithmetic (``_kernel.block_update``) written out entry by entry from
the block structure (``_model.Structure``: its constant matrices decide at trace time which
products are zero), with the trial axis *last*: each operation is one loop over the lanes. The
covariance is stored as its upper triangle (symmetric by construction). ``_lanes`` strings the
steps together over rows; ``_lanes_adjoint`` runs the reverse pass.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._models._blocks import Structure


def _tri(n: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(n) for j in range(i, n)]


def _tri_index(n: int) -> np.ndarray:
    """``(n, n)``: the position of entry ``(i, j)`` in the upper triangle ``_tri(n)``."""
    out = np.zeros((n, n), int)
    for t, (i, j) in enumerate(_tri(n)):
        out[i, j] = out[j, i] = t
    return out


def _apply(C: np.ndarray, x):
    """``C x`` for a constant ``C`` (``a x b``) and lane arrays ``x`` (``b, ...``): the sums of
    its nonzero terms written out (the constants are known at trace time), stacked. On a CPU
    this is several times faster than a broadcast multiply-sum or a small ``dot``."""
    C = np.asarray(C)
    rows = []
    for i in range(C.shape[0]):
        acc = None
        for j in np.flatnonzero(C[i]):
            w = float(C[i, j])
            term = x[j] if w == 1.0 else (-x[j] if w == -1.0 else w * x[j])
            acc = term if acc is None else acc + term
        rows.append(jnp.zeros_like(x[0]) if acc is None else acc)
    return jnp.stack(rows)


class _Consts:
    """The constant matrices of one block step in upper-triangle form (NumPy, built once per
    structure): the prediction ``S = (C0 + ts C1 + ts^2 C2) P + Qa alpha + Qab beta + Qb
    gamma`` and ``y = (F0 + ts F1) z + ts G1 r``, and the index maps of the updates."""

    def __init__(self, st: Structure):
        nz, ny = st.n_z, st.n_z + st.n_e
        iz, iy = _tri_index(nz), _tri_index(ny)
        ty = _tri(ny)
        F0, F1 = np.asarray(st.F0), np.asarray(st.F1)
        C = [np.zeros((len(ty), len(_tri(nz)))) for _ in range(3)]
        for t, (i, j) in enumerate(ty):
            for a in range(nz):
                for b in range(nz):
                    u = iz[a, b]
                    C[0][t, u] += F0[i, a] * F0[j, b]
                    C[1][t, u] += F0[i, a] * F1[j, b] + F1[i, a] * F0[j, b]
                    C[2][t, u] += F1[i, a] * F1[j, b]
        self.C = C
        self.Q = [np.array([[M[k, i, j] for k in range(M.shape[0])] for (i, j) in ty])
                  for M in (st.Qa, st.Qab, st.Qb)]
        self.F0, self.F1, self.G1 = F0, F1, np.asarray(st.G1)
        self.index = {nz: iz, ny: iy}
        self.restrict = np.array([iy[i, j] for (i, j) in _tri(nz)])
        self.rows = {n: np.array([i for i, _ in _tri(n)]) for n in (nz, ny)}
        self.cols = {n: np.array([j for _, j in _tri(n)]) for n in (nz, ny)}
        # The adjoint's maps: ``S[restrict]`` transposed, and for the update of ``index`` in
        # dimension ``n``, the column ``P e_index`` (entries ``index[n][:, index]``) transposed.
        self.unrestrict = np.zeros((len(ty), len(_tri(nz))))
        self.unrestrict[self.restrict, np.arange(len(_tri(nz)))] = 1.0
        self.column = {}
        for n in (nz, ny):
            for index in range(n):
                M = np.zeros((len(_tri(n)), n))
                M[self.index[n][:, index], np.arange(n)] = 1.0
                self.column[n, index] = M


class LaneStep(NamedTuple):
    """What one block step on lanes computed (``lane_step``; every array ``(n, Nb, B)``).

    Attributes:
        z: the new block state (``Nz``).
        P: the new covariance's upper triangle (``n_tri(Nz)``).
        nu: each joint's fused Hall innovation before its update (``m``; the kernel's
            ``block_step``).
        s: its variance (``m``).
        y: the predicted ``y = [z, e]`` before any update (``Ny``: the smoother's term).
        S: its covariance's upper triangle (``n_tri(Ny)``).
    """

    z: Array
    P: Array
    nu: Array
    s: Array
    y: Array
    S: Array


def lane_step(st: Structure, consts: _Consts, z, P, rates, noise, hb, rb, vb, ts,
              tape: list | None = None) -> LaneStep:
    """One block step on lanes: ``z`` (``Nz, Nb, B``), ``P`` (upper triangle, ``n_tri, Nb,
    B``), ``rates`` (``m1, Nb, B``), ``noise = (alpha, beta, gamma)`` (``m1, Nb, B`` each),
    ``hb, rb, vb`` (``m, Nb, B``), ``ts`` (``Nb, B``): the kernel's ``block_update`` and what
    it computed on the way (a caller's scan keeps only what it returns: XLA computes nothing
    else). ``tape``: a list that every scalar update appends its terms to (``_update``'s), for
    ``lane_step_adjoint``."""
    c = consts
    nz, ny = st.n_z, st.n_z + st.n_e
    # Predicted mean and covariance (Eqs. 3, 9-13).
    y = _apply(c.F0, z) + ts * _apply(c.F1, z) + ts * _apply(c.G1, rates)
    alpha, beta, gamma = noise
    S = (_apply(c.C[0], P) + ts * (_apply(c.C[1], P) + ts * _apply(c.C[2], P))
         + _apply(c.Q[0], alpha) + _apply(c.Q[1], beta) + _apply(c.Q[2], gamma))
    y, S = jax.lax.optimization_barrier((y, S))
    y_pred, S_pred = y, S
    # The constraint e = 0 as a perfect measurement (KCKF), then one update per joint.
    for i in range(st.n_e):
        e = nz + i
        y, S = _update(c, ny, y, S, e, -y[e], jnp.zeros_like(ts), ts > 0, tape)
    z, P = y[:nz], S[c.restrict] if st.n_e else S
    nus, ss = [], []
    for i in range(st.m):
        nus.append(hb[i] - z[i])
        ss.append(P[c.index[nz][i, i]] + rb[i])
        z, P = _update(c, nz, z, P, i, nus[-1], rb[i], vb[i], tape)
    return LaneStep(z, P, jnp.stack(nus), jnp.stack(ss), y_pred, S_pred)


def _update(c: _Consts, n: int, z, P, index: int, innovation, r, valid, tape=None):
    """The kernel's Joseph-form scalar update (``_kalman.coordinate_update``) on lanes;
    appends ``(n, index, k, s, ok, nu)`` to ``tape`` (a list) when given."""
    col, s, ok, k = _gain(c, n, P, index, r, valid)
    nu = jnp.where(ok, innovation, 0.0)
    if tape is not None:
        tape.append((n, index, k, s, ok, nu))
    z = z + k * nu
    a, b = c.rows[n], c.cols[n]
    P = P - k[a] * col[b] - col[a] * k[b] + s * k[a] * k[b]
    return z, P


def _gain(c: _Consts, n: int, P, index: int, r, valid):
    """The scalar update's column ``P e_index``, innovation variance, whether it is used, and
    gain (zero when not)."""
    col = P[c.index[n][:, index]]
    s = col[index] + r
    ok = valid & (s > 0)
    k = jnp.where(ok, col / jnp.where(ok, s, 1.0), 0.0)
    return col, s, ok, k


def pack_tape(tape: list):
    """A step's ``tape`` as one lane array (``tape_size, Nb, B``): for every scalar update in
    order, its gain ``k`` and ``w = nu / s`` (zero when skipped), all the reverse pass needs."""
    parts = []
    for _, _, k, s, ok, nu in tape:
        parts += [k, jnp.where(ok, nu / jnp.where(ok, s, 1.0), 0.0)[None]]
    return jnp.concatenate(parts)


def lane_step_adjoint(st: Structure, consts: _Consts, tape, z_bar, P_bar, ts,
                      z=None, P=None, rates=None, want_ts: bool = False,
                      want_rates: bool = False, nu_bar=None, s_bar=None, y_bar=None,
                      S_bar=None):
    """The reverse mode of ``lane_step`` (its plain form), written by hand from the step's
    packed ``tape`` (``pack_tape``): every piece transposed in reverse order. Given the
    cotangents ``(z_bar, P_bar)`` of the new ``(z, P)``, returns those of ``z``, ``P``,
    ``noise`` (a tuple of three), ``hb`` and ``rb`` (``m, Nb, B``), and of ``ts`` (``Nb, B``;
    needs the step's inputs ``z, P, rates``) and ``rates`` when asked for (else ``None``).
    ``nu_bar``, ``s_bar`` (``m, Nb, B``, or ``None``): the cotangents of the step's other
    outputs with ``innovations``, every joint's innovation ``hb - z_i`` and its variance
    ``P_ii + rb`` before its update. ``y_bar``, ``S_bar`` (``Ny, Nb, B`` and ``n_tri(Ny), Nb,
    B``, or ``None``): those of the predicted moments before any update (``LaneStep.y``,
    ``.S``: the smoother's terms).

    Each update ``z' = z + k nu``, ``P' = P - k c^T - c k^T + s k k^T`` (Joseph form, ``c = P
    e_i``, ``s = c_i + r``, ``k = c / s``) is the function ``P - c c^T / s`` of ``(P, r)``, and is
    transposed as that; a skipped update (``k = 0``, ``w = 0``) passes its cotangents through.
    Like the step, every operation is written out entry by entry on lanes, so the reverse pass
    has no scatter: XLA's transpose of the step's gathers made one per gather."""
    c = consts
    nz, ny = st.n_z, st.n_z + st.n_e
    terms, at = [], 0
    for n, index in [(ny, nz + i) for i in range(st.n_e)] + [(nz, i) for i in range(st.m)]:
        terms.append((n, index, tape[at:at + n], tape[at + n]))
        at += n + 1
    hb_bar, rb_bar = [None] * st.m, [None] * st.m
    for n, index, k, w in reversed(terms[st.n_e:]):
        z_bar, P_bar, hb_bar[index], rb_bar[index] = _update_adjoint(
            c, n, index, z_bar, P_bar, k, w, None if nu_bar is None else nu_bar[index],
            None if s_bar is None else s_bar[index])
    y_out_bar, S_out_bar = y_bar, S_bar
    if st.n_e:
        y_bar = jnp.concatenate([z_bar, jnp.zeros((st.n_e,) + z_bar.shape[1:], z_bar.dtype)])
        S_bar = _apply(c.unrestrict, P_bar)
    else:
        y_bar, S_bar = z_bar, P_bar
    for n, index, k, w in reversed(terms[:st.n_e]):
        y_bar, S_bar, _, _ = _update_adjoint(c, n, index, y_bar, S_bar, k, w)
    if y_out_bar is not None:  # the predicted moments are outputs too
        y_bar = y_bar + y_out_bar
    if S_out_bar is not None:
        S_bar = S_bar + S_out_bar
    # The prediction is linear in (z, P, rates, noise): its transpose.
    z_bar = _apply(c.F0.T, y_bar) + ts * _apply(c.F1.T, y_bar)
    P_bar = (_apply(c.C[0].T, S_bar)
             + ts * (_apply(c.C[1].T, S_bar) + ts * _apply(c.C[2].T, S_bar)))
    noise_bar = tuple(_apply(Q.T, S_bar) for Q in c.Q)
    ts_bar = rates_bar = None
    if want_ts:
        dy = _apply(c.F1, z) + _apply(c.G1, rates)
        dS = _apply(c.C[1], P) + 2.0 * ts * _apply(c.C[2], P)
        ts_bar = _total(y_bar * dy) + _total(S_bar * dS)
    if want_rates:
        rates_bar = ts * _apply(c.G1.T, y_bar)
    return (z_bar, P_bar, noise_bar, jnp.stack(hb_bar), jnp.stack(rb_bar), ts_bar,
            rates_bar)


def _update_adjoint(c: _Consts, n: int, index: int, v_bar, P_bar, k, w, nu_out_bar=None,
                    s_out_bar=None):
    """The transpose of one scalar update (``_update``, terms from its ``tape``): from the
    cotangents of ``(v', P')``, those of ``(v, P)`` and of the reading ``h`` and its variance
    ``r`` (the innovation is ``h - v[index]``; ``k = c / s`` with cotangent ``w s v_bar``).
    ``nu_out_bar``, ``s_out_bar``: the cotangents of the innovation and of its variance ``s``
    themselves, where the step outputs them (``innovations``); they flow whether or not the
    update was used."""
    iz = c.index[n]
    # P' = P - c c^T / s: c_bar_j = -sum_l W_jl k_l, W the symmetric cotangent (diagonal x 2).
    c_bar = jnp.stack([-_total([(2.0 if j == i else 1.0) * P_bar[iz[j, i]] * k[i]
                                for i in range(n)]) for j in range(n)])
    nu_bar = _total(k * v_bar)
    s_bar = -0.5 * _total(k * c_bar) - w * nu_bar
    if nu_out_bar is not None:
        nu_bar = nu_bar + nu_out_bar
    if s_out_bar is not None:
        s_bar = s_bar + s_out_bar
    one = jnp.asarray(np.eye(n)[index], v_bar.dtype)[:, None, None]
    c_bar = c_bar + w * v_bar + one * s_bar  # s = c_index + r
    P_bar = P_bar + _apply(c.column[n, index], c_bar)
    return v_bar - one * nu_bar, P_bar, nu_bar, s_bar


def _total(x):
    """The sum over the leading axis of a lane array (or of a list of them), written out."""
    acc = x[0]
    for i in range(1, len(x)):
        acc = acc + x[i]
    return acc
