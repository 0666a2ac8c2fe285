"""XDF recordings (``recording.xdf`` beside ``meta.json``, in place of both CSV files).

The file Lab Streaming Layer's recorders (LabRecorder) write: several streams, each with a
header (name, channel labels and units) and time-stamped samples. One stream whose channel
labels are ``sensors.csv``'s column names (without ``t``) holds the sensors; one whose labels
are ``mocap.csv``'s angle names (or their names in ``meta.json``'s ``mocap_columns``) holds the
motion capture, if any. Where several streams match, ``meta.json``'s ``"xdf_streams":
{"sensors": NAME, "mocap": NAME}`` picks them by stream name. ``t`` counts from the first
sensor sample: the first sensor time stamp is subtracted from both streams.

Time stamps, as read by ``pyxdf.load_xdf``:

* ``synchronize_clocks=True``: each stream's stamps are moved onto the recording computer's
  clock through the clock offsets the recorder measured (streams from different machines,
  e.g. the robot's and the motion-capture system's, then share one clock). This is what
  makes the mocap line up with the sensors, and why ``mocap_time_offset_s`` does not apply:
  a ``meta.json`` that sets a nonzero one beside an XDF mocap stream is refused, not
  silently ignored (it was meant for another clock).
* ``dejitter_timestamps=False``: the sensors' own stamps are kept. Dejittering replaces them
  by a straight line at a constant rate; the filter predicts over the real time steps, and
  its gap rule (``GapPolicy``) needs the real gaps, which a regularised clock would smear.

Samples that are NaN stay NaN (missing readings); gyro columns the filters do not read may be
absent (NaN). Channel units: angles in rad unless a channel's ``unit`` says deg, gyro rates in
rad/s or deg/s, Hall readings in V or mV; anything else is refused.

``pyxdf`` is the ``lab`` extra (``pip install 'kckf-jax[lab]'``), needed only here.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

from ._csvio import META_FILE, SessionError, _columns_for, _listing
from ._robot import Robot

XDF_FILE = "recording.xdf"
_RAD = ("", "rad", "radian", "radians")
_DEG = ("deg", "degree", "degrees")
#: Accepted channel units (lower case) -> factor to ours, per kind of channel.
_UNITS = {
    "angle": {**dict.fromkeys(_RAD, 1.0), **dict.fromkeys(_DEG, math.pi / 180.0)},
    "gyro": {**dict.fromkeys(("", "rad/s", "radians/s", "rad/sec", "rad s-1"), 1.0),
             **dict.fromkeys(("deg/s", "degrees/s", "deg/sec", "dps"), math.pi / 180.0)},
    "hall": {**dict.fromkeys(("", "v", "volt", "volts"), 1.0),
             **dict.fromkeys(("mv", "millivolt", "millivolts"), 1e-3)},
}


class XdfRecording(NamedTuple):
    """What ``read_xdf`` found: arrays in the robot's column order, float64."""

    t: np.ndarray  #: (T,) s from the first sensor sample
    gyro: np.ndarray  #: (T, 3 (n + 1)) rad/s, NaN for an absent column
    hall_v: np.ndarray  #: (T, M) V
    mocap_t: np.ndarray | None  #: (F,) s on the same clock as ``t``; None without mocap
    mocap: np.ndarray | None  #: (F, K) rad
    sensors_stream: str
    mocap_stream: str | None


class _Stream(NamedTuple):
    name: str
    labels: list[str]
    units: list[str]
    fmt: str
    stamps: np.ndarray
    values: object  # (S, C) array, or a list of lists for a text stream
    source_id: str = ""


def read_xdf(file: str, robot: Robot, mocap_columns: Mapping[str, str],
             xdf_streams: Mapping[str, str], context: str) -> XdfRecording:
    """The sensors and (if a stream holds it) the motion capture of an XDF recording.

    Args:
        file: the ``recording.xdf``.
        robot: the joint layout (which labels to look for).
        mocap_columns: our angle name -> its channel label (may be empty).
        xdf_streams: ``{"sensors": NAME, "mocap": NAME}`` (either optional) picking streams.
        context: what the robot is, for the messages.

    Raises:
        SessionError: pyxdf missing, not an XDF file, no stream (or several) matching, a
            required label missing from the best match, a unit it cannot convert, a time stamp
            that does not increase, an infinite sample; one line naming the file and stream.
    """
    streams = _load(file)
    used = set(robot.used_gyro_columns)
    required = (*robot.used_gyro_columns, *robot.hall_names)
    sensors = _choose(file, streams, "sensors", required, {}, xdf_streams.get("sensors"))
    if sensors is None:
        raise SessionError(
            f"{file}: no stream holds the sensors (channel labels {_listing(required, 3)}, as "
            f"sensors.csv's columns; {context}); the streams: {_describe(streams)}")
    optional = [n for n in robot.gyro_names if n not in used and n in sensors.labels]
    cols = _columns(file, sensors, [*required, *optional], required + tuple(optional))
    stamps = _stamps(file, sensors)
    t0 = stamps[0]
    nan = np.full(stamps.shape, np.nan)
    gyro = np.stack([cols.get(n, nan) for n in robot.gyro_names], axis=1)
    hall_v = np.stack([cols[n] for n in robot.hall_names], axis=1)

    mocap = _choose(file, streams, "mocap", robot.angle_names, mocap_columns,
                    xdf_streams.get("mocap"))
    if mocap is None:
        return XdfRecording(stamps - t0, gyro, hall_v, None, None, sensors.name, None)
    labels = _columns_for(f"{file}, stream {mocap.name!r}", robot.angle_names, mocap.labels,
                          mocap_columns, context)
    mcols = _columns(file, mocap, labels, robot.angle_names)
    angles = np.stack([mcols[n] for n in robot.angle_names], axis=1)
    return XdfRecording(stamps - t0, gyro, hall_v, _stamps(file, mocap) - t0, angles,
                        sensors.name, mocap.name)


def xdf_streams_of(meta: Mapping, meta_path: str) -> dict[str, str]:
    """``meta.json``'s ``xdf_streams`` validated (``{}`` when absent)."""
    picks = meta.get("xdf_streams", {})
    if not isinstance(picks, dict) or not set(picks) <= {"sensors", "mocap"} or not all(
            isinstance(v, str) and v for v in picks.values()):
        raise SessionError(
            f"{meta_path}: 'xdf_streams' must be an object like {{\"sensors\": \"stream name\", "
            f"\"mocap\": \"stream name\"}} (either key optional), got {picks!r}")
    return dict(picks)


def _load(file: str) -> list[_Stream]:
    # pyxdf is the optional ``lab`` extra: imported here, when an XDF file is read, so that
    # CSV sessions need nothing more.
    try:
        import pyxdf
    except ImportError:
        raise SessionError(
            f"{file}: reading XDF needs pyxdf: pip install 'kckf-jax[lab]'") from None
    # The magic bytes first: pyxdf leaves the file open when they are wrong.
    try:
        with open(file, "rb") as f:
            magic = f.read(4)
    except OSError as e:
        raise SessionError(f"{file}: cannot read ({e.strerror})") from None
    if magic != b"XDF:":
        raise SessionError(f"{file}: not an XDF file (it starts with {magic!r}, an XDF file "
                           "with b'XDF:')")
    try:
        raw, _ = pyxdf.load_xdf(file, synchronize_clocks=True, dejitter_timestamps=False)
    except Exception as e:  # noqa: BLE001 (pyxdf raises OSError, ValueError, XML and struct errors)
        reason = " ".join(f"{type(e).__name__}: {e}".split())
        raise SessionError(f"{file}: not a readable XDF file ({reason})") from None
    return [_stream(s) for s in raw]


def _stream(raw: dict) -> _Stream:
    info = raw.get("info", {})
    listing = _first(_first(info, "desc"), "channels")  # desc/channels/channel[]
    channels = listing.get("channel", []) if isinstance(listing, dict) else []
    labels = [str(_first(c, "label") or "").strip() for c in channels]
    units = [str(_first(c, "unit") or "").strip() for c in channels]
    return _Stream(str(_first(info, "name") or ""), labels, units,
                   str(_first(info, "channel_format") or ""),
                   np.asarray(raw.get("time_stamps", ()), dtype=np.float64),
                   raw.get("time_series", []), str(_first(info, "source_id") or ""))


def _first(d, key):
    """``d[key][0]`` of pyxdf's nested dicts of lists, or None."""
    v = d.get(key) if isinstance(d, dict) else None
    return v[0] if isinstance(v, list) and v else None


def _choose(file: str, streams: list[_Stream], kind: str, names: Sequence[str],
            mapping: Mapping[str, str], pick: str | None) -> _Stream | None:
    """The stream holding ``names``: the one ``xdf_streams`` names, else the only one with
    all of them; None when no stream has any of them; one-line errors otherwise. Our own
    estimates recorded alongside (``kckf stream --sink lsl://``: source id ``kckf-...``,
    the angles' labels) are never taken for motion capture unless ``xdf_streams`` names
    them."""

    def found(s: _Stream) -> int:
        return sum((mapping.get(n) in s.labels) or (n in s.labels) for n in names)

    if pick is not None:
        named = [s for s in streams if s.name == pick]
        if len(named) != 1:
            what = "no stream" if not named else f"{len(named)} streams"
            raise SessionError(
                f"{file}: {what} named {pick!r} ({META_FILE}'s xdf_streams.{kind}); the "
                f"streams: {_describe(streams)}")
        return named[0]
    streams = [s for s in streams if not s.source_id.startswith("kckf-")]
    full = [s for s in streams if found(s) == len(names)]
    if len(full) > 1:
        raise SessionError(
            f"{file}: {len(full)} streams hold the {kind} ({_listing([s.name for s in full])}); "
            f'name one in {META_FILE}: "xdf_streams": {{"{kind}": "<stream name>"}}')
    if full:
        return full[0]
    best = max(streams, key=found, default=None)
    if best is None or found(best) == 0:
        return None
    return best  # a partial match: the caller names the first missing label


def _columns(file: str, s: _Stream, labels: Sequence[str], ours: Sequence[str]
             ) -> dict[str, np.ndarray]:
    """Channels ``labels`` of stream ``s`` as float64, converted to our units, keyed by
    ``ours``."""
    where = f"{file}, stream {s.name!r}"
    if s.fmt == "string":
        raise SessionError(f"{where}: holds text (channel_format string), expected numbers")
    values = np.asarray(s.values)
    if values.ndim != 2 or values.shape[1] != len(s.labels):
        raise SessionError(f"{where}: {len(s.labels)} channel labels in its header for "
                           f"{values.shape[-1] if values.ndim == 2 else 0} channels of samples")
    if values.shape[0] == 0:
        raise SessionError(f"{where}: no samples")
    out = {}
    for label, name in zip(labels, ours):
        if label not in s.labels:
            more = [n for n in labels if n not in s.labels]
            raise SessionError(
                f"{where}: no channel labelled {label!r}"
                + (f" (and {len(more) - 1} more)" if len(more) > 1 else "")
                + f"; its labels: {_listing(s.labels)}")
        if s.labels.count(label) > 1:
            raise SessionError(f"{where}: channel label {label!r} appears more than once")
        j = s.labels.index(label)
        kind = "angle" if name.startswith(("theta", "phi")) else name[:4]
        factor = _UNITS[kind].get(s.units[j].lower())
        if factor is None:
            ours_unit = {"angle": "rad", "gyro": "rad/s", "hall": "V"}[kind]
            raise SessionError(
                f"{where}, channel {label!r}: unit {s.units[j]!r}, expected one of "
                f"{', '.join(u for u in _UNITS[kind] if u)} (no unit means {ours_unit})")
        col = values[:, j].astype(np.float64)
        if factor != 1.0:
            col = col * factor
        bad = np.flatnonzero(np.isinf(col))
        if bad.size:
            raise SessionError(f"{where}, channel {label!r}, sample {int(bad[0]) + 1}: "
                               f"{float(col[bad[0]])!r}, expected a finite number (NaN for a "
                               "missing reading)")
        out[name] = col
    return out


def _stamps(file: str, s: _Stream) -> np.ndarray:
    stamps = s.stamps
    bad = np.flatnonzero(~np.isfinite(stamps))
    if bad.size:
        raise SessionError(f"{file}, stream {s.name!r}, sample {int(bad[0]) + 1}: time stamp "
                           f"{float(stamps[bad[0]])!r}, expected a finite time (s)")
    back = np.flatnonzero(np.diff(stamps) <= 0.0)
    if back.size:
        k = int(back[0]) + 1
        raise SessionError(
            f"{file}, stream {s.name!r}, sample {k + 1}: time stamp {float(stamps[k])!r} is not "
            f"after the previous sample's {float(stamps[k - 1])!r}; time stamps must be "
            "strictly increasing")
    return stamps


def _describe(streams: list[_Stream]) -> str:
    """Each stream in brief, for a message: name, channel count and first labels."""
    if not streams:
        return "none"
    return "; ".join(
        f"{s.name!r} ({len(s.labels)} channels: {_listing(s.labels, 3)})" for s in streams)
