"""The fixed-interval (Rauch-Tung-Striebel) smoother of the Kalman methods, over the filter's
own steps.

Offline, the best estimate of an angle uses the readings after it too. The forward pass is the
kernel's ``step`` (``kalman_step_moments``: the same arithmetic, with the predicted moments it
computed on the way); the backward pass is the RTS recursion in the filter's block
coordinates, block by block (``_rts.py``). For the KCKF the constraint is a perfect
measurement at every row with a time step, so the next row's smoothed ``y = [z, e]`` is
``[z_k+1|T, 0]`` with no variance in ``e``: the smoothed estimates satisfy the constraint too
(``phi = sum theta`` by construction of the block coordinates). A row with no time step (the
first, padding) has no constraint and no process noise, and a coordinate with no variance (a
padding joint) none either; their rows are left out of the solve. A skipped row (its update
was not finite) keeps the state, so its smoothed state is the next one's.

The same smoother has the filter's faster layouts (``_paths``): ``SteadySmoother`` (regular
recordings: the backward pass a constant map too) and the lanes smoother (batches); ``smooth``
and ``smooth_batch`` pick one as ``Auto`` picks the filter's path.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from .._models._classes import (
    KALMAN_METHODS,
    AbstractModel,
    init_state,
    init_states,
    kalman_step_moments,
    method_name,
    model_estimate,
    model_of,
    structure,
)
from .._models._kernel import Estimate, FilterState, SensorSeries, StepMoments
from .._models._params import Params
from .._readings._prepare import prepare
from . import AbstractPath, SmootherLayout, as_path, is_traced
from ._lanes_smooth import lane_smooth
from ._rts import rts_rows
from ._steady_smooth import SteadySmoother


def filter_moments(params: Params, series: SensorSeries, method: str,
                   state: FilterState | None = None):
    """The forward pass: ``lax.scan`` of ``kalman_step_moments`` over one trial. Returns the
    final state, the filtered block states and covariances per row (``T Nb Nz``, ``T Nb Nz
    Nz``) and the ``StepMoments`` per row."""
    state = init_state(params, method) if state is None else state
    dtype = state.z.dtype
    series = prepare(params, series, method, dtype)

    @jax.checkpoint
    def body(carry, row):
        new, _, mom = kalman_step_moments(params, carry, row, method)
        return new, (new.z, new.P, mom)

    final, (zs, Ps, mom) = jax.lax.scan(body, state, series)
    return final, zs, Ps, mom


def rts(params: Params, method: str, zs, Ps, mom: StepMoments):
    """The backward pass over the forward pass's rows: the smoothed block states and
    covariances per row (the last row's are its filtered ones). ``kckf3d``'s steps bring
    their own maps (``StepMoments.F``: the model linearised at each filtered state, the
    extended RTS smoother)."""
    st = model_of(method).smoother_structure(params.robot)
    F = None if mom.F is None else mom.F[1:]
    z, P = rts_rows(st, zs[:-1], Ps[:-1], mom.y[1:], mom.S[1:], mom.dt[1:], mom.skipped[1:],
                    (zs[-1], Ps[-1]), F)
    return jnp.concatenate([z, zs[-1:]]), jnp.concatenate([P, Ps[-1:]])


def _smoothed(params: Params, series: SensorSeries, method: str, state: FilterState | None,
              innovations: bool = False):
    _, zs, Ps, mom = filter_moments(params, series, method, state)
    z, P = rts(params, method, zs, Ps, mom)
    est = jax.vmap(lambda a, b: model_estimate(params.robot, method, a, b))(z, P)
    return dataclasses.replace(est, skipped=mom.skipped, innovations=(
        (mom.nu, mom.s, mom.valid) if innovations else None))


def smooth(params: Params, series: SensorSeries, method: str | AbstractModel = "kckf",
           state: FilterState | None = None, path: str | AbstractPath = "auto") -> Estimate:
    """The fixed-interval (RTS) smoothed estimates of one recording (``run_filter``'s
    arguments; ``method`` a Kalman method: ``"kckf"``, ``"kf"``, ``"kckf3d"``): each row's
    angles, their standard deviations and biases given every reading of the recording, before
    and after it.
    ``path`` as ``smooth_batch``'s (``"auto"``: steady where it applies, else sequential); an
    entering ``state`` is taken by the sequential path only.

    Example:
        >>> robot = Robot.from_spec("x")
        >>> series = SensorSeries(jnp.full(5, 0.01), jnp.zeros((5, 6)), jnp.ones((5, 2)))
        >>> smooth(Params.paper_defaults(robot), series).angles.shape
        (5, 2)
    """
    method = _check(method)
    if state is None and path != "sequential":
        batch = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], series)
        layout = _smooth_path(params, batch, method, path)
        if layout.name != "sequential":
            est = _smooth_on(layout, params, batch, method)
            return dataclasses.replace(est, angles=est.angles[0], angle_std=est.angle_std[0],
                                       bias=est.bias[0], skipped=est.skipped[0])
    elif state is not None and path not in ("auto", "sequential"):
        raise ValueError(f"smooth: an entering state is taken by the sequential path only, "
                         f"not {path!r}")
    est = _smooth_one(params, series, method, state)
    return dataclasses.replace(est, path="smoothed", names=params.robot.angle_names)


SMOOTH_PATHS = ("auto", "sequential", "lanes", "steady")


def smooth_batch(params: Params, series: SensorSeries, method: str | AbstractModel = "kckf",
                 path: str | AbstractPath = "auto", innovations: bool = False) -> Estimate:
    """``smooth`` over a batch of padded trials (leading axis ``B``; ``pad_series``).

    ``path``, as the filter's: ``"steady"`` (a regular recording whose filter and smoother
    converge: the backward pass a constant map too, ``SteadySmoother``), ``"lanes"`` (the
    ``Lanes`` arithmetic with the trials as lanes, forward and backward), ``"sequential"``
    (``vmap`` of the one-recording smoother) or ``"auto"``: steady where it applies, else lanes
    for a batch of at least ``Lanes.min_trials`` trials, else sequential (inside ``jit`` or
    ``grad`` the data cannot be checked: ``"auto"`` does not take the steady path there, an
    explicit ``"steady"`` vouches for the data); or a path object, which decides
    (``AbstractPath.smoother_layout``: an ``Auto`` of the caller's moves the smoother as it
    moves the filter). The same estimates to rounding;
    ``Estimate.path`` is ``"smoothed"`` (sequential), ``"smoothed:lanes"`` or
    ``"smoothed:steady"``. ``innovations``: the estimate also carries the forward pass's
    fused Hall innovations (``Estimate.innovations``, the filter's, as ``filter_batch(...,
    innovations=True)`` gives them; every layout computes them in that pass)."""
    method = _check(method)
    return _smooth_on(_smooth_path(params, series, method, path), params, series, method,
                      innovations)


def _smooth_on(layout: SmootherLayout, params: Params, series: SensorSeries, method: str,
               innovations: bool = False) -> Estimate:
    """The batch smoothed in ``layout`` (the path's ``smoother_layout``), labelled."""
    if layout.name == "steady":
        smoother = SteadySmoother(steady=layout.steady)
        if not layout.checked and not is_traced(params, series):
            why = smoother.applies(params, series, method)
            if why is not None:
                raise ValueError(f"smooth: the steady path does not apply: {why}")
        est = _smooth_steady(smoother, params, series, method, innovations)
    elif layout.name == "lanes":
        # Inside a caller's trace (a fitting loss), laid out for its gradient.
        est = _smooth_lanes(params, series, method, innovations, is_traced(params, series))
    else:
        est = _smooth_many(params, series, method, innovations)
    label = "smoothed" if layout.name == "sequential" else f"smoothed:{layout.name}"
    return dataclasses.replace(est, path=label, names=params.robot.angle_names)


def _smooth_path(params: Params, series: SensorSeries, method: str,
                 path: str | AbstractPath) -> SmootherLayout:
    """The smoother's layout for a batch: the path's answer (``smoother_layout``)."""
    if isinstance(path, str) and path not in SMOOTH_PATHS:
        raise ValueError(f"smooth: unknown path {path!r}; expected one of "
                         f"{', '.join(SMOOTH_PATHS)} or a path object")
    return as_path(path).smoother_layout(params, series, method)


def _check(method) -> str:
    """``method``'s name (``_classes.method_name``), a Kalman model's."""
    method = method_name(method)
    if not model_of(method).kalman:
        raise ValueError(f"smoothing needs a Kalman filter ({', '.join(KALMAN_METHODS)}), got "
                         f"{method!r}")
    return method


@eqx.filter_jit
def _smooth_one(params, series, method, state):
    return _smoothed(params, series, method, state)


@eqx.filter_jit
def _smooth_many(params, series, method, innovations=False):
    return jax.vmap(lambda s: _smoothed(params, s, method, None, innovations))(series)


@eqx.filter_jit
def _smooth_lanes(params, series, method, innovations=False, gradient=True):
    state = init_states(params, method, jnp.shape(series.dt)[0])
    return lane_smooth(params, structure(params.robot, method), series, state, innovations,
                       gradient)


@eqx.filter_jit
def _smooth_steady(smoother, params, series, method, innovations=False):
    state = init_states(params, method, jnp.shape(series.dt)[0])
    return smoother.run(params, series, method, state, innovations)
