"""Plausibility at read time: a well-formed session whose numbers cannot mean what the format
says (``../shared/spec/session-format.md``), named with its likely cause and the fix.

``check_plausible`` refuses timestamps that are not in seconds and mocap angles beyond 2 pi;
``mocap_unit_finding`` names motion-capture joint angles no joint can reach (below 2 pi: the
way degrees written where radians are said get past the 2 pi rule) and angles that the gyros
say are in another unit than the file says (``gyro_scale``). ``read_session`` refuses the
second for the commands that score against the motion capture and warns for the others;
``--accept-implausible`` (``plausible=False``) skips both. Plain NumPy, at the edge of the
package.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from .._models._limits import SensorLimits
from .._models._robot import Robot
from ._csvio import META_FILE, MOCAP_FILE, SessionError
from ._storage import STORAGE_FILES
from ._xdf import XDF_FILE


@runtime_checkable
class Session(Protocol):
    """What these checks read of a ``_session.Session`` (which imports this module)."""

    robot: Robot
    t: np.ndarray
    gyro: np.ndarray
    mocap: np.ndarray | None
    sample_rate_hz: float
    limits: SensorLimits | None
    extra_meta: dict
    path: str | None
    sensors_file: str
    mocap_file: str

    @property
    def n_steps(self) -> int: ...

    def dt(self) -> np.ndarray: ...

    def truth(self) -> np.ndarray: ...

#: The median time step may differ from ``1 / sample_rate_hz`` by at most this factor, and
#: motion-capture angles may not exceed this magnitude (rad).
STEP_FACTOR = 2.0
MAX_ANGLE_RAD = 2.0 * math.pi


def check_plausible(session: Session, *, mocap_units: Sequence[str] = ()) -> None:
    """Reject a well-formed session whose numbers cannot be what the format says they are:
    a ``SessionError`` naming the file, the column, what was found and what was expected.

    * the median time step differs from ``1 / sample_rate_hz`` by more than a factor of
      ``STEP_FACTOR`` (2): timestamps in milliseconds, or the wrong rate in ``meta.json``;
    * a motion-capture angle beyond ``MAX_ANGLE_RAD`` (2 pi): angles in degrees.

    ``mocap_units`` (the unit each angle column is written in, ``rad`` or ``deg``) lets the
    message say what to fix (an OpenSim header's ``inDegrees=no``, an XDF channel's unit).
    ``read_session(..., plausible=False)`` (the commands' ``--accept-implausible``) skips it."""
    folder = session.path or "session"
    sensors_path = os.path.join(folder, session.sensors_file)
    if session.n_steps > 1:
        med = float(np.median(np.diff(session.t)))
        expected = 1.0 / session.sample_rate_hz
        if not expected / STEP_FACTOR <= med <= expected * STEP_FACTOR:
            raise SessionError(
                f"{sensors_path}, column 't': the median time step is "
                f"{med:.6g} s, but {META_FILE}'s sample_rate_hz = {session.sample_rate_hz:g} Hz "
                f"means {expected:.6g} s (t must be in seconds; timestamps in milliseconds?); "
                "fix the file or sample_rate_hz, or pass --accept-implausible")
    if session.mocap is not None:
        big = np.abs(np.nan_to_num(session.mocap)) > MAX_ANGLE_RAD
        if big.any():
            k = int(np.argmax(big.any(axis=0)))
            worst = float(np.nanmax(np.abs(session.mocap[:, k])))
            unit = mocap_units[k] if mocap_units else "rad"
            fix = (_unit_fix(session.mocap_file) if unit == "rad" else
                   "in deg, as the file says, it is more than a turn: check which column holds "
                   f"which angle ({META_FILE}'s mocap_columns)")
            raise SessionError(
                f"{os.path.join(folder, session.mocap_file)}, column "
                f"{session.robot.angle_names[k]!r}: "
                f"|angle| reaches {worst:.6g}, beyond 2 pi (angles must be in rad; degrees?); "
                f"{fix}, or pass --accept-implausible")


def mocap_unit_finding(session: Session, mocap_units: Sequence[str] = ()) -> str:
    """A one-line finding ("" when none) about the motion capture's joint angles, with its
    likely cause and fix:

    * an angle beyond what any joint can reach (``SensorLimits.joint_range_rad``: the
      session's ``meta.json``, default 120 deg). Cause: the numbers are degrees in a file said
      to be in rad, where the gyros say so (``gyro_scale``) or, without their word, where the
      numbers would be within reach as degrees; a joint that does reach that far, where the
      gyros agree with the angles as written; else a column holding another angle.
    * numbers in a file said to be in degrees that the gyros say are radians (they turn about
      57 times faster than these angles in degrees): small numbers alone say nothing, since a
      real motion of a few degrees has them too.

    Only joint angles (``theta``) are checked: a torso angle sums several joints.
    ``mocap_units`` as in ``check_plausible``: the unit each angle column is written in."""
    if session.mocap is None:
        return ""
    robot = session.robot
    K = robot.n_joint_axes  # the joint angles come first in robot.angle_names
    units = list(mocap_units) or ["rad"] * robot.n_angles
    reach = (session.limits or SensorLimits()).joint_range_rad
    peak = np.max(np.abs(np.nan_to_num(session.mocap[:, :K])), axis=0, initial=0.0)
    over = [k for k in range(K) if peak[k] > reach]
    theirs = session.extra_meta.get("mocap_columns", {})
    path = os.path.join(session.path or "session", session.mocap_file)

    def columns(ks: list[int]) -> str:
        names = [robot.angle_names[j] for j in ks]
        return f"column{'s' if len(names) > 1 else ''} " + ", ".join(
            f"{n!r}" + (f" ({theirs[n]!r} in the file)" if n in theirs else "") for n in names)

    if not over:  # within reach: numbers said to be degrees that the gyros say are radians
        said_deg = [k for k in range(K) if units[k] == "deg"]
        scales = {k: gyro_scale(session, k) for k in said_deg}
        small = [k for k, x in scales.items() if x is not None and x < 1 / UNIT_SPLIT]
        if not small:
            return ""
        times = 1 / float(np.median([scales[k] for k in small]))
        return (f"{path}, {columns(small)}: the gyros turn {times:.0f} times faster than these "
                f"angles in deg (a factor 57 is radians read as degrees): "
                f"{_unit_fix(session.mocap_file, to='rad')}")
    k = max(over, key=lambda j: peak[j])
    unit = units[k]
    written = float(peak[k]) if unit == "rad" else math.degrees(peak[k])  # the file's number
    scale = gyro_scale(session, k)
    if scale is not None and 1 / UNIT_SPLIT <= scale <= UNIT_SPLIT:
        cause = (f"the gyros agree with these angles in {unit} (their rate x{scale:.2f}), so the "
                 "joint does move that far: state its reach in "
                 f"{META_FILE} (\"joint_range_rad\": rad)")
    elif unit == "rad" and (scale is not None and scale > UNIT_SPLIT or scale is None
                            and math.radians(written) <= reach):
        why = (f" (the gyros turn {scale:.0f} times slower than these numbers as rad)"
               if scale is not None else "")
        cause = (f"{_unit_fix(session.mocap_file, written)}{why}; if the joints do reach that "
                 f"far, state it in {META_FILE} (\"joint_range_rad\": rad)")
    else:
        cause = (f"in no unit would that be within reach: check which of the file's columns "
                 f"holds which angle ({META_FILE}'s mocap_columns); if the joints do reach that "
                 f"far, state it in {META_FILE} (\"joint_range_rad\": rad)")
    return (f"{path}, {columns(over)}: |angle| reaches {written:.4g} "
            + (f"rad ({math.degrees(peak[k]):.0f} deg)" if unit == "rad" else "deg")
            + f", beyond any joint's reach (+-{math.degrees(reach):.0f} deg, joint_range_rad): "
            f"{cause}")


#: ``gyro_scale`` beyond this factor (or below its inverse) is another unit: the geometric
#: mean of 1 (the same unit) and 57.3 (degrees against radians).
UNIT_SPLIT = math.sqrt(180.0 / math.pi)
#: The window over which angle changes are compared (s), the agreement asked of them, and
#: how many windows (sensor rows) at least.
_SCALE_WINDOW_S = 0.1
_SCALE_MIN_CORR = 0.8
_SCALE_MIN_WINDOWS = 200


def gyro_scale(session: Session, k: int) -> float | None:
    """How many times the gyros' change of joint angle ``k`` its motion capture changes by:
    about 1 when both are in rad, 57.3 for degrees read as radians, 1 / 57.3 for radians read
    as degrees; None where they do not agree well enough to say (correlation under 0.8, fewer
    than 200 windows: a still joint, a short overlap, a column that holds another angle).
    Simulated sessions agree at 0.91-0.9997 (6 to 140 deg of motion); two unrelated slow
    sines over a second reach 0.5.

    Over windows of 0.1 s of sensor rows: the change of the truth on the sensor times
    (``Session.truth``) against the integral of the joint's rate from its two gyros (Eq. 2,
    ``Robot.rate_pairs``), the least-squares slope through zero. The window keeps a gyro
    bias's integral and the mocap's noise small against the motion."""
    plus, minus = session.robot.rate_pairs
    rate = session.gyro[:, plus[k]] - session.gyro[:, minus[k]]
    dt = session.dt()
    turned = np.concatenate([[0.0], np.cumsum(np.nan_to_num(rate[1:]) * dt[1:])])
    lost = np.concatenate([[0], np.cumsum(~np.isfinite(rate[1:]))])
    h = max(1, round(_SCALE_WINDOW_S * session.sample_rate_hz))
    if session.n_steps <= h:
        return None
    truth = session.truth()[:, k]
    dm, dg = truth[h:] - truth[:-h], turned[h:] - turned[:-h]
    ok = (np.isfinite(dm) & (lost[h:] == lost[:-h])
          & (session.t[h:] - session.t[:-h] <= 2 * h / session.sample_rate_hz))
    if ok.sum() < _SCALE_MIN_WINDOWS:
        return None
    dm, dg = dm[ok], dg[ok]
    if not (dm.std() > 0 and dg.std() > 0):
        return None
    if abs(float(np.corrcoef(dm, dg)[0, 1])) < _SCALE_MIN_CORR:
        return None
    return abs(float(dm @ dg) / float(dg @ dg))


def _unit_fix(mocap_file: str, written: float | None = None, to: str = "deg") -> str:
    """What to fix where a file said to be in rad holds degrees (``to="deg"``), or said to
    be in degrees holds radians (``to="rad"``)."""
    peak = f" (max {written:.4g})" if written is not None else ""
    said = "rad" if to == "deg" else "deg"
    words = {"deg": "degrees", "rad": "radians"}
    if mocap_file in STORAGE_FILES:
        flag = {"rad": "no", "deg": "yes"}
        return (f"the file says inDegrees={flag[said]} but its numbers look like {words[to]}"
                f"{peak}: fix the header to inDegrees={flag[to]}")
    if mocap_file == XDF_FILE:
        none = " (no unit means rad)" if said == "rad" else ""
        return (f"its channels' unit is {said}{none} but their numbers look like {words[to]}"
                f"{peak}: give the channels the unit {to}")
    return (f"{MOCAP_FILE} is in rad (session-format.md); these look like degrees{peak}: "
            "convert them to rad")
