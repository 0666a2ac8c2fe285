"""Lab Streaming Layer (LSL): ``lsl://NAME`` as a source (a stream of sensor samples, found
by its name, one sample a packet) and as a sink (an outlet of the estimated angles, with a
marker stream of the statuses other than ``ok``).

LSL finds streams by multicast and broadcast on the local network unless its configuration
says otherwise: ``lsl_loopback_config`` writes one that keeps it on this machine, for the
caller to name in ``LSLAPICFG`` before ``pylsl`` is first used (docs/streaming.md).
"""

from __future__ import annotations

import json
import math
import os
import time

import numpy as np

from .._models._robot import Robot
from .._sessions._xdf import _UNITS
from ._packets import Packet
from ._source import Source

#: An ``lsl_api.cfg`` that keeps LSL on this machine: streams are resolved on the loopback
#: address only, and nothing is sent to the network (``lsl_loopback_config``).
LOOPBACK_CONFIG = """\
[ports]
IPv6 = disable
[multicast]
ResolveScope = machine
MachineAddresses = {127.0.0.1}
[lab]
KnownPeers = {127.0.0.1}
"""

# The channel formats of a numeric stream (liblsl's ``cf_*`` codes: float32, double64, int32,
# int16, int8, int64); 3 is ``cf_string`` and 0 ``cf_undefined``.
_NUMERIC_FORMATS = {1: "float32", 2: "double64", 4: "int32", 5: "int16", 6: "int8", 7: "int64"}


def _pylsl():
    # pylsl is the optional ``lab`` extra (its wheel bundles liblsl): imported here, on first
    # use, so that the package imports without it, and so that importing kckf_jax never loads
    # liblsl (which reads its configuration, ``LSLAPICFG``, on first use).
    try:
        import pylsl
    except (ImportError, OSError, RuntimeError) as exc:  # no pylsl, or no liblsl for it
        raise ValueError(f"lsl://: the Lab Streaming Layer needs pylsl ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0] if str(exc) else exc!r}); "
                         "pip install 'kckf-jax[lab]'") from None
    return pylsl


def lsl_loopback_config(path: str | os.PathLike) -> str:
    """Write an ``lsl_api.cfg`` that keeps the Lab Streaming Layer on this machine
    (``LOOPBACK_CONFIG``: streams resolved over 127.0.0.1 only, IPv6 off) and return its path.

    It sets nothing: LSL reads the file named by the ``LSLAPICFG`` environment variable when
    it is first used, so set that variable (in this process before ``pylsl`` is first used,
    or in the environment of the processes to start) to isolate them.

    Args:
        path: where to write the file (overwritten).

    Returns:
        ``path``, as a string.

    Example:
        >>> os.environ["LSLAPICFG"] = lsl_loopback_config("lsl_api.cfg")  # doctest: +SKIP
    """
    path = os.fspath(path)
    with open(path, "w", encoding="utf-8") as f:
        f.write(LOOPBACK_CONFIG)
    return path


def _stream_channels(info) -> tuple[list[str], list[str]]:
    """The channel labels and units of a full stream description
    (``desc/channels/channel/label`` and ``unit``)."""
    labels, units = [], []
    ch = info.desc().child("channels").child("channel")
    while not ch.empty():
        labels.append(ch.child_value("label").strip())
        units.append(ch.child_value("unit").strip())
        ch = ch.next_sibling("channel")
    return labels, units


def _who(info) -> str:
    return f"source_id {info.source_id() or '(none)'} on host {info.hostname()}"


class LslSource(Source):
    """``lsl://NAME``: the samples of a Lab Streaming Layer stream found by its name, one
    sample a packet, ``t`` its LSL timestamp.

    Args:
        name: the stream's name.
        robot: the robot layout; the stream's channel labels are ``sensors.csv`` column names:
            every used gyro column (``robot.used_gyro_columns``) and every Hall column
            (``robot.hall_names``) must be among them, the other gyro columns may be (missing
            ones are missing readings, NaN), other labels are ignored. A reading of NaN is a
            missing reading. The channel format must be numeric. Each channel's ``unit`` is
            read as in ``recording.xdf`` (``_xdf``): rad/s or deg/s, V or mV, none meaning
            rad/s and V; another unit is refused.
        allow_from: take the stream of that ``source_id`` (one robot per stream); without it,
            the first stream of that name found. Other streams of that name are named in
            ``announce`` and never opened.
        resolve_timeout: how long ``open`` looks for the stream (s).
        settle_s: once found, how long ``open`` looks on for other streams of that name (s).
            liblsl asks again about every 0.5 s and a first round can miss some answers:
            with three outlets of one name on one machine, 0.5 s found all three in 0 of 10
            tries, 0.8 s and 1 s in 10 of 10.

    The timestamps are the sender's own, as sent (no post-processing: no clock
    synchronisation, no dejittering). The filter's time step is the difference of two
    consecutive stamps, so it must be the sender's sampling interval: LSL's clock
    synchronisation would add the estimated clock offset, which it revises while the stream
    runs (steps of the offset would be steps of ``dt``), and dejittering would replace each
    stamp by a regression line over the recent ones (smoothing a real gap or a late sample
    into a wrong ``dt``). A consumer that must align the estimates with other streams does so
    afterwards, as LabRecorder's recordings do (``recording.xdf``).

    After ``open``: ``sender`` names the stream used, ``announce`` is a line for stderr
    saying which stream is used and which others of that name are not, ``n_read`` counts
    the samples read.

    Example:
        >>> source = LslSource("exoshell", Robot.from_spec("x,y,x,y"))  # doctest: +SKIP
        >>> source.open(); print(source.announce)  # doctest: +SKIP
        using LSL stream 'exoshell' (source_id exo-17 on host lab-pc)
    """

    def __init__(self, name: str, robot: Robot, allow_from: str | None = None,
                 resolve_timeout: float = 10.0, *, settle_s: float = 1.0,
                 max_buflen: int = 360):
        _pylsl()  # a missing pylsl says so here, before anything is compiled or opened
        self.name, self.robot, self.allow_from = name, robot, allow_from
        self.resolve_timeout, self.settle_s = float(resolve_timeout), float(settle_s)
        # liblsl's unit: seconds of a regular stream, hundreds of samples of an irregular one
        # (360: six minutes, or 36,000 samples) buffered while the filter falls behind.
        self.max_buflen = int(max_buflen)
        self.description = f"lsl://{name}"
        self.sender = ""
        self.announce = ""
        self.n_read = 0
        self._inlet = None

    def _resolve(self, lsl) -> list:
        """The streams named ``name``: until the wanted one is found or ``resolve_timeout``
        passed, then ``settle_s`` more to see the others of that name."""
        seen: dict = {}

        def add(infos):
            for info in infos:
                seen.setdefault(info.uid(), info)

        def found() -> bool:
            if self.allow_from is None:
                return bool(seen)
            return any(i.source_id() == self.allow_from for i in seen.values())

        deadline = time.monotonic() + self.resolve_timeout
        while not found():
            left = deadline - time.monotonic()
            if left <= 0:
                break
            # Returns as soon as one stream more than seen answers, else after ``left``.
            add(lsl.resolve_byprop("name", self.name, minimum=len(seen) + 1, timeout=left))
        if seen and self.settle_s > 0:
            add(lsl.resolve_byprop("name", self.name, minimum=1024, timeout=self.settle_s))
        return list(seen.values())

    def open(self) -> None:
        lsl = _pylsl()
        spec = f"lsl://{self.name}"
        streams = self._resolve(lsl)
        if not streams:
            cfg = os.environ.get("LSLAPICFG")
            scope = f"LSLAPICFG={cfg}" if cfg else "LSLAPICFG not set: LSL's default scope"
            raise ValueError(f"{spec}: no LSL stream named {self.name!r} found within "
                             f"{self.resolve_timeout:g} s; is the outlet running? ({scope})")
        if self.allow_from is not None:
            chosen = [i for i in streams if i.source_id() == self.allow_from]
            if not chosen:
                ids = ", ".join(repr(i.source_id()) for i in streams)
                raise ValueError(f"{spec}: no stream of source_id {self.allow_from!r} "
                                 f"(--allow-from); found source_id {ids}")
            info = chosen[0]
        else:
            info = streams[0]
        fmt = info.channel_format()
        if fmt not in _NUMERIC_FORMATS:
            kind = {3: "string", 0: "undefined"}.get(fmt, str(fmt))
            raise ValueError(f"{spec}: the stream's channel format is {kind}; expected a "
                             f"numeric one ({', '.join(_NUMERIC_FORMATS.values())})")
        others = [i for i in streams if i is not info]
        self.sender = f"{self.name} ({_who(info)})"
        self.announce = f"using LSL stream {self.name!r} ({_who(info)})"
        if others:
            n = len(others)
            self.announce += (f"; not used: {n} other stream{'s' if n > 1 else ''} of that "
                              "name (" + "; ".join(_who(i) for i in others) + ")")
        # No post-processing (``processing_flags=0``): the sender's own stamps (see the class
        # docstring). ``recover``: an outlet restarted with the same source_id is picked up.
        inlet = lsl.StreamInlet(info, max_buflen=self.max_buflen, max_chunklen=1,
                                recover=True, processing_flags=0)
        try:
            timeout = max(self.resolve_timeout, 1.0)
            try:
                full = inlet.info(timeout)  # the resolved description has no channels
                self._map(full, spec)
                inlet.open_stream(timeout)
            except RuntimeError as exc:  # pylsl's TimeoutError, LostError
                raise ValueError(f"{spec}: the stream did not answer while being opened "
                                 f"({type(exc).__name__}: {exc})") from None
        except BaseException:
            inlet.close_stream()
            del inlet
            raise
        self._inlet = inlet
        self._lost = getattr(lsl, "LostError", None) or lsl.util.LostError

    def _map(self, info, spec: str) -> None:
        """Index arrays from the stream's channels to the robot's columns (the sample is
        copied before a NaN slot: index ``C`` is a missing column), and unit factors."""
        labels, units = _stream_channels(info)
        C = info.channel_count()
        if len(labels) != C:
            raise ValueError(f"{spec}: the stream has {C} channels but {len(labels)} channel "
                             "labels (desc/channels/channel/label); label every channel with "
                             "its sensors.csv column name")
        where = {}
        for i, label in enumerate(labels):
            where.setdefault(label, i)
        shown = ", ".join(labels[:40]) + (", ..." if C > 40 else "")
        for name in self.robot.used_gyro_columns + self.robot.hall_names:
            if name not in where:
                raise ValueError(f"{spec}: the stream has no channel labelled {name!r} "
                                 f"(needed for this robot); its labels: {shown or '(none)'}")
        for name in self.robot.gyro_names + self.robot.hall_names:
            if labels.count(name) > 1:
                raise ValueError(f"{spec}: channel label {name!r} appears more than once")
        self._gyro_idx = np.array([where.get(n, C) for n in self.robot.gyro_names], np.intp)
        self._hall_idx = np.array([where[n] for n in self.robot.hall_names], np.intp)
        scale = np.ones(C + 1)
        for kind, idx in (("gyro", self._gyro_idx), ("hall", self._hall_idx)):
            for i in idx[idx < C]:
                factor = _UNITS[kind].get(units[i].lower())
                if factor is None:
                    ours = {"gyro": "rad/s", "hall": "V"}[kind]
                    raise ValueError(
                        f"{spec}, channel {labels[i]!r}: unit {units[i]!r}, expected one of "
                        f"{', '.join(u for u in _UNITS[kind] if u)} (no unit means {ours})")
                scale[i] = factor
        # Channels in other units are scaled in place: one product per sample, only if any.
        self._scale = None if np.all(scale == 1.0) else scale[:C]
        self._row = np.full(C + 1, np.nan)  # one sample, then the NaN slot
        self._C = C

    def read(self, timeout: float) -> Packet | None:
        # One sample a call: pull_sample returns after a sample or ``timeout``, also while the
        # inlet recovers a lost outlet (liblsl 1.18's pull_chunk blocks there, past its
        # timeout, which would keep SIGINT and --idle-timeout from ending the run).
        try:
            sample, t = self._inlet.pull_sample(timeout)
        except self._lost:  # lost and not recoverable (an outlet without a source_id)
            raise EOFError from None
        if t is None:
            return None
        self.n_read += 1
        row = self._row
        row[: self._C] = sample
        if self._scale is not None:
            row[: self._C] *= self._scale
        return Packet(float(t), row[self._gyro_idx], row[self._hall_idx], "ok")

    def close(self) -> None:
        if self._inlet is not None:
            self._inlet.close_stream()
            self._inlet = None  # destroys the liblsl inlet


class LslSink:
    """``lsl://NAME``: an LSL outlet of the estimated angles, and one of the statuses.

    Args:
        name: the outlet's name (its ``source_id`` is ``kckf-NAME``).
        robot: the robot layout; one channel per angle, labelled as in ``mocap.csv``
            (``robot.angle_names``), unit ``rad``, type ``angle``; ``cf_double64``, irregular
            rate (stream type ``Angles``).
        linger_s: on ``close``, how long to leave the outlets up for consumers to receive
            what was pushed (liblsl drops what it has not sent when an outlet goes) (s).

    ``write`` pushes the angles of every used packet (``ok``, ``masked``, ``gap``; NaN for an
    angle the record does not have), stamped with the packet's time, and for every status
    other than ``ok`` one marker on ``NAME-status`` (type ``Markers``, one string channel,
    ``source_id`` ``kckf-NAME-status``): ``{"t": t, "status": s, "note": note}`` as JSON,
    stamped with the packet's time, or with ``local_clock()`` when it has none. It never
    raises: a consumer gone must not stop the filter (``n_failed`` counts failed pushes).
    LSL takes a stamp of exactly 0.0 for "now": a packet time of 0.0 is sent as the smallest
    positive double (5e-324) instead.

    Example:
        >>> sink = LslSink("exoshell-angles", Robot.from_spec("x,y,x,y"))  # doctest: +SKIP
        >>> sink.write({"t": 12.5, "theta1_x": 0.1, "status": "ok"})  # doctest: +SKIP
    """

    def __init__(self, name: str, robot: Robot, *, linger_s: float = 0.2):
        lsl = _pylsl()
        self.name, self.robot, self.linger_s = name, robot, float(linger_s)
        self.description = f"lsl://{name}"
        self.names = robot.angle_names
        self.n_failed = 0
        info = lsl.StreamInfo(name, "Angles", len(self.names), lsl.IRREGULAR_RATE,
                              lsl.cf_double64, f"kckf-{name}")
        channels = info.desc().append_child("channels")
        for n in self.names:
            ch = channels.append_child("channel")
            ch.append_child_value("label", n)
            ch.append_child_value("unit", "rad")
            ch.append_child_value("type", "angle")
        status = lsl.StreamInfo(f"{name}-status", "Markers", 1, lsl.IRREGULAR_RATE,
                                lsl.cf_string, f"kckf-{name}-status")
        self._outlet = lsl.StreamOutlet(info)
        self._status = lsl.StreamOutlet(status)
        self._clock = lsl.local_clock

    def write(self, rec: dict) -> None:
        try:
            t, status = rec.get("t"), rec.get("status")
            stamp = None
            if isinstance(t, int | float) and not isinstance(t, bool) and math.isfinite(t):
                stamp = float(t) or 5e-324  # 0.0 would be "now" to LSL
            if status in ("ok", "masked", "gap") and stamp is not None:
                self._outlet.push_sample([rec.get(n, math.nan) for n in self.names], stamp)
            if status != "ok":
                marker = {"t": t if stamp is not None else None, "status": status,
                          "note": rec.get("note", "")}
                self._status.push_sample([json.dumps(marker)],
                                         stamp if stamp is not None else self._clock())
        except Exception:  # a consumer gone, a closed sink: never stop the filter
            self.n_failed += 1

    def close(self) -> None:
        outlets = [o for o in (getattr(self, "_outlet", None), getattr(self, "_status", None))
                   if o is not None]
        try:
            if self.linger_s > 0 and any(o.have_consumers() for o in outlets):
                time.sleep(self.linger_s)
        except Exception:
            pass
        self._outlet = self._status = None  # destroys the liblsl outlets
