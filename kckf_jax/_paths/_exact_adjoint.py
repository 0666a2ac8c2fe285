"""``kckf3d``'s lanes filter (``_exact_lanes``), its reverse pass written by hand.

JAX's own transpose of the entry-by-entry step (``_models/_exact_entries.entry_step``), each row
recomputed under ``jax.checkpoint``, launches many small kernels per row and cost more than
the sequential path's gradient, so a fitting loss took that one, 24x ``kckf``'s fitting step
(docs/kinematics.md). Here the scan is an ``eqx.filter_custom_vjp``: the forward pass keeps
each row's new covariance and held gyro rates and every scalar update's gain (``k``, ``w = nu
/ s``), and the reverse pass, last row first, transposes the step piece by piece:

* each Joseph update ``P' = P - c c' / s`` (``c = P e_i``, ``s = c_i + r``), as
  ``_lanes_adjoint`` does the linear KCKF's, on the full ``Nz x Nz`` covariance;
* the prediction ``S = F P F' + diag(q)``, ``F = I + dt E``, through the sparse joint rows of
  ``E`` (``M = E P``, ``F P F' = P + dt (M + M') + dt^2 M E'``): ``P`` gets ``F' S_bar F`` and
  each entry of ``E`` its own sum, written out over the pattern as the forward is;
* the entries of ``E`` and the joints' rates ``u`` are the rotations' closed forms
  (``prediction_rows``): only that small elementwise function is differentiated by JAX
  (``jax.vjp``), at the row's entering state, for the joint angles and the gyro rates.

The same derivative as JAX's own of the plain scan, to rounding (``tests/test_exact_adjoint.py``,
float64, with skipped rows and the rows' variances and innovations as outputs). A skipped row
(its step not finite) passes its cotangents through, and nothing of its step reaches the
inputs, as the forward passes its state through. Only the cotangents asked for are formed:
the time steps' when they are differentiated.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from .._models import _exact
from .._models._exact_entries import angle_variances, prediction_rows, times
from ._reverse import dense, entering, if_perturbed, is_perturbed


class _Args(NamedTuple):
    """What the scan is differentiated with respect to: the entering state (trials last) and
    every row's inputs (``ExactLaneInputs``)."""

    z0: jax.Array
    P0: jax.Array
    hold0: jax.Array
    rows: tuple


class _Tape(NamedTuple):
    """What the forward pass keeps per row: its new state and held rates (the next row's
    entering ones), whether it was skipped, and every update's ``k`` (``J Nz B``) and ``w``
    (``J B``)."""

    z: jax.Array
    P: jax.Array
    hold: jax.Array
    skipped: jax.Array
    k: jax.Array
    w: jax.Array


def exact_scan_rows(model: _exact.ExactModel, body, z0, P0, hold0, rows):
    """``lax.scan(body, (z0, P0, hold0), rows)`` of ``_exact_lanes``' body, differentiated
    by hand. ``body(carry, row, record=True)`` also returns the row's updates' ``(k, w)``.
    Returns ``((zT, PT, holdT), kept)`` (``ExactLaneRows`` per row)."""

    @eqx.filter_custom_vjp
    def run(args: _Args):
        return jax.lax.scan(body, (args.z0, args.P0, args.hold0), args.rows)

    @run.def_fwd
    def fwd(perturbed: _Args, args: _Args):
        def body_t(carry, row):
            new, (kept, (k, w)) = body(carry, row, record=True)
            return new, (kept, _Tape(new[0], new[1], new[2], kept.skipped, k, w))

        final, (kept, tape) = jax.lax.scan(body_t, (args.z0, args.P0, args.hold0), args.rows)
        return (final, kept), tape

    @run.def_bwd
    def bwd(tape: _Tape, cts, perturbed: _Args, args: _Args):
        z0, P0, hold0, rows = args
        want_ts = is_perturbed(perturbed.rows.ts)
        (zT_bar, PT_bar, holdT_bar), kept_bar = cts

        T = tape.skipped.shape[0]

        def back(carry, xs):
            zb, Pb, hb = carry
            t, row, sk, k, w, z_out, P_out, z_row_bar, var_bar, nu_bar, s_bar = xs
            if z_row_bar is not None:
                zb = zb + z_row_bar
            if var_bar is not None:
                _, vjp_var = jax.vjp(lambda z, P: angle_variances(model, z, P), z_out, P_out)
                dz, dP = vjp_var(var_bar)
                zb, Pb = zb + dz, Pb + dP
            fin = ~sk
            z_in, P_in, hold_in = (entering(t, tape.z, z0), entering(t, tape.P, P0),
                                   entering(t, tape.hold, hold0))
            zero = jnp.zeros((), zb.dtype)
            step = step_adjoint(
                model, z_in, P_in, hold_in, row.ts, jnp.where(fin, k, zero),
                jnp.where(fin, w, zero), jnp.where(fin, zb, zero), jnp.where(fin, Pb, zero),
                nu_bar, s_bar, want_ts)

            def kept(x):  # nothing of a skipped row's step reaches its inputs
                return None if x is None else jnp.where(fin, x, zero)

            # hold' = g where the row is kept and g finite, else hold
            take = fin & jnp.isfinite(row.gyro)
            g_bar = jnp.where(take, hb, zero)
            new = (jnp.where(fin, step.z, zb), jnp.where(fin, step.P, Pb),
                   jnp.where(take, zero, hb) + kept(step.hold))
            return new, (kept(step.h), kept(step.rh), kept(step.q), kept(step.ts), g_bar)

        per_row = (jnp.arange(T), rows, tape.skipped, tape.k, tape.w, tape.z, tape.P,
                   kept_bar.z, kept_bar.var, kept_bar.nu, kept_bar.s)
        carry = (dense(zT_bar, z0), dense(PT_bar, P0), dense(holdT_bar, hold0))
        (z0_bar, P0_bar, hold0_bar), (h_bar, rh_bar, q_bar, ts_bar, g_bar) = jax.lax.scan(
            back, carry, per_row, reverse=True)
        pr = perturbed.rows
        rows_bar = type(rows)(if_perturbed(ts_bar, pr.ts), if_perturbed(g_bar, pr.gyro),
                              if_perturbed(h_bar, pr.h), if_perturbed(rh_bar, pr.rh), None,
                              if_perturbed(q_bar, pr.q))
        return _Args(if_perturbed(z0_bar, perturbed.z0), if_perturbed(P0_bar, perturbed.P0),
                     if_perturbed(hold0_bar, perturbed.hold0), rows_bar)

    return run(_Args(z0, P0, hold0, rows))


class StepCotangents(NamedTuple):
    """``step_adjoint``'s result: the cotangents of the step's entering state ``z`` (``Nz
    B``), ``P`` (``Nz Nz B``) and held rates (``G B``), of the Hall readings and their
    variances (``J B``), of the process noise's diagonal (``Nz B``) and of the time step
    (``B``, or ``None`` when not asked for)."""

    z: jax.Array
    P: jax.Array
    hold: jax.Array
    h: jax.Array
    rh: jax.Array
    q: jax.Array
    ts: jax.Array | None


def step_adjoint(model: _exact.ExactModel, z, P, hold, ts, k, w, zb, Pb, nu_out_bar=None,
                 s_out_bar=None, want_ts: bool = False) -> StepCotangents:
    """The reverse mode of ``entry_step`` at its entering ``(z, P, hold)`` and time step
    ``ts``, from its updates' tape ``k`` (``J Nz B``), ``w`` (``J B``) and the cotangents of
    its new ``(z, P)`` (``zb``, ``Pb``) and, where given, of its innovations and their
    variances (``J B``)."""
    J, nz = model.J, z.shape[0]
    dtype = z.dtype
    one = jnp.eye(nz, dtype=dtype)

    def col(i):  # e_i as a column over the lanes
        return one[:, i].reshape((nz,) + (1,) * (z.ndim - 1))

    def tr(A):
        return jnp.swapaxes(A, 0, 1)

    # The updates, last first. Each is P' = P - c c' / s of (P, r), c = P e_i, s = c_i + r;
    # z' = z + k nu, nu = h_i - z_i; k = c / s (w = nu / s). Its transpose adds c_bar to P's
    # column i; added symmetrically (half to the row), the cotangent stays symmetric, which
    # changes nothing (the prediction's symmetrisation takes the symmetric part) and lets
    # every update's P_bar k be read from the last one's: P_bar_i k = P_bar_J k + the
    # earlier adds' terms, vectors only. So the covariance's cotangent is read once and
    # written once, not twice per update.
    Pb = 0.5 * (Pb + tr(Pb))
    PK = jnp.sum(Pb[:, None] * k[None], axis=2)  # (Nz, J, B): P_bar_J k_i
    h_bar, rh_bar, c_bars = [None] * J, [None] * J, [None] * J
    for i in reversed(range(J)):
        ki, wi = k[i], w[i]
        Pk = PK[:, i]
        if i + 1 < J:  # the adds of the updates after this one: 0.5 (c_j k_i[j] + e_j c_j'k_i)
            later = jnp.stack(c_bars[i + 1:])  # (n, Nz, B)
            dots = jnp.sum(later * ki[None], axis=1)  # (n, B)
            Pk = Pk + 0.5 * (jnp.sum(later * ki[i + 1:J, None], axis=0)
                             + jnp.concatenate([jnp.zeros((i + 1,) + dots.shape[1:], dtype),
                                                dots, jnp.zeros((nz - J,) + dots.shape[1:],
                                                                dtype)]))
        nu_bar = jnp.sum(ki * zb, axis=0)
        c_bar = -2.0 * Pk
        s_bar = jnp.sum(ki * Pk, axis=0) - wi * nu_bar
        if nu_out_bar is not None:
            nu_bar = nu_bar + nu_out_bar[i]
        if s_out_bar is not None:
            s_bar = s_bar + s_out_bar[i]
        c_bars[i] = c_bar + wi[None] * zb + col(i) * s_bar[None]
        zb = zb - col(i) * nu_bar[None]
        h_bar[i], rh_bar[i] = nu_bar, s_bar
    C = jnp.stack(c_bars, axis=1)  # (Nz, J, B)
    Cpad = jnp.concatenate([C, jnp.zeros((nz, nz - J) + C.shape[2:], dtype)], axis=1)
    Pb = Pb + 0.5 * (Cpad + tr(Cpad))
    # S = sym(S0) + diag(q): the predicted covariance.
    q_bar = jnp.stack([Pb[j, j] for j in range(nz)])
    Sb = 0.5 * (Pb + tr(Pb))
    # The rates u and the joint rows of E at the entering state (the closed forms, by JAX).
    beta_col = {c: i for i, c in enumerate(model.channels)}
    gyro = [hold[c] - z[J + beta_col[c]] if c in beta_col else hold[c] for c in range(model.G)]
    pattern: list = []

    # The angles' cosines and sines once (every kernel of the closed forms' transpose
    # would recompute them), then the forms as functions of them.
    trig = jax.lax.optimization_barrier(jnp.stack([jnp.cos(z[:J]), jnp.sin(z[:J])]))
    cs = [(trig[0, j], trig[1, j]) for j in range(J)]

    def closed_forms(cs, gyro):
        rows, u = prediction_rows(model, None, gyro, trig=cs)
        pattern[:] = [[(c, e if isinstance(e, (int, float)) else None) for c, e in row]
                      for row in rows]
        return [e for row in rows for _, e in row if not isinstance(e, (int, float))], u

    (arrays, u), vjp_forms = jax.vjp(closed_forms, cs, gyro)
    it = iter(arrays)
    rows = [[(c, next(it) if e is None else e) for c, e in row] for row in pattern]
    M = jnp.stack([sum((times(e, P[c]) for c, e in row), jnp.zeros_like(P[0]))
                   for row in rows])  # E P: (J, Nz, B)
    dt = ts[None]
    # S0 = P + dt (M + M') + dt^2 M E' (M in the joint rows): P, M and E's cotangents.
    Mbar_cols = [2.0 * dt * Sb[:J, c] for c in range(nz)]
    for r, row in enumerate(rows):
        for c, e in row:
            Mbar_cols[c] = Mbar_cols[c] + dt ** 2 * times(e, Sb[:J, r])
    Mbar = jnp.stack(Mbar_cols, axis=1)  # (J, Nz, B)
    P_rows = [None] * nz
    for r, row in enumerate(rows):
        for c, e in row:
            term = times(e, Mbar[r])
            P_rows[c] = term if P_rows[c] is None else P_rows[c] + term
    P_bar = Sb + jnp.stack([jnp.zeros_like(P[0]) if x is None else x for x in P_rows])
    # Every entry's cotangent at once, two reductions (one kernel each, where each entry's
    # own sums were two), read where the pattern has an entry:
    # (Mbar P')[r, c] + dt^2 (Sb[:J, :J]' M)[r, c].
    E_all = (jnp.sum(Mbar[:, None] * P[None], axis=2)
             + dt[None] ** 2 * jnp.sum(Sb[:J, :J, None] * M[:, None], axis=0))
    E_bar = [E_all[r, c] for r, row in enumerate(rows) for c, e in row
             if not isinstance(e, (int, float))]
    ts_bar = None
    if want_ts:
        MEt = jnp.stack([sum((times(e, M[:, c]) for c, e in row), jnp.zeros_like(M[:, 0]))
                         for row in rows], axis=1)  # (J, J, B)
        ts_bar = (2.0 * jnp.sum(Sb[:J] * M, axis=(0, 1))
                  + 2.0 * ts * jnp.sum(Sb[:J, :J] * MEt, axis=(0, 1))
                  + jnp.sum(zb[:J] * jnp.stack(u), axis=0))
    # z' = z + dt [u; 0]
    u_bar = [ts * zb[j] for j in range(J)]
    cs_bar, gyro_bar = vjp_forms((E_bar, u_bar))
    theta_bar = [cos * sb - sin * cb for (cos, sin), (cb, sb) in zip(cs, cs_bar, strict=True)]
    z_bar = [zb[j] + theta_bar[j] for j in range(J)]
    z_bar += [zb[J + i] - gyro_bar[c] for i, c in enumerate(model.channels)]
    return StepCotangents(jnp.stack(z_bar), P_bar, jnp.stack(gyro_bar), jnp.stack(h_bar),
                          jnp.stack(rh_bar), q_bar, ts_bar)


__all__ = ["StepCotangents", "exact_scan_rows", "step_adjoint"]
