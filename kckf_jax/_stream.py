"""Live filtering: packets, sources, sinks, and ``StreamingFilter`` over the batch filter's step.

A packet is one UTF-8 JSON object keyed by ``sensors.csv`` column names (``t`` required; a
missing key or ``null`` is a missing reading). ``StreamingFilter`` runs the very ``step`` that
``run_filter`` scans (no second implementation), compiled once, with the state kept on the
device between packets; the host keeps only the previous timestamp (float64). Nothing a sender
does can stop the stream or poison the state: every packet gets a ``status`` and a bad one is
skipped (see ``STATUSES``).
"""

from __future__ import annotations

import json
import math
import select
import socket
import sys
import time
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._fast import CONVERGING_METHODS, HEAD_ROWS, STEADY_STEPS, STEADY_TOL, converged_map
from ._filter import METHODS, FilterState, SensorSeries, init_state, step
from ._model import structure
from ._params import Params
from ._robot import Robot

#: Every ``status`` an output line can carry. Used packets: ``ok``; ``masked`` (some readings
#: were unusable and treated as missing, ``note`` says which); ``gap`` (time jumped by more
#: than the gap limit; ``gap`` says whether the filter predicted across it or restarted).
#: Skipped packets (the state is unchanged): ``malformed`` (not UTF-8 JSON, not an object),
#: ``oversized``, ``missing_t``, ``bad_t`` (not a finite number), ``out_of_order`` (``t`` not
#: after the previous packet's), ``rejected`` (the update was not finite; never seen in tests).
STATUSES = ("ok", "masked", "gap", "malformed", "oversized", "missing_t", "bad_t",
            "out_of_order", "rejected")
USED = ("ok", "masked", "gap")
#: Plausibility limits of a reading: beyond them it is treated as missing (``masked``).
MAX_RATE_RAD_S = 100.0  # the LSM6DSO's widest range is 2000 dps = 35 rad/s
HALL_V_RANGE = (-1.0, 10.0)
MAX_PACKET_BYTES = 8192


@dataclass
class Packet:
    """One parsed packet: time (s, float64), readings (NaN = missing), status, note."""

    t: float | None
    gyro: np.ndarray
    hall_v: np.ndarray
    status: str
    note: str = ""


class PacketParser:
    """Turns bytes into ``Packet``s for one robot; never raises.

    Example:
        >>> parser = PacketParser(Robot.from_spec("x"))
        >>> parser.parse(b'{"t": 0.01, "gyro1_x": 0.1, "hall1_x_l": 1.3}').status
        'ok'
        >>> parser.parse(b"garbage").status
        'malformed'
    """

    def __init__(self, robot: Robot, max_bytes: int = MAX_PACKET_BYTES):
        self.robot = robot
        self.max_bytes = max_bytes
        self._names = robot.gyro_names + robot.hall_names
        self._slots = set(self._names)
        self._G, self._M = len(robot.gyro_names), robot.n_hall
        # Plausible range of each reading: |rate| <= MAX_RATE_RAD_S, V within HALL_V_RANGE.
        self._lo = np.r_[np.full(self._G, -MAX_RATE_RAD_S), np.full(self._M, HALL_V_RANGE[0])]
        self._hi = np.r_[np.full(self._G, MAX_RATE_RAD_S), np.full(self._M, HALL_V_RANGE[1])]

    def empty(self, status: str, note: str = "", t: float | None = None) -> Packet:
        return Packet(t, np.full(self._G, np.nan), np.full(self._M, np.nan), status, note)

    def parse(self, data: bytes | str) -> Packet:
        try:
            return self._parse(data)
        except Exception as exc:  # a parser bug must not stop the stream either
            return self.empty("malformed", f"unparseable packet ({type(exc).__name__})")

    def _parse(self, data: bytes | str) -> Packet:
        if len(data) > self.max_bytes:
            return self.empty("oversized", f"{len(data)} bytes, limit {self.max_bytes}")
        try:
            text = data.decode("utf-8") if isinstance(data, bytes | bytearray) else data
            obj = json.loads(text)
        except (UnicodeDecodeError, ValueError, RecursionError):
            return self.empty("malformed", "not a UTF-8 JSON object")
        if not isinstance(obj, dict):
            return self.empty("malformed", f"a JSON {type(obj).__name__}, not an object")
        t = obj.get("t")
        if t is None:
            return self.empty("missing_t", "no 't'")
        if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
            return self.empty("bad_t", f"t = {str(t)[:40]!r} is not a finite number")
        pkt = self.empty("ok", t=float(t))
        values = [obj.get(name) for name in self._names]
        try:  # fast path: numbers and nulls (None becomes NaN)
            if any(type(v) is bool for v in values):
                raise TypeError
            arr = np.array(values, dtype=np.float64)
            problems = []
        except (TypeError, ValueError, OverflowError):
            arr, problems = self._slow_values(values)
        bad = ~(np.isnan(arr) | ((arr >= self._lo) & (arr <= self._hi)))
        if bad.any():
            problems += [f"{self._names[i]} = {arr[i]} out of range" for i in np.flatnonzero(bad)]
            arr[bad] = np.nan
        pkt.gyro[:] = arr[: self._G]
        pkt.hall_v[:] = arr[self._G:]
        notes = []
        if problems:
            pkt.status = "masked"
            notes.append("treated as missing: " + "; ".join(problems[:4]))
        if len(obj) - 1 > sum(1 for name in self._names if name in obj):
            unknown = [k for k in obj if k != "t" and k not in self._slots]
            notes.append("ignored unknown key(s) " + ", ".join(repr(k[:30]) for k in unknown[:4]))
        pkt.note = " | ".join(notes)
        return pkt

    def _slow_values(self, values: list) -> tuple[np.ndarray, list[str]]:
        arr = np.full(len(values), np.nan)
        problems = []
        for i, v in enumerate(values):
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, int | float):
                problems.append(f"{self._names[i]} is not a number")
                continue
            try:
                arr[i] = float(v)
            except OverflowError:
                problems.append(f"{self._names[i]} is too large")
        return arr, problems


class _HostMap:
    """The converged filter as one NumPy float64 matrix, for packets on the host.

    Once the covariance has converged (constant time step, every reading present), a packet
    changes the block states ``z`` by the affine map of ``_fast.converged_map``; with the
    Hall model's two exponentials as inputs (``theta = s a e^{bV} - s c e^{-dV}``, Eq. 1) the
    whole step is one product ``M x`` for ``x = [z, (scratch), g_prev, e^{bV}, e^{-dV}, g]``,
    giving the new ``z``, the angles and a check row (the sum of every input, finite exactly
    when every reading is). Two buffers take turns: the product writes the next packet's
    ``x`` directly. No jitted call, so no dispatch: a packet costs a few NumPy calls.
    """

    def __init__(self, params: Params, method: str, P, dt: float):
        robot = params.robot
        st = structure(robot, method)
        P_new, A, Wg, Wh, std = (np.asarray(x, np.float64) for x in _converged_map(
            params, method, P, jnp.asarray(dt, P.dtype)))
        self.P, self.std, self.dt = P_new, std, float(dt)
        nb, nz = A.shape[:2]
        N, K, M = nb * nz, len(st.block_of), robot.n_hall
        self.used = np.flatnonzero(np.any(robot.rate_map != 0.0, axis=0))
        Gu = len(self.used)
        a, b, c, d, sign = (np.asarray(x, np.float64) for x in params.hall_coeffs)
        Az = np.zeros((N, N))
        for p in range(nb):
            Az[p * nz:(p + 1) * nz, p * nz:(p + 1) * nz] = A[p]
        Wh = Wh.reshape(M, N).T
        # Columns: z | scratch (the previous angles and check, weight 0) | g_prev | e^{bV} |
        # e^{-dV} | g (weight 0 but in the check).
        Mz = np.concatenate([Az, np.zeros((N, K + 1)), Wg.reshape(Gu, N).T, Wh * (sign * a),
                             -Wh * (sign * c), np.zeros((N, Gu))], axis=1)
        Tang = np.zeros((K, N))  # angles from z: angle k is row slot_of[k] of T z in its block
        for k, (p, i) in enumerate(zip(st.block_of, st.slot_of)):
            Tang[k, p * nz:(p + 1) * nz] = st.T[i]
        check = np.ones((1, Mz.shape[1]))
        check[0, N:N + K + 1] = 0.0
        self.M = np.ascontiguousarray(np.vstack([Mz, Tang @ Mz, check]))
        self.kb, self.kd = b, -d  # exponents per volt
        self.N, self.K, self.nz, self.nb = N, K, nz, nb
        g0 = N + K + 1
        e0 = g0 + Gu

        def views(buf):  # (x, the product's target, g_prev, both exponentials, e^{bV}, e^{-dV}, g)
            return (buf, buf[:g0], buf[g0:e0], buf[e0:e0 + 2 * M], buf[e0:e0 + M],
                    buf[e0 + M:e0 + 2 * M], buf[e0 + 2 * M:])

        self._views = [views(np.zeros(self.M.shape[1])), views(np.zeros(self.M.shape[1]))]
        self._cur = 0

    def start(self, z: np.ndarray, gyro_prev: np.ndarray) -> None:
        x = self._views[self._cur]
        x[0][: self.N] = z.ravel()
        x[2][:] = gyro_prev[self.used]

    def step(self, dt: float, gyro: np.ndarray, hall_v: np.ndarray) -> np.ndarray | None:
        """The angles after this packet, or None (state untouched) when the packet is not one
        the converged map describes: another time step, or a reading missing or absurd."""
        if abs(dt - self.dt) > 1e-9:
            return None
        x, _, _, e, eb, ed, g = self._views[self._cur]
        nxt = self._views[1 - self._cur]
        np.multiply(self.kb, hall_v, out=eb)
        np.multiply(self.kd, hall_v, out=ed)
        np.exp(e, out=e)
        g[:] = gyro[self.used]
        out = np.dot(self.M, x, out=nxt[1])
        if not math.isfinite(out[-1]):
            return None
        nxt[2][:] = g
        self._cur ^= 1
        return out[self.N:self.N + self.K]

    def z(self) -> np.ndarray:
        return self._views[self._cur][0][: self.N].reshape(self.nb, self.nz).copy()

    def gyro_prev(self) -> np.ndarray:
        return self._views[self._cur][2].copy()


#: Packets between two checks of the covariance for the host path.
HOST_CHECK_EVERY = 64
#: Compiled once per parameter layout (``StreamingFilter.warmup`` compiles it up front).
_converged_map = eqx.filter_jit(converged_map)


class StreamingFilter:
    """The batch filter's ``step``, one packet at a time, compiled once.

    Args:
        params: filter parameters (their dtype sets the precision).
        method: one of ``METHODS``.
        gap_s: a time step longer than this is a gap (status ``gap``).
        on_gap: ``"predict"`` (step across the gap: the covariance grows with it) or
            ``"restart"`` (start again from the initial state at this packet).
        max_predict_s: a gap longer than this restarts even with ``on_gap="predict"`` (as
            does a gap whose prediction overflows).

    The state stays on the device between packets; per packet, one array of readings goes in
    and one array of estimates comes out. On CPU, Python's dispatch of the jitted call
    dominates the latency: ``low_latency()`` turns off JAX's async dispatch, which the
    ``kckf stream`` command does (see benchmarks/README.md).

    **Host path** (``host_path=True``, the KCKF with the constant Hall noise model): once the
    packets arrive at a constant time step with every reading and the covariance has
    converged (after ``HEAD_ROWS`` such packets, checked every ``HOST_CHECK_EVERY``, to
    ``STEADY_TOL``), the filter is the steady path's affine map (``_fast.converged_map``)
    and each packet is one NumPy product on the host, with no jitted call (``on_host``). Any
    other packet (another time step, a missing or masked reading, a gap) hands the state back
    to the device step for that packet, and the watch starts again. The estimates are the
    device step's to rounding.

    Example:
        >>> sf = StreamingFilter(Params.paper_defaults(Robot.from_spec("x")))
        >>> sf.push(PacketParser(sf.robot).parse(b'{"t": 0.0, "hall1_x_l": 1.3}'))["status"]
        'ok'
    """

    def __init__(self, params: Params, method: str = "kckf", *, gap_s: float = 0.5,
                 on_gap: str = "predict", max_predict_s: float = 3600.0,
                 host_path: bool = True):
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
        if on_gap not in ("predict", "restart"):
            raise ValueError(f"on_gap must be 'predict' or 'restart', got {on_gap!r}")
        if not gap_s > 0:
            raise ValueError(f"gap_s must be positive, got {gap_s}")
        self.params, self.method, self.robot = params, method, params.robot
        self.gap_s, self.on_gap, self.max_predict_s = float(gap_s), on_gap, float(max_predict_s)
        self.dtype = params.log_q.dtype
        self._G, self._M = 3 * self.robot.n_links, self.robot.n_hall
        self._K = self.robot.n_angles
        self.names = self.robot.angle_names
        estimated = np.ones(self._K, bool)
        if method in ("hall_l", "hall_r"):
            estimated[self.robot.n_joint_axes:] = False
        self._estimated = estimated
        self._all_estimated = bool(estimated.all())
        self._fn, self._flatten, self._unflatten = _compiled_step(params, method)
        self._x = np.empty(1 + self._G + self._M, dtype=self.dtype)
        self._initial = jax.device_put(self._flatten(init_state(params, method)))
        self._host_ok = (host_path and method in CONVERGING_METHODS
                         and params.hall_noise == "angle")
        self._used = np.flatnonzero(np.any(self.robot.rate_map != 0.0, axis=0))
        self._tol = STEADY_TOL.get(np.dtype(self.dtype), 1e-5)
        # As in the batch steady path: at least its head of regular rows before switching.
        self._min_regular = HEAD_ROWS.get(np.dtype(self.dtype), STEADY_STEPS)
        self.reset()

    def reset(self) -> None:
        """Back to the initial state (before the first packet)."""
        self._state = self._initial
        self.t_prev: float | None = None
        self._host: _HostMap | None = None
        self._regular, self._last_dt, self._P_check = 0, None, None

    def warmup(self) -> None:
        """Compile the step (and the host path's map; call before the first real packet),
        then reset."""
        self._x[:] = 0.0
        jax.block_until_ready(self._fn(self._state, self._x))
        if self._host_ok:
            _HostMap(self.params, self.method, self._unflatten(self._state).P, 0.01)
        self.reset()

    @property
    def on_host(self) -> bool:
        """Whether packets currently take the host path (see the class docstring)."""
        return self._host is not None

    @property
    def state(self):
        """The current ``FilterState`` (a copy assembled from the device vector, or from the
        host path's state)."""
        if self._host is not None:
            return self._host_state()
        return self._unflatten(self._state)

    def _host_state(self) -> FilterState:
        host = self._host
        hold = self._hold_host.copy()
        hold[self._used] = host.gyro_prev()
        return FilterState(jnp.asarray(host.z(), self.dtype), jnp.asarray(host.P, self.dtype),
                           jnp.asarray(hold, self.dtype))

    def _leave_host(self) -> None:
        self._state = jax.device_put(self._flatten(self._host_state()))
        self._host = None
        self._regular, self._last_dt, self._P_check = 0, None, None

    def _watch(self, dt: float, pkt: Packet) -> None:
        """After a device step: count regular complete packets and, from ``HEAD_ROWS`` of
        them on (the batch steady path's switch point), every ``HOST_CHECK_EVERY`` compare
        the covariance over one step; once it has converged, switch to the host path."""
        complete = (dt > 0 and bool(np.isfinite(pkt.hall_v).all())
                    and bool(np.isfinite(pkt.gyro[self._used]).all()))
        if complete and self._last_dt is not None and abs(dt - self._last_dt) <= 1e-9:
            self._regular += 1
        else:
            self._regular, self._P_check = 0, None
        self._last_dt = dt if complete else None
        phase = self._regular % HOST_CHECK_EVERY
        if self._regular < max(HOST_CHECK_EVERY, self._min_regular) or phase > 1:
            return
        state = self._unflatten(self._state)
        P = np.asarray(state.P, np.float64)
        if phase == 0:
            self._P_check = P
            return
        if self._P_check is None:
            return
        change = np.max(np.abs(P - self._P_check)) / max(np.max(np.abs(P)), 1e-300)
        if change <= self._tol:
            self._host = _HostMap(self.params, self.method, state.P, dt)
            self._hold_host = np.asarray(state.gyro_hold, np.float64)
            self._host.start(np.asarray(state.z, np.float64), self._hold_host)

    def push(self, pkt: Packet) -> dict:
        """Filter one packet; returns the output record (``t``, angles in rad, ``status``)."""
        if pkt.status not in USED:
            return self._record(pkt.t, pkt.status, pkt.note)
        if self.t_prev is not None and not pkt.t > self.t_prev:
            return self._record(pkt.t, "out_of_order",
                                f"t = {pkt.t!r} is not after the previous t = {self.t_prev!r}")
        status, note, extra = pkt.status, pkt.note, {}
        dt = 0.0 if self.t_prev is None else pkt.t - self.t_prev  # float64 on the host
        if dt > self.gap_s:
            status = "gap"
            predict = self.on_gap == "predict" and dt <= self.max_predict_s
            extra = {"gap": "predict" if predict else "restart", "gap_s": dt}
            if not predict:
                self.reset()
                dt = 0.0
        out = self._run(dt, pkt)
        if out is None and extra.get("gap") == "predict":
            # Predicting across this gap overflowed: start again at this packet instead.
            self.reset()
            extra["gap"] = "restart"
            out = self._run(0.0, pkt)
        if out is None:
            return self._record(pkt.t, "rejected", "the update was not finite; state kept")
        self.t_prev = pkt.t
        rec = self._record(pkt.t, status, note, out)
        rec.update(extra)
        return rec

    def _run(self, dt: float, pkt: Packet) -> np.ndarray | None:
        """One step: on the host path when it applies, else on the device; the new state is
        kept only when it is finite."""
        if self._host is not None:
            angles = self._host.step(dt, pkt.gyro, pkt.hall_v)
            if angles is not None:
                return angles
            self._leave_host()
        x = self._x
        x[0] = dt
        x[1:1 + self._G] = pkt.gyro
        x[1 + self._G:] = pkt.hall_v
        state, out = self._fn(self._state, x)
        out = np.asarray(out)
        if out[-1] < 0.5:
            return None
        self._state = state
        if self._host_ok:
            self._watch(dt, pkt)
        return out[: self._K]

    def _record(self, t, status, note="", angles=None) -> dict:
        rec: dict = {"t": t}
        if angles is not None:
            values = angles.tolist()
            if self._all_estimated:
                rec.update(zip(self.names, values))
            else:
                rec.update((n, a) for n, a, e in zip(self.names, values, self._estimated) if e)
        rec["status"] = status
        if note:
            rec["note"] = note
        return rec


def stream_step_fn(params: Params, method: str):
    """The pure per-packet function ``(s, x) -> (s, [angles, std, ok])`` over ``step``.

    ``s`` is the whole filter state flattened into one vector and ``x = [dt, gyro (G),
    hall_v (M)]``: two arrays in, two out (dispatch cost on CPU grows with every argument). A
    non-finite result (impossible for finite readings, but the stream must survive anything)
    leaves the state as it was and reports ``ok = 0``. Returns ``(fn, flatten, unflatten)``;
    ``StreamingFilter`` jits it, ``kckf export`` serialises it.
    """
    G = 3 * params.robot.n_links
    leaves, treedef = jax.tree_util.tree_flatten(init_state(params, method))
    shapes = [leaf.shape for leaf in leaves]
    cuts = np.cumsum([int(np.prod(sh)) for sh in shapes])[:-1].tolist()

    def unflatten(flat):
        parts = jnp.split(flat, cuts)
        return jax.tree_util.tree_unflatten(treedef, [p.reshape(sh) for p, sh in
                                                      zip(parts, shapes)])

    def flatten(state):
        return jnp.concatenate([jnp.ravel(leaf) for leaf in jax.tree_util.tree_leaves(state)])

    def fn(flat, x, p=params):
        state = unflatten(flat)
        inputs = SensorSeries(x[0], x[1:1 + G], x[1 + G:])
        new, est = step(p, state, inputs, method)
        new_flat = flatten(new)
        ok = jnp.all(jnp.isfinite(new_flat))
        out = jnp.concatenate([est.angles, est.angle_std, ok[None].astype(x.dtype)])
        return jnp.where(ok, new_flat, flat), out

    return fn, flatten, unflatten


def _compiled_step(params: Params, method: str):
    """``stream_step_fn`` jitted; traced once (a retrace raises, via
    ``eqx.debug.assert_max_traces``)."""
    fn, flatten, unflatten = stream_step_fn(params, method)
    return jax.jit(eqx.debug.assert_max_traces(lambda flat, x: fn(flat, x), max_traces=1)), \
        flatten, unflatten


LOW_LATENCY_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def low_latency() -> None:
    """Settings for one-packet-at-a-time filtering on a CPU. Global; call before filtering.

    Turns off JAX's asynchronous CPU dispatch (a call per packet then costs about a third,
    ``../shared/notes/jax-cpu-hazards.md`` item 2) and, if no computation has run yet, keeps
    XLA's kernels on the calling thread (``LOW_LATENCY_XLA_FLAGS``; they are tiny, and a
    hand-off to a thread pool costs more than it saves)."""
    import os

    jax.config.update("jax_cpu_enable_async_dispatch", False)
    flags = os.environ.get("XLA_FLAGS", "")
    if "intra_op_parallelism_threads" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " " + LOW_LATENCY_XLA_FLAGS).strip()


# ---------------------------------------------------------------------------- sources
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
    nothing arrived for ``idle_timeout`` seconds, or ``should_stop()``. Returns counts."""
    import gc

    counts = {s: 0 for s in STATUSES}
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
            pkt = item if isinstance(item, Packet) else parser.parse(item)
        rec = sf.push(pkt)
        counts[rec["status"]] += 1
        sink.write(rec)
    sink.close()
    return {"packets": n, **{k: v for k, v in counts.items() if v}}

