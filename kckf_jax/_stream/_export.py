"""Serialise the streaming step with ``jax.export`` for deployment without kckf-jax.

The file holds a small JSON header (layout, names, dtype, initial state, parameters when they
are passed rather than baked in) and the serialised ``jax.export.Exported`` of the very
function ``StreamingFilter`` runs. ``kckf_jax/export_loader.py`` runs it in a process that
imports only jax and numpy.
"""

from __future__ import annotations

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._models._classes import AbstractModel, estimated, init_state, method_name
from .._models._params import Params, get_leaf, leaf_names
from .._readings._gaps import GapPolicy
from .._readings._health import init_health
from .._readings._screen import FAULT_KINDS
from .._sessions._atomic import atomic_write
from . import stream_step_fn

MAGIC = b"KCKF-JAXEXPORT/1\n"


def export_step(params: Params, path: str, method: str | AbstractModel = "kckf", baked: bool = True,
                gaps: GapPolicy = GapPolicy()) -> int:
    """Write the per-packet step of ``method`` to ``path``; returns the file size in bytes.

    Args:
        params: the filter parameters (their dtype is the exported precision).
        path: output file (``.jaxexport``).
        method: a model of ``_models`` or its name (``METHODS``).
        baked: bake the parameters into the program (default); otherwise the program takes
            the vector of unconstrained parameter leaves as its first input, so new fitted
            parameters can be loaded without exporting again.
        gaps: the gap policy the loader applies (its defaults; ``kckf stream``'s rule).

    The step judges every reading as ``kckf stream`` does (``_screen``, ``_health``: its
    state carries the sensors' health) and its output ends with each reading's fault code, so
    the loader names faulty readings (``masked``, by column and kind: the header's
    ``fault_kinds``).
    """
    method = method_name(method)
    robot = params.robot
    dtype = params.log_q.dtype
    fn, flatten, _ = stream_step_fn(params, method, health=True)
    s0 = np.asarray(flatten((init_state(params, method), init_health(robot, dtype))))
    x_size = 1 + 3 * robot.n_links + robot.n_hall
    spec_s = jax.ShapeDtypeStruct(s0.shape, dtype)
    spec_x = jax.ShapeDtypeStruct((x_size,), dtype)
    names = leaf_names(params)
    shapes = [np.shape(get_leaf(params, n)) for n in names]
    sizes = [int(np.prod(shape, dtype=int)) for shape in shapes]
    leaves = np.concatenate([np.ravel(np.asarray(get_leaf(params, n))) for n in names])
    if baked:
        exported = jax.export.export(jax.jit(lambda s, x: fn(s, x)))(spec_s, spec_x)
    else:
        cuts = np.cumsum(sizes)[:-1].tolist()

        def with_params(p_flat, s, x):
            parts = [part.reshape(shape) for part, shape in zip(jnp.split(p_flat, cuts), shapes)]
            p = eqx.tree_at(lambda q: [get_leaf(q, n) for n in names], params, parts)
            return fn(s, x, p)

        spec_p = jax.ShapeDtypeStruct(leaves.shape, dtype)
        exported = jax.export.export(jax.jit(with_params))(spec_p, spec_s, spec_x)
    header = {
        "format": "kckf-export/1", "method": method, "joints": robot.to_meta(),
        "dtype": np.dtype(dtype).name, "gyro_names": list(robot.gyro_names),
        "hall_names": list(robot.hall_names), "angle_names": list(robot.angle_names),
        "estimated": estimated(robot, method).tolist(), "initial_state": s0.tolist(),
        "x_size": x_size,
        "params_mode": "baked" if baked else "passed",
        "params": None if baked else leaves.tolist(),
        "param_leaves": [[n, k] for n, k in zip(names, sizes)],
        "limits": params.limits.to_meta(),
        "fault_kinds": list(FAULT_KINDS),
        "gaps": {"gap_s": gaps.gap_s, "on_gap": gaps.on_gap,
                 "max_predict_s": gaps.max_predict_s},
    }
    head = json.dumps(header).encode()
    blob = exported.serialize()
    with atomic_write(path, "wb") as f:
        f.write(MAGIC)
        f.write(len(head).to_bytes(8, "little"))
        f.write(head)
        f.write(blob)
    return len(MAGIC) + 8 + len(head) + len(blob)
