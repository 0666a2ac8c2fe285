"""Learned sensor effects: what the readings carry beyond the paper's sensor models.

Each effect is off unless named (``SensorEffects.on``), has a physical meaning and a unit, and
is learned by the one training loop with the rest of ``Params`` (``kckf fit --learn``). The
definitions are the simulator's (``SimConfig``, docs/simulator.md "Sensor effects"), so a fit
on a simulated session can be checked against the truth (``training/recovery.py``):

* ``gyro_timing``: where in each step the gyros' rate is taken. The paper integrates the rate
  of the previous row over the step (Euler: ``theta_k = theta_{k-1} + dt * omega_{k-1}``), so
  its angle lags by half a step wherever the rate changes; a gyro whose reading is delayed
  (its digital low-pass filter's group delay) lags more. The step integrates
  ``(1 - lambda) omega_{k-1} + lambda omega_k`` instead: ``lambda = 0`` is the paper's rule,
  ``1/2`` the step's midpoint (a gyro without delay), and a gyro delayed by ``d`` against
  the Hall sensors wants ``lambda = 1/2 + d / dt``. Unit: a fraction of the step (the
  parameter file also gives ``d`` at the recording's step). A reading that is missing holds
  the last one, as the paper's hold does.
* ``gyro_scale``: each gyro channel reads ``(1 + s) * rate`` (plus its bias and noise); the
  correction divides by ``1 + s``. Unit: %.
* ``play``: the magnets the Hall sensors of a joint axis read lag the joint through the
  origami's mechanical play: moving steadily, both sensors see ``theta - h * sign(rate)``,
  ``h`` the play's half-width (deg, one per joint axis: the play is the joint's; the rate is
  the joint's, from the gyros of the same row). The correction
  adds ``h * tanh(rate / PLAY_RATE_RAD_S)``: a sign that stays differentiable, and that is
  0 when the joint is still (where the true play operator remembers the last direction:
  the model's approximation).
* ``curve``: each Hall sensor's true curve differs from Eq. 1's shape by a smooth deviation
  in angle, ``delta(theta) = c2 P2(u) + c3 P3(u)``, ``u = theta / 30 deg`` (Legendre
  polynomials; deg). The correction subtracts ``delta`` at the angle Eq. 1 reads.
* ``offset``: the motion capture lags the sensors by ``tau`` seconds beyond what
  ``meta.json``'s ``mocap_time_offset_s`` says (a frame showing the robot at sensor time
  ``t`` lands at ``t + tau``). Not a property of the readings: it moves where the estimates
  are compared with motion capture (the fitting loss, ``kckf evaluate``) and nothing the
  filter computes; a live stream has no motion capture, so the stream and the export carry
  it in the parameters but do not use it.
* ``gyro_mounting``: each link's gyro board sits turned on its link (strapped or glued on a
  few degrees off), so it reads ``R' omega``, the link's rate in its own frame. The correction
  turns each triad back, ``R g``, ``R`` the rotation of a rotation vector per link (deg, one
  per board: ``x, y, z``). It mixes a triad's three axes, so where one of them is missing the
  corrected triad is missing (its rows hold the last one, as for any missing reading). Read
  by ``kckf`` through its gyro pairs as by ``kckf3d`` through the whole triads.

The Hall corrections are made on the voltage: the reading ``V`` becomes ``V'`` with
``theta(V') = theta(V) + correction`` (Newton's method on Eq. 1 from ``V``; the curve is
monotone, and four steps reach the root to rounding for corrections of degrees), so every
path, the smoother, the likelihood, the stream and the exported step use the corrected
readings through their own Eq. 1, and the voltage noise model takes the slope where the
corrected reading sits. The corrections are made once per series, after the readings are
judged (``_readings._prepare``): a faulty reading is judged on what the sensor gave.

Leaves are unconstrained and in units where a typical size is about 1 (the optimiser's steps
are about its learning rate): play and curve in deg, gyro scale in %, the offset in units of
10 ms; the physical values are properties. The mounting is in deg too, where a worn board's
is 5-12: the fit gives its leaf steps 10 times the rate (``STEP_SCALES``).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._hall import hall_angle, hall_slope
from ._robot import Robot

DEG = math.pi / 180.0
#: The effects that can be learned, in the order the docs give them.
EFFECTS = ("offset", "gyro_timing", "gyro_scale", "play", "curve", "gyro_mounting")
#: The leaves of ``SensorEffects``, in order (the exported step's parameter vector).
LEAVES = ("offset", "timing", "gyro_scale", "play", "curve", "mounting")
#: The effect each leaf belongs to.
EFFECT_OF_LEAF = dict(zip(LEAVES, EFFECTS))
#: Leaves whose typical size in their unit is far from 1, with their Adam steps' factor (the
#: fit's ``TrainConfig.leaf_scales`` when their effect is learned): a worn board's rotation
#: (deg) is 5-12, so it takes 0.3 deg a step at the default rate 0.03 while the log-noise
#: leaves keep 0.03 (docs/fitting.md: one rate of 0.3 for all let them wander).
STEP_SCALES = (("mounting", 10.0),)
#: The joint rate at which the play's correction is 76 % of its size (tanh(1)): 5 deg/s, about
#: 4 times the largest gyro bias of a pair (LSM6DSO zero-rate level +-1 dps each), so an
#: unknown bias moves the correction of a still joint by at most a quarter of its size.
PLAY_RATE_RAD_S = 5.0 * DEG
#: The angle that maps to ``u = 1`` in the curve's Legendre polynomials (a joint's range).
CURVE_SCALE_RAD = 30.0 * DEG
_OFFSET_UNIT_S = 0.01
_SCALE_UNIT = 0.01
NEWTON_STEPS = 4


class SensorEffects(eqx.Module):
    """The learned sensor effects of one robot layout (``EFFECTS``; the module docstring).

    Leaves (unconstrained; zero is "no effect"): ``offset`` (scalar, in 10 ms), ``timing``
    (scalar, a fraction of the step: ``lambda`` of ``gyro_timing``), ``gyro_scale``
    (``G``, %), ``play`` (``J``: per joint axis, deg), ``curve`` (``M 2``: each Hall sensor's
    P2 and P3 coefficients, deg), ``mounting`` (``L 3``: each link's board's rotation vector,
    deg).
    Static: ``on``, the effects in use; an effect not in ``on`` changes nothing, whatever its
    leaf holds.

    Example:
        >>> e = SensorEffects.zeros(Robot.from_spec("x"), on=("play",))
        >>> e.play_rad.shape
        (1,)
    """

    offset: Float[Array, ""]
    timing: Float[Array, ""]
    gyro_scale: Float[Array, " G"]
    play: Float[Array, " J"]
    curve: Float[Array, "M 2"]
    mounting: Float[Array, "L 3"]
    on: tuple[str, ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        unknown = [e for e in self.on if e not in EFFECTS]
        if unknown:
            raise ValueError(f"SensorEffects.on: unknown effect {unknown[0]!r}; expected some "
                             f"of {', '.join(EFFECTS)}")

    @classmethod
    def zeros(cls, robot: Robot, on=(), dtype=None) -> SensorEffects:
        """No effect yet: every leaf 0, ``on`` the effects to learn."""
        dt = dtype or jnp.asarray(0.0).dtype
        G, J, M = 3 * robot.n_links, robot.n_joint_axes, robot.n_hall
        return cls(jnp.zeros((), dt), jnp.zeros((), dt), jnp.zeros(G, dt), jnp.zeros(J, dt),
                   jnp.zeros((M, 2), dt), jnp.zeros((robot.n_links, 3), dt),
                   on=tuple(e for e in EFFECTS if e in on))

    # ------------------------------------------------------------------ physical values
    time_offset_s = property(lambda self: self.offset * _OFFSET_UNIT_S)
    gyro_scale_error = property(lambda self: self.gyro_scale * _SCALE_UNIT)
    play_rad = property(lambda self: self.play * DEG)
    curve_rad = property(lambda self: self.curve * DEG)
    mounting_rad = property(lambda self: self.mounting * DEG)

    def uses(self, effect: str) -> bool:
        return effect in self.on

    def astype(self, dtype) -> SensorEffects:
        return SensorEffects(*(jnp.asarray(getattr(self, x), dtype) for x in LEAVES),
                             on=self.on)


# ---------------------------------------------------------------------------- the readings
def curve_deviation(effects: SensorEffects, angle: Array) -> Array:
    """Each Hall sensor's deviation from Eq. 1 (rad) at ``angle`` (rad, ``... M``)."""
    u = angle / CURVE_SCALE_RAD
    p2 = 0.5 * (3.0 * u**2 - 1.0)
    p3 = 0.5 * (5.0 * u**3 - 3.0 * u)
    c = effects.curve_rad
    return c[..., 0] * p2 + c[..., 1] * p3


def angle_rates(robot: Robot, gyro: Array) -> Array:
    """Every angle's rate (rad/s, ``... K``: joint axes, then torso axes) from one row's (or
    every row's) gyros: the difference of the gyros across it (``Robot.rate_pairs``, Eq. 2);
    NaN where one is missing."""
    plus, minus = robot.rate_pairs
    return gyro[..., plus] - gyro[..., minus]


def corrected_readings(effects: SensorEffects, robot: Robot, hall_coeffs, gyro: Array,
                       hall_v: Array) -> tuple[Array, Array]:
    """The readings with the effects in ``effects.on`` taken out: ``(gyro, hall_v)`` of any
    leading shape (``... G``, ``... M``); a missing reading stays missing, and neither value
    nor gradient is NaN because of one."""
    g_valid = jnp.isfinite(gyro)
    g = jnp.where(g_valid, gyro, 0.0)  # a missing reading makes no NaN gradient
    if effects.uses("gyro_scale"):
        g = g / (1.0 + effects.gyro_scale_error)
        gyro = jnp.where(g_valid, g, gyro)
    if effects.uses("gyro_mounting"):
        gyro = mounted_gyro(effects.mounting_rad, gyro)
        g_valid = jnp.isfinite(gyro)
        g = jnp.where(g_valid, gyro, 0.0)
    if effects.uses("gyro_timing") and jnp.ndim(gyro) >= 2:  # rows in time (a row: the step's)
        gyro = timed_gyro(effects.timing, gyro)
    play, curve = effects.uses("play"), effects.uses("curve")
    if not (play or curve):
        return gyro, hall_v
    valid = jnp.isfinite(hall_v)
    v = jnp.where(valid, hall_v, 1.5)  # a missing reading: a finite stand-in, no NaN gradient
    angle = hall_angle(v, *hall_coeffs)
    target = angle
    if play:
        J = robot.n_joint_axes
        both = angle_rates(robot, jnp.where(g_valid, 0.0, jnp.nan))[..., :J]  # NaN: one missing
        rate = jnp.where(jnp.isfinite(both), angle_rates(robot, g)[..., :J], 0.0)
        lag = effects.play_rad * jnp.tanh(rate / PLAY_RATE_RAD_S)  # ... J
        target = target + lag[..., robot.hall_joint_axis]
    if curve:
        target = target - curve_deviation(effects, angle)
    v_new = v
    for _ in range(NEWTON_STEPS):
        v_new = v_new - (hall_angle(v_new, *hall_coeffs) - target) / hall_slope(v_new,
                                                                                  *hall_coeffs)
    return gyro, jnp.where(valid, v_new, hall_v)


def rotation(v: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """The rotations of rotation vectors ``v`` (rad; Rodrigues, ``I + a K + b K^2`` with ``K =
    [v]_x``), their series near zero so that value and gradient are exact at ``v = 0`` too."""
    a2 = jnp.sum(v**2, axis=-1)[..., None, None]
    small = a2 < 1e-8
    a = jnp.sqrt(jnp.where(small, 1.0, a2))
    c1 = jnp.where(small, 1.0 - a2 / 6.0, jnp.sin(a) / a)
    c2 = jnp.where(small, 0.5 - a2 / 24.0, (1.0 - jnp.cos(a)) / jnp.where(small, 1.0, a2))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    K = jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1),
                   jnp.stack([-y, x, o], -1)], -2)
    return jnp.eye(3, dtype=v.dtype) + c1 * K + c2 * (K @ K)


def mounted_gyro(mounting: Float[Array, "L 3"], gyro: Array) -> Array:
    """``gyro_mounting``'s correction of gyro readings (``... G``, ``G = 3 L``): each link's
    triad turned back by its board's rotation (``mounting``, rad), ``R g``; a triad with a
    missing axis is missing."""
    tri = gyro.reshape(gyro.shape[:-1] + (-1, 3))
    ok = jnp.all(jnp.isfinite(tri), axis=-1, keepdims=True)
    turned = jnp.einsum("lij,...lj->...li", rotation(mounting), jnp.where(ok, tri, 0.0))
    return jnp.where(ok, turned, jnp.nan).reshape(gyro.shape)


def timed_gyro(timing: Array, gyro: Array) -> Array:
    """``gyro_timing`` over rows in time (``... T G``): row ``k`` (the rate the step into row
    ``k + 1`` integrates) becomes ``(1 - lambda) H_k + lambda g_{k+1}``, ``H_k`` the last
    reading up to row ``k`` (0 before any: the filter's initial hold) and ``g_{k+1}`` the next
    row's reading (``H_k`` where that is missing): what the step does with its hold and its
    row's reading (``timed_hold``), so a recording and a stream agree to rounding."""
    T = gyro.shape[-2]
    valid = jnp.isfinite(gyro)
    idx = jnp.where(valid, jnp.arange(T)[:, None], -1)
    last = jax.lax.cummax(idx, axis=idx.ndim - 2)
    held = jnp.take_along_axis(jnp.where(valid, gyro, 0.0), jnp.maximum(last, 0), axis=-2)
    held = jnp.where(last >= 0, held, 0.0)
    nxt = jnp.concatenate([gyro[..., 1:, :], jnp.full_like(gyro[..., :1, :], jnp.nan)], axis=-2)
    ok = jnp.isfinite(nxt)
    return jnp.where(ok, (1.0 - timing) * held + timing * jnp.where(ok, nxt, 0.0), held)


def timed_hold(effects: SensorEffects | None, hold: Array, gyro: Array) -> Array:
    """The rate one step integrates under ``gyro_timing``: ``(1 - lambda) hold + lambda g``
    with this row's reading ``g`` (the hold where it is missing); ``hold`` as it is when the
    effect is off."""
    if effects is None or not effects.uses("gyro_timing"):
        return hold
    ok = jnp.isfinite(gyro)
    return jnp.where(ok, (1.0 - effects.timing) * hold + effects.timing * jnp.where(ok, gyro, 0.0),
                     hold)


def physical(effects: SensorEffects, robot: Robot, step_s: float | None = None) -> dict:
    """The effects in use as ``{effect: value}`` in their ``UNITS``, keyed by column (the
    parameter file's ``effects`` entry)."""
    out = {}
    if effects.uses("offset"):
        out["offset"] = {"time_offset_s": float(effects.time_offset_s)}
    if effects.uses("gyro_timing"):
        lam = float(effects.timing)
        out["gyro_timing"] = {"fraction_of_step": lam}
        if step_s:
            out["gyro_timing"]["gyro_delay_s"] = (lam - 0.5) * step_s
    if effects.uses("gyro_scale"):
        s = np.asarray(effects.gyro_scale_error, np.float64)
        out["gyro_scale"] = {n: float(s[i]) for i, n in enumerate(robot.gyro_names)}
    if effects.uses("play"):
        h = np.asarray(effects.play, np.float64)
        out["play"] = {n: {"half_width_deg": float(h[j])}
                       for j, n in enumerate(robot.angle_names[:robot.n_joint_axes])}
    if effects.uses("curve"):
        c = np.asarray(effects.curve, np.float64)
        out["curve"] = {n: {"p2_deg": float(c[m, 0]), "p3_deg": float(c[m, 1])}
                        for m, n in enumerate(robot.hall_names)}
    if effects.uses("gyro_mounting"):
        r = np.asarray(effects.mounting, np.float64)
        out["gyro_mounting"] = {n: {"rotation_deg": [float(x) for x in r[i]]}
                                for i, n in enumerate(link_boards(robot))}
    return out


def link_boards(robot: Robot) -> list[str]:
    """Each link's gyro board by name (``gyro1`` ...: its channels' prefix)."""
    return [f"gyro{i + 1}" for i in range(robot.n_links)]


def from_physical(doc: dict, robot: Robot, where: str, dtype=None) -> SensorEffects:
    """Parse ``physical``'s form (``where`` names the file in errors, a ``ValueError``)."""
    e = SensorEffects.zeros(robot, on=tuple(doc), dtype=dtype)

    def num(x, field):
        ok = isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
        if not ok:
            raise ValueError(f"{where}: effects.{field}: expected a number, got {x!r}")
        return float(x)

    def obj(x, field):
        if not isinstance(x, dict):
            raise ValueError(f"{where}: effects.{field}: expected an object, got {x!r}")
        return x

    def per(name, names):
        d = obj(doc[name], name)
        extra = sorted(set(d) - set(names))
        if extra:
            raise ValueError(f"{where}: effects.{name}.{extra[0]}: not a name of joints "
                             f"{robot.spec}")
        return [d.get(n) for n in names]

    unknown = sorted(set(doc) - set(EFFECTS))
    if unknown:
        raise ValueError(f"{where}: effects.{unknown[0]}: unknown effect; expected some of "
                         f"{', '.join(EFFECTS)}")
    vals = {k: getattr(e, k) for k in LEAVES}
    if "offset" in doc:
        vals["offset"] = num(obj(doc["offset"], "offset").get("time_offset_s"),
                             "offset.time_offset_s") / _OFFSET_UNIT_S
    if "gyro_timing" in doc:
        vals["timing"] = num(obj(doc["gyro_timing"], "gyro_timing").get("fraction_of_step"),
                             "gyro_timing.fraction_of_step")
    if "gyro_scale" in doc:
        vals["gyro_scale"] = [num(x, f"gyro_scale.{n}") / _SCALE_UNIT
                              for n, x in zip(robot.gyro_names, per("gyro_scale",
                                                                    robot.gyro_names))]
    if "play" in doc:
        axes = robot.angle_names[:robot.n_joint_axes]
        vals["play"] = [num(obj(x, f"play.{n}").get("half_width_deg"),
                            f"play.{n}.half_width_deg")
                        for n, x in zip(axes, per("play", axes))]
    if "curve" in doc:
        vals["curve"] = [[num(obj(x, f"curve.{n}").get(k), f"curve.{n}.{k}")
                          for k in ("p2_deg", "p3_deg")]
                         for n, x in zip(robot.hall_names, per("curve", robot.hall_names))]
    if "gyro_mounting" in doc:
        boards = link_boards(robot)
        vals["mounting"] = [_triple(obj(x, f"gyro_mounting.{n}").get("rotation_deg"),
                                    f"gyro_mounting.{n}.rotation_deg", num)
                            for n, x in zip(boards, per("gyro_mounting", boards))]
    dt = dtype or jnp.asarray(0.0).dtype
    return SensorEffects(*(jnp.asarray(vals[k], dt) for k in LEAVES), on=e.on)


def _triple(x, field: str, num) -> list[float]:
    """A rotation vector of the parameter file: three numbers."""
    if not isinstance(x, list) or len(x) != 3:
        raise ValueError(f"effects.{field}: expected three numbers [x, y, z] in deg, got {x!r}")
    return [num(v, field) for v in x]


def parse_learn(text: str | None) -> tuple[str, ...]:
    """``--learn offset,play``'s list; a ``ValueError`` names an unknown effect."""
    if not text:
        return ()
    names = tuple(x.strip() for x in text.split(",") if x.strip())
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise ValueError(f"--learn: unknown effect {unknown[0]!r}; expected some of "
                         f"{', '.join(EFFECTS)} (comma-separated)")
    return tuple(e for e in EFFECTS if e in names)
