"""The lanes filter's reverse pass, written by hand.

XLA's transpose of ``lane_step`` launches many small kernels per row: a scatter-add for each
of the step's constant gathers, index arithmetic, zero fills and copies (x, y, x, y robot: 154
fusions and 17 copies in the reverse loop body against 56 fusions in the forward). The
reverse pass is bound by kernels launched per row, not arithmetic (benchmarks/README.md,
"where the lanes gradient's time goes"). Here ``lane_scan``'s filter is a
``jax.custom_vjp``: the forward scan keeps every scalar update's gain (``pack_tape``: 19
numbers a block and row for the bench robot; the filter outputs its states anyway), and the
reverse scan, last
row first, applies ``lane_step_adjoint`` to them (nothing is recomputed), written out entry by
entry like the step: 46 fusions in the reverse loop body. The
likelihood's scan (``innovations``) takes it too, with the cotangents of every innovation and
its variance.

Exact: the same derivative as the automatic one, to rounding (``tests/test_lanes_adjoint.py``
checks it against it, and against finite differences, in float64). Only the cotangents that
are asked for are formed: those of the time steps and of the gyro readings only when they
are differentiated (``symbolic_zeros``). A skipped row (its update not finite) passes its
cotangents through, as the forward passes its state through.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import CustomVJPPrimal, SymbolicZero

from .._model import Structure
from ._lane_step import _apply, _Consts, lane_step_adjoint


def scan_rows(st: Structure, consts: _Consts, Rm: np.ndarray, body, x0, hold0, rows,
              innovations: bool = False):
    """``lax.scan(body, (x0, hold0), rows)`` of ``lane_scan``'s body, differentiated by hand.
    Returns ``((xT, holdT), outputs)``, per row ``(z, P, skipped)``, or with ``innovations``
    ``(nu, s, valid)`` (every joint's fused Hall innovation and its variance, before its
    update); ``Rm`` maps the held gyro rates to the block rates (``lane_scan``'s)."""

    @jax.custom_vjp
    def run(x0, hold0, rows):
        (xT, holdT), out = jax.lax.scan(body, (x0, hold0), rows)
        return (xT, holdT) + out

    def fwd(x0, hold0, rows):
        def unwrap(tree):
            return jax.tree_util.tree_map(lambda p: p.value, tree,
                                          is_leaf=lambda p: isinstance(p, CustomVJPPrimal))

        def perturbed(tree):
            return any(p.perturbed for p in jax.tree_util.tree_leaves(
                tree, is_leaf=lambda p: isinstance(p, CustomVJPPrimal)))

        flags = (perturbed(x0), perturbed(hold0), perturbed(rows[0]), perturbed(rows[5]))
        x0, hold0, rows = unwrap(x0), unwrap(hold0), unwrap(rows)

        def body_h(carry, row):  # the body, keeping every row's skipped flag and tape, and
            # for the derivative in the time steps its state and held rates
            new, out = body(carry, row, record=True)
            return new, out + (new if flags[2] else ())

        (xT, holdT), out = jax.lax.scan(body_h, (x0, hold0), rows)
        at = 3 if innovations else 2  # (nu, s, valid, skipped, ...) or (z, P, skipped, ...)
        res = (x0, hold0, rows) + out[at:]
        return (xT, holdT) + out[:3], (res, flags)

    def bwd(saved, cts):
        (x0, hold0, rows, skipped, tapes, *states), flags = saved
        want_x0, want_hold0, want_ts, want_gyro = flags
        want_hold = want_hold0 or want_gyro
        xT_bar, holdT_bar, first_bar, second_bar, _ = cts
        nz = st.n_z
        nb = st.angle_index.shape[0]
        T = skipped.shape[0]

        def dense(ct, like):
            return jnp.zeros_like(like) if isinstance(ct, SymbolicZero) else ct

        xT_bar = dense(xT_bar, x0)
        carry = (xT_bar[:nz], xT_bar[nz:])
        if want_hold:
            carry += (dense(holdT_bar, hold0),)
        # Per row: the cotangents of (z, P), or with innovations of (nu, s).
        per_row = tuple(None if isinstance(ct, SymbolicZero) else ct
                        for ct in (first_bar, second_bar))

        def before(t, x_rows, first):  # the state entering row t
            prev = jax.lax.dynamic_index_in_dim(x_rows, jnp.maximum(t - 1, 0), keepdims=False)
            return jnp.where(t == 0, first, prev)

        def back(carry, row):
            z_bar, P_bar = carry[:2]
            t, (ts, noise, hb, rb, vb, g), sk, tape, first_bar, second_bar = row
            outputs_bar = {}
            if innovations:
                outputs_bar = dict(nu_bar=first_bar, s_bar=second_bar)
            else:
                if first_bar is not None:
                    z_bar = z_bar + first_bar
                if second_bar is not None:
                    P_bar = P_bar + second_bar
            fin = ~sk
            tsb = jnp.broadcast_to(ts, (nb,) + ts.shape)
            inputs = {}
            if want_ts:  # the step's inputs, for the derivative in its time step
                x, hold = before(t, states[0], x0), before(t, states[1], hold0)
                inputs = dict(z=x[:nz], P=x[nz:],
                              rates=_apply(Rm, hold).reshape((st.m + 1, nb) + hold.shape[1:]))
            z_new, P_new, noise_bar, hb_bar, rb_bar, ts_bar, rates_bar = lane_step_adjoint(
                st, consts, tape, jnp.where(fin, z_bar, 0.0), jnp.where(fin, P_bar, 0.0), tsb,
                want_ts=want_ts, want_rates=want_hold, **inputs, **outputs_bar)

            # A skipped row kept its state: its cotangent passes through, and nothing of the
            # (non-finite) step reaches the inputs.
            def kept(x):
                return jnp.where(fin, x, 0.0)

            new = (jnp.where(fin, z_new, z_bar), jnp.where(fin, P_new, P_bar))
            g_bar = None
            if want_hold:  # hold' = g where the row is kept and g finite, else hold
                take = fin & jnp.isfinite(g)
                g_bar = jnp.where(take, carry[2], 0.0)
                from_rates = _apply(Rm.T, rates_bar.reshape((-1,) + rates_bar.shape[2:]))
                new += (jnp.where(take, 0.0, carry[2]) + kept(from_rates),)
            out = (tuple(kept(x) for x in noise_bar), kept(hb_bar), kept(rb_bar),
                   kept(ts_bar.sum(axis=0)) if want_ts else None, g_bar)
            return new, out

        final, (noise_bar, hb_bar, rb_bar, ts_bar, g_bar) = jax.lax.scan(
            back, carry, (jnp.arange(T), rows, skipped, tapes) + per_row, reverse=True)
        x0_bar = jnp.concatenate(final[:2]) if want_x0 else None
        hold0_bar = final[2] if want_hold0 else None
        rows_bar = (ts_bar, noise_bar, hb_bar, rb_bar, None, g_bar if want_gyro else None)
        return x0_bar, hold0_bar, rows_bar

    run.defvjp(fwd, bwd, symbolic_zeros=True)
    xT, holdT, z_rows, P_rows, skipped = run(x0, hold0, rows)
    return (xT, holdT), (z_rows, P_rows, skipped)
