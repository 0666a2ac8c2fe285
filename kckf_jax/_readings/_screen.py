"""Which readings the filter uses, and why not: one decision for every path, the stream and
the exported step.

A reading that cannot be a measurement is not used, and is named:

* ``out_of_range``: beyond what its ADC or gyro can read (``SensorLimits``): a transmission
  or logging fault;
* ``railed``: a Hall reading at either end of its ADC's range (within ``SensorLimits.rail_v``):
  a short or an open wire (a disconnected sensor reads 0 V), not a measurement;
* ``unreachable``: a Hall reading whose angle through the sensor's curve (Eq. 1, the
  parameters' coefficients) is beyond what a joint can reach (``SensorLimits.joint_range_rad``):
  Eq. 1 turns a low voltage into an enormous angle (0.5 V is -3,279 deg with the paper's
  coefficients), which the filter would otherwise weigh like any other reading;
* ``saturated``: a gyro reading at its full scale (``SensorLimits.gyro_rad_s``): the true rate
  may be larger.

A reading that is not there (NaN) is missing, not faulty. A gyro channel the filters read whose
reading has been missing or faulty for a while takes the reading of a gyro that measures the
same rate (``stand_in``, ``Robot.gyro_stand_ins``: the same axis, on a link no joint about that
axis separates from it; ``_health`` decides when), so its joints' rates come from the other
links' gyros; only where no such gyro reads does the channel hold its last value (the
kernel's ``gyro_hold``).

Each decision looks at one row alone, so it is the same whether a row comes from a recording,
a batch of trials or a live packet: ``screen`` works on any leading axes, on NumPy (the report
and the packet parser: ``xp=np``) or JAX arrays (``_prepare``, which every path and the
stream call). It is not differentiated: the decisions are constants of the parameters, and the
curve is evaluated on ``stop_gradient``-ed coefficients.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._models._hall import hall_angle, hall_angle_np
from .._models._limits import SATURATION_FRACTION

#: The kinds of faulty reading, by code (``codes == k + 1`` is ``FAULT_KINDS[k]``; 0: used or
#: missing).
FAULT_KINDS = ("out_of_range", "railed", "unreachable", "saturated", "noisy", "stuck",
               "bias_step")
OUT_OF_RANGE, RAILED, UNREACHABLE, SATURATED = 1, 2, 3, 4


class Screened(NamedTuple):
    """``screen``'s result: the readings the filter uses (NaN: not used), and per reading the
    fault code (0: used or missing; ``FAULT_KINDS``)."""

    gyro: object
    hall_v: object
    gyro_code: object
    hall_code: object


def screen(params, gyro, hall_v, xp=jnp) -> Screened:
    """The readings of ``gyro`` (``... G``) and ``hall_v`` (``... M``) the filter uses, and why
    the others are not used.

    ``params``: anything with ``robot``, ``limits`` and ``hall_coeffs`` (``Params``;
    ``hall_coeffs=None`` leaves out the curve's check). ``xp``: ``np`` for host arrays
    (float64 decisions), ``jnp`` inside the filters. No gyro stands in for another here
    (``_health`` does it, once a reading has been missing for a while: ``stand_in``).
    """
    limits = params.limits
    lo, hi = limits.hall_v
    rail = limits.rail_v
    g_abs = xp.abs(gyro)
    g_code = xp.where(g_abs > limits.gyro_rad_s, OUT_OF_RANGE,
                      xp.where(g_abs >= SATURATION_FRACTION * limits.gyro_rad_s, SATURATED, 0))
    coeffs = params.hall_coeffs
    if coeffs is None:
        angle = xp.zeros_like(hall_v)
    elif xp is np:
        finite_v = np.where(np.isfinite(hall_v), hall_v, 0.5 * (lo + hi))
        angle = hall_angle_np(finite_v, coeffs)
    else:
        coeffs = tuple(jax.lax.stop_gradient(c) for c in coeffs)
        finite_v = jnp.where(jnp.isfinite(hall_v), hall_v, 0.5 * (lo + hi))
        angle = hall_angle(finite_v, *coeffs)
    h_code = xp.where(
        (hall_v < lo) | (hall_v > hi), OUT_OF_RANGE,
        xp.where((hall_v <= lo + rail) | (hall_v >= hi - rail), RAILED,
                 xp.where(xp.abs(angle) > limits.joint_range_rad, UNREACHABLE, 0)))
    g_used = xp.where(g_code > 0, xp.nan, gyro)
    h_used = xp.where(h_code > 0, xp.nan, hall_v)
    return Screened(g_used, h_used, g_code.astype(xp.int8), h_code.astype(xp.int8))


#: How far inside the joints' range ``clean_bounds`` keeps its ends (relative): far above
#: float64's rounding of Eq. 1, far below anything a reading could tell apart.
CLEAN_MARGIN = 1e-9


def clean_bounds(params) -> tuple[np.ndarray, np.ndarray]:
    """Per reading (``Robot.gyro_names`` then ``Robot.hall_names``) a closed interval
    ``[lo, hi]`` (float64) inside which ``screen`` (``xp=np``) finds nothing wrong with it: a
    packet whose every reading lies in its interval, or is missing, needs no ``screen``. The
    stream's check of one packet is then four NumPy calls instead of ``screen``'s forty
    (``StreamingFilter``'s host path, ``PacketParser``); a reading outside is screened as
    before, so the decisions are ``screen``'s exactly.

    Shown, not sampled: a gyro is clean below its saturation (``SATURATION_FRACTION`` of its
    full scale), a Hall reading strictly between the rails and where its angle through Eq. 1
    is within the joints' range. Eq. 1 is strictly monotone for positive ``a, b, c, d``
    (``_hall``), so the angle over ``[lo, hi]`` lies between the angles at its ends, which
    are checked with ``screen``'s own arithmetic, ``CLEAN_MARGIN`` inside the range; a sensor
    whose coefficients are not all positive gets an empty interval (each of its readings
    screened).
    """
    limits = params.limits
    G, M = len(params.robot.gyro_names), params.robot.n_hall
    g = float(np.nextafter(SATURATION_FRACTION * limits.gyro_rad_s, 0.0))
    v_lo, v_hi = limits.hall_v
    rail = limits.rail_v
    a = float(np.nextafter(v_lo + rail, np.inf))
    b = float(np.nextafter(v_hi - rail, -np.inf))
    h_lo, h_hi = np.full(M, a), np.full(M, b)
    coeffs = params.hall_coeffs
    if coeffs is not None:
        cs = [np.broadcast_to(np.asarray(c, np.float64), (M,)) for c in coeffs]
        reach = limits.joint_range_rad * (1.0 - CLEAN_MARGIN)
        grid = np.linspace(a, b, 1025)
        for m in range(M):
            one = tuple(c[m] for c in cs)
            ok = np.abs(hall_angle_np(grid, one)) <= reach
            if not (all(c > 0 for c in one[:4]) and ok.any()):
                h_lo[m], h_hi[m] = np.inf, -np.inf
                continue
            inside = np.flatnonzero(ok)
            h_lo[m] = _edge(one, reach, grid, inside[0], -1)
            h_hi[m] = _edge(one, reach, grid, inside[-1], +1)
            ends = hall_angle_np(np.array([h_lo[m], h_hi[m]]), one)
            if not np.all(np.abs(ends) <= reach):  # cannot happen for a monotone curve
                h_lo[m], h_hi[m] = np.inf, -np.inf
    return np.r_[np.full(G, -g), h_lo], np.r_[np.full(G, g), h_hi]


def _edge(coeffs, reach, grid, i, step) -> float:
    """The end of the clean stretch of one Hall sensor's voltages that starts at ``grid[i]``
    (clean), towards ``step`` (-1: lower voltages): bisection between it and its neighbour."""
    j = i + step
    if not 0 <= j < len(grid):
        return float(grid[i])
    good, bad = float(grid[i]), float(grid[j])
    for _ in range(80):
        mid = 0.5 * (good + bad)
        if mid in (good, bad):
            break
        if abs(float(hall_angle_np(np.array([mid]), coeffs)[0])) <= reach:
            good = mid
        else:
            bad = mid
    return good


def stand_ins(robot, exact: bool = False) -> tuple[tuple[int, ...], ...]:
    """Per gyro channel the channels that measure the same rate: ``Robot.gyro_stand_ins``
    under the paper's first-order model; none under the chain's exact kinematics (``exact``,
    the ``kckf3d`` method's), where a joint turned by any angle turns its child's rates about
    its other axes too (``g_{i+1} = R^T g_i + J dtheta``), so no two channels read the same
    rate (measured: on 60 s of exact walking of ``x,y,x,y`` the paper's pairs flagged gyro3_x
    and gyro4_x as bias steps for 62 % of the rows)."""
    return tuple(() for _ in robot.gyro_stand_ins) if exact else robot.gyro_stand_ins


def stand_in(robot, gyro, exact: bool = False):
    """Every channel the filters read that has no reading (``... G``) takes the reading of its
    first stand-in (``stand_ins``) that has one."""
    used = set(int(i) for i in robot.used_gyro_index)
    cols = []
    for c, mates in enumerate(stand_ins(robot, exact)):
        col = gyro[..., c]
        if c in used and mates:
            fill = gyro[..., mates[-1]]
            for m in reversed(mates[:-1]):
                fill = jnp.where(jnp.isnan(gyro[..., m]), fill, gyro[..., m])
            col = jnp.where(jnp.isnan(col), fill, col)
        cols.append(col)
    return jnp.stack(cols, axis=-1)


def fault_codes(params, gyro, hall_v, xp=jnp):
    """Per reading (``... G + M``: ``Robot.gyro_names`` then ``Robot.hall_names``) the code of
    why the filter does not use it, judging each row alone (``screen``; 0: used or
    missing). ``_health.series_codes`` adds what only time shows."""
    used = screen(params, gyro, hall_v, xp)
    return xp.concatenate([used.gyro_code, used.hall_code], axis=-1)


def fault_stretches(t, codes, names, join_s: float = 1.0) -> list[dict]:
    """The faulty readings of one recording by column, kind and stretch of time: ``[{"column",
    "kind", "from_s", "to_s", "count"}]`` (the ``"faults"`` of ``kckf evaluate --json``),
    ordered by column then time. ``t`` (``T``, s), ``codes`` (``T x C``, ``fault_codes``),
    ``names`` (``C`` column names). Faulty readings of one kind in one column less than
    ``join_s`` apart are one stretch (a flickering sensor is one entry, not hundreds)."""
    t = np.asarray(t, np.float64)
    codes = np.asarray(codes)
    out = []
    for c in np.flatnonzero((codes != 0).any(axis=0)):
        for code in np.unique(codes[:, c][codes[:, c] != 0]):
            rows = np.flatnonzero(codes[:, c] == code)
            breaks = np.flatnonzero(np.diff(t[rows]) > join_s) + 1
            for part in np.split(rows, breaks):
                out.append({"column": names[c], "kind": FAULT_KINDS[int(code) - 1],
                            "from_s": float(t[part[0]]), "to_s": float(t[part[-1]]),
                            "count": int(part.size)})
    return out


#: The kinds the plausibility screen decides row by row (not used under every fault policy).
SCREEN_KINDS = FAULT_KINDS[:4]


def describe_faults(name: str, stretches: list[dict], policy=None,
                    limit: int = 6) -> str | None:
    """One line for people about a recording's faulty readings (``fault_stretches``), by
    column and kind, or None when there are none. ``policy``: the fault policy they were
    found under (``FaultPolicy``; ``None``: ``isolate``): under ``report`` the health
    monitor's findings were still used, and the line says so."""
    if policy is not None and policy.monitors and not policy.isolates:
        kept = [f for f in stretches if f["kind"] not in SCREEN_KINDS]
        out = [f for f in stretches if f["kind"] in SCREEN_KINDS]
        lines = [x for x in (describe_faults(name, out, None, limit),
                             _describe(name, kept, limit, "reading(s) judged faulty, still "
                                       "used (--faults report; isolate would leave them out)"))
                 if x]
        return " | ".join(lines) or None
    return _describe(name, stretches, limit, "faulty reading(s) not used")


def _describe(name: str, stretches: list[dict], limit: int, what: str) -> str | None:
    if not stretches:
        return None
    groups: dict[tuple[str, str], list[dict]] = {}
    for f in stretches:
        groups.setdefault((f["column"], f["kind"]), []).append(f)
    parts = []
    for (column, kind), fs in list(groups.items())[:limit]:
        n = sum(f["count"] for f in fs)
        where = f"{fs[0]['from_s']:.6g}-{fs[-1]['to_s']:.6g} s"
        if len(fs) > 1:
            where += f" in {len(fs)} stretches"
        parts.append(f"{column} {kind} x{n} at {where}")
    more = f" and {len(groups) - limit} more" if len(groups) > limit else ""
    total = sum(f["count"] for f in stretches)
    return (f"{name}: {total} {what}: " + ", ".join(parts) + more + " (docs/faults.md)")
