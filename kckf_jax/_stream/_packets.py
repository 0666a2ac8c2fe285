"""Sensor packets: what a stream sends, parsed and validated, never raising.

A packet is one UTF-8 JSON object keyed by ``sensors.csv`` column names (``t`` required; a
missing key or ``null`` is a missing reading). ``PacketParser`` turns bytes into a ``Packet``
with a ``status`` (``STATUSES``); a reading it cannot use is treated as missing and named in
the packet's ``note``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

from .._models._limits import SensorLimits
from .._models._robot import Robot
from .._readings._screen import FAULT_KINDS, clean_bounds, screen

#: Every ``status`` an output line can carry (``kckf stream`` and ``export_loader.py`` alike).
#: Used packets: ``ok`` (absent readings, a missing key, ``null`` or NaN, are missing
#: readings, as an empty cell of ``sensors.csv``); ``masked`` (some readings were faulty: not
#: a number, infinite, outside the physical range (``SensorLimits``) or not a measurement
#: (railed, unreachable, saturated: ``_screen``), and were treated as missing, ``note`` names
#: them and ``Packet.faults`` gives each column's kind); ``gap`` (time jumped by more than
#: the gap limit; ``gap`` says whether the filter predicted across it or restarted).
#: Skipped packets (the state is unchanged): ``malformed`` (not UTF-8 JSON, not an
#: object), ``oversized``, ``missing_t``, ``bad_t`` (not a finite number),
#: ``out_of_order`` (``t`` not after the previous packet's), ``rejected`` (the update was
#: not finite), ``foreign`` (from another sender than the stream's one robot: not read).
STATUSES = ("ok", "masked", "gap", "malformed", "oversized", "missing_t", "bad_t",
            "out_of_order", "rejected", "foreign")
USED = ("ok", "masked", "gap")
MAX_PACKET_BYTES = 8192


@dataclass(frozen=True)
class HostScreen:
    """The part of ``Params`` that ``_screen.screen`` reads, as NumPy float64 arrays."""

    robot: Robot
    limits: SensorLimits
    hall_coeffs: tuple


def host_screen(params) -> HostScreen:
    """``params`` (``Params``) for judging readings on the host, packet by packet."""
    return HostScreen(params.robot, params.limits,
                      tuple(np.asarray(c, np.float64) for c in params.hall_coeffs))


@dataclass
class Packet:
    """One parsed packet: time (s, float64), readings (NaN = missing), status, note, the
    columns whose readings were faulty (``masked``) and ``{column: kind}`` for them
    (``faults``; ``_screen.FAULT_KINDS``, or ``"not_a_number"``). ``screened``: each reading
    was judged alone (``_screen.screen``: faulty ones missing; no gyro stood in for yet:
    ``StreamingFilter`` does it with the sensors' health over time), so ``StreamingFilter``
    need not judge them again."""

    t: float | None
    gyro: np.ndarray
    hall_v: np.ndarray
    status: str
    note: str = ""
    faulty: tuple[str, ...] = ()
    faults: dict | None = None
    screened: bool = False


class PacketParser:
    """Turns bytes into ``Packet``s for one robot; never raises.

    Example:
        >>> parser = PacketParser(Robot.from_spec("x"))
        >>> parser.parse(b'{"t": 0.01, "gyro1_x": 0.1, "hall1_x_l": 1.3}').status
        'ok'
        >>> parser.parse(b"garbage").status
        'malformed'
    """

    def __init__(self, robot: Robot, max_bytes: int = MAX_PACKET_BYTES,
                 limits: SensorLimits = SensorLimits(), params=None):
        """``params`` (``Params``, optional): judge every reading as the filter does
        (``_screen.screen``: railed, unreachable and saturated readings named and masked);
        without it only the physical range is checked."""
        self.robot = robot
        self.max_bytes = max_bytes
        self.limits = params.limits if params is not None else limits
        # What ``screen`` reads of the parameters, as NumPy (a JAX leaf per packet would cost
        # a dispatch each: ``Params.hall_coeffs`` is computed from the learned logs).
        self.params = None if params is None else host_screen(params)
        # Where ``screen`` finds nothing wrong with a reading: a packet inside needs no screen.
        self._bounds = None if params is None else clean_bounds(self.params)
        limits = self.limits
        self._names = robot.gyro_names + robot.hall_names
        self._slots = set(self._names)
        self._G, self._M = len(robot.gyro_names), robot.n_hall
        # The physical range of each reading (the kernel masks the same ones: SensorLimits).
        g, (lo, hi) = limits.gyro_rad_s, limits.hall_v
        self._lo = np.r_[np.full(self._G, -g), np.full(self._M, lo)]
        self._hi = np.r_[np.full(self._G, g), np.full(self._M, hi)]

    def clean(self, readings: np.ndarray) -> bool:
        """Whether ``screen`` would find nothing wrong with any of ``readings`` (``G + M``:
        gyros, then Hall sensors; a missing one, NaN, is fine): each inside its interval of
        ``_screen.clean_bounds``. Needs the parser to have been given ``params``."""
        lo, hi = self._bounds
        return not (np.less(readings, lo) | np.greater(readings, hi)).any()

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
        values = [obj.get(name) for name in self._names]
        try:  # fast path: numbers and nulls (None becomes NaN)
            if bool in map(type, values):
                raise TypeError
            arr = np.array(values, dtype=np.float64)
            problems = []
        except (TypeError, ValueError, OverflowError):
            arr, problems = self._slow_values(values)
        if arr.shape != (self._G + self._M,):  # lists of one length each: not readings
            arr, problems = self._slow_values(values)
        # The packet's readings are views of ``arr``, which is this packet's own.
        pkt = Packet(float(t), arr[: self._G], arr[self._G:], "ok")
        extra = ""
        if len(obj) - 1 > len(self._slots.intersection(obj)):
            unknown = [k for k in obj if k != "t" and k not in self._slots]
            extra = "ignored unknown key(s) " + ", ".join(repr(k[:30]) for k in unknown[:4])
        return self._finish(pkt, arr, problems, extra)

    def check(self, pkt: Packet) -> Packet:
        """A packet that did not come through ``parse`` (``replay://`` rows) validated the
        same way: its faulty readings (infinite, outside the physical range) masked."""
        if pkt.status not in ("ok", "masked"):
            return pkt
        arr = np.r_[pkt.gyro, pkt.hall_v].astype(np.float64)
        out = self.empty("ok", t=pkt.t)
        out = self._finish(out, arr, [], "", list(pkt.faulty))
        if pkt.status == "masked":
            out.status = "masked"
            out.faulty = tuple(dict.fromkeys(pkt.faulty + out.faulty))
            out.faults = {**(pkt.faults or {}), **(out.faults or {})}
        out.note = " | ".join(n for n in (pkt.note, out.note) if n)
        return out

    def _finish(self, pkt: Packet, arr: np.ndarray, problems: list[tuple[int, str]],
                extra: str = "", faulty: list[str] | None = None) -> Packet:
        """Mask the readings outside the physical range (absent ones, NaN, are missing and
        fine), fill ``pkt`` and set its status and note."""
        problems = list(problems)
        kinds = {i: "not_a_number" for i, _ in problems}
        if self._bounds is not None and not problems and self.clean(arr):
            pkt.gyro[:] = arr[: self._G]  # every reading clean or missing: screen says so
            pkt.hall_v[:] = arr[self._G:]
            pkt.screened = True
        elif self.params is not None:
            with np.errstate(invalid="ignore"):
                used = screen(self.params, arr[: self._G], arr[self._G:], np)
            codes = np.r_[used.gyro_code, used.hall_code]
            for i in map(int, np.flatnonzero(codes)):
                kind = FAULT_KINDS[codes[i] - 1]
                problems.append((i, f"{self._names[i]} = {arr[i]:.6g} {kind}"))
                kinds[i] = kind
            pkt.gyro[:] = used.gyro
            pkt.hall_v[:] = used.hall_v
            pkt.screened = True
        else:
            bad = np.less(arr, self._lo) | np.greater(arr, self._hi)  # NaN (missing): fine
            if bad.any():
                out = [int(i) for i in np.flatnonzero(bad)]
                problems += [(i, f"{self._names[i]} = {arr[i]:.6g} out of range") for i in out]
                kinds.update((i, "out_of_range") for i in out)
                arr[bad] = np.nan
            pkt.gyro[:] = arr[: self._G]
            pkt.hall_v[:] = arr[self._G:]
        notes = []
        if problems:
            pkt.status = "masked"
            problems.sort()
            notes.append("treated as missing: " + "; ".join(p for _, p in problems[:4]))
            pkt.faulty = tuple(dict.fromkeys((faulty or []) + [self._names[i]
                                                               for i, _ in problems]))
            pkt.faults = {self._names[i]: k for i, k in sorted(kinds.items())}
        if extra:
            notes.append(extra)
        pkt.note = " | ".join(notes)
        return pkt

    def _slow_values(self, values: list) -> tuple[np.ndarray, list[tuple[int, str]]]:
        arr = np.full(len(values), np.nan)
        problems = []
        for i, v in enumerate(values):
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, int | float):
                problems.append((i, f"{self._names[i]} is not a number"))
                continue
            try:
                arr[i] = float(v)
            except OverflowError:
                problems.append((i, f"{self._names[i]} is too large"))
        return arr, problems
