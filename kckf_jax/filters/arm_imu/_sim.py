"""A simulator of the arm exoskeleton + IMU + optical tracking setup.

No recording of the exoskeleton of Chen, Yang and Hofschulte is public, so the filter of
``_filter.py`` is demonstrated on synthetic trials (NumPy float64, seeded by a
``numpy.random.Generator``). Every number is a field of ``ArmSimConfig``; those from a
datasheet or the paper say so, the others are stated assumptions (docs/other_filters.md).

* **Arm**: a 7-joint serial chain of human-arm size (upper arm 0.30 m, forearm 0.27 m, wrist to
  the tool point at the handle 0.09 m): shoulder flexion, abduction and rotation, elbow
  flexion, forearm pronation, wrist flexion and deviation. The exoskeleton's frame has its
  origin at the shoulder, ``x`` forward, ``y`` left, ``z`` up.
* **Manufacturing errors** (drawn once per exoskeleton): encoder zero offsets, tilts of the
  joint axes and errors of the link vectors. The exoskeleton computes its pose with the
  nominal geometry; the true pose follows the true geometry.
* **Joint deflection** (unmeasured): play in the bearings and the adjustable link clamps,
  taken up in the direction of motion, and elastic deflection of the light links under the
  inertial load (proportional to the joint's angular acceleration: the quasi-static response
  of a first structural mode). The encoders see the joint angle minus this deflection.
* **Encoders**: 12 bits per turn (paper Sec. II.A), read at ``exo_rate_hz``.
* **IMU**: Xsens MTi at the end effector (its accelerometer's origin is the tool point), at
  its own rate and phase; typical datasheet noise, a bias per trial, a small mounting
  misalignment the filter does not know.
* **Optical tracking** (the truth): its own rate and phase, with its own small noise.
* **Motion**: reaching. After ``rest_s`` at rest, point-to-point movements between random
  targets in a comfortable range of every joint, each a minimum-jerk profile (Flash and Hogan,
  J. Neurosci. 5:1688, 1985) of 0.7-1.5 s, with 0.3-1.0 s pauses, and a small postural sway.

All clocks are one clock (the host's); every sensor's timestamps are its sampling instants.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._filter import GRAVITY_MPS2

DEG = np.pi / 180.0

#: Joint names, axes in the zero pose (arm hanging along -z, palm facing the body) and the
#: range each joint covers while reaching in front of the body, deg (assumption, well inside
#: the normal ranges of motion).
JOINTS = (
    ("shoulder flexion", (0.0, -1.0, 0.0), (15.0, 75.0)),
    ("shoulder abduction", (1.0, 0.0, 0.0), (-35.0, -5.0)),
    ("shoulder rotation", (0.0, 0.0, 1.0), (-25.0, 25.0)),
    ("elbow flexion", (0.0, -1.0, 0.0), (30.0, 100.0)),
    ("forearm pronation", (0.0, 0.0, 1.0), (-40.0, 40.0)),
    ("wrist flexion", (0.0, 1.0, 0.0), (-25.0, 25.0)),
    ("wrist deviation", (1.0, 0.0, 0.0), (-15.0, 15.0)),
)


@dataclass(frozen=True)
class ArmSimConfig:
    """Physical constants of the simulated setup (sources in the comments)."""

    duration_s: float = 20.0
    rest_s: float = 1.0  # at rest before the first movement
    # Link lengths (assumption: an adult arm; Winter, "Biomechanics and Motor Control of Human
    # Movement", gives upper arm 0.186 H and forearm 0.146 H for a body height H = 1.6-1.8 m).
    upper_arm_m: float = 0.30
    forearm_m: float = 0.27
    hand_m: float = 0.09  # wrist centre to the tool point at the handle
    # Exoskeleton: 12-bit optical encoders (paper Sec. II.A), read at 100 Hz (assumption).
    exo_rate_hz: float = 100.0
    encoder_bits: int = 12
    # Manufacturing, 1 sigma (assumptions for a machined, hand-assembled exoskeleton). The
    # encoder zeros are set on an assembly jig to within one count (0.088 deg): uniform, so
    # 0.088 / sqrt(12) = 0.025 deg.
    joint_offset_deg: float = 360.0 / 4096 / np.sqrt(12.0)
    axis_tilt_deg: float = 0.05  # joint axis direction, per perpendicular component
    link_error_mm: float = 0.2  # link vectors, per component (adjustable links set by hand)
    # Joint deflection (assumptions for a light, 2 kg passive exoskeleton).
    play_deg: float = 0.2  # total play per joint, taken up in the direction of motion
    play_speed_dps: float = 5.0  # joint speed over which the play is taken up (tanh scale)
    compliance_s2: float = 2e-4  # rad per rad/s^2: a first structural mode near 11 Hz
    # IMU: Xsens MTi, typical values of "MTi and MTx User Manual and Technical Documentation"
    # (Xsens, MT0100P): noise densities and bandwidths below, accelerometer bias stability
    # 0.02 m/s^2, alignment error 0.1 deg; inertial data up to 512 Hz (paper Sec. II.B).
    imu_rate_hz: float = 400.0
    acc_noise_density: float = 0.002  # m/s^2/sqrt(Hz)
    acc_bandwidth_hz: float = 30.0
    acc_bias_mps2: float = 0.02  # drawn per trial and axis, 1 sigma
    gyro_noise_density_dps: float = 0.05  # deg/s/sqrt(Hz)
    gyro_bandwidth_hz: float = 40.0
    # Gyro turn-on bias: repeatability +-0.5 deg/s (Xsens knowledge base, "Bias repeatability
    # of gyroscopes"), drawn per trial and axis with this 1 sigma. The experiment removes it
    # with a no-rotation estimate over the rest period, as Xsens recommends.
    gyro_bias_dps: float = 0.5
    imu_align_deg: float = 0.1  # mounting/axis misalignment per component, unknown to the filter
    imu_mount_deg: tuple[float, float, float] = (0.0, 0.0, 90.0)  # nominal mount, rotation vector
    # Optical tracking (assumption: a six-camera system, a marker body on the handle).
    ots_rate_hz: float = 120.0
    ots_pos_mm: float = 0.1  # per axis, 1 sigma
    ots_rot_deg: float = 0.05  # per axis, 1 sigma
    gravity_mps2: float = GRAVITY_MPS2


@dataclass(frozen=True)
class ArmTrial:
    """One simulated trial (float64, SI units, exoskeleton frame; every sensor on its own
    timeline).

    ``geom_pos``/``geom_rot`` are what the exoskeleton would read at the tracking instants with
    exact encoders and no deflection: its manufacturing error alone.
    """

    t_exo: np.ndarray  # (Te,) s
    exo_pos: np.ndarray  # (Te, 3) m, forward kinematics with the nominal geometry
    exo_rot: np.ndarray  # (Te, 3, 3)
    t_imu: np.ndarray  # (Ti,) s
    imu_acc: np.ndarray  # (Ti, 3) m/s^2, IMU frame, gravity included
    imu_gyro: np.ndarray  # (Ti, 3) rad/s, IMU frame
    t_ots: np.ndarray  # (To,) s
    ots_pos: np.ndarray  # (To, 3) m, tracking readings (the truth the experiment scores against)
    ots_rot: np.ndarray  # (To, 3, 3)
    true_pos: np.ndarray  # (To, 3) m, noise-free pose at the tracking instants
    true_rot: np.ndarray  # (To, 3, 3)
    geom_pos: np.ndarray  # (To, 3)
    geom_rot: np.ndarray  # (To, 3, 3)
    imu_mount: np.ndarray  # (3, 3) nominal IMU mount (what the filter is told)


# ------------------------------------------------------------------ rotations (NumPy)
def _hat(w: np.ndarray) -> np.ndarray:
    w = np.asarray(w, np.float64)
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, vectorised over leading axes (float64)."""
    w = np.asarray(w, np.float64)
    t = np.linalg.norm(w, axis=-1)[..., None, None]
    K = _hat(w)
    ts = np.where(t > 1e-8, t, 1.0)
    A = np.where(t > 1e-8, np.sin(ts) / ts, 1.0)
    B = np.where(t > 1e-8, (1 - np.cos(ts)) / ts**2, 0.5)
    return np.eye(3) + A * K + B * (K @ K)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vectors of rotation matrices (angles below about 170 deg), vectorised."""
    R = np.asarray(R, np.float64)
    w = 0.5 * np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                        R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    s = np.linalg.norm(w, axis=-1)
    t = np.arctan2(s, 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1))
    k = np.where(s > 1e-12, t / np.where(s > 1e-12, s, 1.0), 1.0)
    return k[..., None] * w


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angles of rotation matrices, rad (robust near 0)."""
    w = 0.5 * np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                        R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    return np.arctan2(np.linalg.norm(w, axis=-1), 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1))


# ------------------------------------------------------------------ the arm
@dataclass(frozen=True)
class ArmGeometry:
    """A 7-joint chain: ``R = prod_j fixed_j Rot(axes_j, q_j)``, ``p = sum_j R_j links_j``."""

    axes: np.ndarray  # (7, 3) unit joint axes
    fixed: np.ndarray  # (7, 3, 3) fixed rotation before each joint (axis tilt)
    links: np.ndarray  # (7, 3) link vector after each joint, in that joint's frame, m


def nominal_geometry(cfg: ArmSimConfig = ArmSimConfig()) -> ArmGeometry:
    """The exoskeleton's design geometry (what its forward kinematics use)."""
    links = np.zeros((7, 3))
    links[2, 2] = -cfg.upper_arm_m  # shoulder to elbow, after shoulder rotation
    links[4, 2] = -cfg.forearm_m  # elbow to wrist, after pronation
    links[6, 2] = -cfg.hand_m  # wrist to the tool point
    axes = np.array([j[1] for j in JOINTS], np.float64)
    return ArmGeometry(axes=axes, fixed=np.tile(np.eye(3), (7, 1, 1)), links=links)


def forward_kinematics(geom: ArmGeometry, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tool-point position (m) and orientation at joint angles ``q`` (..., 7) rad."""
    q = np.asarray(q, np.float64)
    R = np.broadcast_to(np.eye(3), q.shape[:-1] + (3, 3))
    p = np.zeros(q.shape[:-1] + (3,))
    for j in range(7):
        R = R @ geom.fixed[j] @ rotvec_to_matrix(q[..., j, None] * geom.axes[j])
        p = p + R @ geom.links[j]
    return p, R


def draw_exoskeleton(rng: np.random.Generator, cfg: ArmSimConfig = ArmSimConfig()) -> dict:
    """One exoskeleton unit: ``{"nominal", "true"}`` geometries and encoder ``"offset"`` (rad)."""
    nominal = nominal_geometry(cfg)
    tilt = rotvec_to_matrix(cfg.axis_tilt_deg * DEG * rng.standard_normal((7, 3)))
    links = nominal.links + 1e-3 * cfg.link_error_mm * rng.standard_normal((7, 3))
    # Joints without a link after them sit at one point: no link error there.
    links = np.where(np.any(nominal.links != 0, axis=1, keepdims=True), links, 0.0)
    true = ArmGeometry(axes=nominal.axes, fixed=tilt, links=links)
    half = np.sqrt(3.0) * cfg.joint_offset_deg * DEG  # uniform with this 1 sigma
    return {"nominal": nominal, "true": true, "offset": rng.uniform(-half, half, 7)}


# ------------------------------------------------------------------ the motion
class _Sway:
    """Small smooth zero-mean signal per joint (sum of sinusoids): value and two derivatives."""

    def __init__(self, rng: np.random.Generator, rms_rad: float, f_lo: float, f_hi: float,
                 n: int = 5):
        self.f = rng.uniform(f_lo, f_hi, (7, n))
        self.p = rng.uniform(0, 2 * np.pi, (7, n))
        a = rng.uniform(0.5, 1.0, (7, n))
        self.a = rms_rad * a / np.sqrt(0.5 * np.sum(a**2, axis=1, keepdims=True))

    def __call__(self, t: np.ndarray):
        w = 2 * np.pi * self.f
        arg = w[None] * t[:, None, None] + self.p[None]
        a = self.a[None]
        return (np.sum(a * np.sin(arg), -1), np.sum(a * w * np.cos(arg), -1),
                -np.sum(a * w**2 * np.sin(arg), -1))


class _Reaching:
    """Minimum-jerk point-to-point movements between random joint-space targets, with pauses,
    and a postural sway (0.15 deg RMS per joint, 0.2-1.5 Hz) faded in over the first second of
    movement (the rest period is still)."""

    def __init__(self, rng: np.random.Generator, cfg: ArmSimConfig):
        lo = np.array([j[2][0] for j in JOINTS]) * DEG
        hi = np.array([j[2][1] for j in JOINTS]) * DEG
        mid, half = (lo + hi) / 2, (hi - lo) / 2
        starts, ends, t0s, durs = [], [], [], []
        q, t = mid, cfg.rest_s
        while t < cfg.duration_s or not starts:  # at least one movement
            target = mid + half * rng.uniform(-1, 1, 7)
            dur = rng.uniform(0.7, 1.5)
            starts.append(q)
            ends.append(target)
            t0s.append(t)
            durs.append(dur)
            q = target
            t += dur + rng.uniform(0.3, 1.0)
        self.q0 = mid
        self.starts, self.ends = np.array(starts), np.array(ends)
        self.t0, self.dur = np.array(t0s), np.array(durs)
        self.sway = _Sway(rng, 0.15 * DEG, 0.2, 1.5)

    def __call__(self, t: np.ndarray):
        """Joint angles, rates and accelerations (rad, rad/s, rad/s^2) at times ``t`` (s)."""
        t = np.asarray(t, np.float64)
        k = np.searchsorted(self.t0, t, side="right") - 1  # the last movement started
        before = k < 0
        kk = np.maximum(k, 0)
        dur = self.dur[kk]
        s = np.clip((t - self.t0[kk]) / dur, 0.0, 1.0)
        moving = ((s > 0) & (s < 1) & ~before)[:, None]
        shape = 10 * s**3 - 15 * s**4 + 6 * s**5
        dshape = (30 * s**2 - 60 * s**3 + 30 * s**4) / dur
        ddshape = (60 * s - 180 * s**2 + 120 * s**3) / dur**2
        delta = self.ends[kk] - self.starts[kk]
        q = np.where(before[:, None], self.q0, self.starts[kk] + shape[:, None] * delta)
        qd = np.where(moving, dshape[:, None] * delta, 0.0)
        qdd = np.where(moving, ddshape[:, None] * delta, 0.0)
        ramp = np.clip(t - self.t0[0], 0.0, 1.0)[:, None]
        sv, sd, sa = self.sway(t)
        return q + ramp * sv, qd + ramp * sd, qdd + ramp * sa


# ------------------------------------------------------------------ a trial
def simulate_arm_trial(
    rng: np.random.Generator, cfg: ArmSimConfig = ArmSimConfig(), exo: dict | None = None
) -> ArmTrial:
    """Simulate one trial: a reaching motion seen by exoskeleton, IMU and optical tracking.

    Args:
        rng: the random generator (all randomness of the trial comes from it).
        cfg: the physical constants.
        exo: the exoskeleton unit, ``draw_exoskeleton(rng, cfg)`` (drawn here if omitted);
            pass the same one to several trials to simulate one exoskeleton.

    Returns:
        An ``ArmTrial``.

    Example:
        >>> trial = simulate_arm_trial(np.random.default_rng(0), ArmSimConfig(duration_s=2.0))
        >>> trial.exo_pos.shape, trial.imu_acc.shape
        ((200, 3), (800, 3))
    """
    if exo is None:
        exo = draw_exoskeleton(rng, cfg)
    nominal, true = exo["nominal"], exo["true"]
    motion = _Reaching(rng, cfg)
    lsb = 2 * np.pi / 2**cfg.encoder_bits

    def start(rate_hz):  # each sensor's own sampling phase
        return rng.uniform(0, 1.0 / rate_hz)

    # Exoskeleton: joint angle minus the deflection plus the zero offset, quantised.
    t_exo = np.arange(start(cfg.exo_rate_hz), cfg.duration_s, 1.0 / cfg.exo_rate_hz)
    q, qd, qdd = motion(t_exo)
    play = 0.5 * cfg.play_deg * DEG * np.tanh(qd / (cfg.play_speed_dps * DEG))
    deflection = play + cfg.compliance_s2 * qdd
    enc = np.round((q - deflection + exo["offset"]) / lsb) * lsb
    exo_pos, exo_rot = forward_kinematics(nominal, enc)

    # Optical tracking at its own instants.
    t_ots = np.arange(start(cfg.ots_rate_hz), cfg.duration_s, 1.0 / cfg.ots_rate_hz)
    q_ots = motion(t_ots)[0]
    true_pos, true_rot = forward_kinematics(true, q_ots)
    geom_pos, geom_rot = forward_kinematics(nominal, q_ots + exo["offset"])
    n = len(t_ots)
    ots_pos = true_pos + 1e-3 * cfg.ots_pos_mm * rng.standard_normal((n, 3))
    ots_rot = rotvec_to_matrix(cfg.ots_rot_deg * DEG * rng.standard_normal((n, 3))) @ true_rot

    # IMU: true kinematics by central differences (h = 0.1 ms: the rounding error of the
    # second difference is about 1e-8 m/s^2 in float64, its truncation error smaller still).
    t_imu = np.arange(start(cfg.imu_rate_hz), cfg.duration_s, 1.0 / cfg.imu_rate_hz)
    h = 1e-4
    p_m, R_m = forward_kinematics(true, motion(t_imu - h)[0])
    p_0, R_0 = forward_kinematics(true, motion(t_imu)[0])
    p_p, R_p = forward_kinematics(true, motion(t_imu + h)[0])
    acc_world = (p_p - 2 * p_0 + p_m) / h**2
    omega_world = matrix_to_rotvec(R_p @ np.swapaxes(R_m, -1, -2)) / (2 * h)
    mount_nominal = rotvec_to_matrix(np.asarray(cfg.imu_mount_deg) * DEG)
    mount = mount_nominal @ rotvec_to_matrix(cfg.imu_align_deg * DEG * rng.standard_normal(3))
    to_imu = np.swapaxes(R_0 @ mount, -1, -2)  # exoskeleton frame -> IMU frame
    g = np.array([0.0, 0.0, cfg.gravity_mps2])
    m = len(t_imu)
    # White noise over the sensor bandwidth: sigma = density * sqrt(bandwidth).
    acc_sigma = cfg.acc_noise_density * np.sqrt(cfg.acc_bandwidth_hz)
    gyro_sigma = cfg.gyro_noise_density_dps * DEG * np.sqrt(cfg.gyro_bandwidth_hz)
    acc_bias = cfg.acc_bias_mps2 * rng.standard_normal(3)
    gyro_bias = cfg.gyro_bias_dps * DEG * rng.standard_normal(3)
    imu_acc = np.einsum("tij,tj->ti", to_imu, acc_world + g) + acc_bias + (
        acc_sigma * rng.standard_normal((m, 3)))
    imu_gyro = np.einsum("tij,tj->ti", to_imu, omega_world) + gyro_bias + (
        gyro_sigma * rng.standard_normal((m, 3)))
    return ArmTrial(t_exo=t_exo, exo_pos=exo_pos, exo_rot=exo_rot, t_imu=t_imu,
                    imu_acc=imu_acc, imu_gyro=imu_gyro, t_ots=t_ots, ots_pos=ots_pos,
                    ots_rot=ots_rot, true_pos=true_pos, true_rot=true_rot, geom_pos=geom_pos,
                    geom_rot=geom_rot, imu_mount=mount_nominal)


def remove_gyro_bias(t_imu: np.ndarray, imu_gyro: np.ndarray, rest_s: float) -> np.ndarray:
    """Subtract the mean turn rate over ``t < rest_s`` (a no-rotation bias estimate, the
    procedure Xsens recommends for the MTi's gyro bias; the arm must be still then)."""
    rest = np.asarray(t_imu) < rest_s
    if not np.any(rest):
        raise ValueError(f"remove_gyro_bias: no IMU sample before rest_s = {rest_s} s")
    return imu_gyro - np.mean(imu_gyro[rest], axis=0)


# ------------------------------------------------------------------ the experiment
