"""The lanes filter's reverse pass, written by hand.

XLA's transpose of ``lane_step`` launches many small kernels per row: a scatter-add for each
of the step's constant gathers, index arithmetic, zero fills and copies (x, y, x, y robot: 154
fusions and 17 copies in the reverse loop body against 56 fusions in the forward). The
reverse pass is bound by kernels launched per row, not arithmetic (benchmarks/README.md,
"where the lanes gradient's time goes"). Here ``lane_scan``'s filter is a
``eqx.filter_custom_vjp``: the forward scan keeps every scalar update's gain (``pack_tape``: 19
numbers a block and row for the bench robot; the filter outputs its states anyway), and the
reverse scan, last
row first, applies ``lane_step_adjoint`` to them (nothing is recomputed), written out entry by
entry like the step: 46 fusions in the reverse loop body. The
likelihood's scan (``innovations``) takes it too, with the cotangents of every innovation and
its variance, and so does the smoother's forward pass (``LaneMoments``), with those of every
row's predicted moments (``_lanes_smooth``).

Exact: the same derivative as the automatic one, to rounding (``tests/test_lanes_adjoint.py``
checks it against it, and against finite differences, in float64). Only the cotangents that
are asked for are formed: those of the time steps and of the gyro readings only when they
are differentiated (``perturbed``). A skipped row (its update not finite) passes its
cotangents through, as the forward passes its state through.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._models._blocks import Structure
from ._lane_step import _apply, _Consts, lane_step_adjoint
from ._reverse import dense, entering, is_perturbed


def scan_rows(st: Structure, consts: _Consts, Rm: np.ndarray, body, x0, hold0, rows):
    """``lax.scan(body, (x0, hold0), rows)`` of the lanes scan's body (``_lanes._lane_loop``,
    ``rows`` its ``LaneInputs``), differentiated by hand. Returns ``((xT, holdT), kept)``,
    per row the ``LaneRows`` (``z``, ``P``, ``skipped``), ``LaneInnovations`` (``nu``,
    ``s``, ``valid``: every joint's fused Hall innovation and its variance, before its update)
    or ``LaneMoments`` (``LaneRows``' and the predicted ``y``, ``S`` before the updates: the
    smoother's forward pass) that ``body`` keeps; ``Rm`` maps the held gyro rates to the block
    rates."""

    @eqx.filter_custom_vjp
    def run(args: _ScanArgs):
        (xT, holdT), kept = jax.lax.scan(body, (args.x0, args.hold0), args.rows)
        return (xT, holdT), kept

    @run.def_fwd
    def fwd(perturbed: _ScanArgs, args: _ScanArgs):
        flags = _wanted(perturbed)

        def body_h(carry, row):  # the body, keeping every row's skipped flag and tape, and
            # for the derivative in the time steps its state and held rates
            new, (kept, skipped, tape) = body(carry, row, record=True)
            return new, (kept, _Tape(skipped, tape, new if flags.ts else None))

        (xT, holdT), (kept, tape) = jax.lax.scan(body_h, (args.x0, args.hold0), args.rows)
        return ((xT, holdT), kept), tape

    @run.def_bwd
    def bwd(tape_rows: _Tape, cts, perturbed: _ScanArgs, args: _ScanArgs):
        x0, hold0, rows = args
        flags = _wanted(perturbed)
        want_hold = flags.hold0 or flags.gyro
        (xT_bar, holdT_bar), kept_bar = cts
        innovations = hasattr(kept_bar, "nu")
        moments = hasattr(kept_bar, "y")  # the smoother's forward pass (LaneMoments)
        nz = st.n_z
        nb = st.angle_index.shape[0]
        T = tape_rows.skipped.shape[0]

        xT_bar = dense(xT_bar, x0)
        carry = (xT_bar[:nz], xT_bar[nz:])
        if want_hold:
            carry += (dense(holdT_bar, hold0),)
        # Per row: the cotangents of (z, P), or with innovations of (nu, s).
        per_row = (kept_bar.nu, kept_bar.s) if innovations else (kept_bar.z, kept_bar.P)
        if moments:
            per_row += (kept_bar.y, kept_bar.S)

        def back(carry, row):
            z_bar, P_bar = carry[:2]
            t, inputs_t, sk, tape, first_bar, second_bar = row[:6]
            ts, g = inputs_t.ts, inputs_t.gyro
            fin = ~sk
            outputs_bar = {}
            if moments:
                # A skipped row's predicted moments were computed from its entering state
                # too: its updates pass cotangents through (zero gains, as a skipped
                # update's), so the reverse step gives the moments' derivative alone.
                tape = jnp.where(fin, tape, 0.0)
                outputs_bar = dict(y_bar=row[6], S_bar=row[7])
            if innovations:
                outputs_bar = dict(nu_bar=first_bar, s_bar=second_bar)
            else:
                if first_bar is not None:
                    z_bar = z_bar + first_bar
                if second_bar is not None:
                    P_bar = P_bar + second_bar
            tsb = jnp.broadcast_to(ts, (nb,) + ts.shape)
            inputs = {}
            if flags.ts:  # the step's inputs, for the derivative in its time step
                x, hold = (entering(t, tape_rows.state[0], x0),
                           entering(t, tape_rows.state[1], hold0))
                inputs = dict(z=x[:nz], P=x[nz:],
                              rates=_apply(Rm, hold).reshape((st.m + 1, nb) + hold.shape[1:]))
            z_new, P_new, noise_bar, hb_bar, rb_bar, ts_bar, rates_bar = lane_step_adjoint(
                st, consts, tape, jnp.where(fin, z_bar, 0.0), jnp.where(fin, P_bar, 0.0), tsb,
                want_ts=flags.ts, want_rates=want_hold, **inputs, **outputs_bar)

            # A skipped row kept its state: its cotangent passes through, and nothing of the
            # (non-finite) step reaches the inputs (but its predicted moments', above).
            def kept(x):
                return x if moments else jnp.where(fin, x, 0.0)

            if moments:
                new = (z_new + jnp.where(fin, 0.0, z_bar), P_new + jnp.where(fin, 0.0, P_bar))
            else:
                new = (jnp.where(fin, z_new, z_bar), jnp.where(fin, P_new, P_bar))
            g_bar = None
            if want_hold:  # hold' = g where the row is kept and g finite, else hold
                take = fin & jnp.isfinite(g)
                g_bar = jnp.where(take, carry[2], 0.0)
                from_rates = _apply(Rm.T, rates_bar.reshape((-1,) + rates_bar.shape[2:]))
                new += (jnp.where(take, 0.0, carry[2]) + kept(from_rates),)
            out = (tuple(kept(x) for x in noise_bar), kept(hb_bar), kept(rb_bar),
                   kept(ts_bar.sum(axis=0)) if flags.ts else None, g_bar)
            return new, out

        final, (noise_bar, hb_bar, rb_bar, ts_bar, g_bar) = jax.lax.scan(
            back, carry, (jnp.arange(T), rows, tape_rows.skipped, tape_rows.tape) + per_row,
            reverse=True)
        x0_bar = jnp.concatenate(final[:2]) if flags.x0 else None
        hold0_bar = final[2] if flags.hold0 else None
        pr = perturbed.rows

        def wanted(g, p):
            return g if p else None

        rows_bar = type(rows)(wanted(ts_bar, pr.ts),
                              type(rows.noise)(*(wanted(g, p) for g, p in zip(noise_bar,
                                                                               pr.noise))),
                              wanted(hb_bar, pr.hb), wanted(rb_bar, pr.rb), None,
                              wanted(g_bar, pr.gyro))
        return _ScanArgs(x0_bar, hold0_bar, rows_bar)

    return run(_ScanArgs(x0, hold0, rows))


class _ScanArgs(NamedTuple):
    """What the lanes scan is differentiated with respect to: the entering state (lanes
    layout), the entering gyro hold and every row's inputs (``LaneInputs``)."""

    x0: jax.Array
    hold0: jax.Array
    rows: tuple


def _wanted(perturbed: _ScanArgs) -> _Wanted:
    return _Wanted(is_perturbed(perturbed.x0), is_perturbed(perturbed.hold0),
                   is_perturbed(perturbed.rows.ts), is_perturbed(perturbed.rows.gyro))


class _Wanted(NamedTuple):
    """Which cotangents the reverse pass forms: of the entering state, the entering gyro
    hold, the time steps and the gyro readings (only those differentiated)."""

    x0: bool
    hold0: bool
    ts: bool
    gyro: bool


class _Tape(NamedTuple):
    """What the forward pass keeps per row for the reverse one: whether the row was
    skipped, its updates' terms (``pack_tape``) and, only for the derivative in the time
    steps, the state and held rates after it (else ``None``)."""

    skipped: jax.Array
    tape: jax.Array
    state: tuple | None
