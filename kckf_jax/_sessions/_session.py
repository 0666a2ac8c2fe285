"""Recorded sessions: the ``kckf-session/1`` interchange format, validation and mocap alignment.

A session is one folder holding ``meta.json``, ``sensors.csv`` and optionally ``mocap.csv``
(``../shared/spec/session-format.md``); the same data may come in other containers, one reader
each: the motion capture as OpenSim Storage (``mocap.mot``/``.sto``, ``_storage``), sensors and
motion capture as an XDF recording (``recording.xdf``, ``_xdf``). ``read_session`` turns any of
them into the same ``Session`` of float64 NumPy arrays in the robot's column order, and rejects
a malformed file with a one-line ``SessionError`` that names the file, the line and the column;
``write_session`` writes one back (as CSV). ``align_mocap`` interpolates motion-capture frames
onto the sensor clock (the ground truth of every error figure).

Plain NumPy and the standard library: this is the edge of the package, the numerical core
never imports it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from .._models._limits import SensorLimits
from .._models._params import hall_arrays
from .._models._robot import Robot
from .._readings._gaps import GapPolicy, find_gaps, segments
from ._atomic import atomic_write
from ._containers import _s, read_containers  # noqa: F401 (_s: tests read it here)
from ._csvio import (
    META_FILE,
    MOCAP_FILE,
    SENSORS_FILE,
    SessionError,
    _read_text,
    _write_csv,
)
from ._plausible import (  # noqa: F401 (STEP_FACTOR, MAX_ANGLE_RAD: read here)
    MAX_ANGLE_RAD,
    STEP_FACTOR,
    check_plausible,
    mocap_unit_finding,
)

FORMAT = "kckf-session/1"
#: ``meta.json`` keys this module reads into ``Session`` fields; any other key (among them
#: ``mocap_columns`` and ``xdf_streams``, which say how to read the files) goes to
#: ``Session.extra_meta``, and ``write_session`` writes it back.
META_KEYS = (
    "format", "joints", "sample_rate_hz", "mocap_time_offset_s", "hall_models", "description",
    "hall_v_range", "gyro_range_rad_s",
)
#: Default ``max_gap_s`` of ``align_mocap``, in median mocap frame intervals.
MAX_GAP_FRAMES = 3.0


class SessionWarning(UserWarning):
    """What ``read_session`` read but a user must be told, in one line naming the file: a
    recording cut short (what was kept), an empty motion-capture stream (not used), motion
    capture beyond any joint's reach (with its likely cause). The commands print each once on
    stderr (``kckf VERB: warning: ...``)."""


@dataclass(eq=False)
class Session:
    """One recorded trial, as float64 NumPy arrays (NaN marks a missing reading).

    Attributes:
        robot: the joint layout (``meta.json``'s ``joints``).
        t: (T,) sensor clock, s, finite and strictly increasing.
        gyro: (T, 3 (n + 1)) gyro rates, rad/s, columns in ``robot.gyro_names`` order.
        hall_v: (T, M) Hall voltages, V, columns in ``robot.hall_names`` order.
        sample_rate_hz: the nominal sensor rate, Hz (the real step comes from ``t``).
        mocap_t: (F,) motion-capture clock, s, strictly increasing; ``None`` without mocap.
        mocap: (F, K) motion-capture angles, rad, ``robot.angle_names`` order; NaN marks an
            occluded frame; ``None`` without mocap.
        mocap_time_offset_s: added to a mocap time to get sensor time, s.
        hall_models: per-sensor Eq. (1) models as in ``meta.json`` (may be empty).
        description: free text.
        extra_meta: unknown ``meta.json`` keys, kept and written back.
        limits: the readings' physical range (``SensorLimits``; ``meta.json``'s optional
            ``hall_v_range`` and ``gyro_range_rad_s``), ``None`` when the session states
            none (the filter's parameters then decide).
        path: the folder it was read from, if any.
        sensors_file, mocap_file: the files in ``path`` the sensors and the motion capture
            were read from (``sensors.csv`` or ``recording.xdf``; ``mocap.csv``,
            ``mocap.mot``, ``mocap.sto`` or ``recording.xdf``), named in messages.

    The arrays are validated (and numeric arrays converted to float64) on construction; they
    are not meant to be modified afterwards (``truth()`` is cached).

    Example:
        >>> import numpy as np
        >>> robot = Robot.from_spec("x,y")
        >>> t = np.arange(5) / 100.0
        >>> s = Session(robot, t, np.zeros((5, 9)), np.zeros((5, 4)), sample_rate_hz=100.0)
        >>> s.n_steps, round(s.duration_s, 6), s.has_truth
        (5, 0.04, False)
    """

    robot: Robot
    t: np.ndarray
    gyro: np.ndarray
    hall_v: np.ndarray
    sample_rate_hz: float
    mocap_t: np.ndarray | None = None
    mocap: np.ndarray | None = None
    mocap_time_offset_s: float = 0.0
    hall_models: dict = field(default_factory=dict)
    description: str = ""
    extra_meta: dict = field(default_factory=dict)
    path: str | None = None
    limits: SensorLimits | None = None
    sensors_file: str = SENSORS_FILE
    mocap_file: str = MOCAP_FILE
    _truth: np.ndarray | None = field(default=None, init=False, repr=False)

    def __post_init__(self):
        if not isinstance(self.robot, Robot):
            raise ValueError(f"Session.robot: expected a Robot, got {type(self.robot).__name__}")
        self.t = _float_array("t", self.t, ("T",))
        _check_increasing("Session.t", self.t)
        T, G, M = self.t.shape[0], 3 * self.robot.n_links, self.robot.n_hall
        self.gyro = _float_array("gyro", self.gyro, (T, G))
        self.hall_v = _float_array("hall_v", self.hall_v, (T, M))
        if (self.mocap_t is None) != (self.mocap is None):
            raise ValueError(
                "Session.mocap_t, Session.mocap: expected both arrays or both None, got "
                f"{type(self.mocap_t).__name__} and {type(self.mocap).__name__}"
            )
        if self.mocap_t is not None:
            self.mocap_t = _float_array("mocap_t", self.mocap_t, ("F",))
            if self.mocap_t.shape[0] == 0:
                raise ValueError("Session.mocap_t: expected at least one frame, got none")
            _check_increasing("Session.mocap_t", self.mocap_t)
            F, K = self.mocap_t.shape[0], self.robot.n_angles
            self.mocap = _float_array("mocap", self.mocap, (F, K))
        self.sample_rate_hz = _scalar("sample_rate_hz", self.sample_rate_hz, positive=True)
        self.mocap_time_offset_s = _scalar("mocap_time_offset_s", self.mocap_time_offset_s)
        if not isinstance(self.hall_models, Mapping):
            raise ValueError(
                f"Session.hall_models: expected a dict, got {type(self.hall_models).__name__}"
            )
        self.hall_models = dict(self.hall_models)
        hall_arrays(self.robot, self.hall_models)  # raises ValueError naming the sensor
        if not isinstance(self.description, str):
            raise ValueError(
                f"Session.description: expected a str, got {type(self.description).__name__}"
            )
        if not isinstance(self.extra_meta, Mapping):
            raise ValueError(
                f"Session.extra_meta: expected a dict, got {type(self.extra_meta).__name__}"
            )
        self.extra_meta = dict(self.extra_meta)
        for name in ("sensors_file", "mocap_file"):
            if not isinstance(getattr(self, name), str):
                raise ValueError(f"Session.{name}: expected a file name (str), got "
                                 f"{type(getattr(self, name)).__name__}")
        clash = sorted(set(self.extra_meta) & set(META_KEYS))
        if clash:
            raise ValueError(
                f"Session.extra_meta: key {clash[0]!r} is a Session field; set the field instead"
            )

    @property
    def n_steps(self) -> int:
        """``T``: sensor rows."""
        return int(self.t.shape[0])

    @property
    def duration_s(self) -> float:
        """Time from the first to the last sensor row, s (0 for fewer than two rows)."""
        return float(self.t[-1] - self.t[0]) if self.n_steps else 0.0

    def dt(self) -> np.ndarray:
        """(T,) seconds since the previous row, float64: ``dt[0] = 0``, ``t[k] - t[k-1]``."""
        out = np.zeros_like(self.t)
        out[1:] = np.diff(self.t)
        return out

    def truth(self) -> np.ndarray:
        """(T, K) ground-truth angles on the sensor times, rad, ``robot.angle_names`` order.

        Mocap interpolated onto ``t`` by ``align_mocap`` with its default ``max_gap_s``; NaN
        where there is no truth (no mocap, outside the valid frames, or across a long gap).
        Computed once and cached.
        """
        if self._truth is None:
            if self.mocap is None:
                self._truth = np.full((self.n_steps, self.robot.n_angles), np.nan)
            else:
                self._truth = align_mocap(
                    self.t, self.mocap_t, self.mocap, self.mocap_time_offset_s
                )
        return self._truth

    @property
    def has_truth(self) -> bool:
        """Whether at least one sensor time has a ground-truth value for some angle."""
        return bool(self.mocap is not None and np.isfinite(self.truth()).any())


# ---------------------------------------------------------------------- alignment


def align_mocap(
    sensor_t: np.ndarray,
    mocap_t: np.ndarray,
    mocap: np.ndarray,
    offset_s: float,
    max_gap_s: float | None = None,
) -> np.ndarray:
    """Motion-capture angles interpolated onto the sensor clock.

    The sensor time of a frame is ``mocap_t + offset_s``. Each angle column is interpolated
    linearly between its neighbouring *valid* (finite) frames, separately from the others. A
    sensor time outside the span of a column's valid frames, or inside a gap between valid
    frames longer than ``max_gap_s``, gets NaN (a sensor time exactly on a valid frame always
    gets that frame's value).

    Args:
        sensor_t: (T,) sensor times, s, increasing.
        mocap_t: (F,) mocap times, s (mocap clock), increasing.
        mocap: (F, K) or (F,) angles, rad; NaN marks an occluded frame.
        offset_s: added to ``mocap_t`` to get sensor time, s.
        max_gap_s: the longest gap between valid frames that is bridged, s; default
            ``3 x`` the median mocap frame interval (no limit for a single frame).

    Returns:
        (T, K) or (T,) float64 angles, rad, NaN where there is no truth.

    Example:
        >>> t = np.array([0.0, 0.5, 1.0, 1.5])
        >>> align_mocap(t, np.array([0.0, 1.0]), np.array([[0.0], [2.0]]), 0.0)[:, 0].tolist()
        [0.0, 1.0, 2.0, nan]
    """
    sensor_t = np.asarray(sensor_t, dtype=np.float64)
    mocap_t = np.asarray(mocap_t, dtype=np.float64)
    mocap = np.asarray(mocap, dtype=np.float64)
    if sensor_t.ndim != 1:
        raise ValueError(f"align_mocap: sensor_t must have shape (T,), got {sensor_t.shape}")
    if mocap_t.ndim != 1:
        raise ValueError(f"align_mocap: mocap_t must have shape (F,), got {mocap_t.shape}")
    if mocap.ndim not in (1, 2) or mocap.shape[0] != mocap_t.shape[0]:
        raise ValueError(
            f"align_mocap: mocap must have shape ({mocap_t.shape[0]}, K) to match mocap_t, "
            f"got {mocap.shape}"
        )
    if np.any(np.diff(mocap_t) <= 0.0):
        raise ValueError("align_mocap: mocap_t must be strictly increasing")
    if max_gap_s is None:
        max_gap_s = (
            MAX_GAP_FRAMES * float(np.median(np.diff(mocap_t))) if mocap_t.size > 1 else math.inf
        )
    # A relative slack so that a gap of exactly ``max_gap_s`` (e.g. two dropped frames at the
    # default) is bridged whatever the rounding of the timestamps.
    limit = max_gap_s * (1.0 + 1e-9)
    frames_t = mocap_t + offset_s
    columns = mocap.reshape(mocap.shape[0], -1)
    out = np.full((sensor_t.shape[0], columns.shape[1]), np.nan)
    for k in range(columns.shape[1]):
        valid = np.isfinite(columns[:, k])
        tv, yv = frames_t[valid], columns[valid, k]
        if tv.size == 0:
            continue
        col = np.interp(sensor_t, tv, yv)
        # Interval [tv[j-1], tv[j]) holding each sensor time; j = 0 or len(tv) is outside.
        j = np.searchsorted(tv, sensor_t, side="right")
        on_last = sensor_t == tv[-1]
        inside = (j > 0) & (j < tv.size)
        jj = np.clip(j, 1, max(tv.size - 1, 1))
        gap = tv[jj] - tv[jj - 1] if tv.size > 1 else np.zeros_like(sensor_t)
        on_frame = inside & (sensor_t == tv[jj - 1])
        ok = (inside & ((gap <= limit) | on_frame)) | on_last
        col[~ok] = np.nan
        out[:, k] = col
    return out.reshape((sensor_t.shape[0],) + mocap.shape[1:])


# ---------------------------------------------------------------------- reading


def read_session(path: str | os.PathLike, *, require_mocap: bool = False,
                 plausible: bool = True) -> Session:
    """Read and validate a ``kckf-session/1`` folder.

    Args:
        path: the session folder: ``meta.json``; the sensors in ``sensors.csv`` or
            ``recording.xdf``; the motion capture (optional) in ``mocap.csv``, ``mocap.mot``,
            ``mocap.sto`` or a stream of ``recording.xdf``.
        require_mocap: raise when there is no motion capture (to fit or evaluate).
        plausible: also reject a session that is well formed but implausible
            (``check_plausible``: timestamps that are not in seconds, mocap angles that are
            not in radians), and name motion capture no joint can reach or in another unit
            than its file says (``mocap_unit_finding``: refused with ``require_mocap``, a
            ``SessionWarning`` without); ``False`` reads it anyway, without a word.

    Warns:
        SessionWarning: one line each: a recording cut short (where, and what was kept), an
            empty motion-capture stream, a ``mocap_unit_finding`` when mocap is not required.

    Returns:
        A ``Session``; gyro columns the file lacks and the filters do not read (e.g. the ``z``
        rates of a planar robot) are NaN.

    Raises:
        SessionError: a missing file, broken JSON, a missing column, a bad cell, a row of the
            wrong length, a non-increasing ``t``, mocap that does not overlap the sensors, or
            an implausible session; the message is one line and names the file, line and
            column.

    Example:
        >>> s = read_session("data/bench_cyclic_1")  # doctest: +SKIP
        >>> s.gyro.shape, s.truth().shape  # doctest: +SKIP
        ((6000, 15), (6000, 6))
    """
    folder = os.fspath(path)
    if not os.path.exists(folder):
        raise SessionError(f"{folder}: no such session folder")
    if not os.path.isdir(folder):
        raise SessionError(
            f"{folder}: not a folder; a session is a folder holding {META_FILE}, "
            f"{SENSORS_FILE} and optionally {MOCAP_FILE}"
        )
    meta_path = os.path.join(folder, META_FILE)
    meta, robot, hall_models = _read_meta_checked(meta_path)
    sample_rate_hz = meta.get("sample_rate_hz")
    if not _is_number(sample_rate_hz) or not sample_rate_hz > 0 or math.isinf(sample_rate_hz):
        raise SessionError(
            f"{meta_path}: 'sample_rate_hz' must be a positive number (Hz), "
            f"got {sample_rate_hz!r}"
        )
    offset_s = meta.get("mocap_time_offset_s", 0.0)
    if not _is_number(offset_s) or not math.isfinite(offset_s):
        raise SessionError(
            f"{meta_path}: 'mocap_time_offset_s' must be a number (s), got {offset_s!r}"
        )
    description = meta.get("description", "")
    if not isinstance(description, str):
        raise SessionError(f"{meta_path}: 'description' must be a string, got {description!r}")
    extra_meta = {k: v for k, v in meta.items() if k not in META_KEYS}
    limits = _limits_of(meta, meta_path)

    context = f"the robot in {META_FILE} has joints {robot.spec}"
    got = read_containers(folder, meta, robot, offset_s, require_mocap=require_mocap,
                          context=context)

    session = Session(
        robot=robot, t=got.t, gyro=got.gyro, hall_v=got.hall_v,
        sample_rate_hz=float(sample_rate_hz), mocap_t=got.mocap_t, mocap=got.mocap,
        mocap_time_offset_s=float(offset_s), hall_models=hall_models, description=description,
        extra_meta=extra_meta, path=folder, limits=limits, sensors_file=got.sensors_file,
        mocap_file=got.mocap_file,
    )
    for note in got.notes:
        warnings.warn(note, SessionWarning, stacklevel=2)
    if plausible:
        check_plausible(session, mocap_units=got.mocap_units)
        finding = mocap_unit_finding(session, got.mocap_units)
        if finding and require_mocap:  # scoring against a truth that cannot be
            raise SessionError(f"{finding}, or pass --accept-implausible")
        if finding:  # the filter does not read motion capture: said, not refused
            warnings.warn(finding, SessionWarning, stacklevel=2)
    return session


def split_at_gaps(session: Session, policy: GapPolicy) -> list[Session]:
    """``session`` cut at every gap where ``policy`` restarts the filter (``_gaps``): one
    session per stretch (the same motion capture, so the truth of each row is unchanged);
    ``[session]`` when nothing restarts."""
    cuts = segments(session.n_steps, find_gaps(session.t, policy))
    if len(cuts) == 1:
        return [session]
    return [dataclasses.replace(session, t=session.t[a:b], gyro=session.gyro[a:b],
                                hall_v=session.hall_v[a:b]) for a, b in cuts]


def read_meta(meta_path: str | os.PathLike) -> tuple[Robot, dict, SensorLimits | None]:
    """The robot layout, Hall calibration and stated physical limits (or None) of a
    ``meta.json`` (validated as in ``read_session``): what a live stream needs to know about
    the robot."""
    meta, robot, hall_models = _read_meta_checked(os.fspath(meta_path))
    return robot, hall_models, _limits_of(meta, os.fspath(meta_path))


def _limits_of(meta: dict, meta_path: str) -> SensorLimits | None:
    if not {"hall_v_range", "gyro_range_rad_s", "joint_range_rad"} & set(meta):
        return None
    try:
        return SensorLimits.from_meta(meta, meta_path)
    except ValueError as exc:
        raise SessionError(str(exc)) from None


def _read_meta_checked(meta_path: str) -> tuple[dict, Robot, dict]:
    meta = _read_meta(meta_path)
    try:
        robot = Robot.from_meta(meta.get("joints"), where=meta_path)
    except ValueError as e:
        raise SessionError(_prefixed(meta_path, e)) from None
    hall_models = meta.get("hall_models", {})
    if not isinstance(hall_models, dict):
        raise SessionError(
            f"{meta_path}: 'hall_models' must be an object keyed by Hall column name, "
            f"got {hall_models!r}"
        )
    try:
        hall_arrays(robot, hall_models)
    except ValueError as e:
        raise SessionError(f"{meta_path}: {e}") from None
    return meta, robot, hall_models


def _read_meta(meta_path: str) -> dict:
    text = _read_text(meta_path)
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as e:
        raise SessionError(
            f"{meta_path}, line {e.lineno}, column {e.colno}: not valid JSON ({e.msg})"
        ) from None
    if not isinstance(meta, dict):
        raise SessionError(f"{meta_path}: expected a JSON object, got {type(meta).__name__}")
    fmt = meta.get("format")
    if fmt != FORMAT:
        raise SessionError(f"{meta_path}: 'format' must be {FORMAT!r}, got {fmt!r}")
    return meta


# ---------------------------------------------------------------------- writing


def write_session(session: Session, path: str | os.PathLike, digits: int = 9) -> None:
    """Write ``session`` as a ``kckf-session/1`` folder (created if needed).

    Writes ``meta.json`` (indent 2), ``sensors.csv`` (``t``, all of ``robot.gyro_names``, then
    ``robot.hall_names``) and, when the session has mocap, ``mocap.csv`` (``t`` then
    ``robot.angle_names``); a stale ``mocap.csv`` in the folder is removed otherwise. Times are
    written with full (round-trip) precision, other values with ``digits`` significant digits
    (default 9); NaN is an empty cell.

    Example:
        >>> write_session(session, "out/trial1")  # doctest: +SKIP
        >>> read_session("out/trial1").t.tolist() == session.t.tolist()  # doctest: +SKIP
        True
    """
    folder = os.fspath(path)
    os.makedirs(folder, exist_ok=True)
    robot = session.robot
    meta = {
        "format": FORMAT,
        "joints": robot.to_meta(),
        "sample_rate_hz": float(session.sample_rate_hz),
        "mocap_time_offset_s": float(session.mocap_time_offset_s),
        "hall_models": session.hall_models,
        "description": session.description,
        **(session.limits.to_meta() if session.limits is not None else {}),
        **session.extra_meta,
    }
    with atomic_write(os.path.join(folder, META_FILE), encoding="utf-8") as f:
        json.dump(meta, f, indent=2)
        f.write("\n")
    _write_csv(
        os.path.join(folder, SENSORS_FILE),
        ("t", *robot.gyro_names, *robot.hall_names),
        session.t,
        np.concatenate([session.gyro, session.hall_v], axis=1),
        digits,
    )
    mocap_path = os.path.join(folder, MOCAP_FILE)
    if session.mocap is not None:
        _write_csv(mocap_path, ("t", *robot.angle_names), session.mocap_t, session.mocap,
                   digits)
    elif os.path.exists(mocap_path):
        os.remove(mocap_path)


# ---------------------------------------------------------------------- helpers


def _float_array(name: str, x, shape: tuple[int | str, ...]) -> np.ndarray:
    """``x`` as float64 of ``shape`` (a str entry is a free size); ValueError otherwise."""
    arr = np.asarray(x)
    expected = "(" + ", ".join(map(str, shape)) + ("," if len(shape) == 1 else "") + ")"
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"Session.{name}: expected a real number array, got dtype {arr.dtype}")
    if arr.ndim != len(shape) or any(
        isinstance(n, int) and n != m for n, m in zip(shape, arr.shape)
    ):
        raise ValueError(f"Session.{name}: expected shape {expected}, got {arr.shape}")
    arr = arr.astype(np.float64)
    if np.isinf(arr).any():
        raise ValueError(f"Session.{name}: expected finite values or NaN, got an infinite value")
    return arr


def _check_increasing(name: str, t: np.ndarray) -> None:
    if not np.isfinite(t).all():
        raise ValueError(f"{name}: expected finite times, got NaN")
    bad = np.flatnonzero(np.diff(t) <= 0.0)
    if bad.size:
        k = int(bad[0]) + 1
        raise ValueError(
            f"{name}: expected strictly increasing times, got t[{k}] = {float(t[k])!r} "
            f"after t[{k - 1}] = {float(t[k - 1])!r}"
        )


def _is_number(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _scalar(name: str, x, *, positive: bool = False) -> float:
    """``x`` as a finite float (positive if asked); ValueError naming ``Session.name``."""
    what = "a positive number" if positive else "a finite number"
    if isinstance(x, bool) or not isinstance(x, int | float | np.integer | np.floating):
        raise ValueError(f"Session.{name}: expected {what}, got {x!r}")
    if not math.isfinite(x) or (positive and x <= 0):
        raise ValueError(f"Session.{name}: expected {what}, got {x!r}")
    return float(x)


def _prefixed(where: str, error: Exception) -> str:
    message = str(error)
    return message if message.startswith(where) else f"{where}: {message}"
