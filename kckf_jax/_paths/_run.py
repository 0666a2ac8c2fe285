"""Running the filter: the one place that resolves a path and compiles the call.

``run_filter`` (one recording), ``filter_batch`` (padded trials) and ``filter_sessions``
(recorded sessions: what every command calls) each pick the path on concrete inputs
(``choose_path``: ``Auto`` by default), then run it in one jitted call. The estimates say which
path ran (``Estimate.path``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._models._classes import AbstractModel, init_state, init_states, method_name, model_of
from .._models._fault_policy import FaultPolicy
from .._models._kernel import Estimate, FilterInput, FilterState, SensorSeries
from .._models._params import Params
from .._readings._batching import pad_series
from .._readings._gaps import GapPolicy
from .._readings._prepare import ScreenedSeries, judged
from .._sessions._session import Session, split_at_gaps
from . import AbstractPath, PathChoice, as_path
from ._smooth import smooth_batch


def choose_path(params: Params, series: SensorSeries, method: str | AbstractModel = "kckf",
                path: str | AbstractPath = "auto", state: FilterState | None = None
                ) -> PathChoice:
    """The path that computes ``method`` on ``series`` (one recording or a batch): ``Auto``'s
    pick, or ``path`` itself once it is checked to apply (a ``ValueError`` says why not).

    Example:
        >>> robot = Robot.from_spec("x,y")
        >>> series = SensorSeries(jnp.full(5, 0.01), jnp.zeros((5, 9)), jnp.ones((5, 4)))
        >>> choice = choose_path(Params.paper_defaults(robot), series)
        >>> choice.path.name, choice.passed_over["steady"]
        ('sequential', '5 rows, not more than 4096')
    """
    method = method_name(method)
    return as_path(path).choose(params, series, method, state)


def run_filter(
    params: Params, series: SensorSeries, method: str | AbstractModel = "kckf",
    state: FilterState | None = None, path: str | AbstractPath = "auto",
) -> tuple[FilterState, Estimate]:
    """Filter a whole recording: ``lax.scan`` of ``step`` over the rows of ``series``, jitted.

    Args:
        params: the filter parameters (their dtype sets the computation's precision).
        series: one trial, ``dt`` of shape (T,). Use ``filter_batch`` for a batch of padded
            trials.
        method: a model of ``_models`` or its name (``METHODS``).
        state: the starting state (default ``init_state(params, method)``).
        path: how to compute it (all give the same estimates; ``docs/performance.md``): a
            path object (``Sequential()``, ``Steady(...)``, ``Parallel()``, ``Auto()``) or its
            name. ``"auto"`` (default) takes the fastest that applies (``choose_path``).

    Returns:
        The final state and an ``Estimate`` with a leading time axis; ``Estimate.path`` names
        the path that ran.

    Example:
        >>> robot = Robot.from_spec("x,y")
        >>> params = Params.paper_defaults(robot)
        >>> series = SensorSeries(jnp.full(5, 0.01), jnp.zeros((5, 9)), jnp.ones((5, 4)))
        >>> final, est = run_filter(params, series, "kckf")
        >>> est.angles.shape, est.path
        ((5, 4), 'sequential')
    """
    method = method_name(method)
    series, faults = screened(params, series, method)
    chosen = choose_path(params, series, method, path, state).path
    if state is None:
        state = init_state(params, method)
    out = chosen.compute(params, _one(series), method, _one(state))
    return _first(out.final), _named(_first(out.estimate), out.path, params, faults)


def _named(est: Estimate, path: AbstractPath, params: Params, faults) -> Estimate:
    """``est`` with the path that ran, the angles' names and why each reading the filter did
    not use was not used (``Estimate.faults``)."""
    return dataclasses.replace(est, path=path.name, names=params.robot.angle_names,
                               faults=faults)


def screened(params: Params, series: SensorSeries, method: str | AbstractModel = "kckf"
             ) -> tuple[SensorSeries, Array | None]:
    """``series`` (one recording or a batch) judged as the filter uses it, in the parameters'
    dtype (``_prepare.judged``: row by row and over time; a ``ScreenedSeries``), and why each
    reading it does not use is not used (``Estimate.faults``: codes of
    ``_screen.FAULT_KINDS``). Every path is given the screened series, so the readings are
    judged once. To filter one recording many times with parameters of the same Hall curves,
    screen it once and pass the screened series: it is not judged again (its faults are the
    codes returned here; ``Estimate.faults`` is then ``None``). A ``ScreenedSeries`` or a
    ``FilterInput`` is returned as it is, with ``None``."""
    if isinstance(series, (ScreenedSeries, FilterInput)):
        return series, None
    return _screened(params, series, method_name(method))


@eqx.filter_jit
def _screened(params: Params, series: SensorSeries, method: str
              ) -> tuple[ScreenedSeries, Array]:
    return judged(params, series, method, params.log_q.dtype)


def series_faults(params: Params, series: SensorSeries, method: str = "kckf") -> Array:
    """``Estimate.faults`` of ``series`` for ``method``: ``screened``'s codes."""
    return screened(params, series, method)[1]


def _one(x):
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], x)


def _first(x):
    return jax.tree_util.tree_map(lambda a: a[0], x)


def filter_batch(params: Params, series: SensorSeries, method: str | AbstractModel = "kckf",
                 path: str | AbstractPath = "auto", innovations: bool = False) -> Estimate:
    """``run_filter`` over a batch of trials (leading axis ``B``, padded to one length with
    ``pad_series``), one parameter set for all; ``Estimate.path`` names the path that ran.
    ``innovations``: the estimate also carries the fused Hall innovations of the same pass
    where the path that ran computes them there (``Estimate.innovations``; a Kalman method).

    Example:
        >>> robot = Robot.from_spec("x")
        >>> trials = [SensorSeries(jnp.full(n, 0.01), jnp.zeros((n, 6)), jnp.ones((n, 2)))
        ...           for n in (4, 7)]
        >>> filter_batch(Params.paper_defaults(robot), pad_series(trials)).angles.shape
        (2, 7, 2)
    """
    method = method_name(method)
    series, faults = screened(params, series, method)
    chosen = choose_path(params, series, method, path).path
    state = init_states(params, method, jnp.shape(series.dt)[0])
    out = chosen.compute(params, series, method, state,
                         innovations=innovations and model_of(method).kalman)
    return _named(out.estimate, out.path, params, faults)


# ---------------------------------------------------------------------------- sessions
def session_series(session: Session, dtype=None) -> SensorSeries:
    """The filter inputs of a session; time differenced in float64 before any cast.
    ``dtype=np.float64`` keeps NumPy arrays (for ``pad_series``)."""
    if dtype is np.float64:
        return SensorSeries(session.dt(), session.gyro, session.hall_v)
    dtype = dtype or jnp.asarray(0.0).dtype
    return SensorSeries(jnp.asarray(session.dt(), dtype), jnp.asarray(session.gyro, dtype),
                        jnp.asarray(session.hall_v, dtype))


def common_robot(sessions: Sequence[Session]):
    """The robot all ``sessions`` share (a clear error if they differ)."""
    if not sessions:
        raise ValueError("no sessions given")
    robot = sessions[0].robot
    for s in sessions[1:]:
        if s.robot != robot:
            raise ValueError(
                f"{s.path or 'session'}: robot {s.robot.spec!r} differs from "
                f"{sessions[0].path or 'the first session'}'s {robot.spec!r}; "
                "sessions filtered together must share one joint layout"
            )
    return robot


def session_params(sessions: Sequence[Session], params: Params | None = None,
                   dtype=None, faults: FaultPolicy | str | None = None) -> list[Params]:
    """One parameter set per session: ``params`` if given, else the paper defaults with the
    session's own Hall calibration (``meta.json``'s ``hall_models``); either way with the
    physical limits a session states (``Session.limits``), which describe its hardware, and
    the fault policy ``faults`` where given (``Params.with_faults``)."""
    return [p.with_faults(faults) for p in _session_params(sessions, params, dtype)]


def _session_params(sessions: Sequence[Session], params: Params | None, dtype
                    ) -> list[Params]:
    robot = common_robot(sessions)
    if params is not None:
        if params.robot != robot:
            raise ValueError(
                f"parameters are for robot {params.robot.spec!r} but the sessions have "
                f"{robot.spec!r}"
            )
        params = params.astype(dtype) if dtype is not None else params
        return [params if s.limits is None else dataclasses.replace(params, limits=s.limits)
                for s in sessions]
    return [Params.paper_defaults(robot, s.hall_models, dtype=dtype, limits=s.limits)
            for s in sessions]


def same_params(a: Params, b: Params) -> bool:
    """Whether two parameter sets are the same filter (same layout and leaf values)."""
    if a is b:
        return True
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    return ta == tb and all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(la, lb))


def filter_sessions(
    sessions: Sequence[Session], method: str | AbstractModel = "kckf", params: Params | None = None,
    dtype=None, path: str | AbstractPath = "auto", gaps: GapPolicy = GapPolicy(),
    smooth: bool = False, faults: FaultPolicy | str | None = None, innovations: bool = False,
) -> list[Estimate]:
    """Run ``method`` over every session; one ``Estimate`` per session, cut back to the
    session's own length, as NumPy arrays, its ``path`` naming the path that ran.

    Sessions that share one parameter set (``params``, or the same ``meta.json`` calibration)
    are padded to one length and filtered as one batch (``filter_batch``: one compiled call,
    the path chosen on the batch); a single regular session takes the steady path. A gap in
    the sensor rows gets ``gaps``' policy: predicted across, or (``on_gap="restart"``, or
    longer than ``max_predict_s``) the filter starts again after it, the stretches then being
    trials of the batch (``split_at_gaps``). ``smooth``: the fixed-interval (RTS) smoothed
    estimates instead (``smooth_batch``; the Kalman methods), ``path`` ``"smoothed"``.
    ``faults``: the fault policy (``FaultPolicy`` or its name; default: ``params``' own, else
    ``isolate``). ``innovations``: as ``filter_batch``'s (with ``smooth``, the smoother's
    forward pass's: the filter's), each session's restarting where the filter does."""
    method = method_name(method)
    plist = session_params(sessions, params, dtype, faults)
    pieces = [(i, piece) for i, s in enumerate(sessions) for piece in split_at_gaps(s, gaps)]
    groups: list[tuple[Params, list[int]]] = []
    for j, (i, _) in enumerate(pieces):
        for rep, members in groups:
            if same_params(rep, plist[i]):
                members.append(j)
                break
        else:
            groups.append((plist[i], [j]))
    out: list[Estimate | None] = [None] * len(pieces)
    for p, members in groups:
        dtype_p = p.log_q.dtype
        batch = pad_series([session_series(pieces[j][1], np.float64) for j in members])
        batch = jax.tree_util.tree_map(lambda x, d=dtype_p: jnp.asarray(x, d), batch)
        if smooth:  # screened once: the smoother's paths take the screened rows as they are
            screened_batch, faults = screened(p, batch, method)
            est = dataclasses.replace(smooth_batch(p, screened_batch, method,
                                                   innovations=innovations), faults=faults)
        else:
            est = filter_batch(p, batch, method, path, innovations=innovations)
        arrays = jax.tree_util.tree_map(np.asarray, est)
        for b, j in enumerate(members):
            n = pieces[j][1].n_steps
            out[j] = jax.tree_util.tree_map(lambda x, n=n, b=b: x[b, :n], arrays)
    per_session = []
    for i in range(len(sessions)):
        mine = [out[j] for j, (k, _) in enumerate(pieces) if k == i]
        paths = "+".join(dict.fromkeys(e.path for e in mine))
        joined = jax.tree_util.tree_map(lambda *x: np.concatenate(x),
                                        *[dataclasses.replace(e, path=None) for e in mine])
        per_session.append(dataclasses.replace(joined, path=paths))
    return per_session
