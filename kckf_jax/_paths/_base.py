"""What every path shares: the abstract path, the one regularity check and the one convergence
check.

A *path* is one way of computing the filter's estimates (``Sequential``, ``Steady``,
``Parallel``, ...); every path gives the same estimates to rounding. ``applies`` says, on
concrete inputs, why a path cannot compute them (or ``None``); ``run`` computes them for a
batch of trials. ``Auto`` (``_auto.py``) asks the faster paths in turn, and the first that
applies runs. A path answers every other question the filter, the smoother, the likelihood
and the fit ask of it (``compute``, ``batch_layout``, ``smoother_layout``, ``recheck``), so
that nothing outside ``_paths`` looks at which path it is.
"""

from __future__ import annotations

import abc
import functools
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._models._classes import model_of
from .._models._kernel import Estimate, FilterInput, FilterState, SensorSeries
from .._models._params import Params
from .._models._robot import Robot
from .._readings._health import screened_series
from .._readings._prepare import ScreenedSeries
from .._readings._screen import screen

#: Two time steps closer than this (s) count as equal: a constant step to the filter.
STEP_TOL_S = 1e-9


def kalman_only(method: str) -> str | None:
    """Why a path that computes the linear Kalman filters (a fixed block structure, the
    steps' maps known before the data) does not apply to ``method`` (or ``None``: the
    model's ``layout_reason``)."""
    return model_of(method).layout_reason()


class PathRun(NamedTuple):
    """What ``AbstractPath.compute`` computed: the final state and the estimates (leading
    axis ``B``), and the path whose result they are (a checked path whose check failed
    names the path it fell back on)."""

    final: FilterState
    estimate: Estimate
    path: AbstractPath


class PathChoice(NamedTuple):
    """The path chosen (``AbstractPath.choose``), and why each faster one was passed over
    (``{name: reason}``)."""

    path: AbstractPath
    passed_over: dict[str, str]


class PathCost(NamedTuple):
    """What a caller waits for on a path, estimated (``AbstractPath.cost``): the seconds its
    program takes to compile, and to run once."""

    compile_s: float
    run_s: float

    def total(self, runs: int) -> float:
        """Compile once, run ``runs`` times."""
        return self.compile_s + runs * self.run_s


class SmootherLayout(NamedTuple):
    """How the smoother lays out a batch for a path (``AbstractPath.smoother_layout``).

    Attributes:
        name: ``"steady"`` (the backward pass a constant map too: ``SteadySmoother``),
            ``"lanes"`` (trials as lanes) or ``"sequential"`` (a ``vmap`` of the one-trial
            smoother).
        steady: for ``"steady"``, the ``Steady`` path whose constants the smoother uses.
        checked: for ``"steady"``, whether the steady smoother was already found to apply to
            these inputs (``Auto``); if not, the smoother checks and says why not.
    """

    name: str
    steady: AbstractPath | None = None
    checked: bool = False


class AbstractPath(eqx.Module):
    """One way of computing the filter's estimates.

    Subclasses are final, hold their tuning constants as (static) fields, and implement:

    * ``applies(params, series, method, state=None) -> str | None``: why this path cannot
      compute these (concrete) inputs from ``state`` (default the initial state), in words a
      user can read, or ``None`` when it can. Values it cannot see (traced inputs) it does
      not check: the caller vouches for them;
    * ``run(params, series, method, state) -> (FilterState, Estimate)``: the filter over a
      batch of trials (``series`` with a leading axis ``B``, ``state`` batched the same way);
      traceable (no host work), differentiable.

    and may refine what the others ask (defaults here): ``compute`` (how ``run_filter`` and
    ``filter_batch`` run it from the host), ``batch_layout`` and ``smoother_layout`` (how the
    likelihood and the smoother lay out a batch for it), ``recheck`` (whether a fitting loss
    may keep it once the parameters moved), ``cost`` (what a caller waits for on it).
    """

    name: eqx.AbstractClassVar[str]

    def choose(self, params: Params, series: SensorSeries, method: str,
               state: FilterState | None = None) -> PathChoice:
        """The path to run for these inputs: this one, once it is checked to apply (a
        ``ValueError`` says why not); a policy (``Auto``) picks one."""
        why = self.applies(params, series, method, state=state)
        if why is not None:
            raise ValueError(f"path={self.name!r} does not apply: {why}; use path='auto' (the "
                             "fastest that applies) or 'sequential'")
        return PathChoice(self, {})

    #: Whether ``run`` can give the fused Hall innovations from its own pass (``compute``'s
    #: ``innovations``; ``Estimate.innovations``).
    innovations_in_pass: ClassVar[bool] = False

    def compute(self, params: Params, series: SensorSeries, method: str,
                state: FilterState, innovations: bool = False) -> PathRun:
        """``run`` from the host, compiled once per shapes (``run_filter`` and
        ``filter_batch`` call this and nothing else). A path that checks its result on the
        host overrides it (``Segments``: repair passes, each a program of its own, then the
        sequential path). ``innovations``: the estimate also carries the innovations where the
        path computes them in its pass (``innovations_in_pass``; else it carries none)."""
        final, est = _compiled_run(self, params, series, method, state,
                                   innovations and self.innovations_in_pass)
        return PathRun(final, est, self)

    def run_innovations(self, params: Params, series: SensorSeries, method: str,
                        state: FilterState) -> tuple[FilterState, Estimate]:
        """``run``, its estimate carrying the innovations (``innovations_in_pass``)."""
        raise NotImplementedError(f"{self.name}: no innovations in its pass")

    def batch_layout(self, n_trials: int, method: str = "kckf") -> str:
        """How the likelihood's innovations and the smoother lay out a batch of ``n_trials``
        for this path and ``method``: ``"lanes"`` (the trials as the last axis) or
        ``"sequential"`` (a ``vmap`` of the one-trial scan)."""
        return "sequential"

    def smoother_layout(self, params: Params, series: SensorSeries, method: str
                        ) -> SmootherLayout:
        """The smoother's layout for this path on ``series`` (``smooth_batch``): by default
        ``batch_layout``'s."""
        return SmootherLayout(self.batch_layout(int(np.shape(series.dt)[0]), method))

    def cost(self, n_trials: int, n_rows: int) -> PathCost | None:
        """What filtering ``n_trials`` trials of ``n_rows`` rows on this path costs, estimated
        from measurements (``Auto(runs=...)`` weighs compile time with it), or ``None``: no
        estimate (``Auto`` then judges by run time alone)."""
        return None

    def recheck(self, params: Params, method: str, step_s: float | None) -> str | None:
        """Why a fitting loss may no longer run this path once the parameters moved
        (``params`` concrete; ``step_s`` the data's constant time step, or ``None``): only what
        depends on the parameters is checked again, as the data did not change. ``None``:
        keep it."""
        return None

    @abc.abstractmethod
    def applies(self, params: Params, series: SensorSeries, method: str,
                state: FilterState | None = None) -> str | None:
        raise NotImplementedError

    @abc.abstractmethod
    def run(self, params: Params, series: SensorSeries, method: str, state: FilterState
            ) -> tuple[FilterState, Estimate]:
        raise NotImplementedError


@eqx.filter_jit
def _compiled_run(path: AbstractPath, params, series, method, state, innovations=False):
    if innovations:  # a Python bool: static, one program each way
        return path.run_innovations(params, series, method, state)
    return path.run(params, series, method, state)


def is_traced(*trees) -> bool:
    """Whether any leaf of ``trees`` is a tracer (values unknown: inside ``jit``, ``grad``)."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(trees))


# ---------------------------------------------------------------------------- regularity
def readings_present(params, gyro, hall_v, xp=jnp):
    """Per row (any leading axes): whether every used gyro reading (``Robot.used_gyro_index``)
    is there, and whether every Hall reading is, each judged alone (``_screen.screen``: a
    faulty reading is missing). ``params``: anything with ``robot``, ``limits`` and ``hall_coeffs``
    (``Params``). NumPy (``xp=np``: one packet in the streaming filter) or JAX (a
    recording, on the device)."""
    gyro, hall_v = screen(params, gyro, hall_v, xp)[:2]
    used = xp.take(gyro, xp.asarray(params.robot.used_gyro_index), axis=-1)
    return xp.isfinite(used).all(axis=-1), xp.isfinite(hall_v).all(axis=-1)


class _Layout(eqx.Module):
    """What the regularity check needs of ``Params``: the static layout and limits (a jit
    key) and the Hall coefficients, or ``None`` where they are traced (a loss of the
    parameters that closes over concrete data: the curve's check is then the caller's)."""

    robot: Robot = eqx.field(static=True)
    limits: object = eqx.field(static=True)
    hall_coeffs: tuple | None


def _layout(params: Params) -> _Layout:
    coeffs = None if is_traced(params) else params.hall_coeffs
    return _Layout(params.robot, params.limits, coeffs)


@functools.partial(jax.jit, static_argnums=0)
def _regularity(how: str, params, dt: Float[Array, "*B T"], gyro: Float[Array, "*B T G"],
                hall_v: Float[Array, "*B T M"]
                ) -> tuple[Float[Array, ""], Float[Array, ""], Bool[Array, ""], Bool[Array, ""]]:
    """On the device, one small transfer back: the largest deviation of a time step (rows
    after the first) from the first trial's second one, that step, and whether every used
    gyro reading and every Hall reading is there as the filter uses them: judged over time
    (``how="over_time"``: ``_health.screened_series``, the paths' own screening), row by row
    (``"rows"``: ``readings_present``) or, for readings already screened, as they are."""
    dt2 = jnp.reshape(dt, (-1, dt.shape[-1]))
    first = dt2[0, 1]
    if how == "over_time":
        gyro, hall_v, _ = screened_series(params, dt, gyro, hall_v)
    if how == "rows":
        gyro_ok, hall_ok = readings_present(params, gyro, hall_v)
    else:
        used = jnp.take(gyro, jnp.asarray(params.robot.used_gyro_index), axis=-1)
        gyro_ok, hall_ok = jnp.isfinite(used).all(axis=-1), jnp.isfinite(hall_v).all(axis=-1)
    return jnp.max(jnp.abs(dt2[:, 1:] - first)), first, gyro_ok.all(), hall_ok.all()


def regular_step(params: Params, series: SensorSeries) -> tuple[float | None, str | None]:
    """The one regularity check: ``(step_s, None)`` when ``series`` (one recording ``T`` or a
    batch ``B T``) has one constant time step shared by every trial and every reading the
    filters use (``readings_present`` in every row); else ``(None, why)``. Traced inputs:
    ``(None, None)``, unchecked."""
    if is_traced(series):
        return None, None
    if np.ndim(series.dt) < 1 or np.shape(series.dt)[-1] < 2:
        return None, "fewer than two rows"
    # Concrete data inside a caller's trace (a jitted loss of the parameters that closes
    # over its recording) are still checked: evaluated now, not staged into the trace.
    # Judged as the paths will judge them: over time where the parameters are known (a Hall
    # sensor the health monitor isolates makes a recording irregular), row by row where a
    # caller's trace holds them.
    if isinstance(series, (ScreenedSeries, FilterInput)):
        how, p = "as_is", _Layout(params.robot, params.limits, None)
    elif is_traced(params):
        how, p = "rows", _layout(params)
    else:
        how, p = "over_time", params
    with jax.ensure_compile_time_eval():
        dev, first, gyro_ok, hall_ok = _regularity(how, p, series.dt, series.gyro,
                                                   series.hall_v)
    dev, first = float(dev), float(first)
    if not (dev <= STEP_TOL_S and first > 0):  # also false for a NaN step
        return None, ("the time step is not constant" if np.ndim(series.dt) == 1 else
                      "the time step is not one constant shared by every trial")
    if not bool(gyro_ok):
        return None, "a gyro reading is missing or out of range"
    if not bool(hall_ok):
        return None, "a Hall reading is missing or out of range"
    return first, None


# ---------------------------------------------------------------------------- convergence
def relative_change(P_old, P_new, xp=jnp):
    """The one convergence measure: ``max |P_new - P_old| / max |P_new|`` (NumPy or JAX)."""
    return xp.max(xp.abs(P_new - P_old)) / xp.maximum(xp.max(xp.abs(P_new)), 1e-300)
