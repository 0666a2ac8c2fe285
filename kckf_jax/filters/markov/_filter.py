"""The Markovian (MJLS) Kalman filter of a lower-limb exoskeleton, and its per-segment baseline.

Dos Santos, Siqueira, Terra, Zanin and Nogueira, "Markov Jump Linear Systems-based filtering for
a lower-limb exoskeleton", Sensors 2014 (docs/other_filters.md). Trunk (B), thigh (T), shank (S)
and foot (F) each carry an IMU; hip, knee and ankle carry encoders. Two filters share one
``markov_step(params, state, inputs, method) -> (state, estimate)``, strung together by
``jax.lax.scan``:

* ``"kf"``: the standard sensor fusion of Sec. 2.2, replicated for each segment: gyro
  integration with a Gauss-Markov bias, corrected by that segment's own accelerometer
  whenever that accelerometer is reliable (Eq. 30 with its own ``zeta``);
* ``"mkf"``: the Markovian KF of Secs. 2.3-3: one error-state model over all segments
  (Eqs. 14-18); each step the mode ``Theta(k)`` (which accelerometer is used) is the IMU whose
  acceleration modulus is closest to gravity (Eqs. 28-29); when that one is reliable
  (Eq. 30) the filter updates with it and the three encoders, otherwise it only predicts.

Equations the extracted paper text lost, rebuilt from the surrounding text and the standard
derivation (each also in docs/other_filters.md):

* Eq. 1-2: ``theta_dot = theta_dot_g + b_g + eta_g``, ``b_g_dot = -b_g / tau_g + eta_bg``
  (consistent with Eq. 7, which subtracts ``theta_hat_dot_g = theta_dot_g + b_hat_g``);
  Eq. 3-4 the same for the accelerometer (``a = a_a + b_a + mu_a``);
* Eq. 5-6: ``theta_hat_dot_g = theta_dot_g + b_hat_g``, ``b_hat_dot_g = -b_hat_g / tau_g``;
* Eq. 9: ``theta_hat_a = arcsin(a_x / g_e)`` (gravity's component on the IMU x axis);
* Eq. 12-13 and 20: ``theta_hat = theta_hat_g + Delta_hat_theta``,
  ``b_hat_g <- b_hat_g + Delta_hat_b`` (the error estimates fed back, then reset to zero);
* Eq. 19: ``x(k+1) = Phi x(k) + G w(k)``, ``y(k) = H(Theta(k)) x(k) + v(k)`` with
  ``Phi = I + A T`` (so per segment ``[[1, T], [0, 1 - T / tau_g]]``) and
  ``G = A^-1 (Phi - I) B = T B``: ``A`` is singular, but ``Phi - I = A T`` makes the product
  ``T I`` whatever the inverse;
* Eq. 21-25, the Kalman filter for a known mode: ``x- = Phi x``, ``P- = Phi P Phi' + G Q G'``,
  ``K = P- H' (H P- H' + R)^-1``, ``x = x- + K (y - H x-)``, ``P = (I - K H) P- (I - K H)' +
  K R K'`` (Joseph form);
* Eq. 26: ``Q = diag(sigma_g_B^2, sigma_bg_B^2, ..., sigma_g_F^2, sigma_bg_F^2)``;
* Eq. 27: ``R(Theta) = diag(sigma_a_Theta^2, sigma_enc_h^2, sigma_enc_k^2, sigma_enc_a^2)``
  (the paper gives only ``sigma_a`` per mode in Table 2; the encoder terms are ours);
* Eq. 28: ``rho_i(k) = | |a_i(k)| / g_e - 1 |`` (in units of ``g``, as the paper's worked
  example with ``zeta = 0.2`` reads); Eq. 29: ``Theta(k) = argmin_i rho_i(k)``,
  ``rho(k) = min_i rho_i(k)``; Eq. 30: reliable when ``rho(k) < zeta`` (the mode's ``zeta``).

Numerics and conventions (ours, not the paper's):

* the filter runs on the full state with the error estimates fed back after every update
  (Eqs. 12-13): for this linear model it is the same filter as the paper's error-state form;
* it carries the state in the coordinates ``z = [L theta, L b]`` with
  ``L theta = [theta_B, theta_B - theta_T, theta_T - theta_S, theta_S - theta_F]``: the trunk
  angle and the three encoder angles (Eq. 17). ``L`` and its inverse are integer matrices. In
  the paper's coordinates the encoder rows need ``var(theta_B - theta_T)``, some 1e-9 rad^2,
  as a difference of variances near 1e-2 rad^2, which float32 cannot hold (its covariance lost
  positive definiteness); here each encoder row reads one coordinate and nothing cancels
  (the same device as the KCKF's, docs/numerics.md). ``to_paper`` maps back;
* the angle is propagated with the trapezoid rule on two gyro rows
  (``theta += T ((w(k-1) + w(k)) / 2 + b)``); the covariance uses ``Phi`` as in Eq. 19. Euler
  integration, as ``Phi`` alone would have it, lags by ``T / 2`` times the rate (up to 2.4 deg
  for the foot and shank in swing at 100 Hz);
* ``R`` is diagonal, so the update is done one scalar row at a time, each in Joseph form, which
  equals the joint update (Eqs. 23-25) and needs no matrix inverse or LAPACK call;
* the state starts at the first row's accelerometer angles (Eq. 9, the trial starts at rest)
  and zero biases, with standard deviations ``p0_angle`` and ``p0_bias`` (not in the paper);
* ``inputs.dt[k] = t[k] - t[k-1]``, ``dt[0] = 0`` (no prediction before the first row).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ..._models._kalman import row_update, symmetrise

DEG = math.pi / 180.0
G_M_S2 = 9.80665
SEGMENTS = ("trunk", "thigh", "shank", "foot")
JOINTS = ("hip", "knee", "ankle")
METHODS = ("kf", "mkf")
N_SEG = len(SEGMENTS)
N_JOINT = len(JOINTS)

#: The paper's Table 2 ("System parameters", from a genetic algorithm, ref. [8]) as printed,
#: per segment (trunk, thigh, shank, foot). The table gives no units; we read the standard
#: deviations in degrees (deg/s, deg/s^2 for the gyro terms, deg for the accelerometer angle),
#: like the paper's figures. The Kalman gains depend only on ratios of ``Q``, ``R`` and ``P0``,
#: so the unit matters only against the terms that Table 2 does not give (encoders, ``P0``).
TABLE2 = {
    "zeta": (0.01, 0.01, 0.01, 0.01),
    "sigma_g_deg": (0.0103, 0.0017, 0.0008, 7.7482),
    "sigma_bg_deg": (0.0003, 0.0005, 9.6405, 18.594),
    "sigma_a_deg": (46.562, 329.08, 100.94, 291.29),
    "tau_g_s": (839.70, 2138.5, 1465.3, 3567.5),
}
#: Encoder angle noise (ours): a 12-bit absolute encoder's quantisation (0.088 deg / sqrt(12))
#: with 0.02 deg of electrical noise.
DEFAULT_SIGMA_ENC_RAD = 0.032 * DEG
#: Initial uncertainty (ours): the accelerometer angle at rest is off by its bias (5 mg is
#: 0.3 deg) and the gyro bias is unknown within its calibrated 0.5 deg/s.
DEFAULT_P0_ANGLE_RAD = 1.0 * DEG
DEFAULT_P0_BIAS_RAD_S = 0.5 * DEG
#: The system-matrix parameters that the Monte Carlo of Fig. 9 perturbs, in the order of the
#: factors ``perturb_markov_params`` takes: sigma_g (4), sigma_bg (4), sigma_a (4), tau_g (4),
#: sigma_enc (3).
N_SYSTEM = 4 * N_SEG + N_JOINT
PUBLISHED_KF_DEG = 1.20
PUBLISHED_MKF_DEG = 0.94


def _log(x) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.log(np.asarray(x, dtype=np.float64))


class MarkovParams(eqx.Module):
    """Learnable parameters of both filters (logs of positive physical values).

    Per segment (``S = 4``: trunk, thigh, shank, foot):

    * ``log_zeta``: reliability threshold of Eq. 30 (a fraction of ``g``; discrete: its
      gradient is zero);
    * ``log_sigma_g`` (rad/s), ``log_sigma_bg`` (rad/s^2): gyro and bias driving noise of
      Eq. 26 (discrete per-sample standard deviations, entering as ``T^2 sigma^2``);
    * ``log_sigma_a`` (rad): accelerometer angle noise of Eq. 27 (``R`` of that mode);
    * ``log_tau_g`` (s): gyro bias correlation time (Eq. 2, ``A`` in Eq. 18);
    * ``log_p0_angle`` (rad), ``log_p0_bias`` (rad/s): initial standard deviations (ours).

    Per joint (``J = 3``: hip, knee, ankle): ``log_sigma_enc`` (rad), encoder noise of Eq. 27.

    Example:
        >>> p = MarkovParams.table2()
        >>> [round(float(x), 1) for x in p.tau_g]
        [839.7, 2138.5, 1465.3, 3567.5]
    """

    log_zeta: Float[Array, " S"]
    log_sigma_g: Float[Array, " S"]
    log_sigma_bg: Float[Array, " S"]
    log_sigma_a: Float[Array, " S"]
    log_tau_g: Float[Array, " S"]
    log_sigma_enc: Float[Array, " J"]
    log_p0_angle: Float[Array, " S"]
    log_p0_bias: Float[Array, " S"]

    def __check_init__(self):
        for name in _LEAVES:
            n = N_JOINT if name == "log_sigma_enc" else N_SEG
            shape = jnp.shape(getattr(self, name))
            if shape != (n,):
                raise ValueError(f"MarkovParams.{name}: expected shape ({n},), got {shape}")

    zeta = property(lambda self: jnp.exp(self.log_zeta))
    sigma_g = property(lambda self: jnp.exp(self.log_sigma_g))
    sigma_bg = property(lambda self: jnp.exp(self.log_sigma_bg))
    sigma_a = property(lambda self: jnp.exp(self.log_sigma_a))
    tau_g = property(lambda self: jnp.exp(self.log_tau_g))
    sigma_enc = property(lambda self: jnp.exp(self.log_sigma_enc))
    p0_angle = property(lambda self: jnp.exp(self.log_p0_angle))
    p0_bias = property(lambda self: jnp.exp(self.log_p0_bias))

    @classmethod
    def from_physical(
        cls,
        *,
        zeta: float | Sequence[float] | np.ndarray,
        sigma_g: float | Sequence[float] | np.ndarray,
        sigma_bg: float | Sequence[float] | np.ndarray,
        sigma_a: float | Sequence[float] | np.ndarray,
        tau_g: float | Sequence[float] | np.ndarray,
        sigma_enc: float | Sequence[float] | np.ndarray = DEFAULT_SIGMA_ENC_RAD,
        p0_angle: float | Sequence[float] | np.ndarray = DEFAULT_P0_ANGLE_RAD,
        p0_bias: float | Sequence[float] | np.ndarray = DEFAULT_P0_BIAS_RAD_S,
        dtype=None,
    ) -> MarkovParams:
        """Build from physical values in rad, rad/s, rad/s^2 and s (scalars broadcast)."""

        def vec(x, n, name):
            arr = np.asarray(x, dtype=np.float64)
            arr = np.broadcast_to(arr, (n,)) if arr.ndim == 0 else arr
            if arr.shape != (n,):
                raise ValueError(f"MarkovParams.from_physical: {name} must be a scalar or have "
                                 f"shape ({n},), got {arr.shape}")
            if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
                raise ValueError(f"MarkovParams.from_physical: {name} must be finite and > 0, "
                                 f"got {arr}")
            return _log(arr)

        dt = dtype or jnp.asarray(0.0).dtype
        values = dict(zeta=zeta, sigma_g=sigma_g, sigma_bg=sigma_bg, sigma_a=sigma_a,
                      tau_g=tau_g, sigma_enc=sigma_enc, p0_angle=p0_angle, p0_bias=p0_bias)
        leaves = {
            f"log_{k}": jnp.asarray(vec(v, N_JOINT if k == "sigma_enc" else N_SEG, k), dt)
            for k, v in values.items()
        }
        return cls(**leaves)

    @classmethod
    def table2(cls, dtype=None) -> MarkovParams:
        """The paper's Table 2 (degrees read as such, converted to rad) with our encoder
        noise and initial covariance."""
        return cls.from_physical(
            zeta=TABLE2["zeta"],
            sigma_g=np.asarray(TABLE2["sigma_g_deg"]) * DEG,
            sigma_bg=np.asarray(TABLE2["sigma_bg_deg"]) * DEG,
            sigma_a=np.asarray(TABLE2["sigma_a_deg"]) * DEG,
            tau_g=TABLE2["tau_g_s"],
            dtype=dtype,
        )

    def astype(self, dtype) -> MarkovParams:
        """The same parameters with every leaf cast to ``dtype``."""
        return eqx.tree_at(lambda p: [getattr(p, f) for f in _LEAVES], self,
                           [jnp.asarray(getattr(self, f), dtype=dtype) for f in _LEAVES])

    def to_dict(self) -> dict:
        """Physical values (lists, per segment or joint) with units in the keys."""
        out = {}
        for name, unit in (("zeta", ""), ("sigma_g", "_rad_s"), ("sigma_bg", "_rad_s2"),
                           ("sigma_a", "_rad"), ("tau_g", "_s"), ("sigma_enc", "_rad"),
                           ("p0_angle", "_rad"), ("p0_bias", "_rad_s")):
            out[name + unit] = np.asarray(getattr(self, name), np.float64).tolist()
        return out


_LEAVES = ("log_zeta", "log_sigma_g", "log_sigma_bg", "log_sigma_a", "log_tau_g",
           "log_sigma_enc", "log_p0_angle", "log_p0_bias")
_SYSTEM_LEAVES = ("log_sigma_g", "log_sigma_bg", "log_sigma_a", "log_tau_g", "log_sigma_enc")


def perturb_markov_params(params: MarkovParams, factors: Float[Array, " K"]) -> MarkovParams:
    """``params`` with every system-matrix parameter multiplied by its factor.

    ``factors`` (``N_SYSTEM``): sigma_g (4), sigma_bg (4), sigma_a (4), tau_g (4), sigma_enc (3),
    i.e. the components of ``Phi``, ``Q`` and ``R`` (Fig. 9: "varying the components of the
    system matrices"). Traceable: use it inside ``jax.vmap`` to build a batch of parameters.
    """
    if factors.shape != (N_SYSTEM,):
        raise ValueError(f"perturb_markov_params: factors must have shape ({N_SYSTEM},), "
                         f"got {factors.shape}")
    logs = jnp.log(factors.astype(params.log_tau_g.dtype))
    parts = (logs[0:4], logs[4:8], logs[8:12], logs[12:16], logs[16:19])
    return eqx.tree_at(lambda p: [getattr(p, f) for f in _SYSTEM_LEAVES], params,
                       [getattr(params, f) + d for f, d in zip(_SYSTEM_LEAVES, parts)])


# ---------------------------------------------------------------------------- data types
class GaitSeries(eqx.Module):
    """Filter inputs: one row (no leading axis), one trial (``T``) or a batch (``B T``).

    * ``dt``: s since the previous row (0 for the first);
    * ``gyro`` (``S``): rad/s, one axis per IMU (trunk, thigh, shank, foot);
    * ``accel`` (``S 3``): m/s^2, IMU x (Eq. 9's axis), y, z;
    * ``encoder`` (``J``): rad, the paper's relative angles (Eq. 17): trunk - thigh,
      thigh - shank, shank - foot.
    """

    dt: Float[ArrayLike, "*T"]
    gyro: Float[ArrayLike, "*T S"]
    accel: Float[ArrayLike, "*T S 3"]
    encoder: Float[ArrayLike, "*T J"]


class MarkovState(eqx.Module):
    """What a step carries: ``z = [u, v]`` (rad, rad/s), the state in the filter's
    coordinates (``u = L theta``, ``v = L b``; ``to_paper`` gives Eq. 16's ``x``), its
    covariance ``P`` and the previous row's gyro rates."""

    z: Float[Array, " N"]
    P: Float[Array, "N N"]
    gyro_prev: Float[Array, " S"]


class MarkovEstimate(eqx.Module):
    """Per-step output, segments in ``SEGMENTS`` order.

    ``angles`` (rad, Eq. 20), ``angle_std`` (rad), ``bias`` (rad/s); ``rho``: Eq. 28 for every
    IMU; ``mode``: Eq. 29's ``argmin`` (the MKF's Markov state, also given for ``kf``);
    ``updated``: which accelerometers corrected the estimate at this step.
    """

    angles: Float[Array, "*T S"]
    angle_std: Float[Array, "*T S"]
    bias: Float[Array, "*T S"]
    rho: Float[Array, "*T S"]
    mode: Int[Array, "*T"]
    updated: Bool[Array, "*T S"]


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")


# ---------------------------------------------------------------------------- sensor models
def accel_angle(accel: Float[Array, "*b S 3"]) -> Float[Array, "*b S"]:
    """Eq. 9: ``theta_a = arcsin(a_x / g)`` (clipped to +-90 deg when dynamic acceleration
    makes ``|a_x| > g``)."""
    return jnp.arcsin(jnp.clip(accel[..., 0] / G_M_S2, -1.0, 1.0))


def reliability(accel: Float[Array, "*b S 3"]) -> Float[Array, "*b S"]:
    """Eq. 28: ``rho_i = | |a_i| / g - 1 |``, the distance of each IMU's acceleration
    modulus from gravity (a fraction of ``g``)."""
    # The floor keeps the norm's gradient finite for an all-zero reading.
    norm = jnp.sqrt(jnp.maximum(jnp.sum(accel**2, axis=-1), 1e-30))
    return jnp.abs(norm / G_M_S2 - 1.0)


# ---------------------------------------------------------------------------- filter
#: Filter coordinates (see the module docstring): ``u = L theta = [theta_B, theta_B - theta_T,
#: theta_T - theta_S, theta_S - theta_F]``, the trunk angle and the three encoder angles
#: (Eq. 17), and the same map for the biases. ``L`` and its inverse are integer matrices, so the
#: change of coordinates itself adds no round-off.
_L = np.array([[1, 0, 0, 0], [1, -1, 0, 0], [0, 1, -1, 0], [0, 0, 1, -1]], dtype=np.int64)
_LINV = np.array([[1, 0, 0, 0], [1, -1, 0, 0], [1, -1, -1, 0], [1, -1, -1, -1]],
                 dtype=np.int64)
#: ``M`` maps the paper's ``x = [theta_B, b_B, ..., theta_F, b_F]`` (Eq. 16) to ``z = [u, v]``.
_M = np.zeros((2 * N_SEG, 2 * N_SEG), dtype=np.int64)
_M[:N_SEG, 0::2] = _L
_M[N_SEG:, 1::2] = _L
_MINV = np.zeros_like(_M)
_MINV[0::2, :N_SEG] = _LINV
_MINV[1::2, N_SEG:] = _LINV


def to_paper(z: Float[Array, "*b N"], P: Float[Array, "*b N N"]
             ) -> tuple[Float[Array, "*b N"], Float[Array, "*b N N"]]:
    """The state and covariance in the paper's coordinates (Eq. 16) from the filter's."""
    Minv = jnp.asarray(_MINV, z.dtype)
    return z @ Minv.T, Minv @ P @ Minv.T


def markov_init(params: MarkovParams, first: GaitSeries) -> MarkovState:
    """The state at the first row: angles from its accelerometers (Eq. 9; the trial starts at
    rest), zero biases, covariance ``diag(p0_angle^2, p0_bias^2)`` per segment (in the
    paper's coordinates; carried in the filter's)."""
    dtype = params.log_tau_g.dtype
    L = jnp.asarray(_L, dtype)
    theta = accel_angle(jnp.asarray(first.accel, dtype))
    z = jnp.concatenate([L @ theta, jnp.zeros(N_SEG, dtype)])
    Pu = L @ jnp.diag(params.p0_angle**2) @ L.T
    Pv = L @ jnp.diag(params.p0_bias**2) @ L.T
    zero = jnp.zeros((N_SEG, N_SEG), dtype)
    P = jnp.block([[Pu, zero], [zero, Pv]])
    return MarkovState(z, P, jnp.asarray(first.gyro, dtype))


def predict(
    params: MarkovParams, state: MarkovState, dt: Float[Array, ""], gyro: Float[Array, " S"]
) -> MarkovState:
    """Eqs. 21-22 over ``dt`` seconds in the filter's coordinates: ``z = F z + T L w``,
    ``P = F P F' + T^2 M Q M'`` with ``F = M Phi M^-1`` (Eqs. 18-19, 26); the angles are
    integrated with the trapezoid rule on the previous and this row's rates."""
    dtype = state.z.dtype
    L, Linv = jnp.asarray(_L, dtype), jnp.asarray(_LINV, dtype)
    rate = 0.5 * (state.gyro_prev + gyro)
    u, v = state.z[:N_SEG], state.z[N_SEG:]
    # Bias decay in the new coordinates: L (I - dt diag(1/tau)) L^-1 = I - dt L diag(1/tau) L^-1.
    Fb = jnp.eye(N_SEG, dtype=dtype) - dt * (L @ (Linv / params.tau_g[:, None]))
    z = jnp.concatenate([u + dt * (L @ rate + v), Fb @ v])
    eye = jnp.eye(N_SEG, dtype=dtype)
    F = jnp.block([[eye, dt * eye], [jnp.zeros_like(eye), Fb]])
    Qu = L @ jnp.diag(params.sigma_g**2) @ L.T
    Qv = L @ jnp.diag(params.sigma_bg**2) @ L.T
    zero = jnp.zeros_like(eye)
    P = F @ state.P @ F.T + (dt**2) * jnp.block([[Qu, zero], [zero, Qv]])
    return MarkovState(z, P, gyro)


def markov_step(
    params: MarkovParams, state: MarkovState, inputs: GaitSeries, method: str = "mkf"
) -> tuple[MarkovState, MarkovEstimate]:
    """One row of ``method`` (``"kf"`` or ``"mkf"``, static): predict, choose, update.

    Pure and jit-friendly; the mode is data (``argmin`` on traced values, masks), never Python
    control flow, so the step is differentiable in every parameter except ``zeta``.
    """
    _check_method(method)
    dtype = state.z.dtype
    dt = jnp.asarray(inputs.dt, dtype)
    gyro = jnp.asarray(inputs.gyro, dtype)
    accel = jnp.asarray(inputs.accel, dtype)
    enc = jnp.asarray(inputs.encoder, dtype)
    st = predict(params, state, dt, gyro)
    z, P = st.z, st.P
    rho = reliability(accel)
    theta_a = accel_angle(accel)
    mode = jnp.argmin(rho).astype(jnp.int32)  # Eq. 29
    r_a = params.sigma_a**2
    # Row i of H for segment i's angle: theta_i = (L^-1 u)_i.
    H_angle = jnp.concatenate([jnp.asarray(_LINV, dtype), jnp.zeros((N_SEG, N_SEG), dtype)],
                              axis=1)
    if method == "kf":
        # Sec. 2.2 per segment: each accelerometer corrects its own segment when reliable.
        updated = rho < params.zeta
        for i in range(N_SEG):
            z, P = row_update(z, P, H_angle[i], theta_a[i], r_a[i], updated[i])
    else:
        # Eqs. 27-30: the mode's accelerometer, then the encoders, or nothing at all.
        reliable = rho[mode] < params.zeta[mode]
        updated = (jnp.arange(N_SEG) == mode) & reliable
        z, P = row_update(z, P, H_angle[mode], theta_a[mode], r_a[mode], reliable)
        for j in range(N_JOINT):
            h = jnp.zeros(2 * N_SEG, dtype).at[j + 1].set(1.0)  # u_{j+1} is encoder j
            z, P = row_update(z, P, h, enc[j], params.sigma_enc[j] ** 2, reliable)
    P = symmetrise(P)
    Linv = jnp.asarray(_LINV, dtype)
    var = jnp.sum((Linv @ P[:N_SEG, :N_SEG]) * Linv, axis=1)
    # The floor keeps sqrt's gradient finite if a variance ever rounds to zero.
    est = MarkovEstimate(Linv @ z[:N_SEG],
                         jnp.sqrt(jnp.maximum(var, jnp.finfo(dtype).tiny)),
                         Linv @ z[N_SEG:], rho, mode, updated)
    return MarkovState(z, P, gyro), est


def scan_markov(
    params: MarkovParams, series: GaitSeries, method: str = "mkf",
    state: MarkovState | None = None,
) -> tuple[MarkovState, MarkovEstimate]:
    """``lax.scan`` of ``step`` over one trial (not jitted: the building block of
    ``run_markov``, the experiment and the fitting loss)."""
    _check_method(method)
    series = jax.tree_util.tree_map(lambda a: jnp.asarray(a, params.log_tau_g.dtype), series)
    if state is None:
        state = markov_init(params, jax.tree_util.tree_map(lambda a: a[0], series))

    def body(carry, row):
        return markov_step(params, carry, row, method)

    return jax.lax.scan(body, state, series)


@eqx.filter_jit
def run_markov(
    params: MarkovParams, series: GaitSeries, method: str = "mkf",
    state: MarkovState | None = None,
) -> tuple[MarkovState, MarkovEstimate]:
    """Filter one trial: ``lax.scan`` of ``step`` over the rows of ``series``.

    Args:
        params: the filter parameters (their dtype sets the precision).
        series: one trial, ``dt`` of shape (T,). ``jax.vmap`` over a batch of trials
            (``markov_batch`` does it).
        method: ``"mkf"`` (Markovian KF) or ``"kf"`` (per-segment KF).
        state: the starting state (default: ``markov_init`` on the first row).

    Returns:
        The final state and a ``MarkovEstimate`` with a leading time axis.

    Example:
        >>> from kckf_jax.filters import gait_series, simulate_gait
        >>> trial = gait_series(simulate_gait(1, seed=0), index=0)
        >>> final, est = run_markov(MarkovParams.table2(), trial, "mkf")
        >>> est.angles.shape
        (1100, 4)
    """
    return scan_markov(params, series, method, state)


@eqx.filter_jit
def markov_batch(params: MarkovParams, series: GaitSeries, method: str = "mkf",
                 batched_params: bool = False) -> MarkovEstimate:
    """``run_markov`` over a batch of trials (leading axis ``B``); with ``batched_params``
    every leaf of ``params`` has a leading ``B`` too (one parameter set per trial)."""
    _check_method(method)
    axis = 0 if batched_params else None
    return jax.vmap(lambda p, s: scan_markov(p, s, method)[1], in_axes=(axis, 0))(
        params, series)


# ---------------------------------------------------------------------------- helpers
def mean_error_deg(angles: Float[Array, "*b T S"], truth: Float[Array, "*b T S"]
                   ) -> Float[Array, "*b"]:
    """The figure of merit of Fig. 9: mean absolute angle error (deg) over steps and
    segments."""
    return jnp.mean(jnp.abs(angles - truth), axis=(-2, -1)) / DEG


def markov_loss(params: MarkovParams, series: GaitSeries, truth: Float[Array, "B T S"],
                method: str = "mkf") -> Float[Array, ""]:
    """RMS angle error (rad) over trials, steps and segments: the fitting loss."""
    est = jax.vmap(lambda s: scan_markov(params, s, method)[1])(series)
    return jnp.sqrt(jnp.mean((est.angles - truth) ** 2) + 1e-18)


