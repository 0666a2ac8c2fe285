"""Where packets come from and where estimates go: sources (UDP, serial, replay, LSL), sinks
(stdout, UDP, LSL) and the loop that joins them through a ``StreamingFilter``.

One robot per stream: a source that can hear several senders (UDP) takes packets from one,
the first it hears or those ``allow_from`` names; any other sender's packet comes back as
``Foreign`` and gets the status ``foreign``. A robot that restarts comes back from the same
host on a new port: once its sender has been silent for ``handover_s``, the UDP source takes
the new port as the same robot (``Handover``) and the loop restarts the filter if the robot's
clock started again. What the operating system dropped before the source could read it is
``Source.dropped`` (UDP on Linux: the socket's overflow count)."""

from __future__ import annotations

import json
import math
import os
import select
import socket
import struct
import sys
import time
import urllib.parse
from collections.abc import Callable, Sequence

from ._filter import StreamingFilter
from ._packets import MAX_PACKET_BYTES, STATUSES, USED, Packet, PacketParser
from ._source import Foreign, Handover, Oversized, Source

#: Linux's socket option that adds the count of datagrams dropped so far to each one received.
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40 if sys.platform.startswith("linux") else None)
#: Linux's socket option that stamps each datagram with the time it arrived (a ``struct
#: timeval`` of the wall clock): a sender's silence is measured between arrivals, whatever
#: the reader was doing meanwhile.
SO_TIMESTAMP = getattr(socket, "SO_TIMESTAMP", 29 if sys.platform.startswith("linux") else None)
_TIMEVAL = struct.Struct("@ll")


def arrival_time(anc) -> float | None:
    """The arrival time (s, wall clock) in a datagram's ancillary data (``SO_TIMESTAMP``),
    else None."""
    for level, kind, data in anc:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMP and len(data) >= _TIMEVAL.size:
            sec, usec = _TIMEVAL.unpack(data[:_TIMEVAL.size])
            return sec + 1e-6 * usec
    return None


def parse_allow_from(values: Sequence[str] | None) -> list[tuple[str, int | None]] | None:
    """``--allow-from HOST[:PORT]`` values as ``(address, port or None)``; a host name is
    looked up once, here. ``None`` when none were given."""
    if not values:
        return None
    out = []
    for v in values:
        host, sep, port = v.rpartition(":")
        if not sep:
            host, port = v, ""
        try:
            number = int(port) if port else None
            if number is not None and not 0 < number < 65536:
                raise ValueError
        except ValueError:
            raise ValueError(f"--allow-from {v!r}: expected HOST or HOST:PORT, PORT 1-65535")\
                from None
        try:
            address = socket.gethostbyname(host)
        except OSError:
            raise ValueError(f"--allow-from {v!r}: cannot resolve host {host!r}") from None
        out.append((address, number))
    return out


class UdpSource(Source):
    """``udp://HOST:PORT``: one datagram = one packet; a large receive buffer absorbs bursts.

    Packets are taken from one sender: those ``allow_from`` names (``(address, port or
    None)``, ``parse_allow_from``), else the first heard (``on_sender(sender)`` is told);
    another sender's packet is returned as ``Foreign`` unread.

    Handover (without ``allow_from``): a packet from another port of the sender's host, once
    the sender has been silent for ``handover_s`` seconds or more (a restarted robot's new
    socket), makes that port the sender: ``on_handover(previous, sender, silence_s)`` is
    told, it is returned as a ``Handover`` and the previous port's packets are ``Foreign``
    from then on (listed in ``handovers``). A second sender while the first is live stays
    ``Foreign``, even once the first falls silent (a port first heard before the sender's
    last packet is another sender); another host is never taken over; ``handover_s=math.inf``:
    never. The silence is measured between the datagrams' arrival times (``SO_TIMESTAMP`` on
    Linux; elsewhere when they are read), so a reader that falls behind does not shorten it.

    ``dropped``: what the kernel dropped because the receive buffer was full
    (``SO_RXQ_OVFL`` on each datagram read, and ``count_dropped``: the socket's count in
    ``/proc/net/udp``, which also has what was dropped after the last read)."""

    def __init__(self, host: str, port: int, rcvbuf: int = 8 << 20,
                 max_bytes: int = MAX_PACKET_BYTES,
                 allow_from: Sequence[tuple[str, int | None]] | None = None,
                 on_sender: Callable[[str], None] | None = None, handover_s: float = 0.5,
                 on_handover: Callable[[str, str, float], None] | None = None):
        if not handover_s >= 0:
            raise ValueError(f"handover after {handover_s!r} s: expected 0 or more (inf: never)")
        self.host, self.port, self.rcvbuf, self.max_bytes = host, port, rcvbuf, max_bytes
        self.description = f"udp://{host}:{port}"
        self._buf = bytearray(max_bytes + 1)
        self.allow_from = list(allow_from) if allow_from else None
        self.on_sender = on_sender
        self.sender: tuple[str, int] | None = None
        self.foreign = {}
        self._accepted: set[tuple[str, int]] = set()
        self.handover_s, self.on_handover = float(handover_s), on_handover
        self.handovers: list[tuple[str, str]] = []  # (previous, new) senders, in order
        self._heard = -math.inf  # when a packet of an accepted sender was last read
        self._first_foreign: dict[tuple[str, int], float] = {}  # when each was first heard

    def open(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.rcvbuf)
        self._ovfl = self._stamped = False
        if SO_RXQ_OVFL is not None:
            try:
                self.sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
                self._ovfl = True
                self.dropped = 0
            except OSError:
                pass
        if SO_TIMESTAMP is not None:
            try:
                self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMP, 1)
                self._stamped = True
            except OSError:
                pass
        self.sock.bind((self.host, self.port))
        self.rcvbuf_actual = self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        self._timeout = None
        self._inode = os.fstat(self.sock.fileno()).st_ino

    def read(self, timeout: float):
        if timeout != self._timeout:
            self.sock.settimeout(timeout)
            self._timeout = timeout
        now = None
        try:
            if self._ovfl or self._stamped:
                n, anc, _, addr = self.sock.recvmsg_into([self._buf], 128, socket.MSG_TRUNC)
                for level, kind, data in anc:
                    if level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(data) >= 4:
                        self.dropped = int.from_bytes(data[:4], sys.byteorder)
                now = arrival_time(anc)
            else:
                n, addr = self.sock.recvfrom_into(self._buf, len(self._buf), socket.MSG_TRUNC)
        except TimeoutError:
            return None
        if now is None:
            now = time.time()  # when it was read: the same clock as the arrival stamps
        if addr not in self._accepted:
            if self._takes_over(addr, now):
                previous, sender = self.handovers[-1]
                silence, self._heard = now - self._heard, now
                if self.on_handover is not None:
                    self.on_handover(previous, sender, silence)
                data = Oversized(n) if n > self.max_bytes else bytes(self._buf[:n])
                return Handover(data, sender, previous, silence)
            if not self._accept(addr):
                name = f"{addr[0]}:{addr[1]}"
                self.foreign[name] = self.foreign.get(name, 0) + 1
                self._first_foreign.setdefault(addr, now)
                return Foreign(name)
        self._heard = now
        if n > self.max_bytes:
            return Oversized(n)
        return bytes(self._buf[:n])

    def _takes_over(self, addr: tuple[str, int], now: float) -> bool:
        """Whether ``addr`` (not accepted) is the sender's host back on a new port after the
        sender's silence of ``handover_s`` or more; if so it becomes the sender."""
        old = self.sender
        if (self.allow_from is not None or old is None or addr[0] != old[0]
                or not now - self._heard >= self.handover_s
                or self._first_foreign.get(addr, math.inf) <= self._heard):
            # (the last: a port heard while the sender was still sending is another sender)
            return False
        self._accepted.discard(old)
        self._accepted.add(addr)
        self.sender = addr
        self.handovers.append((f"{old[0]}:{old[1]}", f"{addr[0]}:{addr[1]}"))
        return True

    def _accept(self, addr: tuple[str, int]) -> bool:
        if self.allow_from is not None:
            ok = any(addr[0] == h and p in (None, addr[1]) for h, p in self.allow_from)
        else:
            ok = self.sender is None
        if ok:
            self._accepted.add(addr)
            if self.sender is None:
                self.sender = addr
                if self.on_sender is not None:
                    self.on_sender(f"{addr[0]}:{addr[1]}")
        return ok

    def count_dropped(self) -> int | None:
        late = _proc_udp_drops(self._inode)
        if late is not None:
            self.dropped = max(self.dropped or 0, late)
        return self.dropped

    def close(self) -> None:
        self.sock.close()


def _proc_udp_drops(inode: int) -> int | None:
    """The ``drops`` count of the UDP socket with this inode in ``/proc/net/udp`` (Linux),
    else ``None``."""
    try:
        with open("/proc/net/udp") as f:
            lines = f.read().splitlines()[1:]
    except OSError:
        return None
    for line in lines:
        cells = line.split()
        if len(cells) >= 13 and cells[9] == str(inode):
            try:
                return int(cells[-1])
            except ValueError:
                return None
    return None


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


def open_source(spec: str, session=None, realtime: bool = False, robot=None,
                allow_from: Sequence[str] | None = None,
                on_sender: Callable[[str], None] | None = None, handover_s: float = 0.5,
                on_handover: Callable[[str, str, float], None] | None = None) -> Source:
    """Parse a ``--source`` argument (``udp://``, ``serial://``, ``replay://``, ``lsl://``).
    ``allow_from``: ``--allow-from`` (UDP: ``HOST[:PORT]``; LSL: the stream's source id);
    ``on_sender`` is told the sender a UDP source takes when none is named; ``handover_s``,
    ``on_handover``: a UDP source's handover to the sender's host on a new port after that
    much silence (``UdpSource``; ``--handover-after``); ``robot``: the layout an LSL stream's
    channel labels are matched to."""
    url = urllib.parse.urlparse(spec)
    if url.scheme == "udp":
        if not url.hostname or not url.port:
            raise ValueError(f"--source {spec!r}: expected udp://HOST:PORT")
        if not handover_s >= 0:
            raise ValueError(f"--handover-after {handover_s!r}: expected seconds, 0 or more "
                             "(inf: never)")
        return UdpSource(url.hostname, url.port, allow_from=parse_allow_from(allow_from),
                         on_sender=on_sender, handover_s=handover_s, on_handover=on_handover)
    if url.scheme == "lsl":
        name = spec[len("lsl://"):]
        if not name:
            raise ValueError(f"--source {spec!r}: expected lsl://NAME (an LSL stream's name)")
        if allow_from and len(allow_from) > 1:
            raise ValueError("--allow-from: an LSL source takes one stream: give one source id")
        from ._lsl import LslSource

        return LslSource(name, robot, allow_from=allow_from[0] if allow_from else None)
    if allow_from and url.scheme in ("serial", "replay"):
        raise ValueError(f"--allow-from: {spec} has one sender; it applies to udp:// and lsl://")
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
    raise ValueError(f"--source {spec!r}: expected udp://HOST:PORT, serial:///dev/ttyX?baud=B, "
                     "replay://SESSION or lsl://NAME")


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


def open_sink(spec: str, flush: bool = True, robot=None):
    """Parse a ``--sink`` argument (``stdout``, ``udp://HOST:PORT``, ``lsl://NAME``: an outlet
    of ``robot``'s angles and the marker stream ``NAME-status``)."""
    if spec in ("stdout", "-"):
        return StdoutSink(flush)
    url = urllib.parse.urlparse(spec)
    if url.scheme == "udp" and url.hostname and url.port:
        return UdpSink(url.hostname, url.port)
    if url.scheme == "lsl" and spec[len("lsl://"):]:
        from ._lsl import LslSink

        return LslSink(spec[len("lsl://"):], robot)
    raise ValueError(f"--sink {spec!r}: expected stdout, udp://HOST:PORT or lsl://NAME")


# ---------------------------------------------------------------------------- loop
def run_stream(source: Source, sink, sf: StreamingFilter, parser: PacketParser, *,
               max_packets: int | None = None, idle_timeout: float | None = None,
               should_stop: Callable[[], bool] = lambda: False,
               poll_s: float = 0.1) -> dict:
    """Read, filter and write until the source ends, ``max_packets`` packets were read,
    nothing arrived for ``idle_timeout`` seconds, or ``should_stop()``. Returns the count of
    packets, of each status, ``"dropped"`` (what the operating system dropped before the
    source could read it, where it says: ``Source.count_dropped``), ``"handover"`` (where
    the source took its robot back on a new address, ``Handover``) and (``"faulty"``) of
    each column's faulty readings by kind (``"hall1_x_l railed": n``).

    A handover's record says so (``"handover": "HOST:OLD -> HOST:NEW"`` and its ``note``).
    The first packet after it with a usable ``t`` continues the filter when ``t`` is after
    the previous packet's (the gap policy applies to the timestamps), and otherwise (the
    restarted robot's clock started again) restarts it there: status ``gap``, ``"gap":
    "restart"``."""
    import gc

    counts = {s: 0 for s in STATUSES}
    faulty: dict[str, int] = {}
    n = n_handover = 0
    clock_check = None  # the last handover, until a packet with a usable t has followed it
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
        handover = None  # what this record says of a handover
        if isinstance(item, Handover):
            n_handover += 1
            clock_check = f"{item.previous} -> {item.sender}"
            handover = (clock_check, f"sender {item.previous} silent {item.silence_s:.2f} s; "
                                     f"taking {item.sender} (same host) as the same robot")
            item = item.data
        if isinstance(item, Oversized):
            pkt = parser.empty("oversized", f"{item.n_bytes} bytes, limit {parser.max_bytes}")
        elif isinstance(item, Foreign):
            pkt = parser.empty("foreign", f"from {item.sender}")
        else:
            pkt = parser.check(item) if isinstance(item, Packet) else parser.parse(item)
        restart = False
        if clock_check is not None and pkt.status in USED:
            t_prev = sf.t_prev
            if t_prev is not None and not pkt.t > t_prev:  # the robot's clock started again
                sf.reset()
                restart = True
                text = f"its clock started again (t = {pkt.t!r}, previous t = {t_prev!r}): " \
                       "filter restarted"
                handover = (clock_check, "; ".join(
                    (handover[1] if handover else f"after the handover {clock_check}", text)))
            clock_check = None
        rec = sf.push(pkt)  # may name more (a sensor isolated over time)
        if handover is not None:
            rec["handover"] = handover[0]
            rec["note"] = " | ".join(x for x in (rec.get("note"), handover[1]) if x)
            if restart and rec["status"] in ("ok", "masked"):
                rec["status"], rec["gap"] = "gap", "restart"
        for name, kind in (pkt.faults or dict.fromkeys(pkt.faulty, "faulty")).items():
            key = f"{name} {kind}"
            faulty[key] = faulty.get(key, 0) + 1
        counts[rec["status"]] += 1
        sink.write(rec)
    sink.close()
    out = {"packets": n, **{k: v for k, v in counts.items() if v}}
    if n_handover:
        out["handover"] = n_handover
    dropped = source.count_dropped()
    if dropped is not None:
        out["dropped"] = dropped
    if faulty:
        out["faulty"] = faulty
    return out

