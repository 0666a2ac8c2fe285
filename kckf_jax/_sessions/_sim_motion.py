"""How the simulated wearer moves: each kind's joint angles and rates, the base link's
rate, and the gain that takes a kind's motion to a stated joint range (``_simulate``)."""

from __future__ import annotations

import numpy as np

from .._models._hall import DEG
from .._models._robot import AXES, Robot
from .._models._rotations import euler_body_rates

DPS = DEG


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


def _cyclic(rng, robot: Robot, t: np.ndarray, amp_deg=(8.0, 16.0), freq_hz=(0.7, 1.0),
            gain: float = 1.0):
    """Gait-like motion induced by hand: every joint axis oscillates with the shared cycle.

    Joint angles and rates, (T, J). The cycle's frequency and each joint's amplitude wander
    slowly (a hand is not a motor); the chain lags a little from joint to joint. ``gain``
    multiplies the amplitudes (not the posture offsets).
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
        amp = rng.uniform(*amp_deg) * DEG * gain
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


def _human(rng, robot: Robot, t: np.ndarray, rom_deg: float = 30.0, gain: float = 1.0):
    """Upper-torso bending and extension over ``rom_deg`` (paper Sec. 4.3), shared by joints.

    The flexion (about x when the robot has x joints, else its first torso axis) goes from
    upright (0) to ``rom_deg`` and back with a period of 4-6 s; the other axes sway a little.
    ``gain`` multiplies the bend (not the sway).
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
            amp = rom_deg * DEG * share * rng.uniform(0.9, 1.1) * gain
            theta[:, j] = amp * flex + 0.5 * DEG * sway
            rate[:, j] = amp * flex_d + 0.5 * DEG * sway_d
        else:
            theta[:, j] = 2.0 * DEG * sway
            rate[:, j] = 2.0 * DEG * sway_d
    return theta, rate, flex


def _walking(rng, robot: Robot, t: np.ndarray, gain: float = 1.0):
    """The trunk circling over a walking pelvis: every joint axis about x or y moves the trunk
    round a circle (x and y in quadrature, one circle in 4-6 s, the torso angle about each
    reaching 34-50 deg, shared among the joints about that axis), every z axis twists against
    the pelvis at the stride frequency (5-10 deg). Joint angles and rates (T, J), and the
    stride's phase and rate (the pelvis follows it). ``gain`` multiplies the circling (not the
    twist)."""
    J = robot.n_joint_axes
    stride = rng.uniform(0.8, 1.0)
    pn, pn_d = _Smooth(rng, 0.01, 0.05)(t)
    psi_s = 2 * np.pi * stride * t + 0.3 * pn  # the stride's phase
    psi_s_d = 2 * np.pi * stride + 0.3 * pn_d
    period = rng.uniform(4.0, 6.0)
    psi_c = 2 * np.pi * t / period + 0.5 * pn  # the circle's phase
    psi_c_d = 2 * np.pi / period + 0.5 * pn_d
    total = {a: rng.uniform(34.0, 50.0) * DEG * gain for a in ("x", "y")}
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


def _base_motion(rng, t: np.ndarray, kind: str, flex: np.ndarray | None,
                 tilt_deg: float = 10.0):
    """Orientation rate of the base link (worn low on the back), (T, 3) rad/s; ``tilt_deg``:
    the human kind's pelvic tilt at full bend."""
    rate = np.zeros((t.size, 3))
    for ax in range(3):
        _, d = _Smooth(rng, 0.5, 2.0)(t)  # gait-like pelvis rotation, a few degrees
        _, slow = _Smooth(rng, 0.01, 0.1)(t)  # posture changes
        rate[:, ax] = 3.0 * DEG * d + 2.0 * DEG * slow
    if kind == "human" and flex is not None:
        # The pelvis tilts with the trunk (lumbo-pelvic rhythm): about 1/3 of the bend.
        rate[:, 0] += np.gradient(tilt_deg * DEG * flex, t)
    return rate


def _joint_motion(rng, robot: Robot, t: np.ndarray, kind: str, move_s: float, gain: float):
    """The joints' angles and rates (T, J) with the still start (and the static kind's hold),
    the human kind's bend (0..1) or None, the walking stride's phase and rate or None, and the
    fade-in ramp. ``gain`` scales each kind's main motion (``_cyclic``, ``_human``,
    ``_walking``); 1 is the kind's own size."""
    n = t.size
    flex = stride = None
    if kind == "human":
        theta, rate, flex = _human(rng, robot, t, gain=gain)
    elif kind == "walking":
        theta, rate, stride = _walking(rng, robot, t, gain=gain)
    else:
        theta, rate = _cyclic(rng, robot, t, gain=gain)
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
    return theta, rate, flex, stride, ramp


def _range_gain(rng, robot: Robot, t: np.ndarray, kind: str, move_s: float,
                range_deg: float) -> float:
    """The gain of ``_joint_motion`` at which the largest |angle| of the joints and of the
    torso sums (Eq. 14) is ``range_deg``. The angles are ``gain * main + rest`` (the motion is
    linear in its gain) and their largest magnitude is convex in it, so bisection finds the one
    crossing. ``rng`` is left where it was (the motion is drawn again with the gain found)."""
    state = rng.bit_generator.state
    parts = []
    for g in (0.0, 1.0):
        rng.bit_generator.state = state
        theta = _joint_motion(rng, robot, t, kind, move_s, g)[0]
        parts.append(np.concatenate([theta, theta @ robot.torso_sum.T], axis=1))
    rng.bit_generator.state = state
    rest, main = parts[0], parts[1] - parts[0]
    target = range_deg * DEG

    def peak(g: float) -> float:
        return float(np.max(np.abs(g * main + rest)))

    if peak(0.0) >= target:
        raise ValueError(f"simulate: motion_range_deg = {range_deg:g} is within what the "
                         f"{kind} motion does besides its scaled part (up to "
                         f"{peak(0.0) / DEG:.3g} deg of sway, offsets or twist); give more")
    if not np.max(np.abs(main)) > 0:
        raise ValueError(f"simulate: the {kind} motion on {robot.spec} has nothing that "
                         "motion_range_deg scales (walking circles the trunk about x and y)")
    lo, hi = 0.0, 1.0
    while peak(hi) < target:
        lo, hi = hi, 2 * hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if peak(mid) < target else (lo, mid)
    return 0.5 * (lo + hi)
