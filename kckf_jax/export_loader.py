"""Run a step exported by ``kckf export``: needs only jax and numpy (copy this file anywhere).

    python export_loader.py step.jaxexport < packets.jsonl > estimates.jsonl
    python export_loader.py step.jaxexport --udp 0.0.0.0:5005 --sink 127.0.0.1:5006

As a library::

    step = ExportedStep("step.jaxexport")
    est = step.push(t, {"gyro1_x": 0.01, "hall1_x_l": 1.31})   # dict of readings; None = missing
    est = step.push_array(t, x)                                 # x = [gyro (G), hall (M)]

Each packet must be later than the previous one (an earlier or equal ``t`` is skipped, as in
``kckf stream``); ``dt`` comes from the timestamps in float64; a missing reading is NaN.
"""

from __future__ import annotations

import json
import math
import os
import sys

# One thread for XLA's tiny kernels (no thread hand-offs per packet), and synchronous dispatch.
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false "
                      "intra_op_parallelism_threads=1")
import jax  # noqa: E402

jax.config.update("jax_cpu_enable_async_dispatch", False)
import numpy as np  # noqa: E402

MAGIC = b"KCKF-JAXEXPORT/1\n"


class ExportedStep:
    def __init__(self, path: str):
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
        self._x = np.empty(h["x_size"], self.dtype)
        self.reset()

    def reset(self) -> None:
        self.state = jax.device_put(np.asarray(self.header["initial_state"], self.dtype))
        self.t_prev = None

    def push_array(self, t: float, readings: np.ndarray) -> np.ndarray | None:
        """Angles (rad, ``header["angle_names"]`` order) after the packet at ``t``, or None."""
        if self.t_prev is not None and not t > self.t_prev:
            return None
        self._x[0] = 0.0 if self.t_prev is None else t - self.t_prev
        self._x[1:] = readings
        args = (self.state, self._x) if self.params is None else (self.params, self.state,
                                                                   self._x)
        state, out = self._call(*args)
        out = np.asarray(out)
        if out[-1] < 0.5:
            return None
        self.state, self.t_prev = state, t
        return out[: len(self.header["angle_names"])]

    def push(self, t: float, readings: dict) -> dict | None:
        x = np.full(len(self.names), np.nan)
        for key, value in readings.items():
            i = self.index.get(key)
            if i is not None and isinstance(value, int | float) and math.isfinite(value):
                x[i] = value
        angles = self.push_array(t, x)
        if angles is None:
            return None
        return {"t": t, **{n: float(a) for n, a, e in zip(self.header["angle_names"], angles,
                                                          self.header["estimated"]) if e}}


def _handle(step: ExportedStep, data: bytes | str) -> dict:
    try:
        packet = json.loads(data)
        t = float(packet.pop("t"))
        if not math.isfinite(t):
            raise ValueError
    except (ValueError, KeyError, TypeError, AttributeError):
        return {"t": None, "status": "malformed"}
    est = step.push(t, packet)
    return est | {"status": "ok"} if est else {"t": t, "status": "skipped"}


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description="run a step exported by kckf export")
    ap.add_argument("path")
    ap.add_argument("--udp", help="HOST:PORT to receive packets on (default: stdin lines)")
    ap.add_argument("--sink", help="HOST:PORT to send estimates to (default: stdout)")
    ap.add_argument("--idle-timeout", type=float, default=None)
    args = ap.parse_args(argv)
    step = ExportedStep(args.path)
    if args.udp is None:
        for line in sys.stdin:
            print(json.dumps(_handle(step, line)), flush=True)
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
        rec = json.dumps(_handle(step, data))
        if sink:
            tx.sendto(rec.encode(), sink)
        else:
            print(rec, flush=True)


if __name__ == "__main__":
    sys.exit(main())
