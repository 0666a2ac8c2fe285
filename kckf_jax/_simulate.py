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
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from ._hall import DEG, PAPER_HALL_DEG, hall_voltage
from ._params import hall_arrays
from ._robot import AXES, Robot
from ._rotations import chain_rotation, euler_body_rates, euler_xyz, link_rates
from ._session import Session
from ._sim_faults import Fault, inject_faults

KINDS = ("cyclic", "static", "human", "walking")
KINEMATICS = ("linear", "exact")
DPS = DEG  # one degree per second, in rad/s


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
    gyro_scale_error: float = 0.01  # assumption: 1 % sensitivity error per axis
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


class _Smooth:
    """A smooth zero-mean random signal with unit RMS: a sum of sinusoids, value and derivative."""

    def __init__(self, rng: np.random.Generator, f_lo: float, f_hi: float, n: int = 6):
        self.f = rng.uniform(f_lo, f_hi, n)
        self.p = rng.uniform(0, 2 * np.pi, n)
        self.a = rng.uniform(0.5, 1.0, n)
        self.a /= np.sqrt(0.5 * np.sum(self.a**2))

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        arg = 2 * np.pi * self.f[:, None] * t[None, :] + self.p[:, None]
        val = np.sum(self.a[:, None] * np.sin(arg), axis=0)
        der = np.sum((self.a * 2 * np.pi * self.f)[:, None] * np.cos(arg), axis=0)
        return val, der


def _smoothstep(t: np.ndarray, t0: float, width: float) -> tuple[np.ndarray, np.ndarray]:
    """C1 step from 0 (t <= t0) to 1 (t >= t0 + width), and its derivative."""
    s = np.clip((t - t0) / width, 0.0, 1.0)
    return s * s * (3 - 2 * s), 6 * s * (1 - s) / width


def _cyclic(rng, robot: Robot, t: np.ndarray, amp_deg=(8.0, 16.0), freq_hz=(0.7, 1.0)):
    """Gait-like motion induced by hand: every joint axis oscillates with the shared cycle.

    Joint angles and rates, (T, J). The cycle's frequency and each joint's amplitude wander
    slowly (a hand is not a motor); the chain lags a little from joint to joint.
    """
    J = robot.n_joint_axes
    f0 = rng.uniform(*freq_hz)
    phase_noise = _Smooth(rng, 0.02, 0.1)
    pn, pn_d = phase_noise(t)
    psi = 2 * np.pi * f0 * t + 0.8 * pn  # cycle phase, rad
    psi_d = 2 * np.pi * f0 + 0.8 * pn_d
    axis_phase = {a: rng.uniform(0, 2 * np.pi) for a in AXES}
    theta = np.zeros((t.size, J))
    rate = np.zeros((t.size, J))
    for j, (i, a) in enumerate(robot.joint_axes):
        amp = rng.uniform(*amp_deg) * DEG
        m, m_d = _Smooth(rng, 0.01, 0.05)(t)
        mod, mod_d = amp * (1 + 0.2 * m), amp * 0.2 * m_d
        off, off_d = _Smooth(rng, 0.005, 0.03)(t)
        off0 = rng.uniform(-3, 3) * DEG
        ph = axis_phase[a] + 0.3 * i + rng.uniform(-0.2, 0.2)
        h2 = rng.uniform(0.05, 0.2)  # second harmonic: a hand-made cycle is not a pure sine
        s = np.sin(psi + ph) + h2 * np.sin(2 * (psi + ph))
        s_d = (np.cos(psi + ph) + 2 * h2 * np.cos(2 * (psi + ph))) * psi_d
        theta[:, j] = off0 + 2 * DEG * off + mod * s
        rate[:, j] = 2 * DEG * off_d + mod_d * s + mod * s_d
    return theta, rate


def _human(rng, robot: Robot, t: np.ndarray, rom_deg: float = 30.0):
    """Upper-torso bending and extension over ``rom_deg`` (paper Sec. 4.3), shared by joints.

    The flexion (about x when the robot has x joints, else its first torso axis) goes from
    upright (0) to ``rom_deg`` and back with a period of 4-6 s; the other axes sway a little.
    """
    J = robot.n_joint_axes
    flex_axis = "x" if "x" in robot.torso_axes else robot.torso_axes[0]
    period = rng.uniform(4.0, 6.0)
    pn, pn_d = _Smooth(rng, 0.01, 0.05)(t)
    psi = 2 * np.pi * t / period + 0.5 * pn
    psi_d = 2 * np.pi / period + 0.5 * pn_d
    flex = 0.5 * (1 - np.cos(psi))  # 0 (upright) .. 1 (bent)
    flex_d = 0.5 * np.sin(psi) * psi_d
    theta = np.zeros((t.size, J))
    rate = np.zeros((t.size, J))
    flex_joints = [j for j, (_, a) in enumerate(robot.joint_axes) if a == flex_axis]
    w = rng.uniform(0.6, 1.4, len(flex_joints))
    w = w / w.sum()
    for j, (_, a) in enumerate(robot.joint_axes):
        sway, sway_d = _Smooth(rng, 0.05, 0.3)(t)
        if a == flex_axis:
            share = w[flex_joints.index(j)]
            amp = rom_deg * DEG * share * rng.uniform(0.9, 1.1)
            theta[:, j] = amp * flex + 0.5 * DEG * sway
            rate[:, j] = amp * flex_d + 0.5 * DEG * sway_d
        else:
            theta[:, j] = 2.0 * DEG * sway
            rate[:, j] = 2.0 * DEG * sway_d
    return theta, rate, flex


def _walking(rng, robot: Robot, t: np.ndarray):
    """The trunk circling over a walking pelvis: every joint axis about x or y moves the trunk
    round a circle (x and y in quadrature, one circle in 4-6 s, the torso angle about each
    reaching 34-50 deg, shared among the joints about that axis), every z axis twists against
    the pelvis at the stride frequency (5-10 deg). Joint angles and rates (T, J), and the
    stride's phase and rate (the pelvis follows it)."""
    J = robot.n_joint_axes
    stride = rng.uniform(0.8, 1.0)
    pn, pn_d = _Smooth(rng, 0.01, 0.05)(t)
    psi_s = 2 * np.pi * stride * t + 0.3 * pn  # the stride's phase
    psi_s_d = 2 * np.pi * stride + 0.3 * pn_d
    period = rng.uniform(4.0, 6.0)
    psi_c = 2 * np.pi * t / period + 0.5 * pn  # the circle's phase
    psi_c_d = 2 * np.pi / period + 0.5 * pn_d
    total = {a: rng.uniform(34.0, 50.0) * DEG for a in ("x", "y")}
    total["z"] = rng.uniform(5.0, 10.0) * DEG
    shares = {}
    for a in AXES:
        js = [j for j, (_, b) in enumerate(robot.joint_axes) if b == a]
        w = rng.uniform(0.6, 1.4, len(js))
        shares.update(dict(zip(js, w / max(w.sum(), 1e-12))))
    theta = np.zeros((t.size, J))
    rate = np.zeros((t.size, J))
    for j, (_, a) in enumerate(robot.joint_axes):
        sway, sway_d = _Smooth(rng, 0.05, 0.3)(t)
        amp = total[a] * shares[j]
        if a == "x":
            s, s_d = np.sin(psi_c), np.cos(psi_c) * psi_c_d
        elif a == "y":
            s, s_d = np.cos(psi_c), -np.sin(psi_c) * psi_c_d
        else:
            s, s_d = -np.sin(psi_s), -np.cos(psi_s) * psi_s_d
        theta[:, j] = amp * s + 0.5 * DEG * sway
        rate[:, j] = amp * s_d + 0.5 * DEG * sway_d
    return theta, rate, (psi_s, psi_s_d)


def _pelvis(rng, psi, psi_d):
    """The walking pelvis's body rate (T, 3): its orientation as intrinsic x-y-z Euler angles
    (obliquity about x and tilt about y at the stride frequency and twice it, rotation about
    the vertical z at the stride frequency), turned into the body rate exactly."""
    amp = np.array([rng.uniform(3.0, 5.0), rng.uniform(2.0, 4.0), rng.uniform(5.0, 8.0)]) * DEG
    ph = rng.uniform(0, 2 * np.pi, 3)
    mult = np.array([1.0, 2.0, 1.0])  # the tilt rocks twice a stride
    arg = mult[None, :] * psi[:, None] + ph[None, :]
    angles = amp * np.sin(arg)
    rates = amp * np.cos(arg) * mult[None, :] * psi_d[:, None]
    return euler_body_rates(angles, rates)


def _base_motion(rng, t: np.ndarray, kind: str, flex: np.ndarray | None):
    """Orientation rate of the base link (worn low on the back), (T, 3) rad/s."""
    rate = np.zeros((t.size, 3))
    for ax in range(3):
        _, d = _Smooth(rng, 0.5, 2.0)(t)  # gait-like pelvis rotation, a few degrees
        _, slow = _Smooth(rng, 0.01, 0.1)(t)  # posture changes
        rate[:, ax] = 3.0 * DEG * d + 2.0 * DEG * slow
    if kind == "human" and flex is not None:
        # The pelvis tilts with the trunk (lumbo-pelvic rhythm): about 1/3 of the bend.
        rate[:, 0] += np.gradient(10.0 * DEG * flex, t)
    return rate


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
            each Hall sensor's true curve and each gyro axis's scale error. Sessions with the
            same ``device_seed`` are trials of the same exoshell (default: ``seed``).
        true_hall_models: the sensors' true Eq. 1 curves (``meta.json`` form, any unit) instead
            of random ones; for experiments with known ground-truth parameters.
        faults: sensor faults written into the finished session (``inject_faults``, seeded
            by ``seed``; none by default, and then nothing changes).
        kinematics: ``"linear"`` (the paper's model, default) or ``"exact"`` (finite
            rotations; the module docstring). Every random draw is the same for both.

    Returns:
        A ``Session`` with sensors, motion capture (own rate, own clock) and meta. The true
        Hall coefficients and gyro biases are kept in ``session.extra_meta["simulation"]``.

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
    rng = np.random.default_rng(np.random.SeedSequence([seed, KINDS.index(kind), len(robot.spec)]))
    device_seed = seed if device_seed is None else device_seed
    dev = np.random.default_rng(np.random.SeedSequence([device_seed, 7919, len(robot.spec)]))

    # ---- time: the microcontroller samples at its nominal rate with a little jitter.
    ts = 1.0 / cfg.sample_rate_hz
    n = int(round(duration_s * cfg.sample_rate_hz))
    t = np.arange(n) * ts + rng.uniform(-cfg.timestamp_jitter_s, cfg.timestamp_jitter_s, n)
    t[0] = 0.0
    t = np.round(np.maximum.accumulate(t), 6)  # the microcontroller stamps in microseconds

    # ---- joint motion (T, J): angles and rates, with a still start in the neutral pose.
    flex = stride = None
    if kind == "human":
        theta, rate, flex = _human(rng, robot, t)
    elif kind == "walking":
        theta, rate, stride = _walking(rng, robot, t)
    else:
        theta, rate = _cyclic(rng, robot, t)
    ramp, ramp_d = _smoothstep(t, 1.0, 2.0)  # still for 1 s, then the motion fades in
    rate = ramp[:, None] * rate + ramp_d[:, None] * theta
    theta = ramp[:, None] * theta
    if kind == "static":
        hold, hold_d = _smoothstep(t, move_s, 2.0)
        th_end = theta[min(np.searchsorted(t, move_s + 2.0), n - 1)]
        theta_hold = (1 - hold)[:, None] * theta + hold[:, None] * th_end
        rate = (1 - hold)[:, None] * rate + hold_d[:, None] * (th_end - theta)
        theta = theta_hold
        flex = None

    # ---- link rates (T, n+1, 3): base rate plus the rates of the joints below (Eq. 2).
    base = _base_motion(rng, t, kind, flex)
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
    simulation = {
        "kind": kind, "seed": seed, "device_seed": device_seed, "duration_s": duration_s,
        "config": asdict(cfg),
        "true_hall_models": {
            name: {"a": float(c[0]), "b": float(c[1]), "c": float(c[2]), "d": float(c[3]),
                   "sign": int(s), "unit": "deg"}
            for name, c, s in zip(robot.hall_names, true_coef, robot.hall_side_sign)
        },
        "gyro_zero_rate_rad_s": zero_rate.round(8).tolist(),
    }
    if kinematics != "linear":
        simulation["kinematics"] = kinematics
    session = Session(
        robot=robot, t=t, gyro=gyro.reshape(n, -1), hall_v=v,
        sample_rate_hz=cfg.sample_rate_hz,
        mocap_t=t_frames - offset, mocap=truth, mocap_time_offset_s=offset,
        hall_models=hall_models,
        description=(f"simulated {kind} session, seed {seed}, joints {robot.spec}"
                     + (f", {kinematics} kinematics" if kinematics != "linear" else "")
                     + " (kckf-jax)"),
        extra_meta={"simulation": simulation},
    )
    return inject_faults(session, faults, seed=seed) if faults else session
