"""The physical range of the readings: beyond it a reading is a fault in the data, not a reading.

A Hall voltage outside what its ADC can read, or a gyro rate beyond any sensor's range, cannot
have been measured: it is a transmission or logging fault (a byte error, a wrong unit, an
uninitialised buffer). The filter treats such a reading as missing, the same way in the batch
filter, the stream and the exported step (``_kernel.step`` masks it), and the edges that read
data (sessions, packets) count and name them.

Defaults: the shipped Hall model is a DRV5053 read by a 3.3 V ADC (0-3.3 V); the gyro limit,
4,000 deg/s (69.8 rad/s), is beyond the widest range of any MEMS gyroscope of this class (the
LSM6DSO's is 2,000 deg/s). A session's ``meta.json`` may state its own (``hall_v_range``,
``gyro_range_rad_s``; ``../shared/spec/session-format.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

#: 4,000 deg/s in rad/s.
GYRO_LIMIT_RAD_S = 4000.0 * math.pi / 180.0
#: The DRV5053's output read by a 3.3 V ADC.
HALL_V_RANGE = (0.0, 3.3)


@dataclass(frozen=True)
class SensorLimits:
    """The range a reading must lie in to be a reading (inclusive).

    Attributes:
        hall_v: ``(lo, hi)`` in V, every Hall sensor.
        gyro_rad_s: the largest magnitude of a gyro rate, rad/s.

    Example:
        >>> SensorLimits().describe()
        'Hall 0-3.3 V, gyro +-69.8 rad/s'
    """

    hall_v: tuple[float, float] = HALL_V_RANGE
    gyro_rad_s: float = GYRO_LIMIT_RAD_S

    def __post_init__(self):
        lo, hi = self.hall_v
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"SensorLimits.hall_v: expected (lo, hi) with lo < hi in V, got "
                             f"{self.hall_v!r}")
        if not (math.isfinite(self.gyro_rad_s) and self.gyro_rad_s > 0):
            raise ValueError(f"SensorLimits.gyro_rad_s: expected a positive number (rad/s), got "
                             f"{self.gyro_rad_s!r}")

    def outside(self, gyro, hall_v, xp=np):
        """Masks of the readings that are present (finite) but outside the range: ``(gyro,
        hall_v)``, any leading axes. NumPy (``xp=np``) or JAX."""
        lo, hi = self.hall_v
        g = xp.abs(gyro) > self.gyro_rad_s
        h = (hall_v < lo) | (hall_v > hi)
        return g, h

    def mask(self, gyro, hall_v, xp=jnp):
        """``(gyro, hall_v)`` with every reading outside the range made missing (NaN)."""
        g, h = self.outside(gyro, hall_v, xp)
        return xp.where(g, xp.nan, gyro), xp.where(h, xp.nan, hall_v)

    def describe(self) -> str:
        lo, hi = self.hall_v
        return f"Hall {lo:g}-{hi:g} V, gyro +-{self.gyro_rad_s:.1f} rad/s"

    def to_meta(self) -> dict:
        """The ``meta.json`` / parameter-file form."""
        return {"hall_v_range": [float(v) for v in self.hall_v],
                "gyro_range_rad_s": float(self.gyro_rad_s)}

    @classmethod
    def from_meta(cls, doc: dict, where: str = "meta.json") -> SensorLimits:
        """From the optional ``hall_v_range`` and ``gyro_range_rad_s`` of a ``meta.json`` (or a
        parameter file's ``limits``); missing keys keep their defaults. ``ValueError`` names
        the key."""
        hall = doc.get("hall_v_range", list(HALL_V_RANGE))
        gyro = doc.get("gyro_range_rad_s", GYRO_LIMIT_RAD_S)
        ok = (isinstance(hall, list) and len(hall) == 2
              and all(isinstance(v, int | float) and not isinstance(v, bool) for v in hall))
        if not ok:
            raise ValueError(f"{where}: 'hall_v_range' must be [lo, hi] in V, got {hall!r}")
        if isinstance(gyro, bool) or not isinstance(gyro, int | float):
            raise ValueError(f"{where}: 'gyro_range_rad_s' must be a number (rad/s), got "
                             f"{gyro!r}")
        try:
            return cls((float(hall[0]), float(hall[1])), float(gyro))
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
