"""A small XDF writer for the tests, written from the XDF 1.0 specification
(https://github.com/sccn/xdf/wiki/Specifications), so that the readers are tested against
files made independently of the library that reads them.

The layout: the magic bytes ``XDF:``, then chunks. A chunk is a variable-length integer
(one byte saying how many bytes follow: 1, 4 or 8; then the little-endian length, which
counts the tag and the content), a 2-byte tag and the content:

* 1 FileHeader: XML ``<info><version>1.0</version></info>``;
* 2 StreamHeader: the stream id (uint32) and XML: name, type, channel_count, nominal_srate,
  channel_format, and ``desc/channels/channel`` with each channel's label, unit and type;
* 3 Samples: the stream id, a variable-length sample count, then per sample a timestamp flag
  byte (8: a double follows; 0: the stamp is the previous one plus ``1 / nominal_srate``) and
  the values, little-endian (a string value is a variable-length byte count and UTF-8 bytes);
* 4 ClockOffset: the stream id, the collection time and the offset value (doubles);
* 6 StreamFooter: the stream id and XML with first/last timestamp, sample count and the clock
  offsets.

``write_xdf`` returns where each chunk starts and ends, so that a test can cut the file at a
chosen place, as a recorder that crashed leaves it.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from xml.sax.saxutils import escape

import numpy as np

FORMATS = {"float32": "<f4", "double64": "<f8", "int8": "<i1", "int16": "<i2", "int32": "<i4",
           "int64": "<i8"}


@dataclass
class XdfStream:
    """One stream to write: ``values`` (S, C) (a list of lists of str for ``string``)."""

    name: str
    labels: Sequence[str]
    stamps: np.ndarray
    values: object
    fmt: str = "double64"
    units: Sequence[str] | None = None
    type: str = "Misc"
    srate: float = 0.0
    #: (collection time, offset) pairs: this stream's clock + offset = the recorder's clock.
    clock_offsets: Sequence[tuple[float, float]] = ()
    #: samples per Samples chunk.
    chunk: int = 100
    #: leave out a stamp that is exactly the previous one plus 1 / srate (flag byte 0).
    deduce_stamps: bool = False
    extra_desc: str = ""
    header_channels: int | None = None  # channel_count to claim, if not the real one


def varlen(n: int) -> bytes:
    """A variable-length integer: the byte count (1, 4 or 8), then the value."""
    if n < 256:
        return b"\x01" + struct.pack("<B", n)
    if n < 2**32:
        return b"\x04" + struct.pack("<I", n)
    return b"\x08" + struct.pack("<Q", n)


def chunk(tag: int, content: bytes) -> bytes:
    return varlen(len(content) + 2) + struct.pack("<H", tag) + content


def _header_xml(s: XdfStream) -> bytes:
    units = s.units if s.units is not None else [""] * len(s.labels)
    channels = "".join(
        f"<channel><label>{escape(label)}</label><unit>{escape(unit)}</unit>"
        f"<type>{escape(s.type)}</type></channel>" for label, unit in zip(s.labels, units))
    count = s.header_channels if s.header_channels is not None else len(s.labels)
    return (
        '<?xml version="1.0"?><info>'
        f"<name>{escape(s.name)}</name><type>{escape(s.type)}</type>"
        f"<channel_count>{count}</channel_count><nominal_srate>{s.srate!r}</nominal_srate>"
        f"<channel_format>{s.fmt}</channel_format><source_id>{escape(s.name)}-src</source_id>"
        f"<version>1.1</version><created_at>0</created_at><uid>{escape(s.name)}-uid</uid>"
        f"<desc><channels>{channels}</channels>{s.extra_desc}</desc></info>"
    ).encode()


def _samples(s: XdfStream, start: int, stop: int, previous: float | None) -> bytes:
    out = [varlen(stop - start)]
    tdiff = 1.0 / s.srate if s.srate > 0 else 0.0
    for k in range(start, stop):
        stamp = float(s.stamps[k])
        if s.deduce_stamps and previous is not None and previous + tdiff == stamp:
            out.append(b"\x00")
        else:
            out.append(b"\x08" + struct.pack("<d", stamp))
        previous = stamp
        if s.fmt == "string":
            for v in s.values[k]:
                raw = str(v).encode()
                out.append(varlen(len(raw)) + raw)
        else:
            out.append(np.asarray(s.values[k], dtype=FORMATS[s.fmt]).tobytes())
    return b"".join(out)


def write_xdf(path, streams: Sequence[XdfStream], *, offsets_with_samples: bool = False
              ) -> list[tuple[int, int, int, int]]:
    """Write ``streams`` (stream ids 1, 2, ...) to ``path``: header chunks, then the samples
    in chunks interleaved across streams, the clock offsets, then the footers.

    ``offsets_with_samples``: each stream's k-th clock offset right after its k-th Samples
    chunk, as LabRecorder writes them while it records (every few seconds), instead of all
    after the samples.

    Returns:
        ``(start, end, tag, stream id)`` of every chunk (stream id 0 for the file header), in
        bytes from the start of the file (the tests cut files at these places).
    """
    parts = [(1, 0, chunk(1, b'<?xml version="1.0"?><info><version>1.0</version></info>'))]
    for sid, s in enumerate(streams, start=1):
        parts.append((2, sid, chunk(2, struct.pack("<I", sid) + _header_xml(s))))
    per_stream = []
    for sid, s in enumerate(streams, start=1):
        chunks, previous = [], None
        for a in range(0, len(s.stamps), s.chunk):
            b = min(a + s.chunk, len(s.stamps))
            chunks.append((3, sid, chunk(3, struct.pack("<I", sid)
                                          + _samples(s, a, b, previous))))
            previous = float(s.stamps[b - 1])
        offsets = [(4, sid, chunk(4, struct.pack("<Idd", sid, when, value)))
                   for when, value in s.clock_offsets]
        if offsets_with_samples:
            merged = []
            for k, c in enumerate(chunks):
                merged += [c, *offsets[k:k + 1]]
            chunks, offsets = merged + offsets[len(chunks):], []
        per_stream.append((chunks, offsets))
    for i in range(max((len(c) for c, _ in per_stream), default=0)):  # interleaved, as recorded
        parts.extend(c[i] for c, _ in per_stream if i < len(c))
    for _, offsets in per_stream:
        parts.extend(offsets)
    for sid, s in enumerate(streams, start=1):
        n = len(s.stamps)
        offsets = "".join(f"<offset><time>{w!r}</time><value>{v!r}</value></offset>"
                          for w, v in s.clock_offsets)
        footer = ('<?xml version="1.0"?><info>'
                  f"<first_timestamp>{float(s.stamps[0]) if n else 0.0!r}</first_timestamp>"
                  f"<last_timestamp>{float(s.stamps[-1]) if n else 0.0!r}</last_timestamp>"
                  f"<sample_count>{n}</sample_count>"
                  f"<clock_offsets>{offsets}</clock_offsets></info>")
        parts.append((6, sid, chunk(6, struct.pack("<I", sid) + footer.encode())))
    layout, at = [], 4
    for tag, sid, raw in parts:
        layout.append((at, at + len(raw), tag, sid))
        at += len(raw)
    with open(path, "wb") as f:
        f.write(b"XDF:" + b"".join(raw for _, _, raw in parts))
    return layout
