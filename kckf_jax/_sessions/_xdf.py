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

A file cut short (a recorder that crashed or lost power: the commonest defect of XDF files)
is found by walking its chunks before pyxdf reads it (``_walk``: each chunk's length and tag,
not its samples): where the last whole chunk ends, and which streams have their footer, which
a recorder writes when it closes the file. pyxdf is then given the whole chunks only, so that
a cut anywhere (in a chunk's length, a Samples chunk, a ClockOffset chunk, a footer, after the
samples) reads the same way: every whole Samples chunk, and one note (``XdfRecording.notes``,
a warning of ``read_session``) that says where the file stops and what was kept. A stream whose
clock offsets all lie beyond the cut is not put on the others' clock: as motion capture it is
not used (said in the note). A cut before the first sensor sample is refused, saying so.

An empty motion-capture stream (no samples) is no motion capture, said in a note; the commands
that need motion capture refuse the session naming the stream (``XdfRecording.mocap_absent``).

pyxdf's own log records (its progress and clock notes) are not printed while it reads
(``_pyxdf_log``); those that say it skipped over a damaged part of the file become one note.
Where ``kckf_jax``'s logger is at DEBUG (``kckf --debug``), they go out as pyxdf sends them.

``pyxdf`` is the ``lab`` extra (``pip install 'kckf-jax[lab]'``), needed only here.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import os
from collections.abc import Iterator, Mapping, Sequence
from typing import NamedTuple

import numpy as np

from .._models._robot import Robot
from ._csvio import META_FILE, SessionError, _columns_for, _listing

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
    #: what a reader should be told, one line each (a file cut short, an empty mocap stream).
    notes: tuple[str, ...] = ()
    #: why a motion-capture stream that exists gives no motion capture ("" when none exists):
    #: the start of the error of a command that needs motion capture.
    mocap_absent: str = ""
    #: the unit each angle channel of the mocap stream is written in (``rad`` or ``deg``).
    mocap_units: tuple[str, ...] = ()


class _Stream(NamedTuple):
    name: str
    labels: list[str]
    units: list[str]
    fmt: str
    stamps: np.ndarray
    values: object  # (S, C) array, or a list of lists for a text stream
    source_id: str = ""
    sid: int = 0  # the stream id in the file
    offsets: int = 0  # ClockOffset chunks read


class _Walk(NamedTuple):
    """An XDF file's chunk structure (lengths and tags; the samples are not read)."""

    size: int  #: bytes in the file
    whole: int  #: bytes up to the end of the last whole chunk (``size`` when none is cut)
    cut: str  #: what the cut chunk at ``whole`` was, in words ("" when none is)
    damaged: bool  #: a chunk length that no writer writes: pyxdf scans forward past it
    footers: frozenset[int]  #: the stream ids that have their footer
    headers: frozenset[int]  #: the stream ids whose header is whole

    @property
    def truncated(self) -> bool:
        """Cut inside a chunk, a stream without its footer or no stream at all: a file that
        was not closed (a recorder writes every stream's footer when it closes the file)."""
        return not self.damaged and bool(self.cut or not self.headers
                                         or self.headers - self.footers)


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
    streams, walk, damage = _load(file)
    used = set(robot.used_gyro_columns)
    required = (*robot.used_gyro_columns, *robot.hall_names)
    sensors = _choose(file, streams, "sensors", required, {}, xdf_streams.get("sensors"))
    if sensors is None:
        if walk.cut or not walk.headers:
            raise SessionError(f"{_cut_words(file, walk, streams)}, before the sensors' stream "
                               "and its samples: nothing usable remains (the whole chunks hold "
                               f"the streams: {_describe(streams)})")
        raise SessionError(
            f"{file}: no stream holds the sensors (channel labels {_listing(required, 3)}, as "
            f"sensors.csv's columns; {context}); the streams: {_describe(streams)}")
    if not len(sensors.stamps) and walk.truncated:
        raise SessionError(f"{_cut_words(file, walk, streams)}, before the first whole Samples "
                           f"chunk of the sensors' stream {sensors.name!r}: nothing usable "
                           "remains")
    optional = [n for n in robot.gyro_names if n not in used and n in sensors.labels]
    cols = _columns(file, sensors, [*required, *optional], required + tuple(optional))
    stamps = _stamps(file, sensors)
    t0 = stamps[0]
    nan = np.full(stamps.shape, np.nan)
    gyro = np.stack([cols.get(n, nan) for n in robot.gyro_names], axis=1)
    hall_v = np.stack([cols[n] for n in robot.hall_names], axis=1)
    kept = [f"sensors stream {sensors.name!r}: {len(stamps):,} samples, t 0 to "
            f"{stamps[-1] - t0:.3f} s"]
    notes = [damage] if damage else []

    def without(absent: str, said: str) -> XdfRecording:
        """The recording without motion capture: ``absent`` says why (the start of the error
        of a command that needs it), ``said`` what the reader is told."""
        if walk.truncated:
            notes.append(_cut_note(file, walk, streams, [*kept, said] if said else kept))
        elif said:
            notes.append(f"{absent}: {said}")
        return XdfRecording(stamps - t0, gyro, hall_v, None, None, sensors.name, None,
                            tuple(notes), absent)

    mocap = _choose(file, streams, "mocap", robot.angle_names, mocap_columns,
                    xdf_streams.get("mocap"))
    if mocap is None:
        return without("", "")
    where = f"{file}, stream {mocap.name!r}"
    if not len(mocap.stamps):
        if walk.truncated:
            return without(f"{where}: no samples before the file ends (byte {walk.size:,}: it was "
                           "not closed)",
                           f"motion-capture stream {mocap.name!r}: no samples (not used)")
        return without(f"{where}: no samples",
                       "the motion-capture stream is empty, so it gives no motion capture")
    if walk.truncated and not (mocap.offsets and sensors.offsets):
        lacking = [x.name for x in (sensors, mocap) if not x.offsets]
        which = (f"stream {lacking[0]!r} has" if len(lacking) == 1
                 else f"streams {lacking[0]!r} and {lacking[1]!r} have")
        return without(f"{where}: not on the sensors' clock (the file ends at byte "
                       f"{walk.size:,}, before the clock offsets: {which} none)",
                       f"motion-capture stream {mocap.name!r} not used ({which} no clock "
                       "offsets before the file ends, so the two streams' time stamps cannot "
                       "be put on one clock)")
    labels = _columns_for(where, robot.angle_names, mocap.labels, mocap_columns, context)
    mcols = _columns(file, mocap, labels, robot.angle_names)
    angles = np.stack([mcols[n] for n in robot.angle_names], axis=1)
    mocap_t = _stamps(file, mocap) - t0
    units = tuple("deg" if _UNITS["angle"].get(mocap.units[mocap.labels.index(label)].lower())
                  != 1.0 else "rad" for label in labels)
    if walk.truncated:
        kept.append(f"motion-capture stream {mocap.name!r}: {len(mocap_t):,} samples to t "
                    f"{mocap_t[-1]:.3f} s")
        notes.append(_cut_note(file, walk, streams, kept))
    return XdfRecording(stamps - t0, gyro, hall_v, mocap_t, angles, sensors.name, mocap.name,
                        tuple(notes), "", units)


def xdf_streams_of(meta: Mapping, meta_path: str) -> dict[str, str]:
    """``meta.json``'s ``xdf_streams`` validated (``{}`` when absent)."""
    picks = meta.get("xdf_streams", {})
    if not isinstance(picks, dict) or not set(picks) <= {"sensors", "mocap"} or not all(
            isinstance(v, str) and v for v in picks.values()):
        raise SessionError(
            f"{meta_path}: 'xdf_streams' must be an object like {{\"sensors\": \"stream name\", "
            f"\"mocap\": \"stream name\"}} (either key optional), got {picks!r}")
    return dict(picks)


def _load(file: str) -> tuple[list[_Stream], _Walk, str]:
    """The streams pyxdf reads from the file's whole chunks, the file's chunk structure, and a
    note ("" when none) where pyxdf skipped over a damaged part."""
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
        if magic != b"XDF:":
            raise SessionError(f"{file}: not an XDF file (it starts with {magic!r}, an XDF "
                               "file with b'XDF:')")
        walk = _walk(file)
    except OSError as e:
        raise SessionError(f"{file}: cannot read ({e.strerror})") from None
    # A cut chunk goes to pyxdf as no chunk: how it reads a cut depends on where (a cut
    # Samples chunk is skipped with a logged error, a cut length or tag raises).
    # A damaged file (a chunk length no writer writes) goes whole: pyxdf scans forward past it.
    whole = walk.whole == walk.size or walk.damaged
    source = file if whole else io.BufferedReader(_Head(file, walk.whole))
    try:
        with _pyxdf_log() as logged:
            raw, _ = pyxdf.load_xdf(source, synchronize_clocks=True,
                                    dejitter_timestamps=False)
    except Exception as e:  # noqa: BLE001 (pyxdf raises OSError, ValueError, XML and struct errors)
        reason = " ".join(f"{type(e).__name__}: {e}".split())
        raise SessionError(f"{file}: not a readable XDF file ({reason})") from None
    finally:
        if not isinstance(source, str):
            source.close()
    errors = [" ".join(r.getMessage().split()) for r in logged if r.levelno >= logging.ERROR]
    damage = ""
    if errors:
        damage = (f"{file}: damaged: pyxdf skipped over what it could not read "
                  f"({errors[0]}{f'; {len(errors) - 1} more such places' if errors[1:] else ''}"
                  "); the samples in those parts are lost")
    return [_stream(s) for s in raw], walk, damage


#: XDF chunk tags (the specification's), in words.
_TAGS = {1: "the file header", 2: "a stream header", 3: "a Samples chunk",
         4: "a ClockOffset chunk", 5: "a Boundary chunk", 6: "a stream footer"}


def _walk(file: str) -> _Walk:
    """The file's chunks, read by their lengths and tags alone (a seek over each chunk)."""
    size = os.path.getsize(file)
    headers, footers = set(), set()
    with open(file, "rb") as f:
        pos = 4  # after the magic bytes

        def stop(cut: str = "", damaged: bool = False) -> _Walk:
            return _Walk(size, pos, cut, damaged, frozenset(footers), frozenset(headers))

        f.seek(pos)
        while pos < size:
            head = f.read(9)  # the length's byte count and the length, at most 9 bytes
            n = head[0]
            if n not in (1, 4, 8):
                return stop(damaged=True)
            if len(head) < 1 + n:
                return stop("a chunk's length")
            length = int.from_bytes(head[1:1 + n], "little")
            if length < 2:
                return stop(damaged=True)
            end = pos + 1 + n + length
            f.seek(pos + 1 + n)
            body = f.read(min(length, 6))
            tag = int.from_bytes(body[:2], "little") if len(body) >= 2 else 0
            sid = int.from_bytes(body[2:6], "little") if len(body) == 6 else None
            if end > size:
                what = _TAGS.get(tag, "a chunk")
                if sid is not None and tag in (2, 3, 4, 6):
                    what += f" of stream id {sid}"
                return stop(what)
            if tag == 2 and sid is not None:
                headers.add(sid)
            elif tag == 6 and sid is not None:
                footers.add(sid)
            pos = end
            f.seek(pos)
        return stop("the file header" if size == 4 else "")  # the magic bytes alone: cut


class _Head(io.RawIOBase):
    """The first ``limit`` bytes of a file, as a file (pyxdf reads a file object as a file)."""

    def __init__(self, file: str, limit: int):
        self._f = open(file, "rb", buffering=0)  # closed by close()
        self._limit = limit

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def readinto(self, b) -> int:
        n = max(0, min(len(b), self._limit - self._f.tell()))
        return self._f.readinto(memoryview(b)[:n]) if n else 0

    def seek(self, pos: int, whence: int = io.SEEK_SET) -> int:
        if whence == io.SEEK_END:
            pos, whence = self._limit + pos, io.SEEK_SET
        return self._f.seek(pos, whence)

    def tell(self) -> int:
        return self._f.tell()

    def close(self) -> None:
        self._f.close()
        super().close()


class _Keep(logging.Handler):
    def __init__(self, records: list):
        super().__init__(logging.WARNING)
        self.records = records

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@contextlib.contextmanager
def _pyxdf_log() -> Iterator[list[logging.LogRecord]]:
    """pyxdf's log records of WARNING and above while it reads, kept (and yielded), not
    printed; its logger (``pyxdf``, the parent of pyxdf's own) restored after. With
    ``kckf_jax``'s logger at DEBUG (``kckf --debug``) they are kept and also go out as pyxdf
    sends them (its level and propagation untouched)."""
    logger = logging.getLogger("pyxdf")
    records: list[logging.LogRecord] = []
    keep = _Keep(records)
    quiet = not logging.getLogger("kckf_jax").isEnabledFor(logging.DEBUG)
    level, propagate = logger.level, logger.propagate
    logger.addHandler(keep)
    if quiet:
        logger.setLevel(logging.WARNING)
        logger.propagate = False
    try:
        yield records
    finally:
        logger.removeHandler(keep)
        logger.setLevel(level)
        logger.propagate = propagate


def _cut_words(file: str, walk: _Walk, streams: list[_Stream]) -> str:
    """Where the file stops, for a message: ``FILE: cut short at byte N (inside ...)``."""
    if walk.cut:
        names = {s.sid: s.name for s in streams}
        cut = walk.cut
        for sid, name in names.items():  # name the stream where its header was read
            if cut.endswith(f" of stream id {sid}"):
                cut = cut.removesuffix(f"id {sid}") + repr(name)
        return (f"{file}: cut short at byte {walk.size:,} (inside {cut}; the whole chunks end "
                f"at byte {walk.whole:,})")
    lacking = [s.name for s in streams if s.sid in walk.headers - walk.footers]
    if not lacking:
        return f"{file}: ends at byte {walk.size:,} with no stream in it"
    return (f"{file}: ends at byte {walk.size:,} without the footer of stream"
            f"{'s' if len(lacking) > 1 else ''} {_listing(lacking, 4)}")


def _cut_note(file: str, walk: _Walk, streams: list[_Stream], kept: list[str]) -> str:
    return (f"{_cut_words(file, walk, streams)}: a recording that was not closed (a recorder "
            f"that crashed?); read the whole chunks: {'; '.join(kept)}")


def _stream(raw: dict) -> _Stream:
    info = raw.get("info", {})
    listing = _first(_first(info, "desc"), "channels")  # desc/channels/channel[]
    channels = listing.get("channel", []) if isinstance(listing, dict) else []
    labels = [str(_first(c, "label") or "").strip() for c in channels]
    units = [str(_first(c, "unit") or "").strip() for c in channels]
    return _Stream(str(_first(info, "name") or ""), labels, units,
                   str(_first(info, "channel_format") or ""),
                   np.asarray(raw.get("time_stamps", ()), dtype=np.float64),
                   raw.get("time_series", []), str(_first(info, "source_id") or ""),
                   int(info.get("stream_id", 0) or 0), len(raw.get("clock_times", ())))


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
