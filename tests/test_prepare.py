"""The readings prepared once (``_readings._prepare``): three types say how far a series has
come (``SensorSeries`` as recorded, ``ScreenedSeries`` judged, ``FilterInput`` judged and
corrected), the kernel computes only on the last, and a lone row prepared with the state's
hold equals the same row of a prepared recording."""

from __future__ import annotations

import ast
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_effects import some_effects

import kckf_jax as kk
from kckf_jax._models._effects import EFFECTS

ROBOT = kk.Robot.from_spec("x,y")


@pytest.fixture(scope="module")
def session():
    s = kk.simulate(ROBOT, "cyclic", seed=5, duration_s=8.0, drop_prob=0.02)
    # A disconnected Hall sensor (railed): judged, so missing to the filter.
    return kk.inject_faults(s, [kk.Fault.parse("disconnect:hall1_x_l@3-3.4")], seed=1)


def test_the_kernel_takes_only_prepared_readings(session):
    params = kk.Params.paper_defaults(ROBOT, session.hall_models)
    raw = kk.session_series(session)
    with pytest.raises(TypeError, match=r"kk\.prepare\(params, series, method\)"):
        kk.scan_filter(params, raw)
    state = kk.init_state(params)
    row = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[1], raw)
    with pytest.raises(TypeError, match=r"kk\.prepare_row"):
        kk.step(params, state, row)
    ready = kk.prepare(params, raw)
    assert type(ready) is kk.FilterInput
    _, est = kk.scan_filter(params, ready)
    ref = kk.run_filter(params, raw, path="sequential")[1]
    np.testing.assert_array_equal(np.asarray(est.angles), np.asarray(ref.angles))


def test_a_screened_series_is_not_judged_again(session):
    """``screened`` once, then ``prepare`` with any parameters of the same Hall curves: the
    readings the filter uses are those of preparing the raw series, each sensor effect
    applied with the parameters given."""
    params = kk.Params.paper_defaults(ROBOT, session.hall_models).with_effects(
        EFFECTS, some_effects(ROBOT))
    raw = kk.session_series(session)
    judged, codes = kk.screened(params, raw)
    assert type(judged) is kk.ScreenedSeries and int((np.asarray(codes) > 0).sum()) >= 40
    for p in (params, params.with_effects(())):
        a, b = kk.prepare(p, judged), kk.prepare(p, raw, dtype=judged.gyro.dtype)
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # A prepared series is returned as it is.
    ready = kk.prepare(params, judged)
    assert kk.prepare(params, ready) is ready
    # The effects are taken out once: preparing the corrected readings again changes nothing.
    assert not np.allclose(np.asarray(ready.gyro), np.asarray(judged.gyro), equal_nan=True)


def test_a_lone_row_is_prepared_as_the_row_of_a_recording(session):
    """Row by row with ``prepare_row`` (the learned gyro timing applied through the state's
    hold) and the scan over the prepared recording (``timed_gyro`` over its rows): the same
    estimates to rounding, on a recording with missing readings (nothing the monitor would
    take out: the row screen alone is the lone row's judge)."""
    params = kk.Params.paper_defaults(ROBOT, session.hall_models).with_effects(
        EFFECTS, some_effects(ROBOT)).with_faults("off")
    raw = kk.session_series(session)
    _, batch = kk.scan_filter(params, kk.prepare(params, raw))

    @jax.jit
    def one(state, row):
        state, ready = kk.prepare_row(params, state, row)
        assert type(ready) is kk.FilterInput
        return kk.step(params, state, ready)

    state = kk.init_state(params)
    angles = []
    for k in range(raw.dt.shape[0]):
        state, est = one(state, jax.tree_util.tree_map(lambda x: jnp.asarray(x)[k], raw))
        angles.append(np.asarray(est.angles))
    np.testing.assert_allclose(np.array(angles), np.asarray(batch.angles), atol=1e-9)


def test_only_the_preparing_module_judges_or_corrects():
    """The screen over time and the sensor effects reach the readings in one place
    (``_readings/_prepare.py``); the kernel imports nothing of the readings' checks."""
    root = Path(kk.__file__).parent
    callers = {"screened_series": set(), "corrected_readings": set()}
    for f in root.rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and (
                    node.func.id in callers):
                callers[node.func.id].add(f.relative_to(root).as_posix())
    # (_paths/_base.py judges a raw series only to say whether it is regular, and drops it.)
    assert callers["screened_series"] <= {"_readings/_prepare.py", "_readings/_health.py",
                                          "_paths/_base.py"}, callers
    assert callers["corrected_readings"] == {"_readings/_prepare.py"}, callers
    kernel = (root / "_models" / "_kernel.py").read_text()
    assert "_readings" not in "".join(
        line for line in kernel.splitlines() if line.startswith(("from", "import")))
