"""Learnable filter parameters: noise scales, initial covariance and Hall models.

Every leaf is *unconstrained* (a log), so gradient descent can move it freely and the physical
value ``exp(leaf)`` stays positive. A physical value of exactly zero (the paper has no angle or
bias random walk) is stored as ``-inf``: its gradient is zero, so it stays off until a fit
starts it from a positive floor (see ``Params.with_floors``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._effects import EFFECTS, SensorEffects
from ._effects import LEAVES as EFFECT_LEAVES
from ._fault_policy import FaultPolicy
from ._hall import DEG, PAPER_HALL_DEG
from ._limits import SensorLimits
from ._robot import Robot

HALL_NOISE_MODELS = ("angle", "voltage")

#: Paper defaults and the sources of the numbers that are not in the paper.
PAPER_SIGMA_HALL_RAD = 3.2 * DEG  # Eq. 20, sigma_hall = 3.2 deg
#: Eq. 13 gives Q up to a scale; as printed (in the paper's unit, degrees) the scale is 1,
#: i.e. q = (1 deg/s^2)^2: the bias of each coordinate may wander ts * 1 deg/s per step.
PAPER_Q_RAD2_S4 = DEG**2
#: Initial uncertainty (not in the paper): joint angles are unknown within a joint's 60 deg
#: range of motion; gyro differences start within about the LSM6DSO zero-rate level (+-1 dps
#: per gyro, so about 1.4 dps for a difference).
DEFAULT_P0_ANGLE_RAD = 30.0 * DEG
DEFAULT_P0_BIAS_RAD_S = 1.5 * DEG
#: Voltage noise of a Hall channel for the ``"voltage"`` noise model (mechanical play of the
#: magnet against the sensor dominates the DRV5053's electrical noise; see docs/simulator.md).
DEFAULT_SIGMA_HALL_V = 0.03


def _log(x) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.log(np.asarray(x, dtype=np.float64))


class Params(eqx.Module):
    """Learnable KCKF parameters for one robot layout (physical values via properties).

    Leaves (all logs of positive physical values, float):

    * ``log_q`` (K): the scale ``q`` of Eq. 13 per angle coordinate, in rad^2/s^4;
    * ``log_angle_rw`` (K), ``log_bias_rw`` (K): extra angle random walk (rad/sqrt(s)) and bias
      random walk (rad/s/sqrt(s)) added to Eq. 13 (zero in the paper);
    * ``log_sigma_hall`` (M): Hall angle noise, rad (Eq. 20, ``"angle"`` noise model);
    * ``log_sigma_hall_v`` (M): Hall voltage noise, V (``"voltage"`` noise model: the angle
      noise is ``|d theta/dV| * sigma_V``, so a sensor on its saturated side counts less);
    * ``log_p0_angle`` (K), ``log_p0_bias`` (K): initial standard deviations, rad and rad/s
      (the torso angle's own entry is used by ``kf`` only: in the KCKF, ``phi = sum theta``);
    * ``log_hall_a``, ``log_hall_b``, ``log_hall_c``, ``log_hall_d`` (M): Eq. 1 per sensor, rad.

    Static: the ``robot``, each sensor's ``hall_sign``, the ``hall_noise`` model and the
    readings' physical ``limits`` (``SensorLimits``: beyond them a reading is missing).

    ``faults``: what the health monitor's findings do (``FaultPolicy``: ``isolate``, the
    default; ``report``; ``off``), static: a setting of the run, not saved with the
    parameters (``with_faults``).

    ``effects``: the learned sensor effects (``SensorEffects``: gyro scale factors, the
    joints' play, Hall curves beyond Eq. 1, a clock offset against motion capture), or
    ``None`` (the paper's sensor models; the default). ``with_effects`` switches them on.

    Example:
        >>> p = Params.paper_defaults(Robot.from_spec("x,y,x,y"))
        >>> round(float(p.sigma_hall[0]) / DEG, 3)
        3.2
    """

    log_q: Float[Array, " K"]
    log_angle_rw: Float[Array, " K"]
    log_bias_rw: Float[Array, " K"]
    log_sigma_hall: Float[Array, " M"]
    log_sigma_hall_v: Float[Array, " M"]
    log_p0_angle: Float[Array, " K"]
    log_p0_bias: Float[Array, " K"]
    log_hall_a: Float[Array, " M"]
    log_hall_b: Float[Array, " M"]
    log_hall_c: Float[Array, " M"]
    log_hall_d: Float[Array, " M"]
    robot: Robot = eqx.field(static=True)
    hall_sign: tuple[int, ...] = eqx.field(static=True)
    hall_noise: str = eqx.field(static=True, default="angle")
    limits: SensorLimits = eqx.field(static=True, default=SensorLimits())
    effects: SensorEffects | None = None
    faults: FaultPolicy = eqx.field(static=True, default=FaultPolicy())

    def __check_init__(self):
        K, M = self.robot.n_angles, self.robot.n_hall
        sizes = {
            "log_q": K, "log_angle_rw": K, "log_bias_rw": K, "log_p0_angle": K,
            "log_p0_bias": K, "log_sigma_hall": M, "log_sigma_hall_v": M, "log_hall_a": M,
            "log_hall_b": M, "log_hall_c": M, "log_hall_d": M,
        }
        for name, n in sizes.items():
            shape = jnp.shape(getattr(self, name))
            if shape != (n,):
                raise ValueError(
                    f"Params.{name}: expected shape ({n},) for robot {self.robot.spec!r}, "
                    f"got {shape}"
                )
        if len(self.hall_sign) != M or any(s not in (1, -1) for s in self.hall_sign):
            raise ValueError(
                f"Params.hall_sign: expected {M} entries of +1/-1, got {self.hall_sign}")
        if self.hall_noise not in HALL_NOISE_MODELS:
            raise ValueError(
                f"Params.hall_noise: expected one of {HALL_NOISE_MODELS}, got {self.hall_noise!r}"
            )

    # ------------------------------------------------------------------ physical values
    q = property(lambda self: jnp.exp(self.log_q))
    angle_rw = property(lambda self: jnp.exp(self.log_angle_rw))
    bias_rw = property(lambda self: jnp.exp(self.log_bias_rw))
    sigma_hall = property(lambda self: jnp.exp(self.log_sigma_hall))
    sigma_hall_v = property(lambda self: jnp.exp(self.log_sigma_hall_v))
    p0_angle = property(lambda self: jnp.exp(self.log_p0_angle))
    p0_bias = property(lambda self: jnp.exp(self.log_p0_bias))

    @property
    def hall_coeffs(self) -> tuple[Array, Array, Array, Array, Array]:
        """``(a, b, c, d, sign)`` per sensor, rad (for ``hall_angle``)."""
        sign = jnp.asarray(self.hall_sign, dtype=self.log_hall_a.dtype)
        return (jnp.exp(self.log_hall_a), jnp.exp(self.log_hall_b), jnp.exp(self.log_hall_c),
                jnp.exp(self.log_hall_d), sign)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_physical(
        cls,
        robot: Robot,
        *,
        q: float | np.ndarray = PAPER_Q_RAD2_S4,
        angle_rw: float | np.ndarray = 0.0,
        bias_rw: float | np.ndarray = 0.0,
        sigma_hall: float | np.ndarray = PAPER_SIGMA_HALL_RAD,
        sigma_hall_v: float | np.ndarray = DEFAULT_SIGMA_HALL_V,
        p0_angle: float | np.ndarray = DEFAULT_P0_ANGLE_RAD,
        p0_bias: float | np.ndarray = DEFAULT_P0_BIAS_RAD_S,
        hall_models: Mapping[str, Mapping] | None = None,
        hall_noise: str = "angle",
        limits: SensorLimits | None = None,
        dtype=None,
    ) -> Params:
        """Build from physical values (scalars broadcast; arrays per coordinate or sensor).

        ``hall_models`` maps sensor column names to ``{"a", "b", "c", "d", "sign", "unit"}``
        as in ``meta.json``; a sensor without an entry gets the paper's Eq. 1 with sign +1 for
        ``l`` and -1 for ``r``.
        """
        K, M = robot.n_angles, robot.n_hall
        a, b, c, d, sign = hall_arrays(robot, hall_models)

        def vec(x, n, name):
            arr = np.broadcast_to(np.asarray(x, dtype=np.float64), (n,)) if np.ndim(x) == 0 else (
                np.asarray(x, dtype=np.float64))
            if arr.shape != (n,):
                raise ValueError(f"Params.from_physical: {name} must be a scalar or have shape "
                                 f"({n},), got {arr.shape}")
            if np.any(arr < 0) or not np.all(np.isfinite(arr)):
                raise ValueError(f"Params.from_physical: {name} must be finite and >= 0, got {arr}")
            return _log(arr)

        dt = dtype or jnp.asarray(0.0).dtype
        leaves = dict(
            log_q=vec(q, K, "q"), log_angle_rw=vec(angle_rw, K, "angle_rw"),
            log_bias_rw=vec(bias_rw, K, "bias_rw"),
            log_sigma_hall=vec(sigma_hall, M, "sigma_hall"),
            log_sigma_hall_v=vec(sigma_hall_v, M, "sigma_hall_v"),
            log_p0_angle=vec(p0_angle, K, "p0_angle"), log_p0_bias=vec(p0_bias, K, "p0_bias"),
            log_hall_a=_log(a), log_hall_b=_log(b), log_hall_c=_log(c), log_hall_d=_log(d),
        )
        leaves = {k: jnp.asarray(v, dtype=dt) for k, v in leaves.items()}
        return cls(**leaves, robot=robot, hall_sign=tuple(int(s) for s in sign),
                   hall_noise=hall_noise, limits=limits or SensorLimits())

    @classmethod
    def paper_defaults(cls, robot: Robot, hall_models: Mapping[str, Mapping] | None = None,
                       dtype=None, limits: SensorLimits | None = None) -> Params:
        """The paper's filter: Eq. 13 Q (scale 1 deg^2/s^4), sigma_hall = 3.2 deg (Eq. 20);
        ``hall_models`` as in ``meta.json`` (degrees or radians, by their ``unit``)."""
        return cls.from_physical(robot, hall_models=hall_models, dtype=dtype, limits=limits)

    def astype(self, dtype) -> Params:
        """The same parameters with every leaf cast to ``dtype``."""
        out = eqx.tree_at(
            lambda p: [getattr(p, f) for f in _LEAVES], self,
            [jnp.asarray(getattr(self, f), dtype=dtype) for f in _LEAVES],
        )
        if self.effects is None:
            return out
        return dataclasses.replace(out, effects=self.effects.astype(dtype))

    def with_faults(self, policy: FaultPolicy | str | None) -> Params:
        """These parameters with the fault policy ``policy`` (``FaultPolicy`` or its name;
        ``None``: as they are). The policy is a setting of the run, not a fitted value: it is
        not saved with the parameters."""
        if policy is None:
            return self
        return dataclasses.replace(self, faults=FaultPolicy.of(policy))

    def with_effects(self, on=EFFECTS, effects: SensorEffects | None = None) -> Params:
        """These parameters with the sensor effects ``on`` (names of ``EFFECTS``) switched on:
        from ``effects`` where given, else from the ones already here, else from none
        (zero); an empty ``on`` switches every effect off (``effects=None``)."""
        on = tuple(on)
        if not on:
            return dataclasses.replace(self, effects=None)
        base = effects or self.effects or SensorEffects.zeros(self.robot,
                                                              dtype=self.log_q.dtype)
        return dataclasses.replace(self, effects=SensorEffects(
            *(getattr(base, k) for k in EFFECT_LEAVES), on=tuple(e for e in EFFECTS if e in on)))


_LEAVES = ("log_q", "log_angle_rw", "log_bias_rw", "log_sigma_hall", "log_sigma_hall_v",
           "log_p0_angle", "log_p0_bias", "log_hall_a", "log_hall_b", "log_hall_c", "log_hall_d")


#: Every leaf a fit may learn, by name: ``_LEAVES``, then the sensor effects' (``effects.NAME``).
ALL_LEAVES = _LEAVES + tuple(f"effects.{n}" for n in EFFECT_LEAVES)


def leaf_names(params: Params) -> tuple[str, ...]:
    """Every learned leaf of ``params`` by name: ``_LEAVES``, then ``effects.NAME`` for the
    sensor effects' leaves where ``params`` has them (``get_leaf`` reads one)."""
    return _LEAVES if params.effects is None else ALL_LEAVES


def get_leaf(params, name: str):
    """The leaf ``name`` of ``leaf_names`` (any module's: a dotted name reaches into a
    sub-module, ``"effects.timing"``; the training loop's ``freeze`` reads leaves so)."""
    for part in name.split("."):
        params = getattr(params, part)
    return params


def hall_arrays(robot: Robot, hall_models: Mapping[str, Mapping] | None = None):
    """Per-sensor ``(a, b, c, d, sign)`` arrays in rad from ``meta.json``-style models."""
    hall_models = dict(hall_models or {})
    unknown = sorted(set(hall_models) - set(robot.hall_names))
    if unknown:
        raise ValueError(
            f"hall_models: {unknown[0]!r} is not a Hall sensor of robot {robot.spec!r} "
            f"(expected names like {robot.hall_names[0]!r})"
        )
    out = np.zeros((5, robot.n_hall))
    for m, (name, default_sign) in enumerate(zip(robot.hall_names, robot.hall_side_sign)):
        model = hall_models.get(name)
        if model is None:
            model = dict(PAPER_HALL_DEG, sign=default_sign, unit="deg")
        unit = model.get("unit", "deg")
        if unit not in ("deg", "rad"):
            raise ValueError(f"hall_models[{name!r}].unit: expected 'deg' or 'rad', got {unit!r}")
        scale = DEG if unit == "deg" else 1.0
        vals = []
        for key in ("a", "b", "c", "d"):
            v = model.get(key)
            number = isinstance(v, int | float) and not isinstance(v, bool)
            if not number or not math.isfinite(v) or v <= 0:
                raise ValueError(
                    f"hall_models[{name!r}].{key}: expected a positive number, got {v!r}"
                )
            vals.append(float(v))
        sign = model.get("sign", default_sign)
        if sign not in (1, -1):
            raise ValueError(f"hall_models[{name!r}].sign: expected 1 or -1, got {sign!r}")
        out[:, m] = (vals[0] * scale, vals[1], vals[2] * scale, vals[3], sign)
    return out[0], out[1], out[2], out[3], out[4]


# ---------------------------------------------------------------------------- floors
def with_floors(params: Params, *, angle_rw: float = 1e-3 * DEG, bias_rw: float = 1e-3 * DEG,
                sigma_hall: float = 0.05 * DEG) -> Params:
    """``params`` with zero-valued noise terms raised to small positive floors.

    A term that is exactly zero (the paper has no angle or bias random walk) is stored as
    ``log = -inf`` and its gradient is zero, so gradient descent could never switch it on. A fit
    starts from the paper defaults with these floors instead (1e-3 deg/sqrt(s),
    1e-3 deg/s/sqrt(s), 0.05 deg by default); values already above a floor are kept.
    """
    def floor(x, f):
        return jnp.maximum(x, jnp.log(jnp.asarray(f, x.dtype)))

    return eqx.tree_at(
        lambda p: (p.log_angle_rw, p.log_bias_rw, p.log_sigma_hall), params,
        (floor(params.log_angle_rw, angle_rw), floor(params.log_bias_rw, bias_rw),
         floor(params.log_sigma_hall, sigma_hall)),
    )


# ---------------------------------------------------------------------------- JSON form
PARAMS_FORMAT = "kckf-params/1"


class ParamsFileError(ValueError):
    """A parameter file that cannot be used, in one line naming the file and the field."""


def params_to_dict(params: Params, fit_info: Mapping | None = None) -> dict:
    """The human-readable JSON form: physical values with their units, keyed by name."""
    robot = params.robot
    f = {k: np.asarray(getattr(params, k), dtype=np.float64).tolist()
         for k in ("q", "angle_rw", "bias_rw", "sigma_hall", "sigma_hall_v", "p0_angle",
                   "p0_bias")}
    a, b, c, d, _ = (np.asarray(x, dtype=np.float64) for x in params.hall_coeffs)
    doc = {
        "format": PARAMS_FORMAT,
        "joints": robot.to_meta(),
        "hall_noise": params.hall_noise,
        "limits": params.limits.to_meta(),
        "process_noise": {
            name: {"q_rad2_s4": f["q"][k], "angle_rw_rad_rts": f["angle_rw"][k],
                   "bias_rw_rad_s_rts": f["bias_rw"][k]}
            for k, name in enumerate(robot.angle_names)
        },
        "initial_std": {
            name: {"angle_rad": f["p0_angle"][k], "bias_rad_s": f["p0_bias"][k]}
            for k, name in enumerate(robot.angle_names)
        },
        "hall": {
            name: {"a": float(a[m] / DEG), "b": float(b[m]), "c": float(c[m] / DEG),
                   "d": float(d[m]), "sign": int(params.hall_sign[m]), "unit": "deg",
                   "sigma_rad": f["sigma_hall"][m], "sigma_v": f["sigma_hall_v"][m]}
            for m, name in enumerate(robot.hall_names)
        },
    }
    if params.effects is not None:
        from ._effects import physical

        doc["effects"] = physical(params.effects, robot)
    if fit_info:
        doc["fit"] = dict(fit_info)
    return doc


def params_from_dict(doc: object, where: str = "parameters", dtype=None) -> Params:
    """Parse ``params_to_dict``'s form; ``ParamsFileError`` names the field at fault."""

    def fail(field: str, expected: str, got: object) -> ParamsFileError:
        text = repr(got)
        text = text if len(text) <= 60 else text[:57] + "..."
        return ParamsFileError(f"{where}: {field}: expected {expected}, got {text}")

    def obj(x, field):
        if not isinstance(x, dict):
            raise fail(field, "an object", x)
        return x

    def num(x, field, positive=False):
        ok = isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
        if not ok or x < 0 or (positive and x == 0):
            raise fail(field, "a positive number" if positive else "a number >= 0", x)
        return float(x)

    doc = obj(doc, "the file")
    if doc.get("format") != PARAMS_FORMAT:
        raise fail("format", repr(PARAMS_FORMAT), doc.get("format"))
    try:
        robot = Robot.from_meta(doc.get("joints"), where=where)
    except ValueError as exc:
        raise ParamsFileError(str(exc)) from None
    noise = doc.get("hall_noise", "angle")
    if noise not in HALL_NOISE_MODELS:
        raise fail("hall_noise", " or ".join(map(repr, HALL_NOISE_MODELS)), noise)
    try:
        limits = SensorLimits.from_meta(obj(doc.get("limits", {}), "limits"), f"{where}: limits")
    except ValueError as exc:
        raise ParamsFileError(str(exc)) from None
    pn, p0, hall = (obj(doc.get(k), k) for k in ("process_noise", "initial_std", "hall"))
    vals: dict[str, list] = {k: [] for k in ("q", "angle_rw", "bias_rw", "p0_angle", "p0_bias",
                                             "sigma_hall", "sigma_hall_v")}
    for name in robot.angle_names:
        e = obj(pn.get(name), f"process_noise.{name}")
        vals["q"].append(num(e.get("q_rad2_s4"), f"process_noise.{name}.q_rad2_s4"))
        vals["angle_rw"].append(num(e.get("angle_rw_rad_rts"),
                                    f"process_noise.{name}.angle_rw_rad_rts"))
        vals["bias_rw"].append(num(e.get("bias_rw_rad_s_rts"),
                                   f"process_noise.{name}.bias_rw_rad_s_rts"))
        e = obj(p0.get(name), f"initial_std.{name}")
        vals["p0_angle"].append(num(e.get("angle_rad"), f"initial_std.{name}.angle_rad", True))
        vals["p0_bias"].append(num(e.get("bias_rad_s"), f"initial_std.{name}.bias_rad_s", True))
    models = {}
    for name in robot.hall_names:
        e = obj(hall.get(name), f"hall.{name}")
        vals["sigma_hall"].append(num(e.get("sigma_rad"), f"hall.{name}.sigma_rad"))
        vals["sigma_hall_v"].append(num(e.get("sigma_v"), f"hall.{name}.sigma_v"))
        models[name] = {k: e.get(k) for k in ("a", "b", "c", "d", "sign", "unit")}
    for key, names in (("process_noise", robot.angle_names), ("initial_std", robot.angle_names),
                       ("hall", robot.hall_names)):
        extra = sorted(set(doc[key]) - set(names))
        if extra:
            raise ParamsFileError(
                f"{where}: {key}.{extra[0]}: not a name of the robot in this file "
                f"(joints {robot.spec}); expected {', '.join(names)}")
    try:
        params = Params.from_physical(robot, hall_models=models, hall_noise=noise, dtype=dtype,
                                      limits=limits, **{k: np.asarray(v) for k, v in vals.items()})
    except ValueError as exc:
        raise ParamsFileError(f"{where}: {exc}") from None
    if "effects" not in doc:
        return params
    from ._effects import from_physical

    try:
        effects = from_physical(obj(doc["effects"], "effects"), robot, where, dtype)
    except ValueError as exc:
        raise ParamsFileError(str(exc)) from None
    return params.with_effects(effects.on, effects)


def save_params(params: Params, path: str, fit_info: Mapping | None = None) -> None:
    """Write ``params`` as JSON (atomically: a crash never leaves half a file)."""
    import json

    from .._sessions._atomic import atomic_write

    with atomic_write(path) as f:
        json.dump(params_to_dict(params, fit_info), f, indent=2)
        f.write("\n")


def load_params(path: str, dtype=None) -> Params:
    """Read a parameter file written by ``save_params`` / ``kckf fit``.

    Raises ``ParamsFileError`` (a ``ValueError``) naming the file and the field: not JSON or
    truncated, another format or version, wrong types or signs, names that do not belong to
    the robot recorded in the file.
    """
    import json

    try:
        with open(path) as f:
            text = f.read()
    except OSError as exc:
        raise ParamsFileError(f"{path}: cannot read the parameter file ({exc.strerror})") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ParamsFileError(
            f"{path}: truncated or not valid JSON (line {exc.lineno}, column {exc.colno}: "
            f"{exc.msg}); write it again with kckf fit") from None
    return params_from_dict(doc, where=path, dtype=dtype)
