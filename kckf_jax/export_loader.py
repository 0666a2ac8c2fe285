"""Run a step exported by ``kckf export``: needs only jax and numpy (copy this file anywhere).

    python export_loader.py step.jaxexport < packets.jsonl > estimates.jsonl
    python export_loader.py step.jaxexport --udp 0.0.0.0:5005 --sink 127.0.0.1:5006

Over ``--udp`` it takes packets from one sender, as ``kckf stream`` does: the first heard
(named on stderr) or those ``--allow-from HOST[:PORT]`` names; another sender's packet gets
``{"t": null, "status": "foreign", "note": "from HOST:PORT"}`` and changes nothing. A robot that
restarts and comes back from the same host on a new port is taken back once the sender has
been silent for ``--handover-after`` seconds (default 0.5; ``inf``: never): named on stderr
and in the record (``"handover": "HOST:OLD -> HOST:NEW"``), the step restarted if the robot's
clock started again (status ``gap``, ``"gap": "restart"``).

As a library::

    low_latency()   # optional, once, before the first computation: one packet at a time
    step = ExportedStep("step.jaxexport")
    rec = step.handle(b'{"t": 0.01, "gyro1_x": 0.01, "hall1_x_l": 1.31}')  # a packet, as bytes
    est = step.push(t, {"gyro1_x": 0.01, "hall1_x_l": 1.31})   # dict of readings; None = missing
    est = step.push_array(t, x)                                 # x = [gyro (G), hall (M)]

Every output line has the ``status`` vocabulary of ``kckf stream`` (``docs/streaming.md``):
``ok``, ``masked`` (faulty readings, not a number, infinite or outside the physical range the
export's header states, treated as missing), ``gap`` (``"gap": "predict"`` or ``"restart"``),
``malformed``, ``oversized``, ``missing_t``, ``bad_t``, ``out_of_order``, ``rejected`` (the
update was not finite; the state kept). ``dt`` comes from the timestamps in float64; an absent
reading (a missing key, ``null``, NaN) is missing.
"""

from __future__ import annotations

import json
import math
import os
import struct
import sys

import jax
import jax.numpy as jnp
import numpy as np

#: XLA's kernels on the calling thread (no thread hand-offs per packet); a flag of jax
#: 0.10-0.12's XLA (an unknown flag aborts XLA at its start).
LOW_LATENCY_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false"


#: XLA's option that compiles a while loop as one kernel (the exported step is one pass of a
#: loop, so that it runs as one kernel rather than about ninety: 3-4x faster per packet); jax
#: 0.12's XLA does so by default, jax 0.10's for loops under 1 KiB unless told.
LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"


def low_latency() -> None:
    """Settings for one packet at a time, for the process (importing this file changes
    nothing; ``main`` calls this): synchronous dispatch, and if no JAX computation has run yet,
    XLA's kernels on the calling thread (``LOW_LATENCY_XLA_FLAGS``) and the step compiled as
    one kernel (``LOOP_OPTION``, unless ``XLA_FLAGS`` sets it already)."""
    jax.config.update("jax_cpu_enable_async_dispatch", False)
    flags = os.environ.get("XLA_FLAGS", "")
    if LOW_LATENCY_XLA_FLAGS not in flags:
        flags = (flags + " " + LOW_LATENCY_XLA_FLAGS).strip()
    if LOOP_OPTION not in flags:
        extra = "--xla_backend_extra_options="
        entry = f"{LOOP_OPTION}={1 << 40}"
        at = flags.rfind(extra)
        if at < 0:
            flags = f"{flags} {extra}{entry}"
        else:  # a comma-separated list: add to it
            end = flags.find(" ", at)
            end = len(flags) if end < 0 else end
            sep = "," if end > at + len(extra) else ""
            flags = flags[:end] + sep + entry + flags[end:]
    os.environ["XLA_FLAGS"] = flags


MAGIC = b"KCKF-JAXEXPORT/1\n"
#: Linux's socket option stamping each datagram with its arrival (a ``struct timeval``).
SO_TIMESTAMP = 29
TIMEVAL = struct.Struct("@ll")
MAX_PACKET_BYTES = 8192


def _packed_call(exported, n: int):
    """The exported step ``(s, x) -> (s', out)`` jitted as one array in, one out: ``[s, x] ->
    [s', out]`` (and the parameter vector first when passed). A jitted call's cost on a CPU
    grows with its arguments and results: 9.3 us for one in and one out against 11.8 for two
    and two, for a call that does nothing (one process, best of three: benchmarks/README.md,
    issue 46; the step itself: ``benchmarks/exported_step.py``). Traced once (calling
    ``exported.call`` directly re-traces per call)."""

    def packed(*args):
        *p, buf = args
        return jnp.concatenate(exported.call(*p, buf[:n], buf[n:]))

    return jax.jit(packed)


class ExportedStep:
    """The exported step with the stream's packet rules (statuses, gaps, faulty readings).

    ``gap_s``, ``on_gap``, ``max_predict_s``: the gap policy (defaults from the export's
    header, which ``kckf export`` writes from its ``--gap`` and ``--on-gap``)."""

    def __init__(self, path: str, gap_s: float | None = None, on_gap: str | None = None,
                 max_predict_s: float | None = None):
        with open(path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                raise ValueError(f"{path}: not a kckf step export (written by kckf export)")
            n = int.from_bytes(f.read(8), "little")
            self.header = json.loads(f.read(n).decode())
            self.exported = jax.export.deserialize(bytearray(f.read()))
        self._call = _packed_call(self.exported, len(self.header["initial_state"]))
        h = self.header
        if h["dtype"] == "float64":
            jax.config.update("jax_enable_x64", True)
        self.dtype = np.dtype(h["dtype"])
        self.names = h["gyro_names"] + h["hall_names"]
        self.index = {name: i for i, name in enumerate(self.names)}
        self.params = None if h["params"] is None else np.asarray(h["params"], self.dtype)
        limits = h.get("limits", {})
        G = len(h["gyro_names"])
        g = limits.get("gyro_range_rad_s", 4000.0 * math.pi / 180.0)
        lo, hi = limits.get("hall_v_range", [0.0, 3.3])
        self._lo = np.r_[np.full(G, -g), np.full(len(h["hall_names"]), lo)]
        self._hi = np.r_[np.full(G, g), np.full(len(h["hall_names"]), hi)]
        gaps = h.get("gaps", {})
        self.gap_s = float(gap_s if gap_s is not None else gaps.get("gap_s", 0.5))
        self.on_gap = on_gap or gaps.get("on_gap", "predict")
        self.max_predict_s = float(max_predict_s if max_predict_s is not None
                                   else gaps.get("max_predict_s", 1.0))
        self._n = len(h["initial_state"])
        self._buf = np.empty(self._n + h["x_size"], self.dtype)  # [state, dt, readings]
        self._K = len(h["angle_names"])
        self.reset()

    @property
    def state(self) -> np.ndarray:
        """The filter's state after the last packet used (a copy: the flat vector the step
        takes, ``header["initial_state"]``'s layout)."""
        return self._buf[: self._n].copy()

    def reset(self) -> None:
        self._buf[: self._n] = np.asarray(self.header["initial_state"], self.dtype)
        self.t_prev = None
        self._out = np.zeros(2 * self._K + 1)  # no packet yet: no code

    def _step(self, dt: float, readings: np.ndarray):
        buf, n, K = self._buf, self._n, self._K
        buf[n] = dt
        buf[n + 1:] = readings
        o = np.asarray(self._call(buf) if self.params is None else self._call(self.params, buf))
        if o[n + 2 * K] < 0.5:
            return None  # the state kept
        buf[:n] = o[:n]
        self._out = o[n:]
        return self._out[:K]

    @property
    def codes(self) -> np.ndarray:
        """Each reading's fault code after the last packet used (the step's own judgement:
        railed, unreachable, saturated, a sensor isolated over time; 0 for a used or missing
        one; ``header["fault_kinds"][code - 1]``)."""
        return self._out[2 * self._K + 1:].astype(int)

    def push_array(self, t: float, readings: np.ndarray) -> np.ndarray | None:
        """Angles (rad, ``header["angle_names"]`` order) after the packet at ``t``, or None
        (not after the previous packet, or the update was not finite: the state kept)."""
        return self._push(t, readings)[0]

    def _push(self, t: float, readings: np.ndarray):
        """``(angles or None, status, extra)`` for a packet at ``t`` with these readings."""
        if self.t_prev is not None and not t > self.t_prev:
            return None, "out_of_order", {}
        dt = 0.0 if self.t_prev is None else t - self.t_prev
        status, extra = "ok", {}
        if dt > self.gap_s:
            predict = self.on_gap == "predict" and dt <= self.max_predict_s
            status, extra = "gap", {"gap": "predict" if predict else "restart", "gap_s": dt}
            if not predict:
                self.reset()
                dt = 0.0
        angles = self._step(dt, readings)
        if angles is None and extra.get("gap") == "predict":
            self.reset()  # predicting across the gap overflowed: start again here
            extra["gap"] = "restart"
            angles = self._step(0.0, readings)
        if angles is None:
            return None, "rejected", {}
        self.t_prev = t
        return angles, status, extra

    def push(self, t: float, readings: dict) -> dict | None:
        """The estimate record after a packet of readings (None for an absent one), or None
        when the packet was not used."""
        rec = self._record(t, *self._readings(readings))
        return rec if rec["status"] in ("ok", "masked", "gap") else None

    def _readings(self, readings: dict):
        """The readings vector, and the faulty ones (name, why), as ``kckf stream`` has them."""
        x = np.full(len(self.names), np.nan)
        faulty = []
        for key, value in readings.items():
            i = self.index.get(key)
            if i is None or value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int | float):
                faulty.append((i, f"{key} is not a number"))
                continue
            try:
                x[i] = float(value)
            except OverflowError:
                faulty.append((i, f"{key} is too large"))
        bad = ~(np.isnan(x) | ((x >= self._lo) & (x <= self._hi)))
        faulty += [(i, f"{self.names[i]} = {x[i]:.6g} out of range") for i in np.flatnonzero(bad)]
        x[bad] = np.nan
        return x, sorted(faulty)

    def _record(self, t: float, x: np.ndarray, faulty: list) -> dict:
        angles, status, extra = self._push(t, x)
        if angles is not None:
            kinds = self.header.get("fault_kinds", [])
            if self.codes.any():
                faulty = sorted(faulty + [(i, f"{self.names[i]} {kinds[c - 1]}")
                                          for i, c in enumerate(self.codes.tolist())
                                          if 0 < c <= len(kinds)])
        rec: dict = {"t": t}
        if angles is not None:
            rec.update({n: float(a) for n, a, e in zip(self.header["angle_names"], angles,
                                                       self.header["estimated"])
                        if e and math.isfinite(a)})
            if faulty and status == "ok":
                status = "masked"
        rec["status"] = status
        rec.update(extra)
        if faulty and angles is not None:
            rec["note"] = "treated as missing: " + "; ".join(p for _, p in faulty[:4])
        if status == "rejected":
            rec["note"] = "the update was not finite; state kept"
        return rec

    def handle(self, data: bytes | str) -> dict:
        """One packet (UTF-8 JSON bytes) in, one output record out; never raises."""
        try:
            if len(data) > MAX_PACKET_BYTES:
                return {"t": None, "status": "oversized"}
            try:
                text = data.decode("utf-8") if isinstance(data, bytes | bytearray) else data
                packet = json.loads(text)
            except (UnicodeDecodeError, ValueError, RecursionError):
                return {"t": None, "status": "malformed"}
            if not isinstance(packet, dict):
                return {"t": None, "status": "malformed"}
            t = packet.pop("t", None)
            if t is None:
                return {"t": None, "status": "missing_t"}
            if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
                return {"t": None, "status": "bad_t"}
            return self._record(float(t), *self._readings(packet))
        except Exception:  # a loader bug must not stop the stream either
            return {"t": None, "status": "malformed"}


def parse_allow_from(values):
    """``--allow-from HOST[:PORT]`` values as ``(address, port or None)`` (a host name looked
    up once, here), or None when none were given; ValueError for a bad one."""
    if not values:
        return None
    import socket

    out = []
    for v in values:
        host, sep, port = v.rpartition(":")
        if not sep:
            host, port = v, ""
        try:
            number = int(port) if port else None
            if number is not None and not 0 < number < 65536:
                raise ValueError
            out.append((socket.gethostbyname(host), number))
        except (ValueError, OSError):
            raise ValueError(f"--allow-from {v!r}: expected HOST or HOST:PORT (PORT 1-65535) "
                             "of a host that resolves") from None
    return out


class Senders:
    """One robot per stream, ``kckf stream``'s rules for a UDP socket: ``take(addr, now)``
    says what a datagram from ``addr`` that arrived at ``now`` (s, wall clock) is.

    ``"sender"``: the stream's robot. ``"first"``: the first sender heard (without
    ``allow_from``), the robot from now on. ``"handover"``: the robot's host on a new port
    after the robot was silent for ``handover_s`` or more (a restarted robot): the robot from
    now on, its previous address no longer (``handovers`` lists them, ``silence_s`` says how
    long), unless that port was heard while the robot was still sending (another sender).
    ``"foreign"``: anyone else (counted in ``foreign``). With ``allow_from`` (``(address,
    port or None)``, ``parse_allow_from``) those are the robot, and there is no handover."""

    def __init__(self, allow_from=None, handover_s: float = 0.5):
        self.allow_from = allow_from
        self.handover_s = float(handover_s)
        self.sender = None
        self.heard = -math.inf
        self.silence_s = 0.0
        self.foreign: dict[str, int] = {}
        self.handovers: list[tuple[str, str]] = []
        self.first_foreign: dict = {}  # when each foreign address was first heard

    def take(self, addr, now: float) -> str:
        if addr == self.sender:
            self.heard = now
            return "sender"
        if self.allow_from is not None:
            if any(addr[0] == h and p in (None, addr[1]) for h, p in self.allow_from):
                return "sender"
        elif self.sender is None:
            self.sender, self.heard = addr, now
            return "first"
        elif (addr[0] == self.sender[0] and now - self.heard >= self.handover_s
              and self.first_foreign.get(addr, math.inf) > self.heard):
            # (a port heard while the robot was still sending is another sender)
            self.handovers.append((_name(self.sender), _name(addr)))
            self.silence_s = now - self.heard
            self.sender, self.heard = addr, now
            return "handover"
        name = _name(addr)
        self.foreign[name] = self.foreign.get(name, 0) + 1
        self.first_foreign.setdefault(addr, now)
        return "foreign"


def arrival_time(anc) -> float | None:
    """The arrival time (s, wall clock) in a datagram's ancillary data (``SO_TIMESTAMP``),
    else None (as ``kckf_jax._stream._io.arrival_time``; this file imports no kckf_jax)."""
    import socket

    for level, kind, data in anc:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMP and len(data) >= TIMEVAL.size:
            sec, usec = TIMEVAL.unpack(data[:TIMEVAL.size])
            return sec + 1e-6 * usec
    return None


def _name(addr) -> str:
    return f"{addr[0]}:{addr[1]}"


def packet_t(data: bytes):
    """A packet's ``t`` as ``ExportedStep.handle`` reads it, or None where it has none."""
    if len(data) > MAX_PACKET_BYTES:
        return None
    try:
        packet = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        return None
    t = packet.get("t") if isinstance(packet, dict) else None
    if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
        return None
    return float(t)


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description="run a step exported by kckf export")
    ap.add_argument("path")
    ap.add_argument("--udp", help="HOST:PORT to receive packets on (default: stdin lines)")
    ap.add_argument("--sink", help="HOST:PORT to send estimates to (default: stdout)")
    ap.add_argument("--idle-timeout", type=float, default=None)
    ap.add_argument("--gap", type=float, default=None, help="gap threshold, s (from the export)")
    ap.add_argument("--on-gap", choices=("predict", "restart"), default=None)
    ap.add_argument("--allow-from", action="append", metavar="HOST[:PORT]",
                    help="--udp: the sender to take packets from (repeatable); default: the "
                         "first heard; others get the status foreign")
    ap.add_argument("--handover-after", type=float, default=0.5, metavar="SEC",
                    help="--udp: once the sender has been silent this long, a packet from its "
                         "host on a new port (a restarted robot) makes that port the sender "
                         "(default 0.5 s; inf: never); a second sender while the first is "
                         "live stays foreign")
    args = ap.parse_args(argv)
    if not args.handover_after >= 0:
        ap.error(f"--handover-after {args.handover_after!r}: expected 0 or more (inf: never)")
    try:
        allow_from = parse_allow_from(args.allow_from)
    except ValueError as exc:
        ap.error(str(exc))
    low_latency()  # before the first computation
    step = ExportedStep(args.path, gap_s=args.gap, on_gap=args.on_gap)
    if args.udp is None:
        for line in sys.stdin:
            print(json.dumps(step.handle(line.rstrip("\n"))), flush=True)
        return 0
    import socket
    import time

    host, port = args.udp.rsplit(":", 1)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    rx.bind((host, int(port)))
    rx.settimeout(args.idle_timeout)
    # Each datagram stamped with its arrival (Linux's SO_TIMESTAMP): a sender's silence is
    # measured between arrivals, however far the loop has fallen behind.
    stamped = sys.platform.startswith("linux")
    if stamped:
        try:
            rx.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMP, 1)
        except OSError:
            stamped = False
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink = None
    if args.sink:
        sh, sp = args.sink.rsplit(":", 1)
        sink = (sh, int(sp))
    step.push_array(0.0, np.zeros(len(step.names)))  # compile before the first packet
    step.reset()
    print(f"export_loader: listening on udp://{host}:{port}", file=sys.stderr, flush=True)
    senders = Senders(allow_from, args.handover_after)
    n = n_foreign = 0
    clock_check = None  # the last handover, until a packet with a usable t has followed it
    while True:
        try:
            if stamped:
                data, anc, _, addr = rx.recvmsg(65536, 64)
                now = arrival_time(anc)
            else:
                (data, addr), now = rx.recvfrom(65536), None
        except TimeoutError:
            print(f"export_loader: packets {n}, foreign {n_foreign}, handover "
                  f"{len(senders.handovers)}", file=sys.stderr, flush=True)
            return 0
        n += 1
        kind = senders.take(addr, time.time() if now is None else now)
        if kind == "foreign":
            n_foreign += 1
            out = {"t": None, "status": "foreign", "note": f"from {_name(addr)}"}
        else:
            mark = note = None  # the handover this record names, and what it says of it
            if kind == "first":
                print(f"export_loader: taking packets from {_name(addr)} (the first sender "
                      "heard; --allow-from chooses)", file=sys.stderr, flush=True)
            elif kind == "handover":
                previous, new = senders.handovers[-1]
                clock_check = mark = f"{previous} -> {new}"
                note = (f"sender {previous} silent {senders.silence_s:.2f} s; taking {new} "
                        "(same host) as the same robot")
                print(f"export_loader: {note}", file=sys.stderr, flush=True)
            restart = False
            if clock_check is not None:
                t = packet_t(data)
                if t is not None:
                    t_prev = step.t_prev
                    if t_prev is not None and not t > t_prev:  # its clock started again
                        step.reset()
                        restart, mark = True, clock_check
                        note = "; ".join((note or f"after the handover {clock_check}",
                                          f"its clock started again (t = {t!r}, previous "
                                          f"t = {t_prev!r}): step restarted"))
                    clock_check = None
            out = step.handle(data)
            if mark is not None:
                out["handover"] = mark
                out["note"] = " | ".join(x for x in (out.get("note"), note) if x)
                if restart and out["status"] in ("ok", "masked"):
                    out["status"], out["gap"] = "gap", "restart"
        rec = json.dumps(out)
        if sink:
            tx.sendto(rec.encode(), sink)
        else:
            print(rec, flush=True)


if __name__ == "__main__":
    sys.exit(main())
