"""Filters applied to recorded sessions: ``Session`` -> ``SensorSeries`` -> ``Estimate``.

Sessions of one robot are padded to a common length and filtered in one ``vmap`` (with one
parameter set, or one per session, e.g. each session's own Hall calibration from its
``meta.json``), so a command compiles each method once, whatever the number of sessions.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._filter import Estimate, SensorSeries, pad_series, run_filter
from ._params import Params
from ._session import Session


def session_series(session: Session, dtype=None) -> SensorSeries:
    """The filter inputs of a session; time differenced in float64 before any cast."""
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
                   dtype=None) -> list[Params]:
    """One parameter set per session: ``params`` if given, else the paper defaults with the
    session's own Hall calibration (``meta.json``'s ``hall_models``)."""
    robot = common_robot(sessions)
    if params is not None:
        if params.robot != robot:
            raise ValueError(
                f"parameters are for robot {params.robot.spec!r} but the sessions have "
                f"{robot.spec!r}"
            )
        return [params.astype(dtype) if dtype is not None else params] * len(sessions)
    return [Params.paper_defaults(robot, s.hall_models, dtype=dtype) for s in sessions]


def stack_params(params: Sequence[Params]) -> Params:
    """Stack parameter sets leaf by leaf (for ``vmap`` over sessions)."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *params)


@eqx.filter_jit
def _filter_stacked(params: Params, series: SensorSeries, method: str) -> Estimate:
    return jax.vmap(lambda p, s: run_filter(p, s, method)[1])(params, series)


def filter_sessions(
    sessions: Sequence[Session], method: str = "kckf", params: Params | None = None,
    dtype=None,
) -> list[Estimate]:
    """Run ``method`` over every session (padded, vmapped); one ``Estimate`` per session,
    cut back to the session's own length, as NumPy arrays."""
    plist = session_params(sessions, params, dtype)
    dtype = plist[0].log_q.dtype
    batch = pad_series([SensorSeries(s.dt(), s.gyro, s.hall_v) for s in sessions])
    batch = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), batch)
    est = _filter_stacked(stack_params(plist), batch, method)
    est = jax.tree_util.tree_map(np.asarray, est)
    return [jax.tree_util.tree_map(lambda x, n=s.n_steps, b=b: x[b, :n], est)
            for b, s in enumerate(sessions)]
