"""The static layout of a serial-link robot and the index maps derived from it.

A robot has ``n`` joints and ``n + 1`` links (link 1 is the base, link ``n + 1`` the end
effector). Joint ``i`` connects links ``i`` and ``i + 1`` and rotates about one or more of the
axes ``x``, ``y``, ``z``. Every link carries a 3-axis gyroscope; every active joint axis carries
two Hall sensors, ``l`` and ``r``. The torso angle ``phi`` has one component per axis that at
least one joint rotates about (paper Eq. 14: ``phi = sum_i theta_i``).

Everything here is plain Python/NumPy, computed once per layout: the filters use it as static
structure, never as traced data.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Robot:
    """The joint layout of a wearable serial-link robot.

    Args:
        joints: one tuple of active axes per joint, joint 1 first, e.g.
            ``(("x",), ("y",), ("x",), ("y",))`` for the paper's bench robot.

    The derived names and index maps follow the session format
    (``../shared/spec/session-format.md``) and the paper's state ordering (Eq. 7):

    * angle coordinates (``K = J + P``): every active joint axis ``theta{i}_{a}`` (``J`` of
      them, joint by joint, axes in x, y, z order), then every torso axis ``phi_{a}`` (``P``);
    * Hall sensors (``M = 2 J``): ``hall{i}_{a}_l`` then ``hall{i}_{a}_r`` for each joint axis
      (paper Eq. 5);
    * gyroscopes: ``gyro{L}_{a}`` for links ``L = 1 .. n + 1`` and all three axes.

    Example:
        >>> robot = Robot.from_spec("x,y,x,y")
        >>> robot.angle_names
        ('theta1_x', 'theta2_y', 'theta3_x', 'theta4_y', 'phi_x', 'phi_y')
    """

    joints: tuple[tuple[str, ...], ...]

    def __post_init__(self):
        if not isinstance(self.joints, tuple) or not self.joints:
            raise ValueError(
                f"Robot.joints must be a non-empty tuple of axis tuples, got {self.joints!r}"
            )
        for i, axes in enumerate(self.joints, start=1):
            if not isinstance(axes, tuple) or not axes:
                raise ValueError(f"joint {i} must have at least one active axis, got {axes!r}")
            for a in axes:
                if a not in AXES:
                    raise ValueError(
                        f"joint {i}: unknown axis {a!r}; expected one of 'x', 'y', 'z'"
                    )
            if len(set(axes)) != len(axes):
                raise ValueError(f"joint {i}: axis listed twice in {axes!r}")
            if list(axes) != sorted(axes):
                raise ValueError(f"joint {i}: axes must be in x, y, z order, got {axes!r}")

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_spec(cls, spec: str) -> Robot:
        """Parse ``"x,y,x,y"`` (one token per joint; a token may hold several axes: ``"xyz"``)."""
        tokens = [tok.strip().lower() for tok in spec.split(",")]
        if not spec.strip() or any(not tok for tok in tokens):
            raise ValueError(
                f"joint layout {spec!r}: expected comma-separated axes per joint, e.g. 'x,y,x,y'"
                " or 'xyz,xyz'"
            )
        joints = []
        for i, tok in enumerate(tokens, start=1):
            bad = [c for c in tok if c not in AXES]
            if bad:
                raise ValueError(
                    f"joint layout {spec!r}: joint {i} has unknown axis {bad[0]!r}; "
                    "expected letters from 'xyz'"
                )
            joints.append(tuple(a for a in AXES if a in tok))
            if len(joints[-1]) != len(tok):
                raise ValueError(f"joint layout {spec!r}: joint {i} lists an axis twice")
        return cls(tuple(joints))

    @classmethod
    def from_meta(cls, joints: object, where: str = "meta.json") -> Robot:
        """Build from the ``joints`` entry of a session's ``meta.json``."""
        if not isinstance(joints, list) or not joints:
            raise ValueError(f"{where}: 'joints' must be a non-empty list, got {joints!r}")
        out = []
        for i, j in enumerate(joints, start=1):
            axes = j.get("axes") if isinstance(j, dict) else None
            if not isinstance(axes, list) or not axes or not all(isinstance(a, str) for a in axes):
                raise ValueError(
                    f"{where}: joint {i} (joints[{i - 1}]) must look like {{\"axes\": [\"x\"]}}, "
                    f"got {j!r}"
                )
            for a in axes:
                if a not in AXES:
                    raise ValueError(
                        f"{where}: joint {i} (joints[{i - 1}]) has unknown axis {a!r}; expected "
                        "'x', 'y' or 'z'"
                    )
            out.append(tuple(a for a in AXES if a in axes))
        return cls(tuple(out))

    def to_meta(self) -> list[dict]:
        return [{"axes": list(axes)} for axes in self.joints]

    @property
    def spec(self) -> str:
        return ",".join("".join(axes) for axes in self.joints)

    # ------------------------------------------------------------------ sizes
    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def n_links(self) -> int:
        return len(self.joints) + 1

    @functools.cached_property
    def joint_axes(self) -> tuple[tuple[int, str], ...]:
        """``(joint, axis)`` for every active joint axis, joint numbers from 1."""
        return tuple((i, a) for i, axes in enumerate(self.joints, start=1) for a in axes)

    @functools.cached_property
    def torso_axes(self) -> tuple[str, ...]:
        used = {a for axes in self.joints for a in axes}
        return tuple(a for a in AXES if a in used)

    @property
    def n_joint_axes(self) -> int:
        """``J``: active joint axes."""
        return len(self.joint_axes)

    @property
    def n_torso_axes(self) -> int:
        """``P``: torso axes."""
        return len(self.torso_axes)

    @property
    def n_angles(self) -> int:
        """``K = J + P``: estimated angles (joint axes, then torso axes)."""
        return self.n_joint_axes + self.n_torso_axes

    @property
    def n_states(self) -> int:
        """``N = 2 K``: the paper's state (Eq. 7) restricted to active axes."""
        return 2 * self.n_angles

    @property
    def n_hall(self) -> int:
        """``M = 2 J``: Hall sensors."""
        return 2 * self.n_joint_axes

    # ------------------------------------------------------------------ names
    @functools.cached_property
    def joint_angle_names(self) -> tuple[str, ...]:
        return tuple(f"theta{i}_{a}" for i, a in self.joint_axes)

    @functools.cached_property
    def torso_angle_names(self) -> tuple[str, ...]:
        return tuple(f"phi_{a}" for a in self.torso_axes)

    @functools.cached_property
    def angle_names(self) -> tuple[str, ...]:
        return self.joint_angle_names + self.torso_angle_names

    @functools.cached_property
    def hall_names(self) -> tuple[str, ...]:
        return tuple(f"hall{i}_{a}_{s}" for i, a in self.joint_axes for s in ("l", "r"))

    @functools.cached_property
    def gyro_names(self) -> tuple[str, ...]:
        """Row-major over ``(link, axis)``: ``gyro1_x, gyro1_y, gyro1_z, gyro2_x, ...``."""
        return tuple(f"gyro{L}_{a}" for L in range(1, self.n_links + 1) for a in AXES)

    # ------------------------------------------------------------------ index maps
    @functools.cached_property
    def hall_joint_axis(self) -> np.ndarray:
        """For every Hall sensor, the index of the joint axis (0 .. J-1) it measures."""
        return np.repeat(np.arange(self.n_joint_axes), 2)

    @functools.cached_property
    def hall_side_sign(self) -> tuple[int, ...]:
        """The default sign of each sensor's model: +1 for ``l``, -1 for ``r``."""
        return tuple(1 if s == "l" else -1 for _ in self.joint_axes for s in ("l", "r"))

    @functools.cached_property
    def torso_sum(self) -> np.ndarray:
        """``S`` (P x J): ``phi = S @ theta`` (Eq. 14), ``S[p, j] = 1`` when axes match."""
        s = np.zeros((self.n_torso_axes, self.n_joint_axes))
        for j, (_, a) in enumerate(self.joint_axes):
            s[self.torso_axes.index(a), j] = 1.0
        return s

    @functools.cached_property
    def rate_map(self) -> np.ndarray:
        """``W`` (K x 3(n+1)): angle rates from the flattened gyro vector (Eqs. 2, 9, 10).

        Row of joint axis ``(i, a)``: ``omega_{i+1,a} - omega_{i,a}``; row of torso axis ``a``:
        ``omega_{n+1,a} - omega_{1,a}``.
        """
        w = np.zeros((self.n_angles, 3 * self.n_links))
        for k, (i, a) in enumerate(self.joint_axes):
            ax = AXES.index(a)
            w[k, 3 * i + ax] += 1.0  # link i + 1 (0-based i)
            w[k, 3 * (i - 1) + ax] -= 1.0  # link i
        for p, a in enumerate(self.torso_axes):
            ax = AXES.index(a)
            w[self.n_joint_axes + p, 3 * (self.n_links - 1) + ax] += 1.0
            w[self.n_joint_axes + p, ax] -= 1.0
        return w

    @functools.cached_property
    def rate_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """``(plus, minus)``: angle rate ``k`` is ``u[plus[k]] - u[minus[k]]`` (``rate_map``)."""
        w = self.rate_map
        return np.argmax(w > 0, axis=1), np.argmax(w < 0, axis=1)

    @functools.cached_property
    def used_gyro_index(self) -> np.ndarray:
        """The indices (into ``gyro_names``) of the gyro columns the filters read: those with a
        non-zero in ``rate_map``, in column order."""
        return np.flatnonzero(np.any(self.rate_map != 0.0, axis=0))

    @functools.cached_property
    def used_gyro_columns(self) -> tuple[str, ...]:
        """The names of the gyro columns the filters read (``used_gyro_index``)."""
        return tuple(self.gyro_names[i] for i in self.used_gyro_index)

    @functools.cached_property
    def gyro_stand_ins(self) -> tuple[tuple[int, ...], ...]:
        """Per gyro channel (``gyro_names`` order), the channels that measure the same rate
        under the paper's model (Sec. 2.3: rotations add per axis): the gyros about the same
        axis on the links that no joint about that axis separates from this one, nearest
        first (the base link's side first on a tie). A missing or faulty reading of a channel
        the filters read takes the first of these that is there (``_screen``), so a dropped
        or saturated gyro costs only what it must.

        Example:
            >>> Robot.from_spec("x,y,x,y").gyro_stand_ins[9]  # gyro4_x: link 5 turns with it
            (12,)
        """
        n_links = self.n_links
        out = []
        for link in range(n_links):
            for ax, a in enumerate(AXES):
                # joint i (0-based) joins links i and i + 1; one about ``a`` separates them.
                cut = [a in axes for axes in self.joints]
                lo = link
                while lo > 0 and not cut[lo - 1]:
                    lo -= 1
                hi = link
                while hi < n_links - 1 and not cut[hi]:
                    hi += 1
                mates = sorted((L for L in range(lo, hi + 1) if L != link),
                               key=lambda L, link=link: (abs(L - link), L))
                out.append(tuple(3 * L + ax for L in mates))
        return tuple(out)

    def __repr__(self) -> str:
        return f"Robot.from_spec({self.spec!r})"
