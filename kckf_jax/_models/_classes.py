"""The filters kckf-jax runs, as model objects: one class per filter and one table of their
names (``MODELS``), which the command's ``--method`` and the API's ``method`` look up.

Every module asks the model what it needs, never its name: its state before the first row
(``init_state``) and its step (``step``; a Kalman model's ``moments`` and ``estimate``, which
the smoother and the likelihood read), whether it is a Kalman
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
``register_model`` adds one to the table), and the module's functions (``init_state``,
``step``, ``scan_filter``, ``kalman_step_moments``, ``model_estimate``) ask the model named:
a new filter is one class here, and one line registering it. The arithmetic the models share
(the types, the block updates, the exact chain's step) is below, in ``_kernel`` and
``_exact``.
"""

from __future__ import annotations

import abc
import dataclasses
import functools
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _exact
from ._blocks import Structure, block_structure, initial_covariance
from ._chunked_scan import chunked_scan
from ._custom_types import BlockCov, BlockState
from ._exact import exact_model
from ._kernel import (
    Estimate,
    FilterInput,
    FilterState,
    SensorSeries,
    StepMoments,
    block_estimate,
    block_inputs,
    block_step,
    exact_block_estimate,
    exact_parts,
    hall_measurements,
    require_input,
)
from ._params import Params


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

    @abc.abstractmethod
    def init_state(self, params: Params) -> FilterState:
        """The state before the first row (zero angles and biases; a Kalman model's
        covariance from ``params``)."""

    def packet_step(self, params: Params, state: FilterState, inputs: FilterInput
                    ) -> tuple[FilterState, Estimate]:
        """The step the stream and the exported step run, one packet at a time and never
        differentiated: ``step`` itself, unless a model has a faster form of the same
        arithmetic (``ExactKCKF``: its entry-by-entry form)."""
        return self.step(params, state, inputs)

    @abc.abstractmethod
    def step(self, params: Params, state: FilterState, inputs: FilterInput
             ) -> tuple[FilterState, Estimate]:
        """One row: predict from the previous row, then update with this one."""


class AbstractKalman(AbstractModel):
    """A Kalman filter: its step is its ``moments`` (which the smoother and the likelihood
    read), and a step whose new state is not finite is skipped."""

    kalman: ClassVar[bool] = True

    @abc.abstractmethod
    def moments(self, params: Params, state: FilterState, inputs: FilterInput):
        """The new block state and covariance, and what the step computed on the way:
        ``(z, P, y, S, F, nu, s, valid, dt)`` (``StepMoments``' fields; ``F`` ``None`` where
        the model's matrices do not depend on the state)."""

    @abc.abstractmethod
    def estimate(self, robot, z: BlockState, P: BlockCov) -> Estimate:
        """The ``Estimate`` of a block state ``z`` and covariance ``P``."""

    def step(self, params: Params, state: FilterState, inputs: FilterInput
             ) -> tuple[FilterState, Estimate]:
        return self.step_moments(params, state, inputs)[:2]

    def step_moments(self, params: Params, state: FilterState, inputs: FilterInput
                     ) -> tuple[FilterState, Estimate, StepMoments]:
        """``step`` and its ``StepMoments``."""
        return self._kalman_step(params, state, inputs, self.moments(params, state, inputs),
                                 self.estimate)

    def _kalman_step(self, params: Params, state: FilterState, inputs: FilterInput, moments,
                     estimate) -> tuple[FilterState, Estimate, StepMoments | None]:
        """A Kalman step from its ``moments`` and the ``estimate`` of the new state; the
        update skipped where it is not finite. Its ``StepMoments`` are ``None`` where the
        moments have no predicted ``y`` (a forward-only form)."""
        require_input(inputs, "step")
        z, P, y, S, F, nu, s, vb, dt = moments
        gyro = inputs.gyro.astype(state.z.dtype)
        hold = jnp.where(jnp.isfinite(gyro), gyro, state.gyro_hold)
        # An update that is not finite (a time step so long that the prediction overflows)
        # is skipped: the whole state stays as it was, so nothing can poison it.
        ok = jnp.isfinite(z).all() & jnp.isfinite(P).all()
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), FilterState(z, P, hold),
                                     state)
        est = estimate(params.robot, new.z, new.P)
        est = dataclasses.replace(est, skipped=~ok)
        if y is None:  # a forward-only form (``packet_step``): no moments formed
            return new, est, None
        return new, est, StepMoments(y, S, nu, s, vb & ok, dt, ~ok, F)

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

    def init_state(self, params: Params) -> FilterState:
        dtype = params.log_q.dtype
        P0 = initial_covariance(self.structure(params.robot), params)
        return FilterState(jnp.zeros(P0.shape[:2], dtype), P0, _zero_hold(params))

    def moments(self, params: Params, state: FilterState, inputs: FilterInput):
        st = self.structure(params.robot)
        dt, rates, noise, hb, rb, vb = block_inputs(params, st, state.gyro_hold, inputs)
        z, P, y, S, nu, s = jax.vmap(lambda *a: block_step(st, *a, dt))(
            state.z, state.P, rates, *noise, hb, rb, vb)
        return z, P, y, S, None, nu, s, vb, dt

    def estimate(self, robot, z: BlockState, P: BlockCov) -> Estimate:
        return block_estimate(self.structure(robot), z, P)

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

    def init_state(self, params: Params) -> FilterState:
        dtype = params.log_q.dtype
        exact = exact_model(params.robot)
        p0_bias = _exact.gyro_bias_noise(exact, params.q, params.bias_rw, params.p0_bias)[2]
        P0 = _exact.initial_covariance(exact, params.p0_angle, p0_bias)[None].astype(dtype)
        return FilterState(jnp.zeros(P0.shape[:2], dtype), P0, _zero_hold(params))

    def moments(self, params: Params, state: FilterState, inputs: FilterInput):
        return exact_parts(params, state, inputs)

    def estimate(self, robot, z: BlockState, P: BlockCov) -> Estimate:
        return exact_block_estimate(robot, z, P)

    def packet_step(self, params: Params, state: FilterState, inputs: FilterInput
                    ) -> tuple[FilterState, Estimate]:
        """The same step and estimate written entry by entry (``_exact_entries``, one lane):
        the same numbers to rounding, in about a third of the time of the matrix form, whose
        gradient the fit needs (docs/streaming.md)."""
        return self._kalman_step(params, state, inputs,
                                 exact_parts(params, state, inputs, entries=True),
                                 functools.partial(exact_block_estimate, entries=True))[:2]


class Gyro(AbstractModel):
    """Integrated gyro differences (Eq. 2), from the neutral pose."""

    name: ClassVar[str] = "gyro"
    label: ClassVar[str] = "Gyro"
    kalman: ClassVar[bool] = False
    line: ClassVar[str] = "integrated"

    def init_state(self, params: Params) -> FilterState:
        dtype = params.log_q.dtype
        return FilterState(jnp.zeros(params.robot.n_angles, dtype), jnp.zeros((0, 0), dtype),
                           _zero_hold(params))

    def step(self, params: Params, state: FilterState, inputs: FilterInput
             ) -> tuple[FilterState, Estimate]:
        """The joint and torso rates of the previous row integrated (Eq. 2)."""
        require_input(inputs, "step")
        plus, minus = params.robot.rate_pairs
        rates = state.gyro_hold[plus] - state.gyro_hold[minus]
        z = state.z + inputs.dt.astype(state.z.dtype) * rates
        return _baseline_out(params, state, inputs, z, z)


class AbstractHall(AbstractModel):
    """One side's Hall sensor alone through Eq. 1 (a missing reading holds the last one)."""

    side: eqx.AbstractClassVar[int]
    kalman: ClassVar[bool] = False
    torso: ClassVar[bool] = False
    line: ClassVar[str] = "sensor"

    def init_state(self, params: Params) -> FilterState:
        dtype = params.log_q.dtype
        return FilterState(jnp.full(params.robot.n_joint_axes, jnp.nan, dtype),
                           jnp.zeros((0, 0), dtype), _zero_hold(params))

    def step(self, params: Params, state: FilterState, inputs: FilterInput
             ) -> tuple[FilterState, Estimate]:
        """Its side's sensor of each joint axis through Eq. 1, the last angle held where it
        has no reading."""
        require_input(inputs, "step")
        dtype = state.z.dtype
        angle, _, valid = hall_measurements(params, inputs.hall_v.astype(dtype))
        z = jnp.where(valid[self.side::2], angle[self.side::2], state.z)
        K, J = params.robot.n_angles, params.robot.n_joint_axes
        return _baseline_out(params, state, inputs, z,
                             jnp.concatenate([z, jnp.full(K - J, jnp.nan, dtype)]))


def _zero_hold(params: Params):
    return jnp.zeros(3 * params.robot.n_links, params.log_q.dtype)


def _baseline_out(params, state, inputs, z, angles):
    dtype = state.z.dtype
    gyro = inputs.gyro.astype(dtype)
    nan_k = jnp.full(params.robot.n_angles, jnp.nan, dtype)
    hold = jnp.where(jnp.isfinite(gyro), gyro, state.gyro_hold)
    return FilterState(z, state.P, hold), Estimate(angles, nan_k, nan_k, jnp.zeros((), bool))


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


# --------------------------------------------------------------- any model, by its name
def check_method(method: str | AbstractModel) -> None:
    """A ``ValueError`` naming the known methods unless ``method`` is a model or the name of
    one (``MODELS``)."""
    model_of(method)


def estimated(robot, method: str | AbstractModel) -> np.ndarray:
    """Which of ``robot.angle_names`` ``method`` estimates (``K`` bools): every angle, except
    the torso angles for the single-sensor Hall baselines (``AbstractModel.torso``)."""
    return model_of(method).estimated(robot)


def exact_kinematics(method: str | AbstractModel) -> bool:
    """Whether ``method`` models the chain's exact kinematics (``kckf3d``): then no two gyro
    channels measure the same rate (``_screen.stand_ins``; ``AbstractModel.gyro_pairs``)."""
    return not model_of(method).gyro_pairs


def init_state(params: Params, method: str | AbstractModel = "kckf") -> FilterState:
    """The state before the first row of ``method`` (``AbstractModel.init_state``)."""
    return model_of(method).init_state(params)


@eqx.filter_jit  # one program, not a dozen op-by-op ones, when called outside a trace
def init_states(params: Params, method: str, n: int) -> FilterState:
    """``init_state`` for each of ``n`` trials: a leading axis of ``n`` on every leaf (the
    batch of states the paths carry)."""
    return jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n,) + x.shape),
                                  init_state(params, method))


def step(
    params: Params, state: FilterState, inputs: SensorSeries,
    method: str | AbstractModel = "kckf"
) -> tuple[FilterState, Estimate]:
    """One time step of ``method`` (a model or its name: ``AbstractModel.step``): predict
    from the previous row, then update with this row.

    Pure and jit-friendly (``method`` must be static). ``inputs`` is one row of a
    ``FilterInput`` (``kk.prepare_row`` makes one of a lone row: a reading outside
    ``params.limits`` is then missing); anything else is refused with a ``TypeError`` that
    says so.
    """
    require_input(inputs, "step")
    return model_of(method).step(params, state, inputs)


def kalman_step_moments(params: Params, state: FilterState, inputs: FilterInput,
                        method: str | AbstractModel) -> tuple[FilterState, Estimate,
                                                              StepMoments]:
    """``step`` of a Kalman model (``AbstractKalman.step_moments``), and its
    ``StepMoments``."""
    model = model_of(method)
    if not model.kalman:
        raise ValueError(f"method {model.name!r} is not a Kalman filter: it has no moments")
    return model.step_moments(params, state, inputs)


def model_estimate(robot, method: str | AbstractModel, z: BlockState, P: BlockCov
                   ) -> Estimate:
    """A Kalman model's ``Estimate`` of its block state ``z`` and covariance ``P``."""
    return model_of(method).estimate(robot, z, P)


def scan_filter(
    params: Params, series: SensorSeries, method: str | AbstractModel = "kckf",
    state: FilterState | None = None, remat_chunk: int | None = None,
    innovations: bool = False,
) -> tuple[FilterState, Estimate]:
    """``lax.scan`` of ``step`` over one trial (not jitted: the building block of
    ``run_filter`` and of the fitting loss).

    ``remat_chunk``: split the scan into chunks of this many steps and recompute each chunk's
    intermediate values in the backward pass (``jax.checkpoint``), so a gradient through
    ``T`` steps stores about ``T / remat_chunk + remat_chunk`` states instead of all ``T``.
    Either way each row's intermediate values are recomputed in the backward pass (only the
    states are stored). The forward result is unchanged. ``innovations`` (a Kalman method):
    the estimate also carries each row's fused Hall innovations (``Estimate.innovations``),
    from the same steps.
    """
    check_method(method)
    if state is None:
        state = init_state(params, method)
    require_input(series, "scan_filter")

    def body(carry, row):
        if innovations:
            new, est, mom = kalman_step_moments(params, carry, row, method)
            return new, dataclasses.replace(est, innovations=(mom.nu, mom.s, mom.valid))
        return step(params, carry, row, method)

    if not remat_chunk:
        # Each row recomputed under reverse mode (only the carries saved), as on the lanes
        # path: 3 trials x 4,000 recorded-like bench rows, float32, the RMSE gradient 0.28 ->
        # 0.20 s (the same values to the bit; compile 6.7 -> 5.9 s).
        return jax.lax.scan(jax.checkpoint(body), state, series)
    # Padding rows (dt = 0, every reading missing) are no-op steps.
    return chunked_scan(body, state, series, int(remat_chunk), (0.0, jnp.nan, jnp.nan))
