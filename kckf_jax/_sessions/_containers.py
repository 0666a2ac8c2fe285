"""Which files of a session folder hold what, and their arrays: one reader per container.

The sensors come from ``sensors.csv`` (``_csvio``) or ``recording.xdf`` (``_xdf``); the motion
capture, if any, from ``mocap.csv``, ``mocap.mot`` or ``mocap.sto`` (``_storage``) or a stream
of ``recording.xdf``. ``read_session`` builds the same ``Session`` from whichever it was;
nothing after it knows which. Plain NumPy and the standard library, at the edge of the package.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

from .._models._robot import Robot
from ._csvio import META_FILE, MOCAP_FILE, SENSORS_FILE, SessionError, _read_csv
from ._storage import STORAGE_FILES, read_storage
from ._xdf import XDF_FILE, read_xdf, xdf_streams_of


class Containers(NamedTuple):
    """What ``read_containers`` read: float64 arrays in the robot's column order."""

    t: np.ndarray
    gyro: np.ndarray
    hall_v: np.ndarray
    mocap_t: np.ndarray | None  #: None without motion capture
    mocap: np.ndarray | None
    sensors_file: str  #: the file the sensors came from
    mocap_file: str  #: the file the motion capture came from (``mocap.csv`` when none did)
    #: the unit each angle column is written in, in the file (``rad`` or ``deg``; ``()``
    #: without motion capture), for the plausibility messages.
    mocap_units: tuple[str, ...] = ()
    #: what the reader should be told, one line each (a file cut short, an empty stream).
    notes: tuple[str, ...] = ()


def read_containers(folder: str, meta: dict, robot: Robot, offset_s: float, *,
                    require_mocap: bool, context: str) -> Containers:
    """The arrays of a session folder whose ``meta.json`` is read (``meta``).

    Raises:
        SessionError: both ``sensors.csv`` and ``recording.xdf``, several motion-capture
            files, motion capture in both the XDF and a file, a nonzero
            ``mocap_time_offset_s`` beside XDF motion capture, no overlap with the sensors, no
            motion capture when ``require_mocap``, and whatever the readers refuse.
    """
    meta_path = os.path.join(folder, META_FILE)
    mapping = _mocap_columns(meta, meta_path, robot)
    sensors_file, mocap_files = _containers(folder)
    mocap_t = mocap = None
    units: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    absent = ""  # why a motion-capture stream gave none
    if sensors_file == XDF_FILE:
        rec = read_xdf(os.path.join(folder, XDF_FILE), robot, mapping,
                       xdf_streams_of(meta, meta_path), context)
        t, gyro, hall_v = rec.t, rec.gyro, rec.hall_v
        notes, absent = rec.notes, rec.mocap_absent
        if rec.mocap is not None:
            if mocap_files:
                raise SessionError(
                    f"{folder}: both {XDF_FILE} (stream {rec.mocap_stream!r}) and "
                    f"{mocap_files[0]} hold motion capture; keep one")
            if offset_s != 0.0:
                raise SessionError(
                    f"{meta_path}: 'mocap_time_offset_s' is {offset_s!r}, but {XDF_FILE}'s "
                    "streams share the LSL clock and no offset applies; set it to 0 or remove it")
            mocap_t, mocap, mocap_files = rec.mocap_t, rec.mocap, [XDF_FILE]
            units = rec.mocap_units
    else:
        gyro_used = set(robot.used_gyro_columns)
        cols = _read_csv(
            os.path.join(folder, SENSORS_FILE),
            required=("t", *robot.used_gyro_columns, *robot.hall_names),
            optional=tuple(n for n in robot.gyro_names if n not in gyro_used),
            context=context,
        )
        t = cols["t"]
        nan = np.full_like(t, np.nan)
        gyro = np.stack([cols.get(n, nan) for n in robot.gyro_names], axis=1)
        hall_v = np.stack([cols[n] for n in robot.hall_names], axis=1)

    mocap_file = mocap_files[0] if mocap_files else MOCAP_FILE
    mocap_path = os.path.join(folder, mocap_file)
    if mocap_file == MOCAP_FILE and mocap_files:
        mcols = _read_csv(mocap_path, required=("t", *robot.angle_names), optional=(),
                          context=context, rename=mapping)
        mocap_t = mcols["t"]
        mocap = np.stack([mcols[n] for n in robot.angle_names], axis=1)
        units = ("rad",) * robot.n_angles
    elif mocap_file in STORAGE_FILES:
        mocap_t, mocap, in_degrees = read_storage(mocap_path, robot.angle_names, mapping,
                                                  context)
        units = ("deg" if in_degrees else "rad",) * robot.n_angles
    if mocap is not None:
        lo, hi = mocap_t[0] + offset_s, mocap_t[-1] + offset_s
        if not np.any((t >= lo) & (t <= hi)):
            hint = ("the streams' clocks" if mocap_file == XDF_FILE
                    else f"mocap_time_offset_s in {META_FILE}")
            raise SessionError(
                f"{mocap_path}: no overlap with the sensors (mocap covers {_s(lo)}-{_s(hi)} s "
                f"in sensor time, sensors {_s(t[0])}-{_s(t[-1])} s); check {hint}"
            )
    elif require_mocap and absent:
        raise SessionError(
            f"{absent}; motion capture is needed to evaluate or to fit on the RMSE (kckf fit "
            "--loss nll fits on the Hall readings alone)")
    elif require_mocap:
        raise SessionError(
            f"{mocap_path}: file not found; motion capture (t and {', '.join(robot.angle_names)})"
            " is needed to evaluate or to fit on the RMSE (kckf fit --loss nll fits on the Hall"
            f" readings alone); it may also be {' or '.join(STORAGE_FILES)} (OpenSim Storage) or"
            f" a stream of {XDF_FILE}"
        )

    return Containers(t, gyro, hall_v, mocap_t, mocap, sensors_file, mocap_file, units, notes)


def _containers(folder: str) -> tuple[str, list[str]]:
    """Which file holds the sensors, and which files hold motion capture (at most one)."""
    here = [n for n in (SENSORS_FILE, XDF_FILE, MOCAP_FILE, *STORAGE_FILES)
            if os.path.isfile(os.path.join(folder, n))]
    if SENSORS_FILE in here and XDF_FILE in here:
        raise SessionError(
            f"{folder}: both {SENSORS_FILE} and {XDF_FILE}; a session holds its sensors in one "
            "of them: move the other out of the folder")
    mocap = [n for n in here if n in (MOCAP_FILE, *STORAGE_FILES)]
    if len(mocap) > 1:
        raise SessionError(f"{folder}: {len(mocap)} motion-capture files ({', '.join(mocap)}); a "
                           "session holds one: move the others out of the folder")
    return (XDF_FILE if XDF_FILE in here else SENSORS_FILE), mocap


def _mocap_columns(meta: dict, meta_path: str, robot: Robot) -> dict[str, str]:
    """``meta.json``'s ``mocap_columns`` (our angle name -> the file's), validated."""
    mapping = meta.get("mocap_columns", {})
    if not isinstance(mapping, dict) or not all(
            isinstance(v, str) and v.strip() for v in mapping.values()):
        raise SessionError(
            f"{meta_path}: 'mocap_columns' must be an object like {{\"theta1_x\": \"their "
            f"column name\"}}, got {mapping!r}")
    unknown = [k for k in mapping if k not in robot.angle_names]
    if unknown:
        raise SessionError(
            f"{meta_path}: 'mocap_columns' maps {unknown[0]!r}, which is not an angle of this "
            f"robot (joints {robot.spec}: {', '.join(robot.angle_names)})")
    return dict(mapping)


def _s(x: float) -> str:
    """Seconds for a message: at most 6 decimals, always with a decimal point."""
    return repr(round(float(x), 6))


def sample_data_dir() -> str | None:
    """The shipped sample sessions: inside the installed package, or ``data/`` of a checkout
    (``None`` if neither is there)."""
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the package
    for cand in (os.path.join(here, "_data"), os.path.join(os.path.dirname(here), "data")):
        if os.path.isdir(cand):
            return cand
    return None
