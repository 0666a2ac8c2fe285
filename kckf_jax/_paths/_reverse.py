"""What the hand-written reverse passes share (``eqx.filter_custom_vjp`` over a scan:
``_lanes_adjoint``, ``_exact_adjoint``, ``_chunks``): which inputs are differentiated, the
cotangents of outputs that are not, and the state that entered a row."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def is_perturbed(flags) -> bool:
    """Whether any leaf of ``flags`` (a ``filter_custom_vjp``'s ``perturbed`` pytree of
    booleans, or a part of it) is differentiated."""
    return any(jax.tree_util.tree_leaves(flags))


def if_perturbed(cotangent, flags):
    """``cotangent`` where ``flags`` says its input is differentiated, else ``None``."""
    return cotangent if is_perturbed(flags) else None


def dense(cotangent, like):
    """A cotangent as an array: zeros like ``like`` where it is ``None`` (the output is not
    differentiated)."""
    return jnp.zeros_like(like) if cotangent is None else cotangent


def entering(t, after, first):
    """The state that entered row ``t`` of a reverse scan: ``first`` for the first row, else
    row ``t - 1``'s of ``after`` (each row's state after it, rows first)."""
    prev = jax.lax.dynamic_index_in_dim(after, jnp.maximum(t - 1, 0), keepdims=False)
    return jnp.where(t == 0, first, prev)


__all__ = ["dense", "entering", "if_perturbed", "is_perturbed"]
