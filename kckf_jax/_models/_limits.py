"""The physical range of the readings: beyond it a reading is a fault in the data, not a reading.

A Hall voltage outside what its ADC can read, or a gyro rate beyond any sensor's range, cannot
have been measured: it is a transmission or logging fault (a byte error, a wrong unit, an
uninitialised buffer). The filter treats such a reading as missing, the same way in the batch
filter, the stream and the exported step (``_readings._prepare`` masks it before the step),
and the edges that read data (sessions, packets) count and name them.

Inside the range, three more kinds of reading are not measurements (``_screen`` decides, the
kernel's ``step`` applies it): a Hall reading *at* either end of its ADC's range (``railed``:
within ``RAIL_FRACTION`` of the span, a short or an open wire), a Hall reading whose angle
through the sensor's curve (Eq. 1) is beyond what a joint can reach (``joint_range_rad``:
``unreachable``), and a gyro reading at its full scale (``saturated``: the true rate may be
larger).

Defaults: the shipped Hall model is a DRV5053 read by a 3.3 V ADC (0-3.3 V); the gyro limit,
4,000 deg/s (69.8 rad/s), is beyond the widest range of any MEMS gyroscope of this class (the
LSM6DSO's is 2,000 deg/s); a joint reaches +-120 deg at most (the exoshell's joints bend about
+-30 deg in use; a reading through Eq. 1 beyond 120 deg is a voltage near the saturated end of
the curve, where 0.1 V is tens of degrees: 0.8 V is -261 deg with the paper's coefficients). A
session's ``meta.json`` may state its own (``hall_v_range``, ``gyro_range_rad_s``,
``joint_range_rad``; ``../shared/spec/session-format.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: 4,000 deg/s in rad/s.
GYRO_LIMIT_RAD_S = 4000.0 * math.pi / 180.0
#: The DRV5053's output read by a 3.3 V ADC.
HALL_V_RANGE = (0.0, 3.3)
#: The largest joint angle a Hall reading may stand for (rad): 120 deg.
JOINT_RANGE_RAD = 2.0 * math.pi / 3.0
#: A Hall reading within this fraction of the ADC's span from either end is railed: 0.5 %
#: (16.5 mV of 3.3 V, 20 steps of a 12-bit ADC). Simulated clean sessions stay 0.9 V from
#: either end (0.93-2.26 V over 120 sessions of every kind).
RAIL_FRACTION = 0.005
#: A gyro reading at or beyond this fraction of its full scale is saturated.
SATURATION_FRACTION = 0.999


@dataclass(frozen=True)
class SensorLimits:
    """The range a reading must lie in to be a reading (inclusive).

    Attributes:
        hall_v: ``(lo, hi)`` in V, every Hall sensor.
        gyro_rad_s: the largest magnitude of a gyro rate, rad/s (its full scale).
        joint_range_rad: the largest joint angle a Hall reading may stand for, rad.

    Example:
        >>> SensorLimits().describe()
        'Hall 0-3.3 V, gyro +-69.8 rad/s, joints +-120 deg'
    """

    hall_v: tuple[float, float] = HALL_V_RANGE
    gyro_rad_s: float = GYRO_LIMIT_RAD_S
    joint_range_rad: float = JOINT_RANGE_RAD

    def __post_init__(self):
        lo, hi = self.hall_v
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"SensorLimits.hall_v: expected (lo, hi) with lo < hi in V, got "
                             f"{self.hall_v!r}")
        if not (math.isfinite(self.gyro_rad_s) and self.gyro_rad_s > 0):
            raise ValueError(f"SensorLimits.gyro_rad_s: expected a positive number (rad/s), got "
                             f"{self.gyro_rad_s!r}")
        if not (math.isfinite(self.joint_range_rad) and self.joint_range_rad > 0):
            raise ValueError(f"SensorLimits.joint_range_rad: expected a positive number (rad), "
                             f"got {self.joint_range_rad!r}")

    @property
    def rail_v(self) -> float:
        """How close to either end of the ADC's range a railed Hall reading is, V."""
        lo, hi = self.hall_v
        return RAIL_FRACTION * (hi - lo)

    def outside(self, gyro, hall_v, xp=np):
        """Masks of the readings that are present (finite) but outside the range: ``(gyro,
        hall_v)``, any leading axes. NumPy (``xp=np``) or JAX."""
        lo, hi = self.hall_v
        g = xp.abs(gyro) > self.gyro_rad_s
        h = (hall_v < lo) | (hall_v > hi)
        return g, h

    def describe(self) -> str:
        lo, hi = self.hall_v
        return (f"Hall {lo:g}-{hi:g} V, gyro +-{self.gyro_rad_s:.1f} rad/s, joints "
                f"+-{math.degrees(self.joint_range_rad):.0f} deg")

    def to_meta(self) -> dict:
        """The ``meta.json`` / parameter-file form."""
        return {"hall_v_range": [float(v) for v in self.hall_v],
                "gyro_range_rad_s": float(self.gyro_rad_s),
                "joint_range_rad": float(self.joint_range_rad)}

    @classmethod
    def from_meta(cls, doc: dict, where: str = "meta.json") -> SensorLimits:
        """From the optional ``hall_v_range``, ``gyro_range_rad_s`` and ``joint_range_rad`` of a
        ``meta.json`` (or a parameter file's ``limits``); missing keys keep their defaults.
        ``ValueError`` names the key."""
        hall = doc.get("hall_v_range", list(HALL_V_RANGE))
        gyro = doc.get("gyro_range_rad_s", GYRO_LIMIT_RAD_S)
        reach = doc.get("joint_range_rad", JOINT_RANGE_RAD)
        ok = (isinstance(hall, list) and len(hall) == 2
              and all(isinstance(v, int | float) and not isinstance(v, bool) for v in hall))
        if not ok:
            raise ValueError(f"{where}: 'hall_v_range' must be [lo, hi] in V, got {hall!r}")
        if isinstance(gyro, bool) or not isinstance(gyro, int | float):
            raise ValueError(f"{where}: 'gyro_range_rad_s' must be a number (rad/s), got "
                             f"{gyro!r}")
        if isinstance(reach, bool) or not isinstance(reach, int | float):
            raise ValueError(f"{where}: 'joint_range_rad' must be a number (rad), got "
                             f"{reach!r}")
        try:
            return cls((float(hall[0]), float(hall[1])), float(gyro), float(reach))
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
