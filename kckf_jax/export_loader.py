"""Run a step exported by ``kckf export``: needs only jax and numpy (copy this file anywhere).

    python export_loader.py step.jaxexport < packets.jsonl > estimates.jsonl
    python export_loader.py step.jaxexport --udp 0.0.0.0:5005 --sink 127.0.0.1:5006

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
import sys

import jax
import numpy as np

#: XLA's kernels on the calling thread (no thread hand-offs per packet); a flag of jax
#: 0.10-0.12's XLA (an unknown flag aborts XLA at its start).
LOW_LATENCY_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false"


def low_latency() -> None:
    """Settings for one packet at a time, for the process (importing this file changes
    nothing; ``main`` calls this): synchronous dispatch, and if no JAX computation has run yet,
    XLA's kernels on the calling thread (``LOW_LATENCY_XLA_FLAGS``)."""
    jax.config.update("jax_cpu_enable_async_dispatch", False)
    flags = os.environ.get("XLA_FLAGS", "")
    if LOW_LATENCY_XLA_FLAGS not in flags:
        os.environ["XLA_FLAGS"] = (flags + " " + LOW_LATENCY_XLA_FLAGS).strip()


MAGIC = b"KCKF-JAXEXPORT/1\n"
MAX_PACKET_BYTES = 8192


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
        # One jitted callable, traced once (calling exported.call directly re-traces per call).
        self._call = jax.jit(self.exported.call)
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
        self._x = np.empty(h["x_size"], self.dtype)
        self.reset()

    def reset(self) -> None:
        self.state = jax.device_put(np.asarray(self.header["initial_state"], self.dtype))
        self.t_prev = None
        self.codes = np.zeros(0, int)

    def _step(self, dt: float, readings: np.ndarray):
        self._x[0] = dt
        self._x[1:] = readings
        args = (self.state, self._x) if self.params is None else (self.params, self.state,
                                                                   self._x)
        state, out = self._call(*args)
        out = np.asarray(out)
        K = len(self.header["angle_names"])
        if out[2 * K] < 0.5:
            return None
        self.state = state
        # Each reading's fault code (the step's own judgement: railed, unreachable, saturated,
        # a Hall sensor isolated over time; 0 for a used or missing one).
        self.codes = out[2 * K + 1:].astype(int)
        return out[:K]

    def push_array(self, t: float, readings: np.ndarray) -> np.ndarray | None:
        """Angles (rad, ``header["angle_names"]`` order) after the packet at ``t``, or None
        (not after the previous packet, or the update was not finite: the state kept)."""
        return self._push(t, np.asarray(readings, np.float64))[0]

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
            faulty = sorted(faulty + [(int(i), f"{self.names[i]} {kinds[c - 1]}")
                                      for i, c in enumerate(self.codes) if 0 < c <= len(kinds)])
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


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description="run a step exported by kckf export")
    ap.add_argument("path")
    ap.add_argument("--udp", help="HOST:PORT to receive packets on (default: stdin lines)")
    ap.add_argument("--sink", help="HOST:PORT to send estimates to (default: stdout)")
    ap.add_argument("--idle-timeout", type=float, default=None)
    ap.add_argument("--gap", type=float, default=None, help="gap threshold, s (from the export)")
    ap.add_argument("--on-gap", choices=("predict", "restart"), default=None)
    args = ap.parse_args(argv)
    low_latency()  # before the first computation
    step = ExportedStep(args.path, gap_s=args.gap, on_gap=args.on_gap)
    if args.udp is None:
        for line in sys.stdin:
            print(json.dumps(step.handle(line.rstrip("\n"))), flush=True)
        return 0
    import socket

    host, port = args.udp.rsplit(":", 1)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    rx.bind((host, int(port)))
    rx.settimeout(args.idle_timeout)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink = None
    if args.sink:
        sh, sp = args.sink.rsplit(":", 1)
        sink = (sh, int(sp))
    step.push_array(0.0, np.zeros(len(step.names)))  # compile before the first packet
    step.reset()
    print(f"export_loader: listening on udp://{host}:{port}", file=sys.stderr, flush=True)
    while True:
        try:
            data = rx.recv(65536)
        except TimeoutError:
            return 0
        rec = json.dumps(step.handle(data))
        if sink:
            tx.sendto(rec.encode(), sink)
        else:
            print(rec, flush=True)


if __name__ == "__main__":
    sys.exit(main())
