"""Sensor faults written into a session on request (``kckf simulate --fault``; issue 33).

A ``Fault`` names what goes wrong, on which column, when and how badly; ``inject_faults``
returns a new ``Session`` with the faults written into its readings (or, for ``coeff``, its
calibration), so that users can check that their setup notices them and the tests and
benchmarks have faulty data whose every fault is known. The truth (motion capture) is never
changed, and every injected fault is recorded, with its resolved span and size, in
``extra_meta["simulated_faults"]`` (``meta.json``'s ``simulated_faults``; readers keep and
ignore it).

The text form, as ``kckf simulate --fault`` takes it (times in s on the sensor clock ``t``,
inclusive; sizes in the column's unit, V or rad/s)::

    KIND:COLUMN[@FROM-TO][=SIZE]     noise:hall2_y_r@10-12=0.5
    KIND:COLUMN@FROM                 bias_step:gyro3_x@30=0.2   (from 30 s to the end)
    KIND:COLUMN@-TO                  dropout:gyro1_y@-5         (from the start to 5 s)
    gap@FROM-TO                      gap@120-720                (a gap has no column)

No span means the whole session; no size means the kind's default (``docs/simulator.md``,
"Faults on request", gives each default and its physical reason).

Plain NumPy, like the simulator: the edge of the package, never imported by the numerics.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import re
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .._models._hall import DEG, PAPER_HALL_DEG
from .._models._limits import SensorLimits
from ._session import Session

#: Every kind of fault, in the order the docs list them.
FAULT_KINDS = (
    "disconnect", "short", "noise", "stuck", "flicker", "clip", "bias_step", "blank",
    "dropout", "coeff", "swap", "sign", "gap", "drift",
)
#: ``extra_meta`` (``meta.json``) key of the record of injected faults.
META_KEY = "simulated_faults"
#: The simulator's LSM6DSO full scale, +-250 dps (ST DS12140, Table 2: 8.75 mdps/LSB): a noisy
#: gyro reading saturates there.
GYRO_FULL_SCALE_RAD_S = 250.0 * DEG
#: The simulator's converters, used when a session does not carry its ``simulation.config``:
#: a 12-bit ADC on 3.3 V (0.81 mV a step) and the gyro's 8.75 mdps step.
ADC_BITS = 12
GYRO_LSB_RAD_S = 8.75e-3 * DEG

# What each kind applies to ("hall": a Hall column such as hall1_x_l, "gyro": a gyro column such
# as gyro2_x, "joint": a joint axis such as hall1_x, whose _l and _r columns; none: no column),
# whether it takes a span ("optional", "none": always the whole session or none at all,
# "required": FROM-TO), whether it takes a size, and whether that size may be negative.
_APPLIES = {
    "disconnect": ("hall",), "short": ("hall",), "noise": ("hall", "gyro"),
    "stuck": ("hall", "gyro"), "flicker": ("hall",), "clip": ("gyro",),
    "bias_step": ("gyro",), "blank": ("gyro",), "dropout": ("hall", "gyro"),
    "coeff": ("hall",), "swap": ("joint",), "sign": ("gyro",), "gap": (), "drift": ("hall",),
}
_SPAN = {"coeff": "none", "sign": "none", "gap": "required"}  # the others: "optional"
_SIZELESS = ("dropout", "swap", "sign", "gap")
_SIGNED = ("bias_step", "stuck", "drift")  # signed: a step, a reading, an offset
#: Default sizes that do not depend on the session (``short``'s is the ADC's top,
#: ``disconnect``'s its bottom, ``stuck``'s the reading at FROM).
DEFAULT_SIZE = {
    ("noise", "hall"): 0.5, ("noise", "gyro"): 1.0, ("flicker", "hall"): 0.3,
    ("clip", "gyro"): 2.0, ("bias_step", "gyro"): 0.2, ("blank", "gyro"): 1.2,
    ("coeff", "hall"): 10.0, ("drift", "hall"): 0.25,
}
# Salts the fault seed so that its draws share nothing with the simulator's own streams.
_SALT = 4099
_NUM = r"(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"
_TEXT_RE = re.compile(r"(?P<kind>[A-Za-z_]+)(?::(?P<column>[^@=]*))?(?:@(?P<span>[^=]*))?"
                      r"(?:=(?P<size>.*))?")
_SPAN_RE = re.compile(rf"(?P<a>{_NUM})?(?P<dash>-)?(?P<b>{_NUM})?")
_COLUMN_RE = {
    "hall": re.compile(r"hall\d+_[xyz]_[lr]"),
    "gyro": re.compile(r"gyro\d+_[xyz]"),
    "joint": re.compile(r"hall\d+_[xyz]"),
}
_SYNTAX = "KIND:COLUMN[@FROM-TO][=SIZE] or gap@FROM-TO"


@dataclass(frozen=True)
class Fault:
    """One sensor fault to write into a session (``inject_faults``).

    Attributes:
        kind: one of ``FAULT_KINDS``:

            * ``disconnect`` (Hall): reads ``size`` V, default the ADC's bottom (0 V): an open
              wire on an ADC input with a pull-down, the sensor's output no longer driving it.
            * ``short`` (Hall): reads ``size`` V, default the ADC's top (the session's
              ``hall_v_range`` hi, 3.3 V): the output shorted to the supply. A DRV5053 drives
              0.2-1.8 V (TI SLIS153), so a railed reading is the wiring, never the field.
            * ``noise`` (Hall or gyro): Gaussian noise of std ``size`` added (Hall default
              0.5 V, about half the 1.0-2.2 V the curve spans over +-30 deg: a broken shield or
              ground picking up the body's and the motors' fields; gyro default 1.0 rad/s,
              about the median rate of the motion: a gyro rattling loose on its link), then
              quantised like the simulator's converters (12-bit ADC, 8.75 mdps) and clipped to
              their range (the ADC's, the LSM6DSO's +-250 dps).
            * ``stuck`` (Hall or gyro): holds the reading it had at ``from_s`` (or ``size``):
              a frozen ADC channel or a gyro whose data-ready stopped, the last value resent.
            * ``flicker`` (Hall): each reading in the span reads the ADC's bottom (0 V) with
              probability ``size`` (default 0.3): an intermittent contact in a wire that bends
              with the hinge.
            * ``clip`` (gyro): saturates at +-``size`` rad/s (default 2.0, just below the
              LSM6DSO's smallest full scale, +-125 dps = 2.18 rad/s: a gyro left at that range;
              the bench motion's upper links exceed it 10-30 % of the time).
            * ``bias_step`` (gyro): ``size`` rad/s (default 0.2 = 11.5 dps, ten times the
              LSM6DSO's +-1 dps zero-rate level) added from ``from_s`` on: an offset shift after
              a knock or a reset of the gyro's offset registers.
            * ``blank`` (gyro): missing (NaN) wherever ``|reading| >= size`` rad/s (default
              1.2): a logger that drops the rates it considers implausible; the bench motion's
              upper links exceed it 40-60 % of the time, its lower ones rarely.
            * ``dropout`` (any column): missing over the span: a sensor that stopped answering.
            * ``coeff`` (Hall): ``meta.json``'s Eq. 1 coefficient ``a`` multiplied by ``size``
              (default 10): a wrong calibration (another sensor's, or the wrong unit), the
              readings unchanged. No span.
            * ``swap`` (a joint axis, ``hall1_x``): its ``_l`` and ``_r`` columns exchanged
              (the whole session, or the span): two connectors plugged the wrong way round.
            * ``sign`` (gyro): negated for the whole session: an axis mounted with the wrong
              sign. No span.
            * ``gap`` (no column): every sensor row in the span removed, the timestamps
              jumping over it (a logger that stopped); the motion capture is untouched.
            * ``drift`` (Hall): an offset growing steadily from 0 at the span's first row to
              ``size`` V at its last (default 0.25 V; signed), then quantised and clipped like
              ``noise``: a sensor warming up, or a magnet creeping in its mount.

        column: a sensor column of the robot (``hall2_y_r``, ``gyro3_x``), a joint axis for
            ``swap`` (``hall1_x``), ``None`` for ``gap``.
        from_s, to_s: the span on the sensor clock, s, both ends included; ``None`` means the
            session's first or last row.
        size: how bad, in the column's unit (V, rad/s; a probability for ``flicker``, a factor
            for ``coeff``); ``None`` means the kind's default.

    Example:
        >>> f = Fault.parse("noise:hall2_y_r@10-12=0.5")
        >>> f, str(f)
        (Fault(kind='noise', column='hall2_y_r', from_s=10.0, to_s=12.0, size=0.5), 'noise:hall2_y_r@10-12=0.5')
    """  # noqa: E501

    kind: str
    column: str | None
    from_s: float | None = None
    to_s: float | None = None
    size: float | None = None

    def __post_init__(self):
        for name in ("from_s", "to_s", "size"):
            value = getattr(self, name)
            if value is None:
                continue
            number = isinstance(value, int | float | np.integer | np.floating)
            if isinstance(value, bool) or not number or not math.isfinite(value):
                raise ValueError(f"fault {self._name()}: {name} must be a finite number, got "
                                 f"{value!r}")
            object.__setattr__(self, name, float(value))
        _check(self.kind, self.column, self.from_s, self.to_s, self.size,
               f"fault {self._name()}")

    # ------------------------------------------------------------------ text and JSON
    @classmethod
    def parse(cls, text: str) -> Fault:
        """A fault from its text form ``KIND:COLUMN[@FROM-TO][=SIZE]`` (``gap@FROM-TO``);
        ``@FROM`` runs to the end, ``@-TO`` from the start. ``ValueError`` (one line) naming
        what is wrong and what was expected."""
        text = text.strip()
        m = _TEXT_RE.fullmatch(text)
        if not m:
            raise ValueError(f"fault {text!r}: expected {_SYNTAX}")
        kind, column, span, size = m.group("kind", "column", "span", "size")
        if kind not in FAULT_KINDS:
            raise ValueError(f"fault {text!r}: unknown kind {kind!r}; expected one of "
                             f"{', '.join(FAULT_KINDS)}")
        from_s = to_s = None
        if span is not None:
            s = _SPAN_RE.fullmatch(span)
            if not s or not (s["a"] or s["b"]) or (s["a"] and s["b"] and not s["dash"]):
                raise ValueError(f"fault {text!r}: span {span!r} is not FROM-TO, FROM (to the "
                                 "end) or -TO (from the start), in s")
            from_s = float(s["a"]) if s["a"] else None
            to_s = float(s["b"]) if s["b"] else None
        value = None
        if size is not None:
            try:
                value = float(size)
            except ValueError:
                value = math.nan
            if not math.isfinite(value):
                raise ValueError(f"fault {text!r}: size {size!r} is not a finite number")
        _check(kind, column, from_s, to_s, value, f"fault {text!r}")  # as the user wrote it
        return cls(kind, column, from_s, to_s, value)

    def __str__(self) -> str:
        """The text form (``Fault.parse(str(f)) == f``)."""
        out = self.kind + (f":{self.column}" if self.column is not None else "")
        if self.from_s is not None or self.to_s is not None:
            a = _num(self.from_s) if self.from_s is not None else ""
            b = f"-{_num(self.to_s)}" if self.to_s is not None else ""
            out += f"@{a}{b}"
        if self.size is not None:
            out += f"={_num(self.size)}"
        return out

    def to_json(self) -> dict:
        """``{"kind", "column", "from_s", "to_s", "size"}`` (``None`` as null)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, doc: object) -> Fault:
        """The inverse of ``to_json`` (missing optional keys are ``None``); ``doc`` is any
        parsed JSON, ``ValueError`` unless it is such an object."""
        if not isinstance(doc, Mapping):
            raise ValueError(f"fault: expected a JSON object, got {type(doc).__name__}")
        fields = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(doc) - set(fields))
        if unknown:
            raise ValueError(f"fault: unknown key {unknown[0]!r}; expected {', '.join(fields)}")
        kind, column = doc.get("kind"), doc.get("column")
        if not isinstance(kind, str):
            raise ValueError(f"fault: 'kind' must be one of {', '.join(FAULT_KINDS)}, got "
                             f"{kind!r}")
        if column is not None and not isinstance(column, str):
            raise ValueError(f"fault: 'column' must be a column name or null, got {column!r}")
        for key in ("from_s", "to_s", "size"):
            value = doc.get(key)
            if value is not None and (isinstance(value, bool)
                                      or not isinstance(value, int | float)):
                raise ValueError(f"fault: {key!r} must be a number or null, got {value!r}")
        return cls(kind, column, doc.get("from_s"), doc.get("to_s"), doc.get("size"))

    def _name(self) -> str:
        try:
            return repr(str(self))
        except (TypeError, ValueError):
            return repr(self)


def _check(kind, column, from_s, to_s, size, where: str) -> None:
    """What can be checked of a fault without a session (``_rows`` and ``_size`` check the
    rest); ``where`` starts every message."""
    if not isinstance(kind, str) or kind not in FAULT_KINDS:
        raise ValueError(f"{where}: unknown kind {kind!r}; expected one of "
                         f"{', '.join(FAULT_KINDS)}")
    if kind == "gap":
        if column is not None:
            raise ValueError(f"{where}: a gap takes no column (got {column!r}); expected "
                             "gap@FROM-TO")
    elif not isinstance(column, str) or not column:
        raise ValueError(f"{where}: {kind} needs a column ({_what(kind)}); expected "
                         f"{kind}:COLUMN")
    else:
        ctype = _column_type(column)
        if ctype is None:
            raise ValueError(f"{where}: column {column!r} is not a sensor column; expected "
                             f"{_what(kind)}")
        if ctype not in _APPLIES[kind]:
            raise ValueError(f"{where}: {kind} does not apply to {_TYPE_WORDS[ctype]} "
                             f"{column!r}; expected {_what(kind)}")
    span = _SPAN.get(kind, "optional")
    if span == "none" and (from_s is not None or to_s is not None):
        raise ValueError(f"{where}: {kind} takes no span (it holds for the whole session); "
                         f"expected {kind}:COLUMN" + ("" if kind in _SIZELESS else "[=SIZE]"))
    if span == "required" and (from_s is None or to_s is None):
        raise ValueError(f"{where}: a gap needs both ends of its span; expected gap@FROM-TO "
                         "(s)")
    if from_s is not None and to_s is not None and from_s > to_s:
        raise ValueError(f"{where}: the span starts at {_num(from_s)} s, after its end "
                         f"{_num(to_s)} s; expected FROM <= TO")
    if size is None:
        return
    if kind in _SIZELESS:
        raise ValueError(f"{where}: {kind} takes no size (got {_num(size)})")
    if size < 0 and kind not in _SIGNED:
        raise ValueError(f"{where}: size {_num(size)} is negative; expected "
                         f"{_SIZE_WORDS[kind]}")
    if kind in ("clip", "blank", "coeff") and size == 0:
        raise ValueError(f"{where}: size 0 is not positive; expected {_SIZE_WORDS[kind]}")
    if kind == "flicker" and size > 1:
        raise ValueError(f"{where}: size {_num(size)} is not a probability; expected "
                         f"{_SIZE_WORDS[kind]}")


_TYPE_WORDS = {"hall": "the Hall column", "gyro": "the gyro column", "joint": "the joint axis"}
_SIZE_WORDS = {
    "disconnect": "the voltage it reads, V, in the ADC's range",
    "short": "the voltage it reads, V, in the ADC's range",
    "noise": "a standard deviation >= 0 (V for Hall, rad/s for gyro)",
    "stuck": "the reading it holds",
    "flicker": "a probability in 0..1",
    "clip": "the saturation level > 0, rad/s",
    "bias_step": "the step, rad/s",
    "blank": "the rate > 0 from which a reading is missing, rad/s",
    "drift": "the offset reached at the span's end, V",
    "coeff": "a factor > 0 on the coefficient a",
}


def _what(kind: str) -> str:
    """What a kind's column must be, in words."""
    words = {"hall": "a Hall column like hall1_x_l", "gyro": "a gyro column like gyro2_x",
             "joint": "a joint axis like hall1_x (its _l and _r columns)"}
    return " or ".join(words[c] for c in _APPLIES[kind])


def _column_type(column: str) -> str | None:
    for ctype, pattern in _COLUMN_RE.items():
        if pattern.fullmatch(column):
            return ctype
    return None


def _num(x: float) -> str:
    """A number for the text form: the shortest round-trip repr, ``20`` for ``20.0``."""
    r = repr(float(x))
    return r[:-2] if r.endswith(".0") else r


# ---------------------------------------------------------------------- injecting
def inject_faults(session: Session, faults: Sequence[Fault], seed: int = 0) -> Session:
    """A new session with ``faults`` written into ``session`` (whose arrays are not changed).

    The faults act in the order given (a later one on the readings an earlier one left); a
    ``gap`` removes its rows after all the others, so every span refers to the input's clock.
    A reading that was missing stays missing, except where a fault writes it (a missing
    reading is the link's loss, not the sensor's): only ``dropout``, ``blank`` and ``gap`` make
    readings missing. The motion capture is copied unchanged.

    Args:
        session: the clean session (simulated or recorded).
        faults: what to write (``Fault``; ``Fault.parse`` reads the text form).
        seed: seeds the random faults (``noise``, ``flicker``); each fault draws from its own
            stream, keyed by its resolved text form, so adding a fault changes no other
            fault's draws and the record of a fault draws what the fault drew.

    Returns:
        A ``Session`` (``path`` None) whose ``extra_meta["simulated_faults"]`` lists the
        injected faults (``Fault.to_json``) with resolved span and size, after any already
        recorded there.

    Raises:
        ValueError: one line naming the fault and what was expected: a column that is not the
            robot's, a span outside the session or holding no sensor row, a size outside the
            sensor's range, a gap that would leave no rows before or after it.

    Example:
        >>> from kckf_jax import simulate
        >>> clean = simulate("x,y,x,y", "cyclic", seed=1, duration_s=10.0)
        >>> bad = inject_faults(clean, [Fault.parse("disconnect:hall1_x_l@2-3")])
        >>> float(bad.hall_v[250, 0]), bad.extra_meta["simulated_faults"][0]["size"]
        (0.0, 0.0)
    """
    faults = list(faults)
    for f in faults:
        if not isinstance(f, Fault):
            raise ValueError(f"inject_faults: expected Fault objects, got {type(f).__name__}")
    robot, t = session.robot, session.t
    limits = session.limits or SensorLimits()
    adc_step, gyro_lsb = _converters(session)
    gyro, hall = session.gyro.copy(), session.hall_v.copy()
    hall_models = copy.deepcopy(session.hall_models)
    extra_meta = copy.deepcopy(session.extra_meta)
    recorded = extra_meta.get(META_KEY, [])
    if not isinstance(recorded, list):
        raise ValueError(f"inject_faults: extra_meta[{META_KEY!r}] must be a list, got "
                         f"{type(recorded).__name__}")
    keep = np.ones(t.shape[0], dtype=bool)
    texts = []  # the resolved faults' text forms, which key their random streams
    for fault in faults:
        rows = _rows(fault, session)
        size = _size(fault, session, limits)
        span = _resolved_span(fault, session)
        texts.append(str(Fault(fault.kind, fault.column, *span, size)))
        key = [seed, _SALT, zlib.crc32(texts[-1].encode()), texts.count(texts[-1])]
        rng = np.random.default_rng(np.random.SeedSequence(key))
        kind, column = fault.kind, fault.column
        if kind == "gap":
            keep &= ~rows
        elif kind == "coeff":
            model = hall_models.get(column)
            if model is None:
                side = robot.hall_side_sign[robot.hall_names.index(column)]
                model = dict(PAPER_HALL_DEG, sign=int(side), unit="deg")
            hall_models[column] = {**model, "a": float(model["a"]) * size}
        elif kind == "swap":
            left, right = (robot.hall_names.index(f"{column}_{s}") for s in "lr")
            hall[rows, left], hall[rows, right] = hall[rows, right], hall[rows, left]
        else:
            arrays = hall if column in robot.hall_names else gyro
            names = robot.hall_names if arrays is hall else robot.gyro_names
            k = names.index(column)
            col = arrays[:, k]
            if kind == "stuck" and fault.size is None:
                size = _held(col, rows, fault)
            col[rows] = _apply(kind, col[rows], size, rng, arrays is hall, limits, adc_step,
                               gyro_lsb)
        recorded.append(Fault(kind, column, *span, size).to_json())
    if faults:
        extra_meta[META_KEY] = recorded
    mocap_t = None if session.mocap_t is None else session.mocap_t.copy()
    mocap = None if session.mocap is None else session.mocap.copy()
    return dataclasses.replace(
        session, t=t[keep], gyro=gyro[keep], hall_v=hall[keep], mocap_t=mocap_t, mocap=mocap,
        hall_models=hall_models, extra_meta=extra_meta, path=None)


def _apply(kind: str, x: np.ndarray, size: float | None, rng: np.random.Generator,
           is_hall: bool, limits: SensorLimits, adc_step: float, gyro_lsb: float) -> np.ndarray:
    """The readings ``x`` (one column over the span) with the fault written in."""
    present = np.isfinite(x)
    lo, hi = limits.hall_v
    if kind in ("disconnect", "short", "stuck"):
        return np.where(present, size, np.nan)
    if kind == "noise":
        y = x + size * rng.standard_normal(x.shape)
        if is_hall:
            return np.clip(np.round(y / adc_step) * adc_step, lo, hi)
        top = min(GYRO_FULL_SCALE_RAD_S, limits.gyro_rad_s)
        return np.clip(np.round(y / gyro_lsb) * gyro_lsb, -top, top)
    if kind == "flicker":
        return np.where(rng.random(x.shape) < size, np.where(present, lo, np.nan), x)
    if kind == "clip":
        return np.clip(x, -size, size)
    if kind == "bias_step":
        return np.round((x + size) / gyro_lsb) * gyro_lsb
    if kind == "blank":
        return np.where(np.abs(np.nan_to_num(x)) >= size, np.nan, x)
    if kind == "dropout":
        return np.full_like(x, np.nan)
    if kind == "sign":
        return 0.0 - x  # not -x: a zero reading stays 0, never -0
    if kind == "drift":
        y = x + size * np.linspace(0.0, 1.0, x.size)
        return np.clip(np.round(y / adc_step) * adc_step, lo, hi)
    raise AssertionError(kind)  # every other kind is handled by inject_faults


def _rows(fault: Fault, session: Session) -> np.ndarray:
    """(T,) mask of the sensor rows in the fault's span, after checking the fault against the
    session (column on the robot, span inside the session and holding a row)."""
    robot, t = session.robot, session.t
    where = f"fault {fault._name()}"
    column = fault.column
    if column is not None:
        ctype = _column_type(column)
        names = {"hall": robot.hall_names, "gyro": robot.gyro_names,
                 "joint": tuple(dict.fromkeys(n[:-2] for n in robot.hall_names))}[ctype]
        if column not in names:
            raise ValueError(
                f"{where}: column {column!r} is not on this robot (joints {robot.spec}: "
                f"{_range(robot.hall_names, 'Hall')}, {_range(robot.gyro_names, 'gyro')})")
    if t.shape[0] == 0:
        raise ValueError(f"{where}: the session has no sensor rows")
    if _SPAN.get(fault.kind) == "none":
        return np.ones(t.shape[0], dtype=bool)
    from_s, to_s = _resolved_span(fault, session)
    # The session's length as recorded: T rows of 1 / rate (``--duration``), or its last row.
    end = round(max(float(t[-1]), float(t[0]) + t.shape[0] / session.sample_rate_hz), 6)
    if from_s < t[0] or to_s > end or from_s > t[-1] or to_s < t[0]:
        raise ValueError(f"{where}: the span {_num(from_s)}-{_num(to_s)} s is outside the "
                         f"session ({_num(float(t[0]))}-{_num(end)} s)")
    rows = (t >= from_s) & (t <= to_s)
    if not rows.any():
        raise ValueError(f"{where}: the span {_num(from_s)}-{_num(to_s)} s holds no sensor row "
                         f"(a row every {_num(round(1.0 / session.sample_rate_hz, 9))} s)")
    if fault.kind == "gap" and (rows[0] or rows[-1]):
        raise ValueError(f"{where}: a gap must leave sensor rows before and after it (the "
                         f"session runs {_num(float(t[0]))}-{_num(float(t[-1]))} s)")
    return rows


def _resolved_span(fault: Fault, session: Session) -> tuple[float | None, float | None]:
    if _SPAN.get(fault.kind) == "none":
        return None, None
    from_s = float(session.t[0]) if fault.from_s is None else fault.from_s
    to_s = float(session.t[-1]) if fault.to_s is None else fault.to_s
    return from_s, to_s


def _size(fault: Fault, session: Session, limits: SensorLimits) -> float | None:
    """The fault's size, its default where it has none, checked against the sensor's range;
    ``None`` for a kind that takes none (and for ``stuck`` without one: the held reading)."""
    kind, size = fault.kind, fault.size
    if kind in _SIZELESS:
        return None
    lo, hi = limits.hall_v
    is_hall = fault.column in session.robot.hall_names
    if size is None:
        if kind == "disconnect":
            return lo
        if kind == "short":
            return hi
        if kind == "stuck":
            return None
        return DEFAULT_SIZE[(kind, "hall" if is_hall else "gyro")]
    where = f"fault {fault._name()}"
    if kind in ("disconnect", "short", "stuck") and is_hall and not lo <= size <= hi:
        raise ValueError(f"{where}: {_num(size)} V is outside the ADC's range; expected "
                         f"{_num(lo)}-{_num(hi)} V (meta.json's hall_v_range)")
    if kind == "stuck" and not is_hall and abs(size) > limits.gyro_rad_s:
        raise ValueError(f"{where}: {_num(size)} rad/s is beyond the gyro's range; expected "
                         f"at most {limits.gyro_rad_s:.4g} rad/s (meta.json's gyro_range_rad_s)")
    return size


def _held(col: np.ndarray, rows: np.ndarray, fault: Fault) -> float:
    """The reading a ``stuck`` column holds: the last present one at or before the span's first
    row, else the first present one in the span."""
    first = int(np.argmax(rows))
    before = np.flatnonzero(np.isfinite(col[: first + 1]))
    if before.size:
        return float(col[before[-1]])
    within = np.flatnonzero(np.isfinite(col) & rows)
    if within.size:
        return float(col[within[0]])
    raise ValueError(f"fault {fault._name()}: {fault.column} has no reading to hold up to the "
                     "span's end; give the value as =SIZE")


def _converters(session: Session) -> tuple[float, float]:
    """(ADC step, V; gyro step, rad/s): the session's simulated converters, else the
    simulator's defaults (12 bits over the Hall range; 8.75 mdps)."""
    lo, hi = (session.limits or SensorLimits()).hall_v
    adc_step, gyro_lsb = (hi - lo) / 2**ADC_BITS, GYRO_LSB_RAD_S
    sim = session.extra_meta.get("simulation")
    cfg = sim.get("config") if isinstance(sim, Mapping) else None
    if isinstance(cfg, Mapping):
        vref, bits, lsb = cfg.get("adc_vref"), cfg.get("adc_bits"), cfg.get("gyro_lsb_dps")
        if _positive(vref) and isinstance(bits, int) and not isinstance(bits, bool) and bits > 0:
            adc_step = float(vref) / 2**bits
        if _positive(lsb):
            gyro_lsb = float(lsb) * DEG
    return adc_step, gyro_lsb


def _positive(x) -> bool:
    return (isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
            and x > 0)


def _range(names: Sequence[str], label: str) -> str:
    return f"{label} {names[0]}..{names[-1]}" if len(names) > 1 else f"{label} {names[0]}"
