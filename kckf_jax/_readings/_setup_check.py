"""Set-up mistakes named before filtering: swapped Hall columns, a gyro of the wrong sign, a
Hall curve that cannot be the sensor's (issue 33, item 8); and data that depart from the
model without being a mistake (issue 45).

Labs wire things wrong, and each of these mistakes shows in the first seconds of data: the
Hall readings move against the gyros, or by the wrong amount. The filter cannot tell; it fuses
what it is given. ``setup_check`` looks before it runs. NumPy float64 on the host, no JAX.

The method, its thresholds and what each explanation tests: docs/faults.md, "How the set-up
check decides".
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .._models._hall import DEG, hall_angle_np
from .._models._params import Params
from ._health import CLIP_MIN_RAD_S, CLIP_PEAK_FRACTION, CLIP_REPEATS
from ._screen import screen
from ._stats import hold_last, moving_mean

#: High-pass window, s: each series less its centred moving mean over this span. A gyro bias
#: integrates to a ramp, which a centred mean reproduces exactly, and a Hall curve's offset is
#: a constant: neither survives. Motion faster than about 0.15 Hz passes (the bench cycle is
#: 0.7-1 Hz, bending 0.15-0.25 Hz: gain 0.77 at 0.2 Hz); the slow posture drift does not.
HIGHPASS_S = 4.0
#: The short moving mean, s: cuts the Hall sensors' white noise (about 1 deg a sample near
#: neutral, several on a curve's flat side) by sqrt(11) at 100 Hz (an odd 11 rows); the same
#: mean on both series keeps the slope unbiased.
SMOOTH_S = 0.1
#: A row whose high-pass window spans more than this many windows of clock (a gap) is left out.
GAP_FACTOR = 1.5
#: The RMS (deg) of a joint axis's band-passed gyro angle below which it did not move enough to
#: judge: the Hall angles' noise after smoothing is about 0.3-2 deg, so a smaller motion gives
#: slopes of noise. A wearer's non-bending axes sway by 0.4-1.9 deg (not judged); the bent
#: ones move 2-5 deg, the bench 5-14 deg.
MIN_MOTION_DEG = 2.0
#: A consistent sensor's slope range: a factor 2.5 either way of the gyros' (symmetric in log).
#: Clean simulated data give 0.74-1.56 on the bench's motion and 0.54-1.85 at worst (a
#: wearer's barely moving joints; 180 sessions of five layouts): per-sensor curve errors (10 %
#: on a and c, the curve's slope differing most on its flat side), the wearer's interaction
#: shifts (up to 2 deg over 10-15 deg of bend) and the gyros' 1 % scale; the range leaves room
#: for a real robot's unmodelled kinematics. A coefficient 10x off reads 3-12x where the joint
#: visits that side of the curve (a bend that stays on the other side shows only 1.5-2.8x).
#: Issue 45's sweep (``python tests/test_setup_check.py sweep``: 720 clean sessions, six
#: layouts, cyclic, human, walking and static, 30 seeds) gives 0.54-1.84; under exact
#: rotations 0.09-2.43, the smaller of a joint's two slopes at most 2.18, where both of a
#: joint's curves 10x off read 2.95-8.9.
SLOPE_LO, SLOPE_HI = 0.4, 2.5
#: The correlation a consistent sensor must reach. Clean simulated data give 0.92 or more over
#: the same 180 sessions (0.99 on the bench's motion); a gyro angle blurred by another link's
#: motion (a negated gyro, or a wrong explanation tried) falls to 0.6-0.86. Issue 45's sweep:
#: 0.885 or more on linear data; under exact rotations 0.19 or more, below 0.8 for 178 of
#: 5,722 sensors (the model's mismatch: ``FOLLOW_CORR``).
MIN_CORR = 0.8
#: The correlation with the gyros at which a sensor that is not consistent still follows its
#: joint (its joint's rate departs from the model's: ``model_mismatch``). Measured (issue 45,
#: ``python tests/test_setup_check.py sweep``): a disconnected sensor (noise about mid-scale)
#: 0.22 at most, over 84 joint axes of seven layouts and kinds, linear and exact; clean data
#: under exact rotations 0.19 or more, below 0.5 for 19 of 5,722 sensors (720 sessions),
#: every one on a joint whose two sensors correlate with each other (``PAIR_CORR``; 1,440
#: sessions with 60 more seeds of walking and 30 of static and cyclic: 45 of 12,338).
FOLLOW_CORR = 0.5
#: The correlation of a joint's two sensors with each other at which they follow one angle:
#: then each follows its joint where it correlates with the gyros at all. Clean data 0.78 or
#: more (linear and exact alike: the Hall sensors read the joint), a disconnected sensor
#: against the other 0.17 at most (0.20 with only one disconnected).
PAIR_CORR = 0.5
#: A sensor needs this many usable rows (1 s at 100 Hz) to be judged.
MIN_PAIRS = 100
#: "Far better" between two fits of one sensor or joint axis: less than 1 / DISTINCT_FACTOR of
#: the other's unexplained variance (1 - r^2). A negated gyro must leave its joints' sensors
#: this much better off (or have moved them against the gyros), and no agreeing neighbour this
#: much worse; of a swap and a gyro sign that both explain one joint axis, the better is named
#: alone only by this margin. A right explanation removes a whole link's motion from the gyro
#: angle (1 - r^2 from 0.26-0.6 to 0.01-0.05 in simulation), far beyond it.
DISTINCT_FACTOR = 2.0
#: A Hall angle whose band-passed RMS is below this (rad) does not change at all: a stuck
#: reading (rounding leaves ~1e-16), judged as following nothing (slope and correlation 0).
STILL_RAD = 1e-9

Severity = Literal["warning", "error"]


@dataclass(frozen=True)
class SetupFinding:
    """One set-up mistake found by ``setup_check``.

    Attributes:
        kind: ``"swapped_columns"``, ``"gyro_sign"``, ``"swapped_or_gyro_sign"``,
            ``"bad_curve"``, ``"unobservable"`` or ``"model_mismatch"``.
        columns: the ``sensors.csv`` columns at fault (``model_mismatch``: the joint axis's
            two Hall columns, which follow it).
        severity: ``"warning"`` (the filter runs: one sensor's angle is off, or the data
            depart from the model) or ``"error"`` (some angle cannot be right).
        message: one line naming the columns and what was measured.
        fix: what to change.
    """

    kind: str
    columns: tuple[str, ...]
    severity: Severity
    message: str
    fix: str


@dataclass(frozen=True)
class _Fit:
    """One sensor's band-passed angle regressed on its joint axis's band-passed gyro angle."""

    slope: float
    corr: float
    n: int

    @property
    def known(self) -> bool:
        return self.n >= MIN_PAIRS and math.isfinite(self.slope) and math.isfinite(self.corr)

    @property
    def ok(self) -> bool:
        return self.known and SLOPE_LO <= self.slope <= SLOPE_HI and self.corr >= MIN_CORR

    @property
    def against(self) -> bool:
        return self.known and self.slope < 0.0

    def unexplained(self) -> float:
        """``1 - r^2``: the share of the Hall angle's variance the gyros do not explain."""
        return 1.0 - self.corr**2 if self.known else 1.0

    def words(self) -> str:
        if not self.known:
            return "too few readings"
        return f"x{self.slope:.2f}, r {self.corr:.2f}"


class _Data:
    """The band-passed angles of the first rows of a session (see the module docstring)."""

    def __init__(self, session, params: Params, seconds: float):
        robot = session.robot
        self.robot = robot
        t = np.asarray(session.t, np.float64)
        keep = t - t[0] <= seconds if t.size else np.zeros(0, bool)
        t = t[keep]
        # The readings the filter uses (``_screen.screen``): a faulty one (out of range, railed,
        # unreachable through the curve, saturated) is missing here, as it is to the filter.
        used = screen(params, np.array(session.gyro[keep], np.float64),
                      np.array(session.hall_v[keep], np.float64), xp=np)
        gyro = np.asarray(used.gyro, np.float64)
        self.volts = np.asarray(used.hall_v, np.float64)
        faulty_g = np.asarray(used.gyro_code) > 0
        # A gyro clipped below the range it states (the health monitor's ``saturated``).
        for c in range(gyro.shape[1]):
            faulty_g[:, c] |= _clipped(gyro[:, c])
        gyro[faulty_g] = np.nan
        self.coeffs = tuple(np.asarray(c, np.float64) for c in params.hall_coeffs)

        T = t.size
        dt = np.diff(t, prepend=t[:1]) if T else t
        step = float(np.median(np.diff(t))) if T > 1 else 1.0
        self.half = max(1, int(round(0.5 * HIGHPASS_S / step)))
        self.box = 2 * int(round(0.5 * SMOOTH_S / step)) + 1
        # Rows whose high-pass window lies inside the rows and spans no gap in the clock.
        h = self.half
        self.row_ok = np.zeros(T, bool)
        if T > 2 * h:
            span = t[2 * h:] - t[:-2 * h]
            self.row_ok[h:T - h] = span <= GAP_FACTOR * max(HIGHPASS_S, 2 * h * step)

        # Gyro angle per channel the joint axes read (hold the last reading; kernel timing).
        J = robot.n_joint_axes
        plus, minus = robot.rate_pairs
        self.plus, self.minus = plus[:J], minus[:J]
        self.channels = sorted({int(c) for c in np.concatenate([self.plus, self.minus])})
        self.gyro = {}
        for c in self.channels:
            u = hold_last(gyro[:, c])
            angle = np.concatenate([[0.0], np.cumsum(dt[1:] * u[:-1])]) if T else u
            band = self._band(angle)
            # A held faulty rate (a saturated gyro's true rate was larger) steps the angle by an
            # unknown amount from the next row on; a step before a row's high-pass window is a
            # constant in it and cancels, one inside it does not: such rows are left out.
            band[_near(faulty_g[:, c], h + 1, h)] = np.nan
            self.gyro[c] = band

    def _band(self, x: np.ndarray) -> np.ndarray:
        """The band-passed ``x``: its ``SMOOTH_S`` box mean less its ``HIGHPASS_S`` box mean
        (NaN skipped in a box; NaN where the short box is empty or the row is not usable)."""
        d = moving_mean(x, self.box) - moving_mean(x, 2 * self.half + 1)
        d[~self.row_ok] = np.nan
        return d

    def gyro_band(self, j: int, flip: frozenset[int] = frozenset()) -> np.ndarray:
        """Joint axis ``j``'s band-passed gyro angle, rad, the channels in ``flip`` negated."""
        p, m = int(self.plus[j]), int(self.minus[j])
        sp = -1.0 if p in flip else 1.0
        sm = -1.0 if m in flip else 1.0
        return sp * self.gyro[p] - sm * self.gyro[m]

    def hall_band(self, column: int, curve: int) -> np.ndarray:
        """Hall column ``column``'s voltages through sensor ``curve``'s Eq. 1, band-passed,
        rad."""
        angle = hall_angle_np(self.volts[:, column], [x[curve] for x in self.coeffs])
        angle[~np.isfinite(angle)] = np.nan
        return self._band(angle)

    def pair(self, j: int) -> _Fit:
        """Joint axis ``j``'s ``r`` sensor's band-passed angle on its ``l`` sensor's."""
        return _fit(self.hall_band(2 * j, 2 * j), self.hall_band(2 * j + 1, 2 * j + 1))

    def motion_deg(self, j: int) -> float:
        x = self.gyro_band(j)
        x = x[np.isfinite(x)]
        return float(np.std(x) / DEG) if x.size >= MIN_PAIRS else 0.0

    def joint(self, j: int, flip: frozenset[int] = frozenset(),
              swap: bool = False) -> tuple[_Fit, _Fit]:
        """The fits of joint axis ``j``'s ``l`` and ``r`` sensors, with the gyro channels in
        ``flip`` negated and, if ``swap``, each column read through the other's curve."""
        x = self.gyro_band(j, flip)
        m_l, m_r = 2 * j, 2 * j + 1
        cols = (m_r, m_l) if swap else (m_l, m_r)
        return tuple(_fit(x, self.hall_band(col, curve))
                     for col, curve in zip(cols, (m_l, m_r)))


def _clipped(u: np.ndarray) -> np.ndarray:
    """The readings of one gyro channel that repeat one value, more than ``CLIP_REPEATS`` times
    in a row, at ``CLIP_PEAK_FRACTION`` or more of the largest magnitude read so far and at
    least ``CLIP_MIN_RAD_S``: a gyro clipped below the range it states (``_health``'s test;
    here the whole run, its first readings too)."""
    read = np.isfinite(u)
    if not read.any():
        return np.zeros(u.size, bool)
    same = np.zeros(u.size, bool)
    same[1:] = read[1:] & read[:-1] & (u[1:] == u[:-1])
    run = np.cumsum(~same) - 1
    long = np.bincount(run)[run] > CLIP_REPEATS
    a = np.where(read, np.abs(u), 0.0)
    peak = np.maximum.accumulate(a)
    return read & long & (a >= CLIP_MIN_RAD_S) & (a >= CLIP_PEAK_FRACTION * peak)


def _near(flag: np.ndarray, before: int, after: int) -> np.ndarray:
    """Rows ``k`` with a flagged row in ``k - before .. k + after``."""
    if not flag.any():
        return np.zeros(flag.size, bool)
    c = np.concatenate([[0], np.cumsum(flag)])
    k = np.arange(flag.size)
    lo = np.clip(k - before, 0, flag.size)
    hi = np.clip(k + after + 1, 0, flag.size)
    return c[hi] > c[lo]


def _fit(x: np.ndarray, y: np.ndarray) -> _Fit:
    """Least squares ``y ~ slope x + c``: slope and correlation over the finite pairs."""
    ok = np.isfinite(x) & np.isfinite(y)
    n = int(ok.sum())
    if n < MIN_PAIRS:
        return _Fit(math.nan, math.nan, n)
    xc = x[ok] - x[ok].mean()
    yc = y[ok] - y[ok].mean()
    sxx, syy, sxy = float(xc @ xc), float(yc @ yc), float(xc @ yc)
    if sxx <= 0.0:
        return _Fit(math.nan, math.nan, n)
    if syy <= n * STILL_RAD**2:
        return _Fit(0.0, 0.0, n)  # a reading that does not change while the gyros do: stuck
    return _Fit(sxy / sxx, sxy / math.sqrt(sxx * syy), n)


def _consistent(fits: tuple[_Fit, _Fit]) -> bool:
    return all(f.ok for f in fits)


def _improves(before: tuple[_Fit, _Fit], after: tuple[_Fit, _Fit]) -> bool:
    """Whether each sensor moved against the gyros before, or leaves ``DISTINCT_FACTOR``
    times less unexplained after."""
    return all(b.against or a.unexplained() * DISTINCT_FACTOR <= b.unexplained()
               for b, a in zip(before, after))


def _score(fits: tuple[_Fit, _Fit]) -> float:
    """The larger unexplained share of a joint axis's two sensors (smaller is better)."""
    return max(f.unexplained() for f in fits)


def setup_check(session, params: Params | None = None,
                seconds: float = 20.0, exact: bool = False) -> list[SetupFinding]:
    """Set-up mistakes recognisable in the first ``seconds`` of a session.

    Args:
        session: a ``Session``.
        params: whose Hall curves (``hall_coeffs``) turn voltages into angles and whose limits
            say which readings are readings; default ``Params.paper_defaults`` with the
            session's ``hall_models``. A session that states its limits has them either way
            (as ``session_params`` does).
        seconds: how much of the start to look at, s.
        exact: the data are judged for the chain's exact kinematics (``kckf3d``): a joint of
            several axes turns its coordinates at rates that depend on its angles, not at the
            gyro differences of Eq. 2, so only one-axis joints (whose rate is Eq. 2's at any
            angle) are judged.

    Returns:
        The findings (empty when nothing is wrong, or nothing moved enough to tell), joint axis
        by joint axis; ``describe`` turns them into lines. The method is in the module
        docstring.

    Example:
        >>> from kckf_jax import simulate
        >>> setup_check(simulate("x,y", "cyclic", seed=1, duration_s=10.0))
        []
    """
    robot = session.robot
    if params is None:
        params = Params.paper_defaults(robot, session.hall_models)
    if params.robot != robot:
        raise ValueError(f"setup_check: parameters are for robot {params.robot.spec!r} but the "
                         f"session has {robot.spec!r}")
    if session.limits is not None:  # the session's hardware, as for the filter
        params = dataclasses.replace(params, limits=session.limits)
    if not seconds > 0:
        raise ValueError(f"setup_check: seconds must be positive, got {seconds!r}")
    data = _Data(session, params, float(seconds))
    names = robot.joint_angle_names
    hall = robot.hall_names
    gyro_names = robot.gyro_names

    judged = [j for j, (i, _) in enumerate(robot.joint_axes)
              if not exact or len(robot.joints[i - 1]) == 1]
    moving = [j for j in judged if data.motion_deg(j) >= MIN_MOTION_DEG]
    base = {j: data.joint(j) for j in moving}
    wrong = {j for j in moving if not _consistent(base[j])}

    # Negated gyro channels: every moving joint axis reading the channel must agree once it is
    # negated; none that agreed before may agree far worse (so a moving neighbour that agrees
    # as it is rules the channel out); and for some, both sensors must have moved against the
    # gyros or follow them far more closely. A negated gyro blurs its joints' gyro angles with
    # twice a link's motion, which can leave a slope in range (a negated base gyro) but not the
    # correlation. Rescaling alone is no evidence: where the base's motion follows the joint's
    # (a wearer's pelvis tilts with the bend) a negated channel only rescales the gyro angle,
    # and could pass for a corrected curve.
    gyro_fix: dict[int, tuple[list[int], dict[int, tuple[_Fit, _Fit]]]] = {}
    for c in data.channels:
        users = [j for j in moving if c in (int(data.plus[j]), int(data.minus[j]))]
        if not users:
            continue
        flipped = {j: data.joint(j, flip=frozenset({c})) for j in users}
        if not all(_consistent(f) for f in flipped.values()):
            continue
        if any(_score(flipped[j]) > DISTINCT_FACTOR * _score(base[j])
               for j in users if j not in wrong):
            continue  # a neighbour that agrees as it is agrees far worse negated
        if any(_improves(base[j], flipped[j]) for j in users):
            fixed = [j for j in users if j in wrong or _improves(base[j], flipped[j])]
            gyro_fix[c] = (fixed, flipped)
    # Swapped columns: both sensors against the gyros, both consistent read the other way.
    swap_fix: dict[int, tuple[_Fit, _Fit]] = {}
    for j in sorted(wrong):
        if all(f.against for f in base[j]):
            swapped = data.joint(j, swap=True)
            if _consistent(swapped):
                swap_fix[j] = swapped

    findings: list[tuple[int, SetupFinding]] = []  # (the first joint axis it concerns, it)
    explained: set[int] = set()
    for c, (fixed, flipped) in gyro_fix.items():
        rivals = [j for j in fixed if j in swap_fix]
        if len(fixed) == 1 and rivals:
            # One joint axis, two explanations: the better fit, or both named.
            j = fixed[0]
            s_gyro, s_swap = _score(flipped[j]), _score(swap_fix[j])
            if s_swap * DISTINCT_FACTOR <= s_gyro:
                continue  # the swap fits clearly better: named below
            if s_gyro * DISTINCT_FACTOR > s_swap:
                explained.add(j)
                findings.append((j, _ambiguous(robot, j, c, base[j])))
                continue
        explained.update(fixed)
        findings.append((min(fixed), _gyro_sign(robot, c, fixed, base, flipped)))
    for j, swapped in swap_fix.items():
        if j in explained:
            continue
        explained.add(j)
        col_l, col_r = hall[2 * j], hall[2 * j + 1]
        (bl, br), (sl, sr) = base[j], swapped
        findings.append((j, SetupFinding(
            "swapped_columns", (col_l, col_r), "error",
            f"{col_l} and {col_r} move against the gyros of {names[j]} (slopes {bl.slope:.2f}, "
            f"{br.slope:.2f}); exchanged, they follow them ({sl.slope:.2f}, {sr.slope:.2f})",
            f"swap columns {col_l} and {col_r} in sensors.csv (or their hall_models)")))
    for j in sorted(wrong):
        if j in explained:
            continue
        fits = base[j]
        cols = (hall[2 * j], hall[2 * j + 1])
        gyros = (gyro_names[data.plus[j]], gyro_names[data.minus[j]])
        pair = data.pair(j)
        # The two sensors follow one angle (each other, whatever the gyros say), and at one
        # scale (then neither curve is to blame: the gyros depart from the model).
        together = pair.known and pair.corr >= PAIR_CORR
        agree = together and SLOPE_LO <= pair.slope <= SLOPE_HI
        state = [_state(f, together) for f in fits]
        carried = [m for m in (0, 1) if state[m] in ("ok", "loose")]
        if "wrong" in state and carried and ("ok" in state or not agree):
            m = state.index("wrong")
            f, other = fits[m], fits[1 - m]
            how = _how(f, together)
            wiring = f"the wiring of {cols[m]} and " if how.startswith("does not") else ""
            findings.append((j, SetupFinding(
                "bad_curve", (cols[m],), "warning",
                f"{cols[m]} {how} of {names[j]} ({f.words()}) while {cols[1 - m]} "
                f"follows them ({other.words()})",
                f"check {wiring}hall_models[{cols[m]}] in meta.json (measured scale "
                f"x{f.slope:.2f} of the gyros')")))
        elif "wrong" in state and not carried:
            what = "; ".join(f"{col} {_how(f, together)} ({f.words()})"
                             for col, f in zip(cols, fits))
            # (The report adds that its angle cannot be estimated from this data.)
            findings.append((j, SetupFinding(
                "unobservable", cols, "error",
                f"{names[j]}: no Hall sensor follows the gyros ({gyros[0]} - {gyros[1]}): "
                f"{what}; exchanging them does not help",
                f"check the wiring of {cols[0]} and {cols[1]} and their hall_models in "
                f"meta.json (and, if both are right, the gyros {gyros[0]} and {gyros[1]})")))
        elif "loose" in state:  # (with a wrong one: the two agree, the gyros depart)
            findings.append((j, _mismatch(robot, j, fits, pair, gyros, exact)))
    findings.sort(key=lambda jf: jf[0])
    return [f for _, f in findings]


def _follows(f: _Fit, together: bool) -> bool:
    """Whether a sensor follows its joint: it correlates with the gyros at least
    ``FOLLOW_CORR``, or at all where the joint's two sensors follow each other
    (``together``)."""
    return f.known and (f.corr >= FOLLOW_CORR or (together and f.corr > 0.0))


def _state(f: _Fit, together: bool) -> str:
    """``"ok"`` (consistent), ``"loose"`` (follows the joint with a scale that can be the
    gyros': the model's mismatch), ``"wrong"`` (moves against the gyros, follows nothing, or a
    scale that cannot be the gyros' however their angle departs from the sensor's) or
    ``"unknown"`` (too few readings). The gyros' scale lies between the slope (all the
    departure in the Hall angle) and slope / r^2 (all of it in the gyro angle)."""
    if not f.known:
        return "unknown"
    if f.ok:
        return "ok"
    if _follows(f, together) and SLOPE_LO * f.corr**2 <= f.slope <= SLOPE_HI:
        return "loose"
    return "wrong"


def _how(f: _Fit, together: bool = False) -> str:
    if not f.known:
        return "has too few readings"
    if f.slope < 0 and _follows(_Fit(-f.slope, -f.corr, f.n), together):
        return "moves against the gyros"
    if not _follows(f, together):
        return "does not follow the gyros"
    return "reads a different scale from the gyros"


def _mismatch(robot, j: int, fits, pair: _Fit, gyros: tuple[str, str],
              exact: bool) -> SetupFinding:
    """A joint axis whose sensors follow it, and its gyros only loosely (``model_mismatch``)."""
    names = robot.joint_angle_names
    col_l, col_r = robot.hall_names[2 * j], robot.hall_names[2 * j + 1]
    each = f"; the two with each other: {pair.words()}" if pair.known else ""
    message = (f"{names[j]}: {col_l} ({fits[0].words()}) and {col_r} ({fits[1].words()}) "
               f"follow the gyros ({gyros[0]} - {gyros[1]}) only loosely (a consistent "
               f"sensor: x{SLOPE_LO:g}-{SLOPE_HI:g}, r {MIN_CORR:g} or more{each}): the "
               "joint's rate departs from the gyros' difference by more than a calibration "
               "does")
    if exact:
        fix = (f"check the gyros {gyros[0]} and {gyros[1]} (mounting, timing) and "
               f"hall_models[{col_l}], hall_models[{col_r}] in meta.json")
    else:
        fix = ("under exact rotations (large angles about several axes) the linear model's "
               "joint rates are approximate: use --method kckf3d; otherwise check the gyros "
               f"{gyros[0]} and {gyros[1]} (mounting, timing)")
    return SetupFinding("model_mismatch", (col_l, col_r), "warning", message, fix)


def _gyro_sign(robot, c: int, fixed: list[int], base, flipped) -> SetupFinding:
    names = robot.joint_angle_names
    gname = robot.gyro_names[c]
    before = ", ".join(f"{names[j]} x{base[j][0].slope:.2f}/x{base[j][1].slope:.2f}"
                       for j in fixed)
    after = ", ".join(f"x{flipped[j][0].slope:.2f}/x{flipped[j][1].slope:.2f}" for j in fixed)
    return SetupFinding(
        "gyro_sign", (gname,), "error",
        f"{gname}: the Hall sensors disagree with the gyros ({before}, l/r slopes); with "
        f"{gname} negated they agree ({after})",
        f"negate {gname} (mounted the wrong way round)")


def _ambiguous(robot, j: int, c: int, fits) -> SetupFinding:
    names = robot.joint_angle_names
    gname = robot.gyro_names[c]
    col_l, col_r = robot.hall_names[2 * j], robot.hall_names[2 * j + 1]
    return SetupFinding(
        "swapped_or_gyro_sign", (col_l, col_r, gname), "error",
        f"{col_l} and {col_r} move against the gyros of {names[j]} (slopes "
        f"{fits[0].slope:.2f}, {fits[1].slope:.2f}); exchanging them or negating {gname} "
        "explains it equally well (the link below did not turn about this axis)",
        f"swap columns {col_l} and {col_r} in sensors.csv or negate {gname}; to tell which, "
        "record a few seconds turning the link below the joint too")


def describe(findings: list[SetupFinding]) -> list[str]:
    """One line per finding, for stderr: severity, what was found, and the fix."""
    return [f"setup {f.severity}: {f.message}; fix: {f.fix}" for f in findings]
