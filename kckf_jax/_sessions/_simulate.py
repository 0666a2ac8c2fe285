"""A simulator of the wearable origami exoshell and its sensors (NumPy float64, seeded).

No public recording of the exoshell exists, so the project tests and demonstrates the filters on
synthetic sessions. Every number below is either from a datasheet, from the KCKF paper, or an
assumption stated as such; ``docs/simulator.md`` lists them with their sources.

Kinematics (``kinematics``): ``"linear"`` (default) follows the paper's model (Sec. 2.3 and
Eq. 14): the gyroscope frames are aligned in the neutral pose and rotations add per axis, so
link ``L`` turns at the base rate plus the rates of the joints below it, and the torso angle is
the sum of the joint angles. ``"exact"`` simulates the chain of finite rotations
(``_rotations``): each link's gyro measures its body rate through the chain, a joint with
several axes turns about them in the order written, and the torso truth is the intrinsic
x-y-z Euler angles of link ``n + 1`` relative to link 1 (the session format's definition).
Every random draw is the same for both, so a session and its linear twin differ only there.

Motions (``kind``):

* ``"cyclic"``: the paper's bench test, a gait-like cyclic motion induced by hand (Sec. 4.1);
* ``"static"``: the extended-use test (Sec. 4.2, Fig. 7): movement for ``move_s`` seconds, then
  the robot held still for the rest of the run (an hour in the paper);
* ``"human"``: a person bending and extending the upper torso over a 30 deg range (Sec. 4.3),
  with the sensor shifts at compression and over-extension the paper reports;
* ``"walking"``: a wearer walking: the pelvis (the base) rotating 5-8 deg about the vertical
  with obliquity (3-5 deg) and tilt (2-4 deg) at the stride frequency (0.8-1.0 Hz), the trunk
  circling (the torso angles reaching 34-50 deg about the circling axes, one circle in 4-6 s)
  and twisting against the pelvis (assumptions of this project: gait pelvis ranges of that
  size are textbook values; the circling is a motion chosen to exercise 3D joints).

Larger motion (``SimConfig.motion_range_deg``, ``kckf simulate --range-deg``): each kind's main
motion scaled by one gain so that the session's largest |angle| (joints and the torso's linear
sums) is the range, the frequencies kept; off (``None``) by default, and then nothing changes.

Sensor effects beyond the paper's sensor models, each off by default (``SimConfig``): the
joints' mechanical play as the Hall sensors see it, Hall curves beyond Eq. 1's shape, and a
motion-capture clock error that ``meta.json`` does not know; their true values, and the gyros'
scale errors, are kept in ``meta.json``'s ``simulation.effects``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from .._models._hall import DEG, PAPER_HALL_DEG, hall_voltage
from .._models._limits import JOINT_RANGE_RAD, SensorLimits
from .._models._params import hall_arrays
from .._models._robot import AXES, Robot
from .._models._rotations import chain_rotation, euler_xyz, link_rates
from ._session import Session
from ._sim_faults import Fault, inject_faults
from ._sim_motion import (  # noqa: E402
    _base_motion,
    _joint_motion,
    _pelvis,
    _range_gain,
    _Smooth,
    _smoothstep,
)
from ._sim_mount import mount_rotations, rotation_matrices, soft_mount_rates

KINDS = ("cyclic", "static", "human", "walking")
KINEMATICS = ("linear", "exact")
DPS = DEG  # one degree per second, in rad/s
#: ``kckf simulate --effect NAME=SIZE``: each name's ``SimConfig`` field (play and curve in deg,
#: sync in s).
EFFECTS = {"play": "hall_play_deg", "curve": "hall_curve_deg", "sync": "mocap_sync_error_s",
           "delay": "gyro_delay_s", "mount": "gyro_mount_deg", "soft": "soft_mount_hz"}
_CURVE_RANGE_DEG = 30.0  # u = theta / 30 deg: the span of the paper's Eq. 1 fit, Fig. 3
# Salts the device seed for the effects' own generator (another stream than ``dev``'s 7919).
_EFFECTS_SALT = 6151
_MOUNT_SALT = 4423  # the gyro boards' tilts and soft mounts (a stream of their own)
#: The largest ``motion_range_deg``: beyond +-180 deg an angle wraps round.
MAX_RANGE_DEG = 180.0
#: Above this range (1.5 times the span of Eq. 1's fit) the curve effect's cubic in
#: ``u = theta / 30 deg`` describes no sensor (it reaches 17.6 times its RMS at 45 deg).
_CURVE_MAX_RANGE_DEG = 45.0


@dataclass(frozen=True)
class SimConfig:
    """Physical constants of the simulated hardware (sources in docs/simulator.md)."""

    sample_rate_hz: float = 100.0  # sensor packet rate
    timestamp_jitter_s: float = 0.5e-3  # sampling-instant jitter of the microcontroller loop
    # LSM6DSO gyroscope (ST DS12140, Table 2), +-250 dps full scale, high-performance mode.
    gyro_noise_density_dps_rthz: float = 3.8e-3  # rate noise density, 3.8 mdps/sqrt(Hz)
    gyro_zero_rate_dps: float = 1.0  # zero-rate level, +-1 dps typical (drawn uniformly)
    gyro_temp_coeff_dps_per_c: float = 0.01  # zero-rate change vs temperature, +-0.01 dps/degC
    warmup_delta_c: float = 8.0  # assumption: board warms by ~8 degC against the body
    warmup_tau_s: float = 600.0  # assumption: thermal time constant of the worn board
    gyro_bias_walk_dps_rts: float = 2e-4  # assumption: bias random walk (in-run instability)
    gyro_scale_error: float = 0.01  # 1 % per axis: rate-grade MEMS scale factor 0.1-1 %
    gyro_lsb_dps: float = 8.75e-3  # 8.75 mdps/LSB at +-250 dps
    # DRV5053 Hall sensor read by a 12-bit ADC, 3.3 V reference.
    hall_v_noise: float = 0.03  # V RMS: electrical + EMI + ADC (assumption, see docs)
    hall_v_wander: float = 0.003  # V: slow field disturbance (orientation in Earth's field)
    hall_cal_error_ac: float = 0.10  # relative (log-normal) error of a, c per sensor (mounting)
    hall_cal_error_bd: float = 0.02  # relative error of b, d per sensor
    adc_bits: int = 12
    adc_vref: float = 3.3
    # Vicon-class motion capture.
    mocap_rate_hz: float = 120.0
    mocap_noise_deg: float = 0.15  # joint/torso angle noise from marker jitter
    mocap_margin_s: float = 0.5  # mocap starts later and stops earlier than the sensors
    mocap_offset_range_s: float = 2.0  # |mocap_time_offset_s| drawn below this
    drop_prob: float = 0.0  # probability that any one reading is missing (NaN)
    # Sensor effects, each off (0) by default (docs/simulator.md, "Sensor effects"); their true
    # per-device values are drawn from a generator of their own, so that no other draw moves.
    hall_play_deg: float = 0.0  # backlash half-width the Hall sensors see, deg (x U(0.75, 1.25))
    hall_curve_deg: float = 0.0  # RMS over +-30 deg of each Hall curve's P2/P3 deviation, deg
    mocap_sync_error_s: float = 0.0  # error of the recorded mocap_time_offset_s, s (signed)
    gyro_delay_s: float = 0.0  # the gyros' delay against the Hall sensors (their filters), s
    # Gyros as worn (_sim_mount): each board's tilt on its link, deg (x U(0.5, 1), random
    # axis), and its soft mount's natural frequency, Hz (x U(0.8, 1.2); 0: rigid).
    gyro_mount_deg: float = 0.0
    soft_mount_hz: float = 0.0
    soft_mount_damping: float = 0.3  # the soft mount's damping ratio (assumption, underdamped)
    # The motion's largest |angle| (joint and torso angles), deg; None: each kind's own
    # amplitudes (the paper's small angles). ``kckf simulate --range-deg`` (docs/simulator.md).
    motion_range_deg: float | None = None


def parse_effects(specs: Sequence[str]) -> dict[str, float]:
    """``kckf simulate --effect NAME=SIZE`` texts as ``SimConfig`` fields and values.

    Names: ``play`` (deg, ``hall_play_deg``), ``curve`` (deg, ``hall_curve_deg``), ``sync`` (s,
    ``mocap_sync_error_s``, signed), ``delay`` (s, ``gyro_delay_s``), ``mount`` (deg,
    ``gyro_mount_deg``), ``soft`` (Hz, ``soft_mount_hz``). A bad text raises ``ValueError``
    naming it.

    Example:
        >>> parse_effects(["play=1", "sync=-0.02"])
        {'hall_play_deg': 1.0, 'mocap_sync_error_s': -0.02}
    """
    out: dict[str, float] = {}
    for text in specs:
        name, eq, size = (x.strip() for x in text.partition("="))
        if name not in EFFECTS:
            raise ValueError(f"--effect {text!r}: unknown name {name!r}; expected one of "
                             f"{', '.join(EFFECTS)}")
        if not eq or not size:
            raise ValueError(f"--effect {text!r}: expected NAME=SIZE, e.g. {name}=1")
        try:
            value = float(size)
        except ValueError:
            raise ValueError(f"--effect {text!r}: size {size!r} is not a number") from None
        if not np.isfinite(value) or (name != "sync" and value < 0):
            raise ValueError(f"--effect {text!r}: the size must be a finite number"
                             + ("" if name == "sync" else " >= 0"))
        if EFFECTS[name] in out:
            raise ValueError(f"--effect {text!r}: {name} is given twice")
        out[EFFECTS[name]] = value
    return out


def _check_effects(cfg: SimConfig) -> None:
    for field in EFFECTS.values():
        value = getattr(cfg, field)
        signed = field == "mocap_sync_error_s"
        if not (np.isfinite(value) and (signed or value >= 0)):
            raise ValueError(f"simulate: config.{field} must be a finite number"
                             f"{'' if signed else ' >= 0'}, got {value}")
    if cfg.soft_mount_hz > 0 and not 0 < cfg.soft_mount_damping < 1:
        raise ValueError(f"simulate: config.soft_mount_damping must be in (0, 1) (an "
                         f"underdamped mount), got {cfg.soft_mount_damping}")
    if cfg.soft_mount_hz > 0 and cfg.soft_mount_hz * 1.2 >= cfg.sample_rate_hz / 2:
        raise ValueError(f"simulate: config.soft_mount_hz ({cfg.soft_mount_hz:g} Hz, up to 1.2 "
                         f"times that per link) must stay below half the sample rate "
                         f"({cfg.sample_rate_hz / 2:g} Hz): a faster wobble is not sampled")


def _check_rate_and_range(cfg: SimConfig) -> None:
    if not (np.isfinite(cfg.sample_rate_hz) and cfg.sample_rate_hz > 0):
        raise ValueError(f"simulate: config.sample_rate_hz must be a positive number (Hz), got "
                         f"{cfg.sample_rate_hz}")
    r = cfg.motion_range_deg
    if r is None:
        return
    if not (np.isfinite(r) and 0 < r <= MAX_RANGE_DEG):
        raise ValueError(f"simulate: config.motion_range_deg must be above 0 and at most "
                         f"{MAX_RANGE_DEG:g} deg (or None), got {r}")
    if cfg.hall_curve_deg > 0 and r > _CURVE_MAX_RANGE_DEG:
        raise ValueError(f"simulate: the curve effect (hall_curve_deg) is a cubic in "
                         f"theta / 30 deg, fitted to the paper's +-30 deg; it is refused with "
                         f"motion_range_deg above {_CURVE_MAX_RANGE_DEG:g} deg (got {r:g})")


def _play(angle: np.ndarray, half_width: np.ndarray) -> np.ndarray:
    """The play (backlash) operator: ``p_k = clip(p_{k-1}, a_k - h, a_k + h)``, ``p_0 = a_0``,
    per column of ``angle`` (T, M) with half-widths ``half_width`` (M,), same unit."""
    out = np.empty_like(angle)
    p = out[0] = angle[0]
    lo, hi = angle - half_width, angle + half_width
    for k in range(1, angle.shape[0]):  # path-dependent: each step needs the one before
        p = out[k] = np.minimum(np.maximum(p, lo[k]), hi[k])
    return out


def _curve_deviation_deg(angle_deg: np.ndarray, p2: np.ndarray, p3: np.ndarray) -> np.ndarray:
    """``p2 * P2(u) + p3 * P3(u)`` with ``u = angle / 30 deg`` (Legendre polynomials), deg."""
    u = angle_deg / _CURVE_RANGE_DEG
    return p2 * 0.5 * (3 * u**2 - 1) + p3 * 0.5 * (5 * u**3 - 3 * u)


def simulate(
    robot: Robot | str,
    kind: str = "cyclic",
    seed: int = 0,
    duration_s: float = 120.0,
    *,
    move_s: float = 60.0,
    config: SimConfig | None = None,
    drop_prob: float | None = None,
    device_seed: int | None = None,
    true_hall_models: Mapping[str, Mapping] | None = None,
    faults: Sequence[Fault] = (),
    kinematics: str = "linear",
) -> Session:
    """Simulate one recorded session of the exoshell on ``robot``.

    Args:
        robot: the joint layout (or a spec string like ``"x,y,x,y"``).
        kind: ``"cyclic"`` (bench gait-like test), ``"static"`` (movement for ``move_s``, then
            held still), ``"human"`` (bending and extension, 30 deg range) or ``"walking"``
            (the trunk circling over a walking pelvis).
        seed: seeds everything; the same arguments give the same session.
        duration_s: length of the sensor recording, s.
        config: hardware constants (default ``SimConfig()``).
        drop_prob: overrides ``config.drop_prob`` (probability that a reading is NaN).
        device_seed: seeds what belongs to the physical robot rather than to one recording:
            each Hall sensor's true curve, each gyro axis's scale error and the sensor effects'
            per-sensor values. Sessions with the same ``device_seed`` are trials of the same
            exoshell (default: ``seed``).
        true_hall_models: the sensors' true Eq. 1 curves (``meta.json`` form, any unit) instead
            of random ones; for experiments with known ground-truth parameters.
        faults: sensor faults written into the finished session (``inject_faults``, seeded
            by ``seed``; none by default, and then nothing changes).
        kinematics: ``"linear"`` (the paper's model, default) or ``"exact"`` (finite
            rotations; the module docstring). Every random draw is the same for both.

    Returns:
        A ``Session`` with sensors, motion capture (own rate, own clock) and meta. The true
        Hall coefficients and gyro biases are kept in ``session.extra_meta["simulation"]``,
        and the sensor effects' true values (``SimConfig.hall_play_deg``, ``hall_curve_deg``,
        ``mocap_sync_error_s``; each left out while off) and every gyro column's scale error
        ``s`` (reading = (1 + s) * rate) in its ``"effects"`` (docs/simulator.md).

    Example:
        >>> s = simulate("x,y,x,y", "cyclic", seed=1, duration_s=10.0)
        >>> s.gyro.shape, s.hall_v.shape
        ((1000, 15), (1000, 8))
    """
    if isinstance(robot, str):
        robot = Robot.from_spec(robot)
    if kind not in KINDS:
        raise ValueError(f"simulate: kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if not duration_s > 0:
        raise ValueError(f"simulate: duration_s must be positive, got {duration_s}")
    if kinematics not in KINEMATICS:
        raise ValueError(f"simulate: kinematics must be one of {', '.join(KINEMATICS)}, got "
                         f"{kinematics!r}")
    cfg = config or SimConfig()
    if drop_prob is not None:
        cfg = SimConfig(**{**asdict(cfg), "drop_prob": float(drop_prob)})
    _check_effects(cfg)
    _check_rate_and_range(cfg)
    rng = np.random.default_rng(np.random.SeedSequence([seed, KINDS.index(kind), len(robot.spec)]))
    device_seed = seed if device_seed is None else device_seed
    dev = np.random.default_rng(np.random.SeedSequence([device_seed, 7919, len(robot.spec)]))
    # The sensor effects' device values: a stream of their own, drawn whether or not an effect
    # is on, so that turning one on moves no other draw (and the other effect's values stay).
    fx = np.random.default_rng(np.random.SeedSequence([device_seed, _EFFECTS_SALT,
                                                       len(robot.spec)]))
    # (J,) half-widths: the play is the joint's, and both its sensors see it.
    play_deg = cfg.hall_play_deg * fx.uniform(0.75, 1.25, robot.n_joint_axes)
    direction = fx.uniform(0.0, 2 * np.pi, robot.n_hall)  # (P2, P3) on the unit circle
    # RMS over u in [-1, 1] of cos P2(u) + sin P3(u): P2 and P3 are orthogonal, with mean
    # squares 1/5 and 1/7.
    rms = np.sqrt(np.cos(direction) ** 2 / 5 + np.sin(direction) ** 2 / 7)
    curve_p2 = cfg.hall_curve_deg * np.cos(direction) / rms  # deg, coefficient of P2(u)
    curve_p3 = cfg.hall_curve_deg * np.sin(direction) / rms  # deg, coefficient of P3(u)

    # ---- time: the microcontroller samples at its nominal rate with a little jitter.
    ts = 1.0 / cfg.sample_rate_hz
    n = int(round(duration_s * cfg.sample_rate_hz))
    if n < 2:
        raise ValueError(f"simulate: duration_s * sample_rate_hz must give at least 2 samples, "
                         f"got {duration_s:g} s at {cfg.sample_rate_hz:g} Hz")
    # A jitter of half a step or more would swap samples: above 1 kHz the default 0.5 ms is
    # held to half a step (at or below 1 kHz nothing changes).
    jitter = min(cfg.timestamp_jitter_s, 0.5 * ts)
    t = np.arange(n) * ts + rng.uniform(-jitter, jitter, n)
    t[0] = 0.0
    t = np.round(np.maximum.accumulate(t), 6)  # the microcontroller stamps in microseconds
    if np.any(np.diff(t) <= 0):  # two stamps rounded onto one microsecond: one moves on by 1
        k = np.arange(n) * 1e-6
        t = np.round(np.maximum.accumulate(t - k) + k, 6)

    # ---- joint motion (T, J): angles and rates, with a still start in the neutral pose;
    # with a range, each kind's main motion scaled so that the largest |angle| is that range.
    gain = 1.0
    if cfg.motion_range_deg is not None:
        gain = _range_gain(rng, robot, t, kind, move_s, cfg.motion_range_deg)
    theta, rate, flex, stride, ramp = _joint_motion(rng, robot, t, kind, move_s, gain)

    # ---- link rates (T, n+1, 3): base rate plus the rates of the joints below (Eq. 2).
    # The human kind's pelvic tilt (a third of the bend) grows with the bend.
    base = _base_motion(rng, t, kind, flex, tilt_deg=10.0 * gain)
    if kind == "walking":
        base = base + ramp[:, None] * _pelvis(rng, *stride)
    if kind == "static":
        base = base * (1 - _smoothstep(t, move_s, 2.0)[0])[:, None]  # the bench holds still
    if kinematics == "exact":
        cols = [[j for j, (i, _) in enumerate(robot.joint_axes) if i == k]
                for k in range(1, robot.n_joints + 1)]  # each joint's coordinates
        link_rate = np.stack(link_rates(robot.joints, [theta[:, c] for c in cols],
                                        [rate[:, c] for c in cols], base), axis=1)
    else:
        link_rate = np.repeat(base[:, None, :], robot.n_links, axis=1)
        for j, (i, a) in enumerate(robot.joint_axes):
            link_rate[:, i:, AXES.index(a)] += rate[:, j : j + 1]

    # ---- gyros as worn (_sim_mount): each board moving on a soft mount, tilted on its link.
    mnt = np.random.default_rng(np.random.SeedSequence([device_seed, _MOUNT_SALT,
                                                        len(robot.spec)]))
    tilt = mount_rotations(mnt, robot.n_links, cfg.gyro_mount_deg)  # (L, 3), rad
    soft_hz = cfg.soft_mount_hz * mnt.uniform(0.8, 1.2, robot.n_links)
    wobble = None
    if cfg.soft_mount_hz > 0:
        wobble_rate, wobble = soft_mount_rates(t, link_rate, soft_hz, cfg.soft_mount_damping)
        link_rate = link_rate + wobble_rate
    if cfg.gyro_mount_deg > 0:  # the board reads R' omega
        link_rate = np.einsum("lji,tlj->tli", rotation_matrices(tilt), link_rate)

    # ---- gyroscopes: scale error, bias (zero-rate level + warm-up drift + random walk), noise.
    shape = (robot.n_links, 3)
    zero_rate = rng.uniform(-1, 1, shape) * cfg.gyro_zero_rate_dps * DPS
    temp_coeff = rng.uniform(-1, 1, shape) * cfg.gyro_temp_coeff_dps_per_c * DPS
    warm = cfg.warmup_delta_c * (1 - np.exp(-t / cfg.warmup_tau_s))
    walk_step = cfg.gyro_bias_walk_dps_rts * DPS * np.sqrt(np.diff(t, prepend=0.0))
    walk = np.cumsum(rng.standard_normal((n,) + shape) * walk_step[:, None, None], axis=0)
    bias = zero_rate + temp_coeff * warm[:, None, None] + walk
    scale = 1 + cfg.gyro_scale_error * dev.standard_normal(shape)
    white = cfg.gyro_noise_density_dps_rthz * DPS * np.sqrt(cfg.sample_rate_hz / 2)
    if cfg.gyro_delay_s > 0:
        # The gyro's digital filter chain delays its reading: at t_k it gives the rate at
        # t_k - d (the rate interpolated; before the start, the first sample's).
        flat = link_rate.reshape(n, -1)
        link_rate = np.stack([np.interp(t - cfg.gyro_delay_s, t, flat[:, i])
                              for i in range(flat.shape[1])], axis=1).reshape(link_rate.shape)
    gyro = scale * link_rate + bias + white * rng.standard_normal(link_rate.shape)
    lsb = cfg.gyro_lsb_dps * DPS
    gyro = np.round(gyro / lsb) * lsb

    # ---- Hall sensors: each has its own true curve (mounting), voltage noise, 12-bit ADC.
    M = robot.n_hall
    nominal = np.array([PAPER_HALL_DEG[k] for k in "abcd"])
    rel = np.array([cfg.hall_cal_error_ac, cfg.hall_cal_error_bd] * 2)
    true_coef = nominal * np.exp(rel * dev.standard_normal((M, 4)))  # (M, 4), deg
    if true_hall_models is not None:
        a, b, c, d, sgn = hall_arrays(robot, true_hall_models)  # rad
        if np.any(sgn != np.asarray(robot.hall_side_sign)):
            raise ValueError("simulate: true_hall_models must keep the default signs (+1 for l, "
                             "-1 for r)")
        true_coef = np.stack([a / DEG, b, c / DEG, d], axis=1)
    sign = np.asarray(robot.hall_side_sign, dtype=float)
    meas_angle = theta[:, robot.hall_joint_axis]  # (T, M)
    if kind == "human":
        # Interaction forces shift the sensors (paper Sec. 4.3): compression when upright,
        # over-extension at full bend; each sensor reads up to ~2 deg off at those moments.
        # The shift comes from the robot's and the wearer's mechanics, so it repeats from trial
        # to trial of one device (up to +-2 deg) with a smaller part that changes with every
        # donning (+-0.5 deg).
        f = np.clip(flex if flex is not None else np.zeros(n), 0, 1)
        shift = (dev.uniform(-2, 2, (2, M)) + rng.uniform(-0.5, 0.5, (2, M))) * DEG
        meas_angle = meas_angle + np.outer((1 - f) ** 4, shift[0]) + np.outer(f**4, shift[1])
    if cfg.hall_play_deg > 0:
        # The joint's play as each sensor sees it: its magnet lags the joint through a
        # backlash of half-width h (deg), reading theta - h sign(rate) in a steady motion.
        meas_angle = _play(meas_angle, play_deg[robot.hall_joint_axis] * DEG)
    if cfg.hall_curve_deg > 0:
        # Each true curve departs from Eq. 1's shape: the sensor sees theta + delta(theta).
        meas_angle = meas_angle + DEG * _curve_deviation_deg(meas_angle / DEG, curve_p2, curve_p3)
    v = hall_voltage(meas_angle / DEG, true_coef[:, 0], true_coef[:, 1], true_coef[:, 2],
                     true_coef[:, 3], sign)
    wander = np.stack([_Smooth(rng, 0.01, 0.2)(t)[0] for _ in range(M)], axis=1)
    v = v + cfg.hall_v_wander * wander + cfg.hall_v_noise * rng.standard_normal(v.shape)
    q_v = cfg.adc_vref / 2**cfg.adc_bits
    v = np.clip(np.round(v / q_v) * q_v, 0.0, cfg.adc_vref)

    # ---- dropped readings.
    if cfg.drop_prob > 0:
        gyro_flat = gyro.reshape(n, -1)
        gyro_flat[rng.random(gyro_flat.shape) < cfg.drop_prob] = np.nan
        gyro = gyro_flat.reshape(gyro.shape)
        v[rng.random(v.shape) < cfg.drop_prob] = np.nan

    # ---- motion capture: own rate, own clock (offset), noise, a shorter span.
    offset = rng.uniform(-cfg.mocap_offset_range_s, cfg.mocap_offset_range_s)
    # meta.json's offset may be wrong by the sync error: a frame showing the robot at sensor
    # time t is then aligned to t + mocap_sync_error_s (the motion capture seems to lag).
    recorded_offset = offset + cfg.mocap_sync_error_s if cfg.mocap_sync_error_s else offset
    margin = min(cfg.mocap_margin_s, 0.25 * (t[-1] - t[0]))  # short sessions keep some truth
    t_lo, t_hi = t[0] + margin, t[-1] - margin
    t_frames = np.arange(t_lo, t_hi, 1.0 / cfg.mocap_rate_hz)  # sensor time
    if kinematics == "exact":  # phi: the Euler angles of the chain's rotation
        phi = euler_xyz(chain_rotation(robot.joints, [theta[:, c] for c in cols]))
        phi = phi[:, [AXES.index(a) for a in robot.torso_axes]]
    else:
        phi = theta @ robot.torso_sum.T  # phi = S theta (Eq. 14)
    angles = np.concatenate([theta, phi], axis=1)  # (T, K)
    truth = np.stack([np.interp(t_frames, t, angles[:, k]) for k in range(robot.n_angles)], 1)
    truth = truth + cfg.mocap_noise_deg * DEG * rng.standard_normal(truth.shape)

    hall_models = {
        name: {"a": PAPER_HALL_DEG["a"], "b": PAPER_HALL_DEG["b"], "c": PAPER_HALL_DEG["c"],
               "d": PAPER_HALL_DEG["d"], "sign": int(s), "unit": "deg"}
        for name, s in zip(robot.hall_names, robot.hall_side_sign)
    }
    # An effect that is off is left out of the record, so that a session without effects has
    # the meta.json it had before they existed (apart from "effects": the gyro scales).
    config = {k: v for k, v in asdict(cfg).items()
              if (v or k not in EFFECTS.values()) and not (k == "motion_range_deg" and v is None)
              and not (k == "soft_mount_damping" and not cfg.soft_mount_hz)}
    effects: dict = {}
    if cfg.hall_play_deg > 0:
        effects["hall_play_deg"] = {n: float(h) for n, h in
                                    zip(robot.angle_names[:robot.n_joint_axes], play_deg)}
    if cfg.hall_curve_deg > 0:
        effects["hall_curve_deg"] = {n: {"p2": float(a), "p3": float(b)}
                                     for n, a, b in zip(robot.hall_names, curve_p2, curve_p3)}
    if cfg.mocap_sync_error_s:
        effects["mocap_sync_error_s"] = float(cfg.mocap_sync_error_s)
    if cfg.gyro_delay_s > 0:
        effects["gyro_delay_s"] = float(cfg.gyro_delay_s)
    links = [f"gyro{i + 1}" for i in range(robot.n_links)]
    if cfg.gyro_mount_deg > 0:  # each board's tilt as a rotation vector, deg
        effects["gyro_mount_deg"] = {n: [float(x) for x in v / DEG] for n, v in zip(links, tilt)}
    if cfg.soft_mount_hz > 0:
        effects["soft_mount"] = {
            "damping_ratio": float(cfg.soft_mount_damping),
            "natural_frequency_hz": {n: float(f) for n, f in zip(links, soft_hz)},
            "rms_wobble_deg": {n: float(np.sqrt(np.mean(wobble[:, i] ** 2)) / DEG)
                               for i, n in enumerate(links)}}
    # reading = (1 + s) * rate: the factor minus 1 (exact: the factor lies in [0.5, 2]).
    effects["gyro_scale"] = {n: float(x) for n, x in zip(robot.gyro_names, (scale - 1).ravel())}
    simulation = {
        "kind": kind, "seed": seed, "device_seed": device_seed, "duration_s": duration_s,
        "config": config,
        "true_hall_models": {
            name: {"a": float(c[0]), "b": float(c[1]), "c": float(c[2]), "d": float(c[3]),
                   "sign": int(s), "unit": "deg"}
            for name, c, s in zip(robot.hall_names, true_coef, robot.hall_side_sign)
        },
        "gyro_zero_rate_rad_s": zero_rate.round(8).tolist(),
    }
    if kinematics != "linear":
        simulation["kinematics"] = kinematics
    simulation["effects"] = effects
    session = Session(
        robot=robot, t=t, gyro=gyro.reshape(n, -1), hall_v=v,
        sample_rate_hz=cfg.sample_rate_hz,
        mocap_t=t_frames - offset, mocap=truth, mocap_time_offset_s=recorded_offset,
        hall_models=hall_models,
        description=(f"simulated {kind} session, seed {seed}, joints {robot.spec}"
                     + (f", {kinematics} kinematics" if kinematics != "linear" else "")
                     + " (kckf-jax)"),
        extra_meta={"simulation": simulation},
        limits=_limits_for(cfg.motion_range_deg),
    )
    return inject_faults(session, faults, seed=seed) if faults else session


def _limits_for(range_deg: float | None) -> SensorLimits | None:
    """The session's stated limits: a robot simulated beyond the default reach of the joints
    (``JOINT_RANGE_RAD``, 120 deg) says how far its joints reach (its range and a tenth,
    at most 180 deg), as a real robot's ``meta.json`` would; else none (the defaults)."""
    if range_deg is None or range_deg * DEG <= JOINT_RANGE_RAD:
        return None
    return SensorLimits(joint_range_rad=min(np.pi, 1.1 * range_deg * DEG))
