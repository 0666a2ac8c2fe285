"""The Hall effect sensor model of the KCKF paper, Eq. (1).

``theta(V) = sign * (a * exp(b V) - c * exp(-d V))`` with ``a, b, c, d > 0``. The paper's fit
(one DRV5053 sensor against Vicon, in degrees) is ``a = 0.07, b = 2.87, c = 2.22e5, d = 8.43``.
Coefficients here are always in **radians** (``a`` and ``c`` carry the unit; a model given in
degrees is converted on the way in). ``theta`` is strictly increasing in ``V`` for ``sign = +1``
(its slope ``a b e^{bV} + c d e^{-dV}`` is positive), so the inverse is unique.

The forward model and its slope are JAX functions (they run inside the filters and are
differentiated when fitting); the inverse is NumPy float64 (only the simulator needs it).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Real

#: The paper's Eq. (1) coefficients, in degrees.
PAPER_HALL_DEG = {"a": 0.07, "b": 2.87, "c": 2.22e5, "d": 8.43}
DEG = math.pi / 180.0


def hall_angle(
    v: Float[ArrayLike, "*#M"],
    a: Float[ArrayLike, "*#M"],
    b: Float[ArrayLike, "*#M"],
    c: Float[ArrayLike, "*#M"],
    d: Float[ArrayLike, "*#M"],
    sign: Real[ArrayLike, "*#M"],
) -> Float[Array, "*M"]:
    """Joint angle (rad) from Hall voltage ``v`` (V), Eq. (1); coefficients in rad."""
    v = jnp.asarray(v)
    return sign * (a * jnp.exp(b * v) - c * jnp.exp(-d * v))


def hall_slope(
    v: Float[ArrayLike, "*#M"],
    a: Float[ArrayLike, "*#M"],
    b: Float[ArrayLike, "*#M"],
    c: Float[ArrayLike, "*#M"],
    d: Float[ArrayLike, "*#M"],
    sign: Real[ArrayLike, "*#M"],
) -> Float[Array, "*M"]:
    """``d theta / d V`` (rad/V) of Eq. (1)."""
    v = jnp.asarray(v)
    return sign * (a * b * jnp.exp(b * v) + c * d * jnp.exp(-d * v))


def hall_voltage(
    angle_rad: np.ndarray, a, b, c, d, sign, v_lo: float = -2.0, v_hi: float = 6.0
) -> np.ndarray:
    """The voltage a sensor of model (a, b, c, d, sign) gives at ``angle_rad``; inverse of Eq. 1.

    NumPy float64, vectorised; safeguarded Newton iterations inside the bracket
    ``[v_lo, v_hi]`` (the model is monotone, so the root is unique). Used by the simulator.
    """
    target = np.asarray(angle_rad, dtype=np.float64) * np.asarray(sign, dtype=np.float64)
    a, b, c, d = (np.broadcast_to(np.asarray(x, dtype=np.float64), target.shape)
                  for x in (a, b, c, d))
    lo = np.full(target.shape, v_lo)
    hi = np.full(target.shape, v_hi)

    def f(v):
        return a * np.exp(b * v) - c * np.exp(-d * v) - target

    # Start from whichever exponential dominates at the target.
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        v = np.where(target > 0, np.log(np.maximum(target, 1e-300) / a) / b,
                     -np.log(np.maximum(-target, 1e-300) / c) / d)
    v = np.clip(np.nan_to_num(v, nan=0.5 * (v_lo + v_hi)), v_lo, v_hi)
    for _ in range(100):
        fv = f(v)
        lo = np.where(fv < 0, v, lo)
        hi = np.where(fv >= 0, v, hi)
        step = fv / (a * b * np.exp(b * v) + c * d * np.exp(-d * v))
        v_new = v - step
        outside = (v_new <= lo) | (v_new >= hi)
        v_new = np.where(outside, 0.5 * (lo + hi), v_new)
        if np.all(np.abs(v_new - v) < 1e-13):
            v = v_new
            break
        v = v_new
    return v
