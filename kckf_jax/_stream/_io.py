"""Where packets come from and where estimates go: sources (UDP, serial, replay), sinks
(stdout, UDP) and the loop that joins them through a ``StreamingFilter``."""

from __future__ import annotations

import json
import select
import socket
import sys
import time
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass

from ._filter import StreamingFilter
from ._packets import MAX_PACKET_BYTES, STATUSES, Packet, PacketParser


@dataclass
class Oversized:
    """What a source returns for a packet longer than its limit (its length in bytes)."""

    n_bytes: int


class Source:
    """Yields ``bytes`` (one packet each) or ``Packet``s; ``None`` on a read timeout."""

    description = ""

    def open(self) -> None: ...

    def read(self, timeout: float) -> bytes | Packet | None:
        raise NotImplementedError

    def close(self) -> None: ...


class UdpSource(Source):
    """``udp://HOST:PORT``: one datagram = one packet; a large receive buffer absorbs bursts."""

    def __init__(self, host: str, port: int, rcvbuf: int = 8 << 20,
                 max_bytes: int = MAX_PACKET_BYTES):
        self.host, self.port, self.rcvbuf, self.max_bytes = host, port, rcvbuf, max_bytes
        self.description = f"udp://{host}:{port}"
        self._buf = bytearray(max_bytes + 1)

    def open(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.rcvbuf)
        self.sock.bind((self.host, self.port))
        self.rcvbuf_actual = self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        self._timeout = None

    def read(self, timeout: float):
        if timeout != self._timeout:
            self.sock.settimeout(timeout)
            self._timeout = timeout
        try:
            n, _ = self.sock.recvfrom_into(self._buf, len(self._buf), socket.MSG_TRUNC)
        except TimeoutError:
            return None
        if n > self.max_bytes:
            return Oversized(n)
        return bytes(self._buf[:n])

    def close(self) -> None:
        self.sock.close()


class SerialSource(Source):
    """``serial:///dev/ttyX?baud=B``: one line = one packet (pyserial)."""

    def __init__(self, path: str, baud: int = 115200, max_bytes: int = MAX_PACKET_BYTES):
        self.path, self.baud, self.max_bytes = path, baud, max_bytes
        self.description = f"serial://{path}?baud={baud}"
        self._pending = bytearray()

    def open(self) -> None:
        import serial  # pyserial

        self.port = serial.Serial(self.path, self.baud, timeout=0)

    def read(self, timeout: float):
        deadline = time.monotonic() + timeout
        while True:
            nl = self._pending.find(b"\n")
            if nl >= 0:
                line = bytes(self._pending[:nl]).rstrip(b"\r")
                del self._pending[: nl + 1]
                return line
            if len(self._pending) > self.max_bytes:  # a line that never ends: drop it
                n = len(self._pending)
                self._pending.clear()
                return Oversized(n)
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            ready, _, _ = select.select([self.port.fileno()], [], [], left)
            if ready:
                chunk = self.port.read(self.port.in_waiting or 1)
                if chunk:
                    self._pending.extend(chunk)

    def close(self) -> None:
        self.port.close()


class ReplaySource(Source):
    """``replay://SESSION``: the rows of a session's sensors.csv, as fast as possible or at
    the pace of their timestamps (``realtime``)."""

    def __init__(self, session, realtime: bool = False):
        self.session, self.realtime = session, realtime
        self.description = f"replay://{session.path}" + (" (real time)" if realtime else "")
        self._i = 0

    def open(self) -> None:
        self._start = time.monotonic()

    def read(self, timeout: float):
        s = self.session
        if self._i >= s.n_steps:
            raise EOFError
        i = self._i
        if self.realtime:
            wait = (s.t[i] - s.t[0]) - (time.monotonic() - self._start)
            if wait > timeout:
                time.sleep(timeout)
                return None
            if wait > 0:
                time.sleep(wait)
        self._i += 1
        return Packet(float(s.t[i]), s.gyro[i].copy(), s.hall_v[i].copy(), "ok")


def open_source(spec: str, session=None, realtime: bool = False) -> Source:
    """Parse a ``--source`` argument (``udp://``, ``serial://``, ``replay://``)."""
    url = urllib.parse.urlparse(spec)
    if url.scheme == "udp":
        if not url.hostname or not url.port:
            raise ValueError(f"--source {spec!r}: expected udp://HOST:PORT")
        return UdpSource(url.hostname, url.port)
    if url.scheme == "serial":
        query = urllib.parse.parse_qs(url.query)
        try:
            baud = int(query.get("baud", ["115200"])[0])
        except ValueError:
            raise ValueError(f"--source {spec!r}: baud must be an integer") from None
        if not url.path:
            raise ValueError(f"--source {spec!r}: expected serial:///dev/ttyX?baud=B")
        return SerialSource(url.path, baud)
    if url.scheme == "replay":
        if session is None:
            raise ValueError(f"--source {spec!r}: the session could not be read")
        return ReplaySource(session, realtime)
    raise ValueError(f"--source {spec!r}: expected udp://HOST:PORT, serial:///dev/ttyX?baud=B "
                     "or replay://SESSION")


def replay_path(spec: str) -> str | None:
    """The session folder of a ``replay://SESSION`` source, else ``None``."""
    return spec[len("replay://"):] if spec.startswith("replay://") else None


# ---------------------------------------------------------------------------- sinks
class StdoutSink:
    """JSON lines on stdout; flushed per line for live sources."""

    def __init__(self, flush: bool = True):
        self.flush = flush
        self.out = sys.stdout

    def write(self, rec: dict) -> None:
        self.out.write(json.dumps(rec) + "\n")
        if self.flush:
            self.out.flush()

    def close(self) -> None:
        self.out.flush()


class UdpSink:
    """``udp://HOST:PORT``: one JSON object per datagram."""

    def __init__(self, host: str, port: int):
        self.addr = (host, port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def write(self, rec: dict) -> None:
        try:
            self.sock.sendto(json.dumps(rec).encode(), self.addr)
        except OSError:
            pass  # a receiver that went away must not stop the filter

    def close(self) -> None:
        self.sock.close()


def open_sink(spec: str, flush: bool = True):
    if spec in ("stdout", "-"):
        return StdoutSink(flush)
    url = urllib.parse.urlparse(spec)
    if url.scheme == "udp" and url.hostname and url.port:
        return UdpSink(url.hostname, url.port)
    raise ValueError(f"--sink {spec!r}: expected stdout or udp://HOST:PORT")


# ---------------------------------------------------------------------------- loop
def run_stream(source: Source, sink, sf: StreamingFilter, parser: PacketParser, *,
               max_packets: int | None = None, idle_timeout: float | None = None,
               should_stop: Callable[[], bool] = lambda: False,
               poll_s: float = 0.1) -> dict:
    """Read, filter and write until the source ends, ``max_packets`` packets were read,
    nothing arrived for ``idle_timeout`` seconds, or ``should_stop()``. Returns the count of
    packets, of each status, and (``"faulty"``) of each column's faulty readings by kind
    (``"hall1_x_l railed": n``)."""
    import gc

    counts = {s: 0 for s in STATUSES}
    faulty: dict[str, int] = {}
    n = 0
    gc.freeze()  # everything allocated so far is long-lived: keep it out of GC pauses
    last = time.monotonic()
    while not should_stop():
        if max_packets is not None and n >= max_packets:
            break
        try:
            item = source.read(poll_s)
        except EOFError:
            break
        now = time.monotonic()
        if item is None:
            if idle_timeout is not None and now - last >= idle_timeout:
                break
            continue
        last = now
        n += 1
        if isinstance(item, Oversized):
            pkt = parser.empty("oversized", f"{item.n_bytes} bytes, limit {parser.max_bytes}")
        else:
            pkt = parser.check(item) if isinstance(item, Packet) else parser.parse(item)
        rec = sf.push(pkt)  # may name more (a sensor isolated over time)
        for name, kind in (pkt.faults or dict.fromkeys(pkt.faulty, "faulty")).items():
            key = f"{name} {kind}"
            faulty[key] = faulty.get(key, 0) + 1
        counts[rec["status"]] += 1
        sink.write(rec)
    sink.close()
    out = {"packets": n, **{k: v for k, v in counts.items() if v}}
    if faulty:
        out["faulty"] = faulty
    return out

