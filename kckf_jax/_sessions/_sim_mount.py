"""Gyros as they are worn, for the simulator: each gyro board tilted on its link, and moving on
it where its mount is soft (docs/simulator.md, "Sensor effects").

* **Tilt** (``SimConfig.gyro_mount_deg``): a board strapped or glued onto a link sits a few
  degrees off the link's axes, so it reads the link's rate in its own frame, ``R' omega``. Each
  link's ``R`` turns by ``gyro_mount_deg * U(0.5, 1)`` about an axis drawn uniformly on the
  sphere, per device.
* **Soft mount** (``SimConfig.soft_mount_hz``): on soft material the board is a small mass on
  a rotational spring and damper against its link, the second-order model of a sensor on soft
  tissue (Wright et al., Biomed. Signal Process. Control 70, 102986, 2021; skin markers on the
  leg resonate at 23-51 Hz depending on their mass, Karlsson & Tranberg, J. Biomech. 32(12),
  1999). Its rotation ``phi`` against the link, per axis, follows

      phi'' + 2 zeta w phi' + w^2 phi = -alpha_link,   w = 2 pi f,

  driven by the link's angular acceleration ``alpha_link`` (the board lags when the link
  speeds up), and the gyro reads ``omega + phi'``. ``f`` is ``soft_mount_hz * U(0.8, 1.2)``
  per link and device; ``zeta`` is ``soft_mount_damping`` (0.3: an assumption, underdamped as
  in Wright et al.). Integrated exactly for an input held over each sample step.

Both are drawn from a random stream of their own, so turning them on moves no other draw.
"""

from __future__ import annotations

import numpy as np

DEG = np.pi / 180.0


def mount_rotations(rng: np.random.Generator, n_links: int, size_deg: float) -> np.ndarray:
    """Each link's board tilt as a rotation vector (``L, 3``, rad): angle ``size_deg * U(0.5,
    1)`` about a uniformly drawn axis."""
    axis = rng.standard_normal((n_links, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis * (size_deg * DEG * rng.uniform(0.5, 1.0, n_links))[:, None]


def rotation_matrices(v: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotations (``... 3 3``) of rotation vectors ``v`` (``... 3``, rad)."""
    angle = np.linalg.norm(v, axis=-1)[..., None, None]
    k = v / np.where(angle[..., 0] > 0, angle[..., 0], 1.0)
    K = np.zeros(v.shape + (3,))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def soft_mount_rates(t: np.ndarray, link_rate: np.ndarray, f_hz: np.ndarray,
                     zeta: float) -> tuple[np.ndarray, np.ndarray]:
    """The rate (``T, L, 3``, rad/s) and angle (rad) of each board against its link, from the
    links' rates (``T, L, 3``) at times ``t``: the spring and damper of the module docstring,
    each link's natural frequency ``f_hz`` (``L``), driven by the link's acceleration held
    over each step (its exact solution then: no step-size limit)."""
    if not 0 < zeta < 1:
        raise ValueError(f"soft mount: the damping ratio must be in (0, 1) (underdamped), got "
                         f"{zeta}")
    alpha = np.gradient(link_rate, t, axis=0)
    h = np.diff(t)[:, None]  # (T-1, 1)
    w = 2 * np.pi * np.asarray(f_hz, float)[None, :]  # (1, L)
    wd = w * np.sqrt(1 - zeta**2)
    e = np.exp(-zeta * w * h)
    c, s = np.cos(wd * h), np.sin(wd * h) / wd
    # x' = M x + [0, 1] u, M = [[0, 1], [-w^2, -2 zeta w]]: A = exp(M h), B its held input's.
    a00, a01 = e * (c + s * zeta * w), e * s
    a10, a11 = -e * s * w**2, e * (c - s * zeta * w)
    b0, b1 = (1 - e * (c + s * zeta * w)) / w**2, e * s
    phi = np.zeros(link_rate.shape)
    rate = np.zeros(link_rate.shape)
    x0 = np.zeros(link_rate.shape[1:])
    x1 = np.zeros(link_rate.shape[1:])
    for k in range(len(t) - 1):
        u = -alpha[k]
        x0, x1 = (a00[k, :, None] * x0 + a01[k, :, None] * x1 + b0[k, :, None] * u,
                  a10[k, :, None] * x0 + a11[k, :, None] * x1 + b1[k, :, None] * u)
        phi[k + 1], rate[k + 1] = x0, x1
    return rate, phi
