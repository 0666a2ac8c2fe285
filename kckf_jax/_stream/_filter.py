"""``StreamingFilter``: the batch filter's ``step``, one packet at a time, compiled once, with
the steady path's converged map on the host once a regular stream has converged."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._models._classes import (
    AbstractModel,
    estimated,
    exact_kinematics,
    init_state,
    method_name,
    model_of,
    structure,
)
from .._models._hall import hall_exponentials
from .._models._kernel import FilterState, SensorSeries
from .._models._params import Params
from .._paths import STEP_TOL_S, Steady, converged_map, readings_present, relative_change
from .._readings._gaps import GapPolicy
from .._readings._health import by_policy, health_step, init_health
from .._readings._prepare import ScreenedSeries, prepare_row
from .._readings._screen import FAULT_KINDS, screen
from ._packets import USED, Packet, PacketParser

#: Compiled once per parameter layout (``StreamingFilter.warmup`` compiles it up front).
_converged_map = eqx.filter_jit(converged_map)


class _HostMap:
    """The converged filter as one NumPy float64 matrix, for packets on the host.

    Once the covariance has converged (constant time step, every reading present), a packet
    changes the block states ``z`` by the affine map of ``_paths.converged_map``; with the
    Hall model's two exponentials as inputs (``theta = w1 e^(k1 V) + w2 e^(k2 V)``, Eq. 1 as
    ``_hall.hall_exponentials`` writes it) the whole step is one product ``M x`` for
    ``x = [z, (scratch), g_prev, e^(k1 V), e^(k2 V), g]``,
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
        self.used = robot.used_gyro_index
        Gu = len(self.used)
        (w1, w2), (k1, k2) = hall_exponentials(*(np.asarray(x, np.float64)
                                                 for x in params.hall_coeffs))
        Az = np.zeros((N, N))
        for p in range(nb):
            Az[p * nz:(p + 1) * nz, p * nz:(p + 1) * nz] = A[p]
        Wh = Wh.reshape(M, N).T
        # Columns: z | scratch (the previous angles and check, weight 0) | g_prev | e^(k1 V) |
        # e^(k2 V) | g (weight 0 but in the check).
        Mz = np.concatenate([Az, np.zeros((N, K + 1)), Wg.reshape(Gu, N).T, Wh * w1, Wh * w2,
                             np.zeros((N, Gu))], axis=1)
        Tang = np.zeros((K, N))  # angles from z: angle k is row slot_of[k] of T z in its block
        for k, (p, i) in enumerate(zip(st.block_of, st.slot_of)):
            Tang[k, p * nz:(p + 1) * nz] = st.T[i]
        check = np.ones((1, Mz.shape[1]))
        check[0, N:N + K + 1] = 0.0
        self.M = np.ascontiguousarray(np.vstack([Mz, Tang @ Mz, check]))
        self.k1, self.k2 = k1, k2  # exponents per volt
        self.N, self.K, self.nz, self.nb = N, K, nz, nb
        g0 = N + K + 1
        e0 = g0 + Gu

        def views(buf):  # (x, the product's target, g_prev, both exponentials, each, g)
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
        if abs(dt - self.dt) > STEP_TOL_S:
            return None
        x, _, _, e, eb, ed, g = self._views[self._cur]
        nxt = self._views[1 - self._cur]
        np.multiply(self.k1, hall_v, out=eb)
        np.multiply(self.k2, hall_v, out=ed)
        np.exp(e, out=e)
        gyro.take(self.used, out=g)  # the method: np.take adds a Python wrapper
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


class StreamingFilter:
    """The batch filter's ``step``, one packet at a time, compiled once.

    Args:
        params: filter parameters (their dtype sets the precision).
        method: a model of ``_models`` or its name (``METHODS``).
        gap_s, on_gap, max_predict_s: the gap policy, as the batch filter's (``GapPolicy``):
            a time step longer than ``gap_s`` is a gap (status ``gap``), predicted across
            (``"predict"``: the covariance grows with it) or restarted from the initial state
            at this packet (``"restart"``, or a gap longer than ``max_predict_s``, default
            ``GapPolicy``'s 1 s, or one whose prediction overflows).
        host_path: allow the host path (below; off by default: it skips the sensors'
            health over time).
        steady: the ``Steady`` path whose constants the host path follows (its head length
            and convergence tolerance).

    The state stays on the device between packets; per packet, one array of readings goes in
    and one array of estimates comes out. The step is ``kckf export``'s: it judges every
    reading as the batch filter does (``_screen``, and the sensors' health over time,
    ``_health``, whose state it carries), and the packet's record names what it did not use.
    On CPU, Python's dispatch of the jitted call dominates the latency: ``low_latency()``
    turns off JAX's async dispatch, which the ``kckf stream`` command does (see
    benchmarks/README.md).

    **Host path** (``host_path=True``, the KCKF with the constant Hall noise model; for a
    trusted regular stream whose latency matters more than the sensors' health over time,
    which it does not follow: each reading is still judged alone, and the health monitor
    starts afresh when the device step takes over again): once the
    packets arrive at a constant time step with every reading and the covariance has
    converged (after ``steady.head_rows`` such packets, checked every ``HOST_CHECK_EVERY``
    with the steady path's own convergence measure and tolerance), the filter is the steady
    path's affine map (``_paths.converged_map``)
    and each packet is one NumPy product on the host, with no jitted call (``on_host``). Any
    other packet (another time step, a missing or masked reading, a gap) hands the state back
    to the device step for that packet, and the watch starts again. The estimates are the
    device step's to rounding.

    Example:
        >>> sf = StreamingFilter(Params.paper_defaults(Robot.from_spec("x")))
        >>> sf.push(PacketParser(sf.robot).parse(b'{"t": 0.0, "hall1_x_l": 1.3}'))["status"]
        'ok'
    """

    def __init__(self, params: Params, method: str | AbstractModel = "kckf", *, gap_s: float = 0.5,
                 on_gap: str = "predict", max_predict_s: float | None = None,
                 host_path: bool = False, steady: Steady = Steady()):
        method = method_name(method)
        self.params, self.method, self.robot = params, method, params.robot
        # On the host path, packets that did not come through a parser given these parameters
        # are judged here, as the step would (``_screen``): it must never use a reading the
        # step would not. The device step judges every packet itself.
        self._checker = PacketParser(params.robot, params=params)
        # The batch filter's gap policy (the same threshold and options: GapPolicy).
        self.gaps = GapPolicy(float(gap_s), on_gap,
                              None if max_predict_s is None else float(max_predict_s))
        self.dtype = params.log_q.dtype
        self._G, self._M = 3 * self.robot.n_links, self.robot.n_hall
        self._K = self.robot.n_angles
        self.names = self.robot.angle_names
        self._estimated = estimated(self.robot, method)
        self._named = [(k, n) for k, (n, e) in enumerate(zip(self.names, self._estimated))
                       if e]
        self._every = len(self._named) == self._K  # every angle estimated
        self._fn, self._flatten, self._unflatten = _compiled_step(params, method)
        self._x = np.empty(1 + self._G + self._M, dtype=self.dtype)
        self._fresh_health = init_health(self.robot, self.dtype)
        self._initial = jax.device_put(self._flatten((init_state(params, method),
                                                      self._fresh_health)))
        self._fault_names = self.robot.gyro_names + self.robot.hall_names
        # The host map folds Eq. 1 into one product: learned corrections of the readings
        # (``Params.effects``) are the jitted step's.
        self._host_ok = (host_path and steady.model_reason(params, method) is None
                         and (params.effects is None or not params.effects.on))
        self._used = self.robot.used_gyro_index
        # A packet whose readings all lie where ``screen`` finds nothing wrong needs no
        # screening on the host path (``PacketParser.clean``).
        self._clean_x = np.empty(self._G + self._M)
        self._tol = steady.tol(self.dtype)
        # As in the batch steady path: at least its head of regular rows before switching.
        self._min_regular = steady.head_rows(self.dtype)
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
            _HostMap(self.params, self.method, self._unflatten(self._state)[0].P, 0.01)
        self.reset()

    @property
    def host_after(self) -> int:
        """Regular complete packets after which the host path has engaged, if the covariance
        has converged by then (the steady path's head, then two checks)."""
        return max(HOST_CHECK_EVERY, self._min_regular) + 2 * HOST_CHECK_EVERY

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
        return self._unflatten(self._state)[0]

    def _host_state(self) -> FilterState:
        host = self._host
        hold = self._hold_host.copy()
        hold[self._used] = host.gyro_prev()
        return FilterState(jnp.asarray(host.z(), self.dtype), jnp.asarray(host.P, self.dtype),
                           jnp.asarray(hold, self.dtype))

    def _leave_host(self) -> None:
        self._state = jax.device_put(self._flatten((self._host_state(), self._fresh_health)))
        self._host = None
        self._regular, self._last_dt, self._P_check = 0, None, None

    def _watch(self, dt: float, pkt: Packet) -> None:
        """After a device step: count regular complete packets (the batch paths' regularity
        check, packet by packet) and, from the steady path's head length on, every
        ``HOST_CHECK_EVERY`` compare the covariance over one step; once it has converged,
        switch to the host path."""
        gyro_ok, hall_ok = readings_present(self._checker.params, pkt.gyro, pkt.hall_v, np)
        complete = dt > 0 and bool(gyro_ok) and bool(hall_ok)
        if complete and self._last_dt is not None and abs(dt - self._last_dt) <= STEP_TOL_S:
            self._regular += 1
        else:
            self._regular, self._P_check = 0, None
        self._last_dt = dt if complete else None
        phase = self._regular % HOST_CHECK_EVERY
        if self._regular < max(HOST_CHECK_EVERY, self._min_regular) or phase > 1:
            return
        state = self._unflatten(self._state)[0]
        P = np.asarray(state.P, np.float64)
        if phase == 0:
            self._P_check = P
            return
        if self._P_check is None:
            return
        if relative_change(self._P_check, P, np) <= self._tol:
            self._host = _HostMap(self.params, self.method, state.P, dt)
            self._hold_host = np.asarray(state.gyro_hold, np.float64)
            self._host.start(np.asarray(state.z, np.float64), self._hold_host)

    def push(self, pkt: Packet) -> dict:
        """Filter one packet; returns the output record (``t``, angles in rad, ``status``)."""
        if pkt.status not in USED:
            return self._record(pkt.t, pkt.status, pkt.note)
        if self._host is not None and not pkt.screened and not self._clean(pkt):
            pkt = self._checker.check(pkt)  # the host path must see only usable readings
        if self.t_prev is not None and not pkt.t > self.t_prev:
            return self._record(pkt.t, "out_of_order",
                                f"t = {pkt.t!r} is not after the previous t = {self.t_prev!r}")
        status, note, extra = pkt.status, pkt.note, {}
        dt = 0.0 if self.t_prev is None else pkt.t - self.t_prev  # float64 on the host
        action = self.gaps.action(dt)
        if action is not None:
            status = "gap"
            extra = {"gap": action, "gap_s": dt}
            if action == "restart":
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
        angles, codes = out
        if codes is not None:  # what the step did not use, named
            bad = {self._fault_names[i]: FAULT_KINDS[int(c) - 1]
                   for i, c in enumerate(codes) if c}
            new = {n: k for n, k in bad.items() if (pkt.faults or {}).get(n) != k}
            pkt.faults = {**(pkt.faults or {}), **bad}
            pkt.faulty = tuple(dict.fromkeys(pkt.faulty + tuple(bad)))
            if new:
                text = "not used: " + "; ".join(f"{n} {k}" for n, k in new.items())
                note = " | ".join(x for x in (note, text) if x)
            status = "masked" if status == "ok" else status
        rec = self._record(pkt.t, status, note, angles)
        rec.update(extra)
        return rec

    def _clean(self, pkt: Packet) -> bool:
        """Whether ``screen`` would find nothing wrong with any of the packet's readings
        (each inside ``_screen.clean_bounds``' interval, or missing)."""
        x = self._clean_x
        x[:self._G] = pkt.gyro
        x[self._G:] = pkt.hall_v
        return self._checker.clean(x)

    def _run(self, dt: float, pkt: Packet) -> tuple[np.ndarray | list, list | None] | None:
        """One step: on the host path when it applies, else on the device; the new state is
        kept only when it is finite. Returns the angles and each reading's fault code (the
        device step's, where any is not 0; else ``None``), or ``None``."""
        if self._host is not None:
            angles = self._host.step(dt, pkt.gyro, pkt.hall_v)
            if angles is not None:
                return angles, None
            self._leave_host()
        x = self._x
        x[0] = dt
        x[1:1 + self._G] = pkt.gyro
        x[1 + self._G:] = pkt.hall_v
        state, out = self._fn(self._state, x)
        # One conversion to Python floats: NumPy's calls on a few numbers cost more than the
        # numbers (a microsecond each).
        out = np.asarray(out).tolist()
        K = self._K
        if out[2 * K] < 0.5:
            return None
        self._state = state
        if self._host_ok:
            self._watch(dt, pkt)
        codes = out[2 * K + 1:]
        return out[:K], (codes if any(codes) else None)

    def _record(self, t, status, note="", angles=None) -> dict:
        rec: dict = {"t": t}
        if angles is not None:
            values = angles.tolist() if isinstance(angles, np.ndarray) else angles
            if self._every and math.isfinite(sum(values)):
                rec.update(zip(self.names, values))
            else:
                # An angle not estimated yet (a Hall baseline before its first reading) is
                # left out, as one the method never estimates.
                for k, n in self._named:
                    a = values[k]
                    if math.isfinite(a):
                        rec[n] = a
        rec["status"] = status
        if note:
            rec["note"] = note
        return rec


def stream_step_fn(params: Params, method: str, health: bool = False):
    """The pure per-packet function ``(s, x) -> (s, [angles, std, ok])`` over ``step``.

    ``s`` is the whole filter state flattened into one vector and ``x = [dt, gyro (G),
    hall_v (M)]``: two arrays in, two out (dispatch cost on CPU grows with every argument). A
    non-finite result (impossible for finite readings, but the stream must survive anything)
    leaves the state as it was and reports ``ok = 0``. ``health``: ``s`` also carries the
    sensors' health (``_health``: ``(FilterState, Health)`` unflattened) and the step judges
    each packet's readings first, as the batch filter does, and the output ends with each
    reading's fault code (``G + M``: ``_screen.FAULT_KINDS``), so the stream and a deployment
    name them (``StreamingFilter`` and ``kckf export`` both take it). Returns ``(fn,
    flatten, unflatten)``; ``StreamingFilter`` jits it, ``kckf export`` serialises it.
    """
    G = 3 * params.robot.n_links
    dtype = params.log_q.dtype
    exact = exact_kinematics(method)
    start = init_state(params, method)
    if health:
        start = (start, init_health(params.robot, dtype))
    leaves, treedef = jax.tree_util.tree_flatten(start)
    shapes = [leaf.shape for leaf in leaves]
    kinds = [leaf.dtype for leaf in leaves]
    cuts = np.cumsum([int(np.prod(sh)) for sh in shapes])[:-1].tolist()

    def unflatten(flat):
        parts = jnp.split(flat, cuts)
        return jax.tree_util.tree_unflatten(treedef, [
            (p > 0.5 if k == np.bool_ else p).reshape(sh)
            for p, sh, k in zip(parts, shapes, kinds)])

    def flatten(state):
        return jnp.concatenate([jnp.ravel(leaf).astype(dtype)
                                for leaf in jax.tree_util.tree_leaves(state)])

    def one(flat, x, p):
        state = unflatten(flat)
        inputs = SensorSeries(x[0], x[1:1 + G], x[1 + G:])
        if health:
            state, h = state
            used = screen(p, inputs.gyro, inputs.hall_v)
            watched = None
            if p.faults.monitors:  # as the batch filter's ``_health.screened_series``
                h, *watched = health_step(p, h, inputs.dt, used.gyro, used.hall_v, exact)
            gyro, hall_v, codes = by_policy(p.faults, used, watched)
            inputs = ScreenedSeries(inputs.dt, gyro, hall_v)  # judged: not screened again
        state, row = prepare_row(p, state, inputs, method)
        # (the model's forward-only form: ``packet_step``; a non-finite update keeps the state)
        new, est = model_of(method).packet_step(p, state, row)
        ok = ~est.skipped
        out = [est.angles, est.angle_std, ok[None].astype(x.dtype)]
        if health:
            new = (new, h)
            out.append(codes.astype(x.dtype))
        return flatten(new), jnp.concatenate(out)

    def fn(flat, x, p=params):
        return _one_kernel(lambda s, y: one(s, y, p), flat, x)

    return fn, flatten, unflatten


def _one_kernel(fn, flat, x):
    """``fn(flat, x)`` as the one pass of an XLA while loop, so that XLA's CPU compiles the
    whole step as one kernel.

    Outside a loop, XLA's CPU runtime runs a program kernel by kernel ("thunks"), and each
    costs about half a microsecond to launch whatever it computes: the step with the sensors'
    health is about 90 kernels of a few numbers each (``python benchmarks/stream_latency.py
    --parts``). A while loop whose body has no dot, custom call or collective is compiled as
    one function instead (``_cpu_loops``: on jax 0.10 once ``enable_cpu_loops()`` has run, on
    0.12 by default). The loop runs once, and not at all for a packet whose time step is not
    a number (the state kept, ``ok = 0``: what the step says of a non-finite update); the
    readings pass through the loop's carry so that XLA cannot move their arithmetic out of
    the loop (its invariant code motion), where it would be kernels again. The same
    arithmetic either way, compiled otherwise: equal to float32 rounding, the same faults
    named (tests/test_stream.py)."""
    out = jax.eval_shape(fn, flat, x)[1]

    def body(carry):
        go, s, y, _ = carry
        s, o = fn(s, y)
        return jnp.zeros_like(go), s, jnp.where(go, y, jnp.nan), o

    go = ~jnp.isnan(x[0])
    _, flat, _, o = jax.lax.while_loop(lambda c: c[0], body,
                                       (go, flat, x, jnp.zeros(out.shape, out.dtype)))
    return flat, o


def _compiled_step(params: Params, method: str):
    """``stream_step_fn`` jitted; traced once (a retrace raises, via
    ``eqx.debug.assert_max_traces``)."""
    fn, flatten, unflatten = stream_step_fn(params, method, health=True)
    return jax.jit(eqx.debug.assert_max_traces(lambda flat, x: fn(flat, x), max_traces=1)), \
        flatten, unflatten


#: XLA's kernels on the calling thread (a flag of jax 0.10-0.12's XLA: an unknown flag aborts
#: XLA when its backend starts).
LOW_LATENCY_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false"


def low_latency() -> None:
    """Settings for one-packet-at-a-time filtering on a CPU. Global; call before filtering.

    Turns off JAX's asynchronous CPU dispatch (a call per packet then costs about a third,
    ``../shared/notes/jax-cpu-hazards.md`` item 2) and, if no computation has run yet, keeps
    XLA's Eigen kernels on the calling thread (``LOW_LATENCY_XLA_FLAGS``; they are tiny, and a
    hand-off to a thread pool costs more than it saves)."""
    import os

    jax.config.update("jax_cpu_enable_async_dispatch", False)
    flags = os.environ.get("XLA_FLAGS", "")
    if LOW_LATENCY_XLA_FLAGS not in flags:
        os.environ["XLA_FLAGS"] = (flags + " " + LOW_LATENCY_XLA_FLAGS).strip()


