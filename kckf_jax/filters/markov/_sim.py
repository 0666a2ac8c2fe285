"""A sagittal-plane gait simulator for the Markovian (MJLS) filter of a lower-limb exoskeleton.

One leg of an exoskeleton (trunk, thigh, shank, foot; Dos Santos et al., Sensors 2014, Fig. 2)
walks at a normal pace after standing still. Each segment carries an IMU (one gyro axis about the
sagittal normal, three accelerometer axes) and the hip, knee and ankle carry encoders. Pure NumPy,
seeded with a ``numpy.random.Generator``; no JAX here (``markov.gait_series`` converts).

Sign conventions (all angles in rad, counter-clockwise in the x (forward) - z (up) plane, which
is what the gyro measures):

* absolute angles ``theta = (trunk, thigh, shank, foot)``: 0 in the upright standing pose
  (trunk and leg segments vertical, foot horizontal); a thigh with the knee forward, a shank
  with the ankle forward and a foot with the toes up are positive; trunk forward lean is
  negative;
* clinical joint angles: hip flexion ``h = theta_T - theta_B``, knee flexion
  ``k = theta_T - theta_S``, ankle dorsiflexion ``d = theta_F - theta_S``;
* encoders measure the paper's relative angles (Eq. 17): ``theta_B - theta_T`` (hip),
  ``theta_T - theta_S`` (knee), ``theta_S - theta_F`` (ankle), i.e. ``-h``, ``k``, ``-d``.

Kinematics (docs/other_filters.md has the sources and numbers):

* hip and knee flexion follow normal-gait curves through landmark values of Perry & Burnfield
  (2010) and Winter (2009), smoothed to 7 harmonics of the gait cycle; the foot's pitch follows
  heel strike (toes 22 deg up), an exactly flat foot from 13 % to 35 % of the cycle, heel rise,
  push-off (toe-off at 62 %, toes 62 deg down) and swing; the trunk leans 8 deg forward and
  pitches by 1.5 deg twice per stride;
* segment lengths are Winter's (2009, Fig. 4.1) fractions of body height;
* the stance foot does not slip: it pivots about the heel while the toes are up, lies flat and
  still in mid-stance and pivots about the metatarsal heads after heel rise. The hip joint's
  path makes that possible: forward, a smooth least-squares fit (speed about 1.2 m/s); up, over
  single support exactly the height at which the stance knee has the pattern's flexion, over
  double support a C2 quintic bridge (the pelvis rises and falls about 2 cm per step). The
  stance leg's thigh and shank then follow inverse kinematics (foot pinned) and blend smoothly
  into the free pattern around toe-off and back after heel strike;
* so every IMU sees the dynamic acceleration of its own phase: the foot's accelerometer reads
  gravity alone in mid-stance and is far from it at heel strike, push-off and swing (up to
  about 6 g), the shank's is worst in swing and at toe-off, the thigh's at the transitions,
  and the trunk's sees the pelvis bounce (up to about 2.4 g at heel strike) and sway;
* accelerations are second differences of the IMU positions on a grid ten times finer than the
  sample rate; the gyro reads the derivative of the segment's angle;
* a trial stands still for ``stand_s`` (at mid-stance of the instrumented leg, its foot flat),
  then the cadence ramps up to normal over ``start_s``.

Sensors follow the paper's Eqs. 1-4: ``gyro = theta_dot - b_g - eta_g`` and
``accel = f - b_a - mu_a`` (specific force in the IMU frame), with first-order Gauss-Markov
biases (exact discretisation of ``b_dot = -b / tau + eta_b``, started from the stationary law).
The gyro bias correlation times are the paper's Table 2 ``tau_g``; the noise levels are
datasheet values of an MPU-9250-class IMU (see ``GaitConfig``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np

from ._filter import DEG, G_M_S2, TABLE2, GaitSeries, MarkovParams

#: Normal gait, landmark values (percent of the gait cycle from heel strike, degrees) read off
#: the normative curves of Perry & Burnfield, "Gait Analysis: Normal and Pathological Function",
#: 2nd ed. (2010), and Winter, "Biomechanics and Motor Control of Human Movement",
#: 4th ed. (2009), App. A: hip flexion 30 deg at heel strike, 10 deg of extension at 50-55 %,
#: 31 deg of flexion in late swing; knee 18 deg at loading response, nearly straight at 40 %,
#: 38 deg at toe-off (62 %), 60 deg peak in swing.
HIP_LANDMARKS_DEG = ((0, 30), (10, 27), (20, 19), (30, 10), (40, 1), (50, -8), (55, -10),
                     (62, -2), (70, 12), (80, 26), (87, 31), (95, 30))
KNEE_LANDMARKS_DEG = ((0, 5), (7, 13), (15, 18), (25, 12), (40, 4), (50, 8), (62, 38),
                      (73, 60), (80, 52), (90, 22), (97, 5))
#: Foot pitch (toes up positive) against the ground: heel strike with the toes 22 deg up, flat
#: foot by 13 %, heel rise from 35 %, toe-off at 62 % with the toes 62 deg down, the foot
#: swinging through and rising to heel strike again (Perry's foot-floor angle); with the hip
#: and knee curves this makes the ankle span about -15..+10 deg, as Perry's ankle curve.
FOOT_LANDMARKS_DEG = ((0, 22), (5, 12), (10, 3), (13, 0), (35, 0), (42, -5), (48, -14),
                      (55, -32), (62, -62), (68, -64), (75, -50), (85, -14), (93, 16), (97, 22))
#: The foot lies exactly flat (pitch 0) over this part of the cycle, entered and left over
#: ``FLAT_EDGE`` (C2 blends, so that the foot's acceleration stays continuous).
FOOT_FLAT = (0.13, 0.35)
FLAT_EDGE = 0.05
#: The stance leg follows inverse kinematics (its foot pinned to the ground) from the end of
#: ``STANCE_IN`` to the start of ``STANCE_OUT`` and the free pattern in swing, with C2 blends in
#: these windows (toe-off at 62 % lies inside the second; Perry: toe-off at 60-62 %).
STANCE_IN = (0.06, 0.14)
STANCE_OUT = (0.49, 0.61)
#: Single support of the instrumented leg (Perry: 10-12 % double support after heel strike
#: and before toe-off at 60-62 %).
SINGLE_SUPPORT = (0.13, 0.49)
#: Phase at which the body stands still before walking: mid-stance, the foot flat.
STAND_PHASE = 0.25
#: Harmonics of the step frequency in the hip joint's path.
PATH_HARMONICS = 2
#: Least knee flexion of the inverse kinematics (it stays off the singular straight knee).
MIN_KNEE = 3.0 * DEG
HARMONICS = 7


def _smooth_landmarks(points, harmonics: int = HARMONICS) -> tuple[np.ndarray, np.ndarray]:
    """Fourier coefficients (cos, sin; rad) of the periodic curve through ``points``.

    The landmarks are joined by a periodic piecewise-linear curve, which is then low-passed to
    ``harmonics`` harmonics of the gait cycle: smooth, with analytic derivatives, within a
    degree or two of every landmark.
    """
    phase = np.array([p for p, _ in points], dtype=np.float64) / 100.0
    value = np.array([v for _, v in points], dtype=np.float64) * DEG
    grid = np.arange(1000) / 1000.0
    curve = np.interp(grid, phase, value, period=1.0)
    spec = np.fft.rfft(curve) / grid.size
    n = np.arange(harmonics + 1)
    a = 2.0 * spec.real[n]
    b = -2.0 * spec.imag[n]
    a[0] /= 2.0
    return a, b


def _fourier(coeffs: tuple[np.ndarray, np.ndarray], phase: np.ndarray) -> np.ndarray:
    a, b = coeffs
    n = np.arange(a.size)
    arg = 2.0 * np.pi * np.multiply.outer(phase, n)
    return np.cos(arg) @ a + np.sin(arg) @ b


def _smoothstep(x: np.ndarray) -> np.ndarray:
    """C2 step from 0 (x <= 0) to 1 (x >= 1)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _flat_window(phase: np.ndarray) -> np.ndarray:
    """1 on ``FOOT_FLAT``, 0 outside it widened by ``FLAT_EDGE``, C2 in between."""
    lo, hi = FOOT_FLAT
    up = _smoothstep((phase - (lo - FLAT_EDGE)) / FLAT_EDGE)
    down = 1.0 - _smoothstep((phase - hi) / FLAT_EDGE)
    return up * down


_HIP = _smooth_landmarks(HIP_LANDMARKS_DEG)
_KNEE = _smooth_landmarks(KNEE_LANDMARKS_DEG)
_FOOT = _smooth_landmarks(FOOT_LANDMARKS_DEG)


def gait_pattern(phase: np.ndarray, trunk_lean_rad: float = -8.0 * DEG,
                 trunk_sway_rad: float = 1.5 * DEG, amplitude: float = 1.0
                 ) -> dict[str, np.ndarray]:
    """Normal-gait angles (rad) at gait ``phase`` (fraction of the cycle from heel strike).

    Returns ``hip``, ``knee`` (clinical flexion), ``foot`` (pitch), ``trunk`` (absolute) and
    the derived ``ankle`` dorsiflexion and absolute ``thigh``, ``shank``. The trunk leans
    forward by ``-trunk_lean_rad`` and pitches by ``trunk_sway_rad`` twice per stride
    (Winter 2009: 2-3 deg peak to peak); ``amplitude`` scales the hip, knee and foot
    excursions (trial-to-trial variation).
    """
    phase = np.mod(phase, 1.0)
    hip = amplitude * _fourier(_HIP, phase)
    knee = amplitude * _fourier(_KNEE, phase)
    foot = amplitude * (1.0 - _flat_window(phase)) * _fourier(_FOOT, phase)
    trunk = trunk_lean_rad + trunk_sway_rad * np.cos(4.0 * np.pi * phase)
    thigh = trunk + hip
    shank = thigh - knee
    return dict(hip=hip, knee=knee, foot=foot, trunk=trunk, thigh=thigh, shank=shank,
                ankle=foot - shank)


@dataclass(frozen=True)
class GaitConfig:
    """What the simulator draws from. Units in the names; sources in docs/other_filters.md.

    Body (Winter 2009, Fig. 4.1, fractions of the height ``H``): thigh 0.245 H, shank 0.246 H,
    foot length 0.152 H, ankle height 0.039 H. The heel lies ``heel_frac`` of the foot length
    behind the ankle, the metatarsal heads ``mtp_frac`` in front of it (our choice, within
    Winter's foot). IMU positions along the segments are typical exoskeleton mounts (ours).

    Sensors (MPU-9250-class MEMS IMU, InvenSense datasheet PS-MPU-9250A-01): gyro noise
    density 0.01 dps/sqrt(Hz) over the 50 Hz Nyquist band -> 0.07 dps per sample; accelerometer
    300 ug/sqrt(Hz) -> 2.1 mg per sample and axis. Bias levels are after a turn-on calibration
    (our assumption: 0.5 dps, 5 mg); gyro bias correlation times are the paper's Table 2
    ``tau_g``; accelerometer ones (not in the paper) 600 s. Encoders: 12-bit absolute
    (4096 counts per turn, 0.088 deg per count) with 0.02 deg of electrical noise.
    """

    rate_hz: float = 100.0
    stand_s: float = 1.0
    start_s: float = 1.0  # the cadence ramps from 0 to 1 / stride_s over this time
    duration_s: float = 11.0
    oversample: int = 10
    height_m: float = 1.75
    height_sd_m: float = 0.07
    stride_s: float = 1.1
    stride_sd: float = 0.05  # relative, per trial
    amplitude_sd: float = 0.05  # relative scale of the joint excursions, per trial
    trunk_lean_deg: float = -8.0
    trunk_sway_deg: float = 1.5
    pelvis_sway_m: float = 0.02  # lateral, at stride frequency (trunk IMU only)
    thigh_frac: float = 0.245
    shank_frac: float = 0.246
    foot_frac: float = 0.152
    ankle_height_frac: float = 0.039
    heel_frac: float = 0.25
    mtp_frac: float = 0.50
    imu_trunk_m: float = 0.25  # above the hip joint, along the trunk
    imu_thigh_frac: float = 0.5  # of the thigh from the hip
    imu_shank_frac: float = 0.5  # of the shank from the knee
    imu_foot_frac: float = 0.3  # of the foot length in front of the ankle, on the dorsum
    gyro_noise_dps: float = 0.07
    gyro_bias_dps: float = 0.5
    gyro_tau_s: tuple[float, float, float, float] = (839.70, 2138.5, 1465.3, 3567.5)
    accel_noise_mg: float = 2.1
    accel_bias_mg: float = 5.0
    accel_tau_s: float = 600.0
    encoder_counts: int = 4096
    encoder_noise_deg: float = 0.02

    def __post_init__(self):
        if self.rate_hz <= 0 or self.oversample < 2 or self.duration_s <= self.stand_s:
            raise ValueError("GaitConfig: need rate_hz > 0, oversample >= 2 and "
                             f"duration_s > stand_s, got {self.rate_hz}, {self.oversample}, "
                             f"{self.duration_s}, {self.stand_s}")
        if len(self.gyro_tau_s) != 4 or min(self.gyro_tau_s) <= 0:
            raise ValueError(f"GaitConfig.gyro_tau_s: expected 4 positive values, got "
                             f"{self.gyro_tau_s}")

    @property
    def n_steps(self) -> int:
        return int(round(self.duration_s * self.rate_hz))


@dataclass(frozen=True)
class GaitTrials:
    """Simulated trials (NumPy, leading axis ``B`` = trial, then ``T`` = sample).

    * ``dt`` (B, T) s: time since the previous sample (0 for the first);
    * ``gyro`` (B, T, 4) rad/s, ``accel`` (B, T, 4, 3) m/s^2 (IMU x, y, z), ``encoder``
      (B, T, 3) rad: the sensor readings, segments in ``SEGMENTS`` order;
    * ``angles`` (B, T, 4) rad: the true absolute angles; ``gyro_bias`` (B, T, 4) rad/s;
      ``joints`` (B, T, 3) rad: true clinical hip, knee, ankle angles;
    * ``phase`` (B, T): gait phase in cycles from the instrumented leg's heel strike (held at
      0.25, mid-stance, while standing);
    * ``info``: per-trial height, stride time and amplitude scale.
    """

    dt: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    encoder: np.ndarray
    angles: np.ndarray
    gyro_bias: np.ndarray
    joints: np.ndarray
    phase: np.ndarray
    info: dict = field(default_factory=dict)

    @property
    def n_trials(self) -> int:
        return int(self.dt.shape[0])


def _second_difference(x: np.ndarray, h: float) -> np.ndarray:
    """d2x/dt2 along axis 0 (central, one-sided at the ends)."""
    out = np.empty_like(x)
    out[1:-1] = (x[2:] - 2.0 * x[1:-1] + x[:-2]) / h**2
    out[0], out[-1] = out[1], out[-2]
    return out


def _rot(angle: np.ndarray, v: tuple[float, float]) -> np.ndarray:
    """Rotate the (x, z) vector ``v`` by ``angle`` (counter-clockwise); shape (2, ...)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def _down(angle: np.ndarray) -> np.ndarray:
    """Unit vector of a leg segment at ``angle`` (0 = pointing down)."""
    return np.stack([np.sin(angle), -np.cos(angle)])


class _Body:
    """Segment lengths (m) of one subject and the foot's pivots in the foot frame."""

    def __init__(self, cfg: GaitConfig, height: float):
        self.L_T, self.L_S = cfg.thigh_frac * height, cfg.shank_frac * height
        L_F, h_a = cfg.foot_frac * height, cfg.ankle_height_frac * height
        self.L_F = L_F
        self.heel = (-cfg.heel_frac * L_F, -h_a)
        self.mtp = (cfg.mtp_frac * L_F, -h_a)
        self.toe_ground = (cfg.heel_frac + cfg.mtp_frac) * L_F

    def ankle(self, pitch: np.ndarray, heel_ground_x: np.ndarray) -> np.ndarray:
        """Ankle (x, z) of a foot on the ground: pivoting about the heel while the toes are up,
        about the metatarsal heads while the heel is up (the same point when flat)."""
        on_toes = pitch < 0
        pivot = np.stack([heel_ground_x + np.where(on_toes, self.toe_ground, 0.0),
                          np.zeros_like(pitch)])
        local = np.where(on_toes, _rot(pitch, self.mtp), _rot(pitch, self.heel))
        return pivot - local

    def ik(self, hip: np.ndarray, ankle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Thigh and shank angles that put the ankle at ``ankle`` (knee flexed forward).

        The knee flexion is a smooth maximum (0.5 deg wide) of the exact one and
        ``MIN_KNEE``: out of reach, the leg points at the ankle with the knee at about
        ``MIN_KNEE`` and the foot stays just off the ground, instead of the knee locking straight
        with a kink (the error is 2e-4 rad at ``MIN_KNEE + 2 deg``, 1e-9 rad beyond +8 deg).
        """
        d = ankle - hip
        D2 = np.sum(d**2, axis=0)
        cos_k = np.clip((D2 - self.L_T**2 - self.L_S**2) / (2 * self.L_T * self.L_S), -1, 1)
        width = 0.5 * DEG
        knee = MIN_KNEE + width * np.logaddexp(0.0, (np.arccos(cos_k) - MIN_KNEE) / width)
        D2 = self.L_T**2 + self.L_S**2 + 2 * self.L_T * self.L_S * np.cos(knee)
        cos_b = np.clip((self.L_T**2 + D2 - self.L_S**2) / (2 * self.L_T * np.sqrt(D2)), -1, 1)
        thigh = np.arctan2(d[0], -d[1]) + np.arccos(cos_b)
        return thigh, thigh - knee


def _stance_weight(phase: np.ndarray) -> np.ndarray:
    """How much the stance leg follows inverse kinematics (foot pinned) rather than the
    free pattern: 0 -> 1 over the loading response, 1 -> 0 around toe-off (C2)."""
    ph = np.mod(phase, 1.0)
    a0, a1 = STANCE_IN
    b0, b1 = STANCE_OUT
    rise = _smoothstep((ph - a0) / (a1 - a0))
    fall = 1.0 - _smoothstep((ph - b0) / (b1 - b0))
    return np.where(ph < b0, rise, fall)


def _path_basis(p: np.ndarray) -> np.ndarray:
    """Hip-path regressors over gait phase ``p``: 1, p, then the first ``PATH_HARMONICS``
    harmonics of the step (twice the stride) frequency."""
    cols = [np.ones_like(p), p]
    for m in range(1, PATH_HARMONICS + 1):
        w = 4.0 * np.pi * m * p
        cols += [np.cos(w), np.sin(w)]
    return np.stack(cols, axis=-1)


class _HipPath:
    """The hip joint's path over gait phase ``p`` (stance ``n``'s heel on the ground at
    ``x = n * stride_m``); it repeats every step (the other leg walks the same pattern half a
    cycle later) plus the forward progression.

    * ``x``: least squares of where the pattern puts the hip while the instrumented leg carries
      the body (0-50 %, its foot held on the ground), on a line plus ``PATH_HARMONICS``
      harmonics of the step frequency: a forward speed that varies smoothly within the step.
    * ``z``: over single support (``SINGLE_SUPPORT``), the height at which the stance leg, its
      foot on the ground, has exactly the pattern's knee flexion; over double support a C2
      quintic bridge to the next single support.
    """

    def __init__(self, cfg: GaitConfig, body: _Body, amp: float):
        self.cfg, self.body, self.amp = cfg, body, amp
        p = np.linspace(0.0, 0.5, 128)
        pat = self._pattern(p)
        ankle = body.ankle(pat["foot"], np.zeros_like(p))
        hip = ankle - body.L_T * _down(pat["thigh"]) - body.L_S * _down(pat["shank"])
        self.cx = np.linalg.lstsq(_path_basis(p), hip[0], rcond=None)[0]
        self.stride_m = float(self.cx[1])
        a, b = SINGLE_SUPPORT
        eps = 1e-4
        za = self._z_single(np.array([a - eps, a, a + eps]))
        zb = self._z_single(np.array([b - eps, b, b + eps]))
        span = 0.5 - (b - a)

        def derivs(z):  # value, first and second derivative in the bridge's unit time
            d1 = (z[2] - z[0]) / (2 * eps)
            d2 = (z[2] - 2 * z[1] + z[0]) / eps**2
            return z[1], d1 * span, d2 * span**2

        self.bridge = _quintic(derivs(zb), derivs(za))

    def _pattern(self, p):
        return gait_pattern(p, self.cfg.trunk_lean_deg * DEG, self.cfg.trunk_sway_deg * DEG,
                            self.amp)

    def x(self, p: np.ndarray) -> np.ndarray:
        return _path_basis(p) @ self.cx

    def _z_single(self, p: np.ndarray) -> np.ndarray:
        body = self.body
        pat = self._pattern(p)
        ankle = body.ankle(pat["foot"], np.zeros_like(p))
        D2 = body.L_T**2 + body.L_S**2 + 2 * body.L_T * body.L_S * np.cos(pat["knee"])
        return ankle[1] + np.sqrt(np.maximum(D2 - (self.x(p) - ankle[0]) ** 2, 0.0))

    def z(self, p: np.ndarray) -> np.ndarray:
        a, b = SINGLE_SUPPORT
        q = np.mod(p, 0.5)
        single = (q >= a) & (q <= b)
        s = np.mod(q - b, 0.5) / (0.5 - (b - a))
        return np.where(single, self._z_single(np.clip(q, a, b)), self.bridge(s))


def _quintic(start: tuple[float, float, float], end: tuple[float, float, float]):
    """The quintic on [0, 1] with the given value, slope and curvature at both ends."""
    y0, d0, c0 = start
    y1, d1, c1 = end
    M = np.array([[1, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0], [0, 0, 2, 0, 0, 0],
                  [1, 1, 1, 1, 1, 1], [0, 1, 2, 3, 4, 5], [0, 0, 2, 6, 12, 20]], float)
    coef = np.linalg.solve(M, np.array([y0, d0, c0, y1, d1, c1]))
    return lambda s: np.polyval(coef[::-1], s)


def _trial_kinematics(cfg: GaitConfig, rng: np.random.Generator) -> dict:
    """True angles, rates and IMU specific forces of one trial, on the fine grid then
    decimated to the sample rate."""
    h = 1.0 / (cfg.rate_hz * cfg.oversample)
    n = cfg.n_steps * cfg.oversample + 2  # one extra fine sample each side for differences
    t = (np.arange(n) - 1) * h
    height = max(1.45, cfg.height_m + cfg.height_sd_m * rng.standard_normal())
    stride = cfg.stride_s * (1.0 + cfg.stride_sd * rng.standard_normal())
    amp = 1.0 + cfg.amplitude_sd * rng.standard_normal()
    body = _Body(cfg, height)
    path = _HipPath(cfg, body, amp)

    # Gait phase: frozen at mid-stance while standing, then the cadence ramps up (C2).
    u = np.clip((t - cfg.stand_s) / cfg.start_s, 0.0, 1.0)
    ramp_int = cfg.start_s * (u**6 - 3 * u**5 + 2.5 * u**4) + np.maximum(
        t - cfg.stand_s - cfg.start_s, 0.0)
    phase = STAND_PHASE + ramp_int / stride

    pat = gait_pattern(phase, cfg.trunk_lean_deg * DEG, cfg.trunk_sway_deg * DEG, amp)
    hip = np.stack([path.x(phase), path.z(phase)])
    heel_x = path.stride_m * np.floor(phase)
    ik_thigh, ik_shank = body.ik(hip, body.ankle(pat["foot"], heel_x))
    w = _stance_weight(phase)
    trunk = pat["trunk"]
    thigh = w * ik_thigh + (1 - w) * pat["thigh"]
    shank = w * ik_shank + (1 - w) * pat["shank"]
    foot = pat["foot"]

    knee_p = hip + body.L_T * _down(thigh)
    ankle_p = knee_p + body.L_S * _down(shank)
    pos = [
        hip + cfg.imu_trunk_m * _rot(trunk, (0.0, 1.0)),
        hip + cfg.imu_thigh_frac * body.L_T * _down(thigh),
        knee_p + cfg.imu_shank_frac * body.L_S * _down(shank),
        ankle_p + _rot(foot, (cfg.imu_foot_frac * body.L_F, 0.0)),
    ]
    angles = np.stack([trunk, thigh, shank, foot], axis=-1)
    walking = np.clip((t - cfg.stand_s) / cfg.start_s, 0.0, 1.0)
    lateral = _smoothstep(walking) * cfg.pelvis_sway_m * np.sin(2.0 * np.pi * phase)
    f = np.zeros((n, 4, 3))
    for i, p in enumerate(pos):
        acc = _second_difference(p.T, h)  # (n, 2): x, z
        fx, fz = acc[:, 0], acc[:, 1] + G_M_S2
        th = angles[:, i]
        f[:, i, 0] = np.cos(th) * fx + np.sin(th) * fz
        f[:, i, 2] = -np.sin(th) * fx + np.cos(th) * fz
    f[:, 0, 1] = _second_difference(lateral, h)
    rate = np.gradient(angles, h, axis=0)
    joints = np.stack([thigh - trunk, thigh - shank, foot - shank], axis=-1)
    sl = slice(1, n - 1, cfg.oversample)  # drop the extra samples, then decimate
    return dict(angles=angles[sl], rate=rate[sl], force=f[sl], joints=joints[sl],
                phase=phase[sl], hip=hip[:, sl].T, height=height, stride=stride, amp=amp)


def _gauss_markov(rng: np.random.Generator, shape: tuple[int, ...], std: float | np.ndarray,
                  tau_s: float | np.ndarray, dt: float) -> np.ndarray:
    """Stationary first-order Gauss-Markov paths (exact discretisation), time on axis 0."""
    alpha = np.exp(-dt / tau_s)
    drive = std * np.sqrt(1.0 - alpha**2)
    out = np.empty(shape)
    out[0] = std * rng.standard_normal(shape[1:])
    w = rng.standard_normal(shape)
    for k in range(1, shape[0]):
        out[k] = alpha * out[k - 1] + drive * w[k]
    return out


def simulate_gait(n_trials: int, seed: int = 0, config: GaitConfig | None = None) -> GaitTrials:
    """Simulate ``n_trials`` independent walking trials (each a new subject size, stride time,
    excursion scale, sensor biases and noise), deterministically from ``seed``.

    Example:
        >>> trials = simulate_gait(2, seed=0)
        >>> trials.gyro.shape, trials.accel.shape, trials.encoder.shape
        ((2, 1100, 4), (2, 1100, 4, 3), (2, 1100, 3))
    """
    cfg = config or GaitConfig()
    if n_trials < 1:
        raise ValueError(f"simulate_gait: n_trials must be >= 1, got {n_trials}")
    rng = np.random.default_rng(seed)
    dt = 1.0 / cfg.rate_hz
    T = cfg.n_steps
    out: dict[str, list] = {k: [] for k in ("gyro", "accel", "encoder", "angles", "gyro_bias",
                                            "joints", "phase", "height", "stride", "amp")}
    lsb = 2.0 * np.pi / cfg.encoder_counts
    for _ in range(n_trials):
        kin = _trial_kinematics(cfg, rng)
        b_g = _gauss_markov(rng, (T, 4), cfg.gyro_bias_dps * DEG,
                            np.asarray(cfg.gyro_tau_s), dt)
        b_a = _gauss_markov(rng, (T, 4, 3), cfg.accel_bias_mg * 1e-3 * G_M_S2,
                            np.asarray(cfg.accel_tau_s), dt)
        gyro = kin["rate"] - b_g - cfg.gyro_noise_dps * DEG * rng.standard_normal((T, 4))
        accel = (kin["force"] - b_a
                 - cfg.accel_noise_mg * 1e-3 * G_M_S2 * rng.standard_normal((T, 4, 3)))
        th = kin["angles"]
        rel = th[:, :3] - th[:, 1:]
        rel = rel + cfg.encoder_noise_deg * DEG * rng.standard_normal(rel.shape)
        encoder = np.round(rel / lsb) * lsb
        for key, val in (("gyro", gyro), ("accel", accel), ("encoder", encoder),
                         ("angles", th), ("gyro_bias", b_g), ("joints", kin["joints"]),
                         ("phase", kin["phase"]), ("height", kin["height"]),
                         ("stride", kin["stride"]), ("amp", kin["amp"])):
            out[key].append(val)
    dts = np.full((n_trials, T), dt)
    dts[:, 0] = 0.0
    info = {"height_m": np.asarray(out["height"]), "stride_s": np.asarray(out["stride"]),
            "amplitude": np.asarray(out["amp"]), "seed": seed, "config": cfg}
    return GaitTrials(
        dt=dts, gyro=np.stack(out["gyro"]), accel=np.stack(out["accel"]),
        encoder=np.stack(out["encoder"]), angles=np.stack(out["angles"]),
        gyro_bias=np.stack(out["gyro_bias"]), joints=np.stack(out["joints"]),
        phase=np.stack(out["phase"]), info=info,
    )


def reliability(accel: np.ndarray) -> np.ndarray:
    """Eq. 28 as rebuilt: ``rho_i = | |a_i| / g - 1 |`` for every IMU (last axis xyz)."""
    return np.abs(np.linalg.norm(accel, axis=-1) / G_M_S2 - 1.0)


def gated_accel_error(trials: GaitTrials, zeta: float | np.ndarray = 0.01) -> np.ndarray:
    """RMS error (rad) of each IMU's accelerometer angle (Eq. 9) over the samples that Eq. 30
    calls reliable (``rho_i < zeta``): the accelerometer noise the filters really see, mostly
    dynamic acceleration that the modulus test lets through, plus sensor noise and bias.

    Example:
        >>> np.degrees(gated_accel_error(simulate_gait(4, seed=1))).round(0).shape
        (4,)
    """
    rho = reliability(trials.accel)
    ok = rho < np.broadcast_to(np.asarray(zeta, dtype=np.float64), (4,))
    angle = np.arcsin(np.clip(trials.accel[..., 0] / G_M_S2, -1.0, 1.0))
    err2 = np.where(ok, (angle - trials.angles) ** 2, 0.0)
    return np.sqrt(err2.sum(axis=(0, 1)) / np.maximum(ok.sum(axis=(0, 1)), 1))


# ---------------------------------------------------------------------------- to the filter
def gait_series(trials: GaitTrials, dtype=None, index: int | None = None) -> GaitSeries:
    """The filter inputs of simulated ``trials`` (all, or trial ``index``) as JAX arrays."""
    dtype = dtype or jnp.asarray(0.0).dtype
    sl = slice(None) if index is None else index
    return GaitSeries(*(jnp.asarray(getattr(trials, k)[sl], dtype)
                        for k in ("dt", "gyro", "accel", "encoder")))


def matched_markov_params(config: GaitConfig | None = None, *, calibration_trials: int = 20,
                   seed: int = 12345, dtype=None) -> MarkovParams:
    """The simulator's true values (``GaitConfig``) in the filters' terms: the filters'
    assumed parameters at 0 % uncertainty in ``markov_experiment``.

    * ``sigma_g``: the gyro's per-sample noise; ``tau_g``: its bias correlation times
      (Table 2's); ``sigma_bg = s_b sqrt(2 / (tau_g T))``, the driving noise of a
      Gauss-Markov bias of stationary deviation ``s_b`` (per-sample form of Eq. 26);
    * ``sigma_a``: the RMS error of the accelerometer angle over the samples that Eq. 30
      accepts (``gated_accel_error`` on ``calibration_trials`` trials simulated with
      ``seed``, not the experiment's): sensor noise and bias, and the dynamic acceleration
      that the modulus test lets through, which dominates;
    * ``zeta``: Table 2's 0.01; ``sigma_enc``: quantisation (step / sqrt(12)) and noise;
    * ``p0_angle``: the accelerometer angle's error at rest (bias and noise over ``g``);
      ``p0_bias``: the gyro bias's stationary deviation.
    """
    cfg = config or GaitConfig()
    T = 1.0 / cfg.rate_hz
    tau = np.asarray(cfg.gyro_tau_s, dtype=np.float64)
    s_b = cfg.gyro_bias_dps * DEG
    trials = simulate_gait(calibration_trials, seed, cfg)
    step_rad = 2.0 * math.pi / cfg.encoder_counts
    return MarkovParams.from_physical(
        zeta=TABLE2["zeta"],
        sigma_g=cfg.gyro_noise_dps * DEG,
        sigma_bg=s_b * np.sqrt(2.0 / (tau * T)),
        sigma_a=gated_accel_error(trials, np.asarray(TABLE2["zeta"])),
        tau_g=tau,
        sigma_enc=math.hypot(step_rad / math.sqrt(12.0), cfg.encoder_noise_deg * DEG),
        p0_angle=math.hypot(cfg.accel_bias_mg, cfg.accel_noise_mg) * 1e-3,
        p0_bias=s_b,
        dtype=dtype,
    )
