"""The filters kckf-jax runs, as model objects: one class per filter and one table of their
names (``MODELS``), which the command's ``--method`` and the API's ``method`` look up.

Every module asks the model what it needs, never its name: what kind of filter it is (its
class: ``_kernel``'s ``init_state`` and ``step`` compute it by that), whether it is a Kalman
filter (a covariance: innovations, likelihood, smoother, fit), whether its matrices depend on
the state (``state_dependent``: no layout precomputes them), whether two gyro channels read
one rate under it (``gyro_pairs``: the stand-ins and the monitor's bias-step pairs), which
angles it estimates (``torso``) and why the fixed-point paths do not apply to it
(``layout_reason``, ``unobservable``).

* ``KCKF`` (``"kckf"``): the Kinematically Constrained KF (paper Sec. 3.2): Hall updates plus
  the forward-kinematics constraint ``sum theta = phi`` as a perfect measurement;
* ``KF`` (``"kf"``): the same filter without the constraint (the paper's "Std KF");
* ``Gyro`` (``"gyro"``): integrated gyro differences (Eq. 2), from zero (the neutral pose);
* ``HallL``, ``HallR`` (``"hall_l"``, ``"hall_r"``): one side's Hall sensor alone through Eq. 1
  (a missing reading holds the last one); they give no torso angle;
* ``ExactKCKF`` (``"kckf3d"``): the KCKF on the chain's exact kinematics (finite rotations:
  ``_exact.py``), for robots that turn about more than one axis; to first order in the
  angles it is ``"kckf"``.

The API takes the object itself where it takes a name (``model_of``, ``method_name``;
``register_model`` adds one to the table). The steps themselves are ``_kernel``'s, which asks
the model what it is (its class and the attributes above): this module sits below the kernel
and imports only the model's matrices (``_model``, ``_exact``).
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import numpy as np

from ._blocks import Structure, block_structure
from ._exact import exact_model


class AbstractModel(eqx.Module):
    """A filter: what every path, the smoother, the likelihood, the monitor, the stream and
    the export ask of it (``_kernel``'s ``init_state`` and ``step`` are built from its class
    and these).

    Attributes (class variables):
        name: the command's ``--method`` and the key of ``MODELS``.
        label: its column in the paper's Table 1 layout.
        kalman: a Kalman filter (a covariance: innovations, likelihood, smoother, fit).
        torso: it estimates the torso angles (the Hall baselines do not).
        gyro_pairs: two gyro channels read the same rate under its model (the paper's first
            order: ``_screen.stand_ins``; under the exact kinematics none do).
        state_dependent: its matrices depend on the state (linearised each step).
        unobservable: what it cannot observe, where that keeps its covariance from
            converging (``None``: it converges).
        line: how a plot draws it: ``"filter"``, ``"integrated"`` (drifts) or ``"sensor"``.
    """

    name: eqx.AbstractClassVar[str]
    label: eqx.AbstractClassVar[str]
    kalman: eqx.AbstractClassVar[bool]
    torso: ClassVar[bool] = True
    gyro_pairs: ClassVar[bool] = True
    state_dependent: ClassVar[bool] = False
    unobservable: ClassVar[str | None] = None
    line: ClassVar[str] = "filter"

    def estimated(self, robot) -> np.ndarray:
        """Which of ``robot.angle_names`` it estimates (``K`` bools)."""
        out = np.ones(robot.n_angles, bool)
        if not self.torso:
            out[robot.n_joint_axes:] = False
        return out

    def layout_reason(self) -> str | None:
        """Why the paths that precompute the linear Kalman filters' block maps (lanes,
        steady, segments, parallel) do not apply to it, or ``None``."""
        return f"method {self.name!r} is not a Kalman filter"


class AbstractKalman(AbstractModel):
    """A Kalman filter (``_kernel.kalman_step_moments``)."""

    kalman: ClassVar[bool] = True

    @abc.abstractmethod
    def smoother_structure(self, robot):
        """What the RTS smoother's rows need of the model (``_rts.rts_rows``)."""

    @abc.abstractmethod
    def innovation_channels(self, robot) -> np.ndarray:
        """The joint axis of each innovation slot (``Nb x m``; -1: padding)."""


class AbstractLinearKalman(AbstractKalman):
    """The paper's linear filters: constant block matrices (``_blocks.block_structure``)."""

    constrained: eqx.AbstractClassVar[bool]

    def layout_reason(self) -> str | None:
        return None

    def structure(self, robot) -> Structure:
        """Its constant block matrices for ``robot``."""
        return block_structure(robot, self.constrained)

    def smoother_structure(self, robot):
        return self.structure(robot)

    def innovation_channels(self, robot) -> np.ndarray:
        return self.structure(robot).joint_index


class KCKF(AbstractLinearKalman):
    """The Kinematically Constrained Kalman Filter (paper Sec. 3.2)."""

    name: ClassVar[str] = "kckf"
    label: ClassVar[str] = "KCKF"
    constrained: ClassVar[bool] = True


class KF(AbstractLinearKalman):
    """The standard Kalman filter: the KCKF without its constraint."""

    name: ClassVar[str] = "kf"
    label: ClassVar[str] = "Std KF"
    constrained: ClassVar[bool] = False
    unobservable: ClassVar[str | None] = (
        "the standard KF's torso angle and bias are unobservable (Eq. 21)")


class ExactKCKF(AbstractKalman):
    """The KCKF on the chain's exact kinematics (``_exact``), one block."""

    name: ClassVar[str] = "kckf3d"
    label: ClassVar[str] = "KCKF 3D"
    gyro_pairs: ClassVar[bool] = False
    state_dependent: ClassVar[bool] = True

    def layout_reason(self) -> str | None:
        return ("the exact model's matrices depend on the state (kckf3d linearises every "
                "step at its estimate): no layout precomputes them; sequential only")

    def smoother_structure(self, robot):
        return exact_model(robot)

    def innovation_channels(self, robot) -> np.ndarray:
        return np.arange(robot.n_joint_axes)[None]


class Gyro(AbstractModel):
    """Integrated gyro differences (Eq. 2), from the neutral pose."""

    name: ClassVar[str] = "gyro"
    label: ClassVar[str] = "Gyro"
    kalman: ClassVar[bool] = False
    line: ClassVar[str] = "integrated"


class AbstractHall(AbstractModel):
    """One side's Hall sensor alone through Eq. 1 (a missing reading holds the last one)."""

    side: eqx.AbstractClassVar[int]
    kalman: ClassVar[bool] = False
    torso: ClassVar[bool] = False
    line: ClassVar[str] = "sensor"


class HallL(AbstractHall):
    name: ClassVar[str] = "hall_l"
    label: ClassVar[str] = "Hall l"
    side: ClassVar[int] = 0


class HallR(AbstractHall):
    name: ClassVar[str] = "hall_r"
    label: ClassVar[str] = "Hall r"
    side: ClassVar[int] = 1


#: The one table: each method's name to its model, in the command's order.
MODELS: dict[str, AbstractModel] = {
    m.name: m for m in (KCKF(), KF(), Gyro(), HallL(), HallR(), ExactKCKF())}
#: The built-in methods' names (``--method``).
METHODS = tuple(MODELS)
#: The built-in Kalman methods: a covariance, a likelihood, a smoother.
KALMAN_METHODS = tuple(n for n, m in MODELS.items() if m.kalman)


def model_of(method: str | AbstractModel) -> AbstractModel:
    """The model a method names (``MODELS``), or the model itself. A ``ValueError`` naming
    the known methods for anything else."""
    if isinstance(method, AbstractModel):
        return method
    try:
        return MODELS[method]
    except (KeyError, TypeError):
        raise ValueError(f"unknown method {method!r}; expected one of "
                         f"{', '.join(MODELS)}") from None


def register_model(model: AbstractModel) -> str:
    """Adds ``model`` to the table under its ``name`` (once; the same model again is a no-op)
    and returns the name. A ``ValueError`` where another model has that name."""
    if not isinstance(model, AbstractModel):
        raise ValueError(f"register_model: expected an AbstractModel, got {model!r}")
    known = MODELS.setdefault(model.name, model)
    if type(known) is not type(model) or known != model:
        raise ValueError(f"register_model: the name {model.name!r} is taken by "
                         f"{type(known).__name__}; give {type(model).__name__} another name")
    return model.name


def method_name(method: str | AbstractModel) -> str:
    """The table's name of ``method`` (a name, or a model: registered on first use, so that
    the API takes the object wherever it takes the name)."""
    if isinstance(method, AbstractModel):
        return register_model(method)
    return model_of(method).name


def structure(robot, method: str | AbstractModel) -> Structure:
    """The constant block matrices of ``method`` (a linear model: ``"kckf"``, ``"kf"``) for
    ``robot``."""
    model = model_of(method)
    if not isinstance(model, AbstractLinearKalman):
        linear = tuple(n for n, m in MODELS.items() if isinstance(m, AbstractLinearKalman))
        raise ValueError(f"structure: method must be one of {linear}, got {method!r}")
    return model.structure(robot)
