"""The Hall effect sensor model of the KCKF paper, Eq. (1).

``theta(V) = sign * (a * exp(b V) - c * exp(-d V))`` with ``a, b, c, d > 0``. The paper's fit
(one DRV5053 sensor against Vicon, in degrees) is ``a = 0.07, b = 2.87, c = 2.22e5, d = 8.43``.
Coefficients here are always in **radians** (``a`` and ``c`` carry the unit; a model given in
degrees is converted on the way in). ``theta`` is strictly increasing in ``V`` for ``sign = +1``
(its slope ``a b e^{bV} + c d e^{-dV}`` is positive), so the inverse is unique.

The forward model and its slope are JAX functions (they run inside the filters and are
differentiated when fitting; ``hall_angle_and_slope`` both from one pair of exponentials, for
the health monitor); ``hall_angle_np`` is the same forward model in NumPy float64 for the host's
checks and reports, and the inverse is NumPy float64 (only the simulator needs it). Every
module writes Eq. 1 through these (``hall_exponentials`` underneath; the stream's host path
folds its weights into its matrix), never again by hand; ``tests/test_hall.py`` checks the
forms against each other.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Real

#: The paper's Eq. (1) coefficients, in degrees.
PAPER_HALL_DEG = {"a": 0.07, "b": 2.87, "c": 2.22e5, "d": 8.43}
DEG = math.pi / 180.0


def hall_exponentials(a, b, c, d, sign):
    """Eq. (1) as two weighted exponentials, ``theta = w1 e^(k1 V) + w2 e^(k2 V)``: returns
    ``((w1, w2), (k1, k2)) = ((sign a, -sign c), (b, -d))``, weights in rad, exponents in 1/V.

    The one place Eq. (1) is written: ``hall_angle``, ``hall_slope``, ``hall_voltage`` and the
    streaming filter's host path (which folds the weights into its matrix) all use it. Works
    on NumPy and JAX arrays alike.
    """
    return (sign * a, -sign * c), (b, -d)


def hall_angle(
    v: Float[ArrayLike, "*#M"],
    a: Float[ArrayLike, "*#M"],
    b: Float[ArrayLike, "*#M"],
    c: Float[ArrayLike, "*#M"],
    d: Float[ArrayLike, "*#M"],
    sign: Real[ArrayLike, "*#M"],
) -> Float[Array, "*M"]:
    """Joint angle (rad) from Hall voltage ``v`` (V), Eq. (1).

    Coefficients in **rad** (``a``, ``c``; ``b``, ``d`` in 1/V; ``sign`` +-1): a model
    written in degrees, as ``meta.json`` usually gives it, must be converted first
    (``Params.from_physical`` does it from the ``unit`` field).
    """
    (w1, w2), (k1, k2) = hall_exponentials(a, b, c, d, sign)
    v = jnp.asarray(v)
    return w1 * jnp.exp(k1 * v) + w2 * jnp.exp(k2 * v)


def hall_slope(
    v: Float[ArrayLike, "*#M"],
    a: Float[ArrayLike, "*#M"],
    b: Float[ArrayLike, "*#M"],
    c: Float[ArrayLike, "*#M"],
    d: Float[ArrayLike, "*#M"],
    sign: Real[ArrayLike, "*#M"],
) -> Float[Array, "*M"]:
    """``d theta / d V`` (rad/V) of Eq. (1) at ``v`` (V); coefficients in rad as for
    ``hall_angle``."""
    (w1, w2), (k1, k2) = hall_exponentials(a, b, c, d, sign)
    v = jnp.asarray(v)
    return w1 * k1 * jnp.exp(k1 * v) + w2 * k2 * jnp.exp(k2 * v)


def hall_angle_and_slope(v, w, k):
    """Eq. (1)'s angle and the absolute value of its slope (rad, rad/V) at ``v`` from its two
    exponentials' weights ``w = (w1, w2)`` and exponents ``k = (k1, k2)``
    (``hall_exponentials``): the two exponentials computed once for both. JAX."""
    (w1, w2), (k1, k2) = w, k
    e1, e2 = jnp.exp(k1 * v), jnp.exp(k2 * v)
    return w1 * e1 + w2 * e2, jnp.abs(w1 * k1 * e1 + w2 * k2 * e2)


def hall_angle_np(v, coeffs) -> np.ndarray:
    """Eq. (1) in NumPy float64: the angle (rad) of voltages ``v`` through the curves
    ``coeffs`` (``(a, b, c, d, sign)``, each per sensor or a scalar, in radians:
    ``Params.hall_coeffs``); NaN where ``v`` is NaN, an overflow an infinity, without a
    warning. For the host's checks and reports (``_screen``, ``_setup_check``, ``_mismatch``,
    ``_drift``)."""
    (w1, w2), (k1, k2) = hall_exponentials(*(np.asarray(c, np.float64) for c in coeffs))
    with np.errstate(over="ignore", invalid="ignore"):
        return w1 * np.exp(k1 * v) + w2 * np.exp(k2 * v)


def hall_voltage(
    angle_rad: np.ndarray, a, b, c, d, sign, v_lo: float = -2.0, v_hi: float = 6.0
) -> np.ndarray:
    """The voltage (V) a sensor of model ``(a, b, c, d, sign)`` gives at ``angle_rad`` (rad):
    the inverse of Eq. 1. Coefficients in **rad** as for ``hall_angle`` (with the degree values
    of a ``meta.json`` the curve is 57 times too flat).

    NumPy float64, vectorised; safeguarded Newton iterations inside the bracket
    ``[v_lo, v_hi]`` (V; the model is monotone, so the root is unique). Used by the simulator.
    """
    target = np.asarray(angle_rad, dtype=np.float64)
    shape = target.shape
    a, b, c, d, sign = (np.broadcast_to(np.asarray(x, dtype=np.float64), shape).ravel()
                        for x in (a, b, c, d, sign))
    target = target.ravel()
    (w1, w2), (k1, k2) = hall_exponentials(a, b, c, d, sign)

    # Start from whichever exponential dominates at the target.
    signed = target * sign
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        v = np.where(signed > 0, np.log(np.maximum(signed, 1e-300) / a) / b,
                     -np.log(np.maximum(-signed, 1e-300) / c) / d)
    v = np.clip(np.nan_to_num(v, nan=0.5 * (v_lo + v_hi)), v_lo, v_hi)
    # Each reading iterates until its own Newton step is below 1e-13 V, measured before the
    # bracket's safeguard: at the root the step rounds onto the bracket's end, which the
    # safeguard reads as leaving the bracket and bisects away from (up to 40 steps back to the
    # same root). The converged ones leave the active set.
    active = np.arange(target.size)
    lo = np.full(target.size, v_lo)
    hi = np.full(target.size, v_hi)
    va = v
    for _ in range(100):
        sg, t = sign[active], target[active]
        e1, e2 = np.exp(k1[active] * va), np.exp(k2[active] * va)
        fv = sg * (w1[active] * e1 + w2[active] * e2 - t)  # increasing in v whatever the sign
        slope = sg * (w1[active] * k1[active] * e1 + w2[active] * k2[active] * e2)
        la = np.where(fv < 0, va, lo[active])
        ha = np.where(fv >= 0, va, hi[active])
        newton = va - fv / slope
        converged = np.abs(newton - va) < 1e-13
        outside = ~converged & ((newton <= la) | (newton >= ha))
        v_new = np.where(outside, 0.5 * (la + ha), newton)
        done = converged | (np.abs(v_new - va) < 1e-13)
        v[active], lo[active], hi[active] = v_new, la, ha
        active = active[~done]
        if not active.size:
            break
        va = v[active]
    return v.reshape(shape)
