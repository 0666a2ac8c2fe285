"""The arm exoskeleton + IMU fusion filter of Chen, Yang and Hofschulte.

"Improvement of an Arm Exoskeleton by Data Fusion with an Inertial Measurement Unit": a 7-joint
arm exoskeleton gives the pose of its end effector by forward kinematics (12-bit encoders,
biased by manufacturing and accumulated joint errors); an IMU (Xsens MTi) fixed at the end
effector gives specific force and turn rate in its own frame. A linear Kalman filter per axis
fuses them (paper Sec. III):

* position, per exoskeleton-frame axis: ``[p, v, a]`` with the constant-acceleration model
  of Eqs. 4, 6, 8;
* orientation, per axis: ``[phi, phi_dot]`` with the constant-turn-rate model of Eqs. 5, 7, 9;
* measurements (Eqs. 10-11): the exoskeleton measures ``p`` and ``phi``; the IMU measures
  ``a`` (specific force rotated into the exoskeleton frame, gravity removed: Eq. 2) and
  ``phi_dot`` (turn rate rotated into the exoskeleton frame: Eq. 3); the velocity ``v`` is a
  pseudo-measurement, the difference quotient of consecutive exoskeleton positions, with
  noise variance ``2 sigma_pos^2 / dT^2`` derived from the position's ("the measurement noise
  covariance of velocity is estimated using the measurement noise covariance of position").

What the extracted paper text leaves garbled or open, and how it is rebuilt here (the same
notes sit next to the code):

* Eq. 10 prints ``x(k-1)`` on the right-hand side of a measurement equation and Eq. 11 prints
  the state on both sides; both are rebuilt as ``y(k) = C x(k) + v(k)`` with ``C = I`` (Eq. 13).
* Eq. 3 says the turn rate is rotated "into the coordinate frame of OTS" and Eq. 2's text
  names ``R_imu^ots``; the surrounding text makes the exoskeleton frame the world frame, so
  both use ``R_imu^exo = R_ee(t) R_mount``: the end effector's orientation times the IMU's
  (calibrated, fixed) mounting rotation. The paper does not say where ``R_ee(t)`` comes from;
  we take the filter's own orientation estimate at that step: after the exoskeleton's
  orientation rows for the turn rate, after all orientation rows for the acceleration. It
  exists when the exoskeleton's reading is missing and carries less of its error.
* Gravity (Eq. 2): the exoskeleton frame's ``z`` axis points up, so
  ``a = R_imu^exo f - [0, 0, g]`` for the accelerometer's specific force ``f``.
* The orientation coordinates ``phi`` of Eqs. 5, 7, 9 are not defined in the paper. We use
  the rotation vector of the end effector relative to a fixed reference orientation
  ``R_ref`` (by default the trial's first exoskeleton reading): ``R_ee = exp([phi]x) R_ref``.
  Its rate is ``phi_dot = J_l(phi)^-1 omega`` for the exoskeleton-frame turn rate ``omega``
  (Eq. 3); the paper's ``phi_dot = omega`` is the small-angle form. The gyro row measures
  ``J_l(phi)^-1 omega`` with ``phi`` the current estimate. Readings more than 150 deg from
  ``R_ref`` (where the rotation-vector chart degrades) are dropped.
* ``Q`` and ``R`` are not given. ``Q`` is the continuous white-noise model (white jerk for
  position, white angular acceleration for orientation; Bar-Shalom, Li and Kirubarajan,
  "Estimation with Applications to Tracking and Navigation", 2001, Ch. 6), whose transition
  matrices are those of Eqs. 8-9; ``R`` is diagonal (``ArmImuParams``).
* The velocity pseudo-measurement is treated as independent of the position reading it is
  computed from, as in the paper (in truth it is correlated with it).

Conventions (shared with the NumPy reference in ``tests/test_arm_imu.py``):

* ``inputs.dt[k] = t[k] - t[k-1]`` (``dt[0] = 0``: no prediction before the first row); the
  exoskeleton and the IMU each run at their own rate on one merged timeline
  (``arm_imu_series``), and a row without a new sample of a sensor holds NaN there;
* a missing reading (NaN) removes only its own measurement rows: a position component its
  own row (and its velocity row); an orientation or IMU reading, which enters through a
  rotation, all three of its rows;
* the velocity row uses the previous valid reading of that position component and the time
  elapsed since it;
* order within a step: predict; orientation rows of the exoskeleton, then of the gyro; then
  position, velocity and acceleration rows, the last rotated with the updated orientation;
* a padded step (``dt = 0``, every reading NaN) leaves the state unchanged.

Numerics: the model is block diagonal (three position blocks of 3 states, three orientation
blocks of 2), so each block is filtered on its own (``vmap`` over axes). Measurements are
processed one scalar at a time (``R`` is diagonal, so this equals the joint update), each in
Joseph form, and covariances are symmetrised after each step. There is no matrix inverse and
no LAPACK call in a step; float32 works.

Example:
    >>> import numpy as np
    >>> params = ArmImuParams.paper_defaults()
    >>> T = 5
    >>> series = ArmImuSeries(
    ...     dt=np.r_[0.0, np.full(T - 1, 0.01)], exo_pos=np.zeros((T, 3)),
    ...     exo_rot=np.tile(np.eye(3), (T, 1, 1)), imu_acc=np.tile([0, 0, 9.81], (T, 1)),
    ...     imu_gyro=np.zeros((T, 3)))
    >>> final, est = run_arm_imu(params, series)
    >>> est.pos.shape, est.rot.shape
    ((5, 3), (5, 3, 3))
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ..._models._kalman import coordinate_update, symmetrise
from ..._readings._batching import pad_trials

DEG = np.pi / 180.0
GRAVITY_MPS2 = 9.81
#: Orientation readings further than this from the reference are dropped (rotation-vector chart).
MAX_ROTATION_RAD = 150.0 * DEG

# ------------------------------------------------------------------ default numbers
#: Xsens MTi gyro noise per sample: typical noise density 0.05 deg/s/sqrt(Hz) over its 40 Hz
#: bandwidth ("MTi and MTx User Manual and Technical Documentation", Xsens MT0100P), white:
#: sigma = density * sqrt(bandwidth) = 0.32 deg/s.
MTI_GYRO_NOISE_RAD_S = 0.05 * DEG * np.sqrt(40.0)
#: Default numbers (the paper gives none). The gyro row has the MTi's white noise. The
#: acceleration row has 0.06 m/s^2, not the MTi's 0.011 m/s^2 of white noise (0.002
#: m/s^2/sqrt(Hz) over 30 Hz): it also carries the accelerometer's bias (0.02 m/s^2 bias
#: stability) and the gravity that leaks through the orientation error in Eq. 2 (0.2 deg of
#: tilt is 0.034 m/s^2). The exoskeleton rows and the process noise were picked by a small grid
#: search on simulated experiments (``arm_sim.py``) with seeds 1000-1003, never the reported
#: seed 0; see docs/other_filters.md.
DEFAULTS = dict(
    q_jerk=1000.0,  # m^2/s^5, white-jerk spectral density
    q_alpha=1.0,  # rad^2/s^3, white angular-acceleration spectral density
    sigma_pos=0.5e-3,  # m, exoskeleton position (forward kinematics)
    sigma_rot=1.0 * DEG,  # rad, exoskeleton orientation
    sigma_acc=0.06,  # m/s^2, IMU acceleration after Eq. 2
    sigma_gyro=MTI_GYRO_NOISE_RAD_S,  # rad/s, IMU turn rate after Eq. 3
    # Prior: wide against every reading, yet not so wide that the first update loses the
    # reading's variance to float32 rounding (p0^2 + r must still resolve r).
    p0_pos=0.1,  # m
    p0_vel=0.5,  # m/s
    p0_acc=5.0,  # m/s^2
    p0_rot=10.0 * DEG,  # rad (the reference is the first reading, so phi starts near 0)
    p0_rate=1.0,  # rad/s
)

_LEAVES = tuple(f"log_{k}" for k in DEFAULTS)


def _log(x) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.log(np.asarray(x, dtype=np.float64))


class ArmImuParams(eqx.Module):
    """Noise and prior of the arm + IMU filter, one value per exoskeleton-frame axis.

    Leaves (all logs of positive physical values, shape (3,) for the x, y, z axes):

    * ``log_q_jerk``: white-jerk spectral density of the position model, m^2/s^5;
    * ``log_q_alpha``: white angular-acceleration spectral density of the orientation model,
      rad^2/s^3;
    * ``log_sigma_pos`` (m), ``log_sigma_rot`` (rad): exoskeleton position and orientation
      noise (the velocity pseudo-measurement's variance follows: ``2 sigma_pos^2 / dT^2``);
    * ``log_sigma_acc`` (m/s^2), ``log_sigma_gyro`` (rad/s): IMU noise after Eqs. 2-3;
    * ``log_p0_pos`` (m), ``log_p0_vel`` (m/s), ``log_p0_acc`` (m/s^2), ``log_p0_rot`` (rad),
      ``log_p0_rate`` (rad/s): initial standard deviations.

    Static: ``gravity_mps2`` and ``imu_mount``, the IMU's fixed rotation in the end-effector
    frame (row-major 3x3, identity by default: IMU axes along the end effector's).

    Example:
        >>> p = ArmImuParams.paper_defaults()
        >>> round(float(p.sigma_acc[0]), 3)
        0.06
    """

    log_q_jerk: Float[Array, " 3"]
    log_q_alpha: Float[Array, " 3"]
    log_sigma_pos: Float[Array, " 3"]
    log_sigma_rot: Float[Array, " 3"]
    log_sigma_acc: Float[Array, " 3"]
    log_sigma_gyro: Float[Array, " 3"]
    log_p0_pos: Float[Array, " 3"]
    log_p0_vel: Float[Array, " 3"]
    log_p0_acc: Float[Array, " 3"]
    log_p0_rot: Float[Array, " 3"]
    log_p0_rate: Float[Array, " 3"]
    gravity_mps2: float = eqx.field(static=True, default=GRAVITY_MPS2)
    imu_mount: tuple[tuple[float, float, float], ...] = eqx.field(
        static=True, default=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)))

    def __check_init__(self):
        for name in _LEAVES:
            shape = jnp.shape(getattr(self, name))
            if shape != (3,):
                raise ValueError(f"ArmImuParams.{name}: expected shape (3,), got {shape}")
        mount = np.asarray(self.imu_mount, dtype=np.float64)
        if mount.shape != (3, 3) or not np.allclose(mount @ mount.T, np.eye(3), atol=1e-6) or (
                np.linalg.det(mount) < 0):
            raise ValueError(
                f"ArmImuParams.imu_mount: expected a 3x3 rotation matrix, got {self.imu_mount}")

    q_jerk = property(lambda self: jnp.exp(self.log_q_jerk))
    q_alpha = property(lambda self: jnp.exp(self.log_q_alpha))
    sigma_pos = property(lambda self: jnp.exp(self.log_sigma_pos))
    sigma_rot = property(lambda self: jnp.exp(self.log_sigma_rot))
    sigma_acc = property(lambda self: jnp.exp(self.log_sigma_acc))
    sigma_gyro = property(lambda self: jnp.exp(self.log_sigma_gyro))
    p0_pos = property(lambda self: jnp.exp(self.log_p0_pos))
    p0_vel = property(lambda self: jnp.exp(self.log_p0_vel))
    p0_acc = property(lambda self: jnp.exp(self.log_p0_acc))
    p0_rot = property(lambda self: jnp.exp(self.log_p0_rot))
    p0_rate = property(lambda self: jnp.exp(self.log_p0_rate))

    @classmethod
    def from_physical(cls, *, dtype=None, gravity_mps2: float = GRAVITY_MPS2,
                      imu_mount=None, **values) -> ArmImuParams:
        """Build from physical values (keys of ``DEFAULTS``; scalars or per-axis triples).

        Missing keys take ``DEFAULTS``. Values must be finite and positive.
        """
        unknown = sorted(set(values) - set(DEFAULTS))
        if unknown:
            raise ValueError(f"ArmImuParams.from_physical: unknown value {unknown[0]!r}; "
                             f"expected some of {', '.join(DEFAULTS)}")
        dt = dtype or jnp.asarray(0.0).dtype
        leaves = {}
        for name, default in DEFAULTS.items():
            x = np.asarray(values.get(name, default), dtype=np.float64)
            arr = np.broadcast_to(x, (3,)) if x.ndim == 0 else x
            if arr.shape != (3,):
                raise ValueError(f"ArmImuParams.from_physical: {name} must be a scalar or have "
                                 f"shape (3,), got {x.shape}")
            if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
                raise ValueError(f"ArmImuParams.from_physical: {name} must be finite and > 0, "
                                 f"got {arr}")
            leaves[f"log_{name}"] = jnp.asarray(_log(arr), dtype=dt)
        mount = np.eye(3) if imu_mount is None else np.asarray(imu_mount, dtype=np.float64)
        return cls(**leaves, gravity_mps2=float(gravity_mps2),
                   imu_mount=tuple(tuple(float(v) for v in row) for row in mount))

    @classmethod
    def paper_defaults(cls, dtype=None) -> ArmImuParams:
        """The paper's filter with our numbers (the paper gives none): ``DEFAULTS``."""
        return cls.from_physical(dtype=dtype)

    def astype(self, dtype) -> ArmImuParams:
        """The same parameters with every leaf cast to ``dtype``."""
        return eqx.tree_at(
            lambda p: [getattr(p, f) for f in _LEAVES], self,
            [jnp.asarray(getattr(self, f), dtype=dtype) for f in _LEAVES])


class ArmImuSeries(eqx.Module):
    """Filter inputs: one step (no leading axis), one trial (``T``) or a batch (``B T``).

    * ``dt``: seconds since the previous row (0 for the first row and for padding);
    * ``exo_pos``: end-effector position by forward kinematics, m, exoskeleton frame (z up);
    * ``exo_rot``: end-effector orientation by forward kinematics (rotation matrix, columns
      the end-effector axes in the exoskeleton frame);
    * ``imu_acc``: accelerometer specific force, m/s^2, IMU frame (gravity included);
    * ``imu_gyro``: turn rate, rad/s, IMU frame.

    NaN marks a missing reading (or a row at which that sensor has no new sample).
    """

    dt: Float[ArrayLike, "*T"]
    exo_pos: Float[ArrayLike, "*T 3"]
    exo_rot: Float[ArrayLike, "*T 3 3"]
    imu_acc: Float[ArrayLike, "*T 3"]
    imu_gyro: Float[ArrayLike, "*T 3"]


class ArmImuState(eqx.Module):
    """What the filter carries from one step to the next.

    * ``pos`` (3 axes x ``[p m, v m/s, a m/s^2]``) and ``pos_cov`` (3 x 3 x 3);
    * ``rot`` (3 axes x ``[phi rad, phi_dot rad/s]``) and ``rot_cov`` (3 x 2 x 2): the rotation
      vector of the end effector relative to ``ref`` and its rate;
    * ``ref``: the reference orientation (``R_ee = exp([phi]x) ref``);
    * ``last_pos`` (m), ``since_s`` (s), ``has_last``: the last valid exoskeleton position per
      axis and the time since it, for the velocity pseudo-measurement.
    """

    pos: Float[Array, "3 3"]
    pos_cov: Float[Array, "3 3 3"]
    rot: Float[Array, "3 2"]
    rot_cov: Float[Array, "3 2 2"]
    ref: Float[Array, "3 3"]
    last_pos: Float[Array, " 3"]
    since_s: Float[Array, " 3"]
    has_last: Bool[Array, " 3"]


class ArmImuEstimate(eqx.Module):
    """Per-step output (exoskeleton frame).

    ``pos`` (m), ``vel`` (m/s), ``acc`` (m/s^2), ``rot`` (rotation matrix), ``rotvec`` (rad,
    relative to the state's ``ref``), ``rate`` (rad/s, ``d rotvec / dt``), ``pos_std`` (m) and
    ``rot_std`` (rad): the filter's standard deviations of ``pos`` and ``rotvec``.
    """

    pos: Float[Array, "*T 3"]
    vel: Float[Array, "*T 3"]
    acc: Float[Array, "*T 3"]
    rot: Float[Array, "*T 3 3"]
    rotvec: Float[Array, "*T 3"]
    rate: Float[Array, "*T 3"]
    pos_std: Float[Array, "*T 3"]
    rot_std: Float[Array, "*T 3"]


# ------------------------------------------------------------------ rotations (SO(3))
def _hat(w: Float[Array, " 3"]) -> Float[Array, "3 3"]:
    z = jnp.zeros_like(w[0])
    return jnp.stack([jnp.stack([z, -w[2], w[1]]), jnp.stack([w[2], z, -w[0]]),
                      jnp.stack([-w[1], w[0], z])])


def _safe_sqrt(x: Float[Array, ""], small: Bool[Array, ""]) -> Float[Array, ""]:
    """``sqrt(x)`` where ``small`` is false, else 1: finite value and gradient at ``x = 0``."""
    return jnp.sqrt(jnp.where(small, 1.0, x))


def so3_exp(w: Float[Array, " 3"]) -> Float[Array, "3 3"]:
    """Rotation matrix of the rotation vector ``w`` (rad): Rodrigues' formula.

    ``I + A [w]x + B [w]x^2`` with ``A = sin t / t`` and ``B = (1 - cos t) / t^2 =
    (sin(t/2) / (t/2))^2 / 2`` (no cancellation), Taylor series below ``t = 0.1`` rad.
    """
    t2 = jnp.sum(w * w)
    small = t2 < 1e-2
    t = _safe_sqrt(t2, small)
    A = jnp.where(small, 1 - t2 / 6 * (1 - t2 / 20 * (1 - t2 / 42)), jnp.sin(t) / t)
    h = jnp.sin(t / 2) / (t / 2)
    B = jnp.where(small, 0.5 - t2 / 24 * (1 - t2 / 30 * (1 - t2 / 56)), 0.5 * h * h)
    K = _hat(w)
    return jnp.eye(3, dtype=w.dtype) + A * K + B * (K @ K)


def so3_log(R: Float[Array, "3 3"]) -> tuple[Float[Array, " 3"], Float[Array, ""]]:
    """Rotation vector of ``R`` (rad) and the cosine of its angle.

    From the skew part ``(R - R^T)/2 = sin t [axis]x`` and the trace, ``t = atan2(sin, cos)``;
    valid for angles below about 170 deg (callers drop readings beyond ``MAX_ROTATION_RAD``).
    """
    w = 0.5 * jnp.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = 0.5 * (jnp.trace(R) - 1.0)
    s2 = jnp.sum(w * w)
    small = s2 < 1e-8
    s = _safe_sqrt(s2, small)
    k = jnp.where(small, 1 + s2 / 6, jnp.arctan2(s, c) / s)
    return k * w, c


def _jl_inv_apply(phi: Float[Array, " 3"], omega: Float[Array, " 3"]) -> Float[Array, " 3"]:
    """``J_l(phi)^-1 omega``: the rotation vector's rate for the world-frame turn rate ``omega``.

    ``J_l^-1 = I - [phi]x / 2 + C [phi]x^2`` with ``C = (1 - (t/2) cot(t/2)) / t^2``
    (Taylor series ``1/12 + t^2/720 + t^4/30240`` below ``t = 0.1`` rad, where the closed form
    cancels).
    """
    t2 = jnp.sum(phi * phi)
    small = t2 < 1e-2
    t = _safe_sqrt(t2, small)
    half = t / 2
    C = jnp.where(small, 1 / 12 + t2 / 720 + t2 * t2 / 30240,
                  (1 - half * jnp.cos(half) / jnp.sin(half)) / t2)
    pxo = jnp.cross(phi, omega)
    return omega - 0.5 * pxo + C * jnp.cross(phi, pxo)


# ------------------------------------------------------------------ the filter
def _blocks(dt: Float[Array, ""], dtype):
    """Eqs. 8-9 (``F``) and the continuous white-noise ``Q`` shapes for one time step."""
    one, zero = jnp.ones((), dtype), jnp.zeros((), dtype)
    F3 = jnp.stack([jnp.stack([one, dt, dt * dt / 2]), jnp.stack([zero, one, dt]),
                    jnp.stack([zero, zero, one])])
    Q3 = jnp.stack([jnp.stack([dt**5 / 20, dt**4 / 8, dt**3 / 6]),
                    jnp.stack([dt**4 / 8, dt**3 / 3, dt**2 / 2]),
                    jnp.stack([dt**3 / 6, dt**2 / 2, dt])])
    F2 = jnp.stack([jnp.stack([one, dt]), jnp.stack([zero, one])])
    Q2 = jnp.stack([jnp.stack([dt**3 / 3, dt**2 / 2]), jnp.stack([dt**2 / 2, dt])])
    return F3, Q3, F2, Q2


def _scalar_update(
    x: Float[Array, " N"],
    P: Float[Array, "N N"],
    i: int,
    y: Float[Array, ""],
    r: Float[Array, ""],
    valid: Bool[Array, ""],
) -> tuple[Float[Array, " N"], Float[Array, "N N"]]:
    """Condition on the scalar ``y = x[i] + noise(r)`` (``_kalman.coordinate_update``)."""
    return coordinate_update(x, P, i, y - x[i], r, valid)


def arm_imu_init(params: ArmImuParams, ref_rot: Float[ArrayLike, "3 3"] | None = None
                 ) -> ArmImuState:
    """The state before the first row: zero mean, diagonal prior from ``params``.

    ``ref_rot`` is the reference orientation of the rotation-vector coordinates (identity by
    default; ``run_arm_imu`` uses the first valid exoskeleton orientation).
    """
    dtype = params.log_q_jerk.dtype
    ref = jnp.eye(3, dtype=dtype) if ref_rot is None else jnp.asarray(ref_rot, dtype)
    pos_var = jnp.stack([params.p0_pos, params.p0_vel, params.p0_acc], axis=1) ** 2
    rot_var = jnp.stack([params.p0_rot, params.p0_rate], axis=1) ** 2
    return ArmImuState(
        pos=jnp.zeros((3, 3), dtype), pos_cov=jax.vmap(jnp.diag)(pos_var),
        rot=jnp.zeros((3, 2), dtype), rot_cov=jax.vmap(jnp.diag)(rot_var), ref=ref,
        last_pos=jnp.zeros(3, dtype), since_s=jnp.zeros(3, dtype),
        has_last=jnp.zeros(3, dtype=bool))


def first_valid_rotation(exo_rot: Float[ArrayLike, "T 3 3"]) -> Float[Array, "3 3"]:
    """The first exoskeleton orientation without NaN (identity if there is none)."""
    exo_rot = jnp.asarray(exo_rot)
    valid = jnp.all(jnp.isfinite(exo_rot), axis=(-2, -1))
    R = exo_rot[jnp.argmax(valid)]
    return jnp.where(jnp.any(valid), R, jnp.eye(3, dtype=exo_rot.dtype))


def arm_imu_step(
    params: ArmImuParams, state: ArmImuState, inputs: ArmImuSeries
) -> tuple[ArmImuState, ArmImuEstimate]:
    """One time step: predict over ``inputs.dt`` (Eqs. 8-9, 12), then update (Eqs. 10-11, 13).

    Pure and jit-friendly; ``inputs`` is one row of an ``ArmImuSeries``.
    """
    dtype = state.pos.dtype
    dt = jnp.asarray(inputs.dt, dtype)
    exo_pos = jnp.asarray(inputs.exo_pos, dtype)
    exo_rot = jnp.asarray(inputs.exo_rot, dtype)
    imu_acc = jnp.asarray(inputs.imu_acc, dtype)
    imu_gyro = jnp.asarray(inputs.imu_gyro, dtype)
    eye = jnp.eye(3, dtype=dtype)

    # --- predict (Eqs. 8, 9, 12) with white-jerk / white-angular-acceleration Q.
    F3, Q3, F2, Q2 = _blocks(dt, dtype)
    pos = state.pos @ F3.T
    pos_cov = F3 @ state.pos_cov @ F3.T + params.q_jerk[:, None, None] * Q3
    rot = state.rot @ F2.T
    rot_cov = F2 @ state.rot_cov @ F2.T + params.q_alpha[:, None, None] * Q2
    since = state.since_s + dt

    # --- orientation rows of the exoskeleton (Eq. 11, first row): phi = log(R_exo R_ref^T).
    rot_ok = jnp.all(jnp.isfinite(exo_rot))
    phi_exo, cos_exo = so3_log(jnp.where(rot_ok, exo_rot, eye) @ state.ref.T)
    rot_ok = rot_ok & (cos_exo > np.cos(MAX_ROTATION_RAD))
    upd = jax.vmap(_scalar_update, in_axes=(0, 0, None, 0, 0, None))
    rot, rot_cov = upd(rot, rot_cov, 0, phi_exo, params.sigma_rot**2, rot_ok)

    # --- turn-rate rows of the IMU (Eq. 11, second row; Eq. 3): omega = R_ee R_mount w_imu,
    # measured as the rotation vector's rate J_l(phi)^-1 omega at the current estimate.
    mount = jnp.asarray(params.imu_mount, dtype)
    R_ee = so3_exp(rot[:, 0]) @ state.ref
    R_imu = R_ee @ mount
    gyro_ok = jnp.all(jnp.isfinite(imu_gyro))
    omega = R_imu @ jnp.where(gyro_ok, imu_gyro, 0.0)
    rate_meas = _jl_inv_apply(rot[:, 0], omega)
    rot, rot_cov = upd(rot, rot_cov, 1, rate_meas, params.sigma_gyro**2, gyro_ok)

    # --- position rows of the exoskeleton (Eq. 10, first row), one per axis.
    pos_ok = jnp.isfinite(exo_pos)
    p_meas = jnp.where(pos_ok, exo_pos, 0.0)
    r_pos = params.sigma_pos**2
    upd3 = jax.vmap(_scalar_update, in_axes=(0, 0, None, 0, 0, 0))
    pos, pos_cov = upd3(pos, pos_cov, 0, p_meas, r_pos, pos_ok)
    # Velocity pseudo-measurement (Eq. 10, second row): the difference quotient of this and
    # the previous valid reading, noise variance 2 sigma_pos^2 / dT^2 (paper Sec. III.B).
    vel_ok = pos_ok & state.has_last & (since > 0)
    dT = jnp.where(vel_ok, since, 1.0)
    v_meas = jnp.where(vel_ok, (p_meas - state.last_pos) / dT, 0.0)
    pos, pos_cov = upd3(pos, pos_cov, 1, v_meas, 2 * r_pos / dT**2, vel_ok)
    # IMU acceleration (Eq. 10, third row; Eq. 2), rotated with the updated orientation.
    R_imu = so3_exp(rot[:, 0]) @ state.ref @ mount
    acc_ok = jnp.all(jnp.isfinite(imu_acc))
    gravity = jnp.asarray([0.0, 0.0, params.gravity_mps2], dtype)
    a_meas = R_imu @ jnp.where(acc_ok, imu_acc, 0.0) - gravity
    pos, pos_cov = upd3(pos, pos_cov, 2, a_meas, params.sigma_acc**2,
                        jnp.broadcast_to(acc_ok, (3,)))

    pos_cov, rot_cov = symmetrise(pos_cov), symmetrise(rot_cov)
    new = ArmImuState(
        pos=pos, pos_cov=pos_cov, rot=rot, rot_cov=rot_cov, ref=state.ref,
        last_pos=jnp.where(pos_ok, p_meas, state.last_pos),
        since_s=jnp.where(pos_ok, jnp.zeros_like(since), since),
        has_last=state.has_last | pos_ok)
    est = ArmImuEstimate(
        pos=pos[:, 0], vel=pos[:, 1], acc=pos[:, 2], rot=so3_exp(rot[:, 0]) @ state.ref,
        rotvec=rot[:, 0], rate=rot[:, 1],
        pos_std=jnp.sqrt(jnp.maximum(pos_cov[:, 0, 0], 0.0)),
        rot_std=jnp.sqrt(jnp.maximum(rot_cov[:, 0, 0], 0.0)))
    return new, est


def scan_arm_imu(
    params: ArmImuParams, series: ArmImuSeries, state: ArmImuState | None = None
) -> tuple[ArmImuState, ArmImuEstimate]:
    """``lax.scan`` of ``arm_imu_step`` over one trial (not jitted: the building block)."""
    if state is None:
        state = arm_imu_init(params, first_valid_rotation(series.exo_rot))
    series = jax.tree_util.tree_map(jnp.asarray, series)

    def body(carry, row):
        return arm_imu_step(params, carry, row)

    return jax.lax.scan(body, state, series)


@eqx.filter_jit
def run_arm_imu(
    params: ArmImuParams, series: ArmImuSeries, state: ArmImuState | None = None
) -> tuple[ArmImuState, ArmImuEstimate]:
    """Filter one trial: ``lax.scan`` of ``arm_imu_step`` over the rows of ``series``.

    Args:
        params: the filter parameters (their dtype sets the computation's precision).
        series: one trial, ``dt`` of shape (T,) (``arm_imu_series`` builds it from the two
            sensors' own timelines). For many trials, ``jax.vmap`` over padded trials
            (``arm_imu_batch``).
        state: the starting state (default: ``arm_imu_init`` with the first valid
            exoskeleton orientation as reference).

    Returns:
        The final state and an ``ArmImuEstimate`` with a leading time axis.
    """
    return scan_arm_imu(params, series, state)


def arm_imu_batch(params: ArmImuParams, series: ArmImuSeries) -> ArmImuEstimate:
    """``run_arm_imu`` over a batch of trials (leading axis ``B``), padded to one length."""
    return jax.vmap(lambda s: run_arm_imu(params, s)[1])(series)


# ------------------------------------------------------------------ building inputs
def arm_imu_series(
    t_exo: Float[ArrayLike, " Te"],
    exo_pos: Float[ArrayLike, "Te 3"],
    exo_rot: Float[ArrayLike, "Te 3 3"],
    t_imu: Float[ArrayLike, " Ti"],
    imu_acc: Float[ArrayLike, "Ti 3"],
    imu_gyro: Float[ArrayLike, "Ti 3"],
    tol_s: float = 1e-9,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, ArmImuSeries]:
    """Merge the exoskeleton's and the IMU's own timelines into one filter input (host, NumPy).

    Rows are the sorted union of both sets of timestamps (s, one clock); samples closer than
    ``tol_s`` share a row. A row holds NaN for the sensor that has no new sample there.

    Returns:
        ``(t, exo_row, imu_row, series)``: the merged timestamps (float64), for every
        exoskeleton and IMU sample the row it landed in, and the ``ArmImuSeries`` (float64,
        ``dt`` differenced in float64).
    """
    t_exo = np.asarray(t_exo, np.float64)
    t_imu = np.asarray(t_imu, np.float64)
    if t_exo.ndim != 1 or t_imu.ndim != 1:
        raise ValueError("arm_imu_series: timestamps must be 1-D")
    for name, t in (("t_exo", t_exo), ("t_imu", t_imu)):
        if np.any(np.diff(t) <= 0) or not np.all(np.isfinite(t)):
            raise ValueError(f"arm_imu_series: {name} must be finite and strictly increasing")
    shapes = {"exo_pos": (exo_pos, (len(t_exo), 3)), "exo_rot": (exo_rot, (len(t_exo), 3, 3)),
              "imu_acc": (imu_acc, (len(t_imu), 3)), "imu_gyro": (imu_gyro, (len(t_imu), 3))}
    for name, (x, shape) in shapes.items():
        if np.shape(x) != shape:
            raise ValueError(f"arm_imu_series: {name} must have shape {shape}, "
                             f"got {np.shape(x)}")
    allt = np.sort(np.concatenate([t_exo, t_imu]))
    keep = np.r_[True, np.diff(allt) > tol_s]
    t = allt[keep]
    exo_row = np.searchsorted(t, t_exo - tol_s)
    imu_row = np.searchsorted(t, t_imu - tol_s)
    T = len(t)

    def place(rows, x, shape):
        out = np.full((T,) + shape, np.nan)
        out[rows] = np.asarray(x, np.float64)
        return out

    series = ArmImuSeries(
        dt=np.r_[0.0, np.diff(t)],
        exo_pos=place(exo_row, exo_pos, (3,)),
        exo_rot=place(exo_row, exo_rot, (3, 3)),
        imu_acc=place(imu_row, imu_acc, (3,)),
        imu_gyro=place(imu_row, imu_gyro, (3,)),
    )
    return t, exo_row, imu_row, series


def pad_arm_imu(series: list[ArmImuSeries], length: int | None = None) -> ArmImuSeries:
    """Stack trials of uneven length into one batch; padding rows are no-op steps
    (``kckf_jax._models._kernel.pad_trials``)."""
    return pad_trials(series, length, "pad_arm_imu")
