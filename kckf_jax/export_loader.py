"""Run a step exported by ``kckf export``: needs only jax and numpy (copy this file anywhere).

    python export_loader.py step.jaxexport < packets.jsonl > estimates.jsonl

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
import sys

import jax
import numpy as np

MAGIC = b"KCKF-JAXEXPORT/1\n"


class ExportedStep:
    def __init__(self, path: str):
        with open(path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                raise ValueError(f"{path}: not a kckf step export (written by kckf export)")
            n = int.from_bytes(f.read(8), "little")
            self.header = json.loads(f.read(n).decode())
            self.exported = jax.export.deserialize(bytearray(f.read()))
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
        state, out = self.exported.call(*args)
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


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print(__doc__.splitlines()[2].strip(), file=sys.stderr)
        return 2
    step = ExportedStep(argv[0])
    for line in sys.stdin:
        try:
            packet = json.loads(line)
            t = float(packet.pop("t"))
        except (ValueError, KeyError, TypeError, AttributeError):
            print(json.dumps({"status": "malformed"}))
            continue
        est = step.push(t, packet)
        print(json.dumps(est | {"status": "ok"} if est else {"t": t, "status": "skipped"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
