"""The paths agree with the sequential filter (1e-8 rad in float64), and ``Auto`` picks the
fastest that applies, with reasons.

Most tests use a ``Steady`` with small constants (its fields) and fast-converging noise, so
that the same properties are checked on a few hundred rows; one checks the defaults at full
size.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kckf_jax import (
    AbstractPath,
    Auto,
    Lanes,
    Params,
    Robot,
    SensorSeries,
    Sequential,
    Steady,
    choose_path,
    filter_batch,
    filter_sessions,
    loss_fn,
    make_batch,
    pad_series,
    run_filter,
    session_series,
    simulate,
    smooth_batch,
)
from kckf_jax._paths._likelihood import hall_nll

DEG = np.pi / 180
#: Small constants: the head is 256 / 512 rows, chunk groups nest several levels deep, and a
#: block holds a few chunks, so every branch of the steady path runs on ~1,000 rows.
SMALL = Steady(min_rows=600, head_rows_float32=256, head_rows_float64=512, carry_scan=3,
               carry_group=4, mean_block=512)
T_SMALL = 1037  # a partial last chunk


def fast_params(robot, s=None, dtype=jnp.float64, **kw):
    """Noise that makes the covariance converge within ~500 rows at 100 Hz."""
    return Params.from_physical(robot, q=1e4 * DEG**2, hall_models=s.hall_models if s else None,
                                dtype=dtype, **kw)


def regular(robot, seed, T, dtype=jnp.float64, kind="cyclic"):
    """A session with an exactly constant time step and no missing reading."""
    s = simulate(robot, kind, seed=seed, duration_s=T / 100.0)
    dt = np.r_[0.0, np.full(T - 1, 0.01)]
    return s, SensorSeries(jnp.asarray(dt, dtype), jnp.asarray(s.gyro, dtype),
                           jnp.asarray(s.hall_v, dtype))


def stack(trials):
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *trials)


def close(a, b, atol, rtol=0.0):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=atol, rtol=rtol)


@pytest.mark.parametrize("spec", ["x,y,x,y", "xyz,xyz,xyz,xyz", "xz,y"])
@pytest.mark.long
def test_steady_equals_sequential_float64(spec):
    """Two blocks, three blocks of three joints, and blocks of different sizes (padding)."""
    robot = Robot.from_spec(spec)
    s, series = regular(robot, 1, T_SMALL)
    params = fast_params(robot, s)
    ref_final, ref = run_filter(params, series, "kckf", path="sequential")
    final, est = run_filter(params, series, "kckf", path=SMALL)
    assert (ref.path, est.path) == ("sequential", "steady")
    assert not np.array_equal(np.asarray(est.angles), np.asarray(ref.angles))
    close((est.angles, est.bias, final.z), (ref.angles, ref.bias, ref_final.z), 1e-8)
    close((est.angle_std, final.P), (ref.angle_std, ref_final.P), 1e-10, 1e-6)
    np.testing.assert_array_equal(final.gyro_hold, ref_final.gyro_hold)


def test_parallel_equals_sequential_and_the_standard_kf_never_steady():
    robot = Robot.from_spec("xz,y")
    s, series = regular(robot, 1, T_SMALL)
    params = fast_params(robot, s)
    for method in ("kckf", "kf"):
        ref_final, ref = run_filter(params, series, method, path="sequential")
        final, est = run_filter(params, series, method, path="parallel")
        assert est.path == "parallel"
        close((est.angles, est.bias, final.z), (ref.angles, ref.bias, ref_final.z), 1e-8)
        close((est.angle_std, final.P), (ref.angle_std, ref_final.P), 1e-10, 1e-6)
    # The standard KF: its torso variance grows without bound, so the steady path never
    # applies (Auto passes it over, an explicit request says why).
    choice = choose_path(params, series, "kf", Auto(steady=SMALL))
    assert choice.path.name == "sequential" and "unobservable" in choice.passed_over["steady"]
    with pytest.raises(ValueError, match="path='steady' does not apply: the standard KF"):
        run_filter(params, series, "kf", path=SMALL)


@pytest.mark.long  # a heavy check beside a lighter default one (the default run within 4 min)
def test_default_steady_at_full_size_float64():
    """The defaults on the paper's parameters: ``auto`` takes the steady path past 4,096 rows
    and agrees with the sequential filter."""
    robot = Robot.from_spec("x,y,x,y")
    s, series = regular(robot, 3, 4096 + 900)
    params = Params.paper_defaults(robot, s.hall_models, dtype=jnp.float64)
    assert choose_path(params, series, "kckf") == (Steady(), {})
    _, ref = run_filter(params, series, "kckf", path="sequential")
    _, est = run_filter(params, series, "kckf")
    assert est.path == "steady"
    close((est.angles, est.bias), (ref.angles, ref.bias), 1e-8)


def test_parallel_handles_missing_readings_uneven_steps_and_voltage_noise():
    robot = Robot.from_spec("x,y,x,y")
    s = simulate(robot, "human", seed=4, duration_s=6.0, drop_prob=0.05)
    params = Params.from_physical(robot, hall_models=s.hall_models, hall_noise="voltage",
                                  dtype=jnp.float64)
    series = SensorSeries(jnp.asarray(s.dt()), jnp.asarray(s.gyro), jnp.asarray(s.hall_v))
    choice = choose_path(params, series, "kckf", Auto(steady=SMALL))
    assert choice.path == Sequential()
    assert choice.passed_over["steady"].startswith("the voltage noise model")
    _, ref = run_filter(params, series, "kckf", path="sequential")
    _, par = run_filter(params, series, "kckf", path="parallel")
    close(par.angles, ref.angles, 1e-8)
    with pytest.raises(ValueError, match="does not apply: the voltage noise model"):
        run_filter(params, series, "kckf", path="steady")


def test_reasons_for_every_kind_of_irregular_data():
    robot = Robot.from_spec("x,y")
    _, series = regular(robot, 2, T_SMALL)
    params = fast_params(robot)
    auto = Auto(steady=SMALL)

    def why(x, p=params):
        return choose_path(p, x, "kckf", auto).passed_over.get("steady")

    assert why(series) is None and choose_path(params, series, "kckf", auto).path == SMALL
    hall = np.asarray(series.hall_v).copy()
    hall[T_SMALL - 100, 1] = np.nan  # among the converged rows
    assert why(SensorSeries(series.dt, series.gyro, hall)) == (
        "a Hall reading is missing or out of range")
    gyro = np.asarray(series.gyro).copy()
    gyro[50, int(robot.used_gyro_index[0])] = np.nan
    assert why(SensorSeries(series.dt, gyro, series.hall_v)) == (
        "a gyro reading is missing or out of range")
    unused = np.asarray(series.gyro).copy()
    unused[:, 2] = np.nan  # gyro1_z: the planar robot never reads it
    assert why(SensorSeries(series.dt, unused, series.hall_v)) is None
    dt = np.asarray(series.dt).copy()
    dt[300] += 1e-4
    assert why(SensorSeries(dt, series.gyro, series.hall_v)) == "the time step is not constant"
    short = jax.tree_util.tree_map(lambda x: x[:500], series)
    assert why(short) == "500 rows, not more than 600"
    slow = Params.from_physical(robot, q=1e-16, p0_bias=0.5, dtype=jnp.float64)
    assert why(series, slow).startswith("the covariance has not converged after 512 rows")
    with pytest.raises(ValueError, match="has not converged"):
        run_filter(slow, series, "kckf", path=SMALL)
    # Each trial is regular, but the steps differ: one shared covariance would be wrong.
    b = SensorSeries(series.dt * 2, series.gyro, series.hall_v)
    assert why(stack([series, b])) == "the time step is not one constant shared by every trial"
    # Under a transformation the data cannot be checked: the sequential path, and it says so.
    got = {}

    def traced(x):
        choice = choose_path(params, SensorSeries(x, series.gyro, series.hall_v), "kckf", auto)
        got.update(choice.passed_over, path=choice.path.name)
        return x

    jax.jit(traced)(series.dt)
    assert got["path"] == "sequential" and "traced" in got["steady"]


def test_steady_path_inside_jit_trusts_the_caller():
    robot = Robot.from_spec("x,y")
    s, series = regular(robot, 4, T_SMALL)
    params = fast_params(robot, s)
    est = jax.jit(lambda x: run_filter(params, x, "kckf", path=SMALL)[1].angles)(series)
    _, ref = run_filter(params, series, "kckf", path="sequential")
    close(est, ref.angles, 1e-8)


@pytest.mark.long
def test_batch_steady_float32_and_gradients_float64():
    """A batch of regular trials: the steady path (one shared covariance phase, several whole
    blocks and nested chunk groups) equals the sequential filter, in float32 to 1e-4 rad, and
    in float64 the gradients of a loss of angles and biases with respect to the parameters
    and to the readings themselves, and of one of the angles alone (the hand-written reverse
    modes' every branch), agree to 1e-6; under ``jit`` of the parameters, where the readings
    closed over are still checked concretely (they used to raise a ConcretizationTypeError)."""
    robot = Robot.from_spec("xz,y")
    trials = [regular(robot, seed, T_SMALL)[1] for seed in (5, 6, 7)]
    batch = stack(trials)
    params = fast_params(robot, dtype=jnp.float32)
    b32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), batch)
    assert choose_path(params, b32, "kckf", Auto(steady=SMALL)).path == SMALL
    seq = filter_batch(params, b32, "kckf", path="sequential")
    fast = filter_batch(params, b32, "kckf", path=SMALL)
    assert fast.path == "steady" and not np.array_equal(np.asarray(fast.angles),
                                                        np.asarray(seq.angles))
    close((fast.angles, fast.bias), (seq.angles, seq.bias), 1e-4)
    close(fast.angle_std, seq.angle_std, 1e-4, 1e-5)

    params = fast_params(robot)

    def loss(p, gyro, hall_v, path):
        est = filter_batch(p, SensorSeries(batch.dt, gyro, hall_v), "kckf", path=path)
        return jnp.mean(est.angles ** 2) + jnp.mean(jnp.sin(3.0 * est.bias))

    def angles_only(p, path):
        return jnp.mean(filter_batch(p, batch, "kckf", path=path).angles ** 2)

    for f, args in ((loss, (params, batch.gyro, batch.hall_v)), (angles_only, (params,))):
        argnums = tuple(range(len(args)))
        (v_seq, g_seq), (v_fast, g_fast) = (
            jax.jit(jax.value_and_grad(lambda *a, path=path: f(*a, path), argnums=argnums))(*args)
            for path in (Sequential(), SMALL))
        np.testing.assert_allclose(v_fast, v_seq, rtol=1e-9)
        flat_seq = jax.tree_util.tree_leaves(eqx.filter(g_seq, eqx.is_inexact_array))
        flat_fast = jax.tree_util.tree_leaves(eqx.filter(g_fast, eqx.is_inexact_array))
        assert len(flat_fast) == len(flat_seq)
        for a, b in zip(flat_fast, flat_seq):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9 * float(np.abs(b).max() + 1))
        assert all(np.abs(np.asarray(x)).max() > 0 for x in jax.tree_util.tree_leaves(g_fast[1:]))


@pytest.mark.long
def test_auto_under_grad_and_padded_batches_take_the_sequential_path():
    robot = Robot.from_spec("x")
    rng = np.random.default_rng(0)
    trials = [SensorSeries(np.full(n, 0.01), rng.normal(size=(n, 6)), rng.uniform(1, 2, (n, 2)))
              for n in (700, 650)]
    params = fast_params(robot)
    batch = pad_series(trials)
    assert filter_batch(params, batch, "kckf", path=Auto(steady=SMALL)).path == "sequential"
    assert "time step" in choose_path(params, batch, "kckf", Auto(steady=SMALL)).passed_over[
        "steady"]


def test_unknown_path():
    robot = Robot.from_spec("x")
    with pytest.raises(ValueError, match="path must be one of"):
        run_filter(Params.paper_defaults(robot), regular(robot, 1, 10)[1], path="fast")
    with pytest.raises(ValueError, match="Steady.head_rows_float64"):
        Steady(min_rows=100, head_rows_float32=50, head_rows_float64=200)


@pytest.mark.parametrize("spec", ["x,y,x,y", "xz,y,xyz"])
@pytest.mark.long
def test_lanes_equal_sequential_on_recorded_like_data(spec):
    """Jittered time steps, 5 % missing readings per channel, the voltage noise model, padded
    trials of uneven length and one update that overflows: the lanes path equals the
    sequential one (1e-9 rad in float64, final states and skipped steps included; 1e-4 rad in
    float32), and Auto takes it for a batch."""
    robot = Robot.from_spec(spec)
    trials = []
    for seed, n in ((1, 300), (2, 257), (3, 280), (4, 300), (5, 211), (6, 300), (7, 290),
                    (8, 300)):
        s = simulate(robot, "human", seed=seed, duration_s=n / 100.0, drop_prob=0.05)
        trials.append(SensorSeries(s.dt(), s.gyro, s.hall_v))
    plain = pad_series(trials)
    dt = np.asarray(plain.dt).copy()
    dt[2, 100] = 1e200  # an overflowing prediction: skipped, the state kept
    batch = SensorSeries(dt, plain.gyro, plain.hall_v)
    p64 = Params.from_physical(robot, hall_models=s.hall_models, hall_noise="voltage",
                               dtype=jnp.float64)
    assert choose_path(p64, batch, "kckf", Auto(lanes=Lanes(min_trials=8))).path == Lanes(
        min_trials=8)
    few = choose_path(p64, batch, "kckf")  # the default: lanes pay from 12 trials
    assert few.path == Sequential() and "fewer than 12" in few.passed_over["lanes"]
    ref = filter_batch(p64, batch, "kckf", path="sequential")
    got = filter_batch(p64, batch, "kckf", path="lanes")
    assert got.path == "lanes"
    close((got.angles, got.bias), (ref.angles, ref.bias), 1e-9)
    close(got.angle_std, ref.angle_std, 1e-11, 1e-8)
    np.testing.assert_array_equal(np.asarray(got.skipped), np.asarray(ref.skipped))
    assert np.asarray(got.skipped)[2, 100] and np.asarray(got.skipped).sum() == 1
    p32 = p64.astype(jnp.float32)
    b32 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), plain)
    ref = filter_batch(p32, b32, "kckf", path="sequential")
    est = filter_batch(p32, b32, "kckf", path="lanes")
    close(est.angles, ref.angles, 1e-4)  # float32's own rounding, amplified early on
    one = SensorSeries(batch.dt[2], batch.gyro[2], batch.hall_v[2])
    (f_ref, _), (f_got, _) = (run_filter(p64, one, "kckf", path=p) for p in ("sequential",
                                                                            "lanes"))
    close((f_got.z, f_got.P, f_got.gyro_hold), (f_ref.z, f_ref.P, f_ref.gyro_hold), 1e-9)
    _, one_ref = run_filter(p64, trials[0], "kf", path="sequential")
    one = filter_batch(p64, stack([trials[0]] * 2), "kf", path="lanes")
    close(one.angles[0], one_ref.angles, 1e-9)


@pytest.mark.long
def test_lanes_checkpointed_in_chunks_gives_the_same_values_and_gradients():
    """``Lanes(remat_chunk=...)``: the last chunk padded with no-op rows, the outputs cut back;
    values and gradients equal the plain scan's (float64)."""
    robot = Robot.from_spec("x,y")
    trials = [simulate(robot, "human", seed=s, duration_s=n / 100.0, drop_prob=0.05)
              for s, n in ((1, 60), (2, 47), (3, 55))]
    batch = pad_series([SensorSeries(s.dt(), s.gyro, s.hall_v) for s in trials])
    params = Params.from_physical(robot, hall_models=trials[0].hall_models,
                                  hall_noise="voltage", dtype=jnp.float64)

    def loss(p, path):
        return jnp.nansum(filter_batch(p, batch, "kckf", path=path).angles ** 2)

    (v0, g0), (v1, g1) = (eqx.filter_value_and_grad(loss)(params, path)
                          for path in (Lanes(), Lanes(remat_chunk=7)))
    assert float(v1) == pytest.approx(float(v0), rel=1e-13)
    for a, b in zip(jax.tree_util.tree_leaves(eqx.filter(g0, eqx.is_inexact_array)),
                    jax.tree_util.tree_leaves(eqx.filter(g1, eqx.is_inexact_array))):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-10, atol=1e-14)


class _Reversed(AbstractPath):
    """A toy path by the docs' recipe (``kckf_jax._paths``): the sequential scan of the trials
    in reverse order, reversed back; nothing in the package knows of it."""

    name: ClassVar[str] = "reversed"

    def applies(self, params, series, method, state=None):
        return None if np.ndim(series.dt) > 1 else "needs a batch"

    def run(self, params, series, method, state):
        flip = lambda t: jax.tree_util.tree_map(lambda x: x[::-1], t)  # noqa: E731
        final, est = Sequential().run(params, flip(series), method, flip(state))
        return flip(final), flip(est)


@pytest.mark.long
def test_a_path_added_by_the_recipe_runs_everywhere_and_nothing_else_changes():
    """Passed as ``path=`` to the filter calls and the loss, offered to ``Auto`` as ``before``,
    and asked every question the package asks of a path (its answers the defaults)."""
    robot = Robot.from_spec("x,y")
    sessions = [simulate(robot, "cyclic", seed=s, duration_s=1.0 + 0.3 * s, drop_prob=0.05)
                for s in range(3)]
    params = Params.paper_defaults(robot, dtype=jnp.float64)
    batch = pad_series([session_series(s, np.float64) for s in sessions])
    ref = filter_batch(params, batch, "kckf", path="sequential")
    toy = filter_batch(params, batch, "kckf", path=_Reversed())
    assert toy.path == "reversed"
    close(toy.angles, ref.angles, 1e-12)
    auto = Auto(before=(_Reversed(),))
    assert choose_path(params, batch, "kckf", auto).path == _Reversed()
    assert filter_batch(params, batch, "kckf", path=auto).path == "reversed"
    # One recording: the toy path does not apply, says why, and Auto goes on.
    one = session_series(sessions[0], np.float64)
    choice = choose_path(params, one, "kckf", auto)
    assert choice.passed_over["reversed"] == "needs a batch" and choice.path.name != "reversed"
    with pytest.raises(ValueError, match="path='reversed' does not apply: needs a batch"):
        run_filter(params, one, "kckf", path=_Reversed())
    # The fit's loss, the smoother and the likelihood take it as any path.
    b = make_batch(sessions, jnp.float64)
    assert float(loss_fn(params, b, path=_Reversed())) == pytest.approx(
        float(loss_fn(params, b, path="sequential")), rel=1e-12)
    assert smooth_batch(params, batch, "kckf", path=_Reversed()).path == "smoothed"
    assert float(hall_nll(params, batch, path=_Reversed())) == pytest.approx(
        float(hall_nll(params, batch, path="sequential")), rel=1e-12)
    assert filter_sessions(sessions, "kckf", params, path=_Reversed())[0].path == "reversed"


def test_auto_under_a_callers_trace_decides_on_shapes_as_documented():
    """Inside ``jit``: no steady (its checks need values), lanes for a batch of
    ``lanes.min_trials`` trials, segments for a long recording, else sequential."""
    robot = Robot.from_spec("x")
    params = Params.paper_defaults(robot)
    picked = {}

    def pick(name, series):
        def f(dt, gyro, hall_v):
            choice = choose_path(params, SensorSeries(dt, gyro, hall_v), "kckf")
            picked[name] = (choice.path.name, choice.passed_over)
            return dt.sum()

        jax.jit(f)(series.dt, series.gyro, series.hall_v)

    def rows(B, T):
        shape = (B, T) if B else (T,)
        return SensorSeries(jnp.full(shape, 0.01), jnp.zeros(shape + (6,)),
                            jnp.full(shape + (2,), 1.3))

    lanes = Auto().lanes.min_trials
    pick("batch", rows(lanes, 50))
    pick("few", rows(lanes - 1, 50))
    pick("long", rows(None, 40_000))
    pick("short", rows(None, 500))
    assert picked["batch"][0] == "lanes" and "traced" in picked["batch"][1]["steady"]
    assert picked["few"][0] == "sequential"
    assert picked["long"][0] == "segments"
    assert picked["short"][0] == "sequential"
    # The layouts the smoother and the likelihood take follow the same policy.
    assert Auto().batch_layout(lanes) == "lanes" and Auto().batch_layout(lanes - 1) == (
        "sequential")
    assert Auto(lanes=Lanes(min_trials=4)).batch_layout(4) == "lanes"


@pytest.mark.long  # a heavy check beside a lighter default one (the default run within 4 min)
def test_auto_weighs_compile_time_for_the_runs_it_is_told_and_repairs_it_foresees():
    """``Auto(runs=1)`` (the command's policy) takes the lanes or segments path only where its
    compile plus one run is estimated shorter than the sequential path's; a stretch without a
    joint's Hall readings at least half a warm-up long keeps ``Auto`` off the segments path
    (its check would fail and the repairs cost more, ``benchmarks/one_shot.py``)."""
    robot = Robot.from_spec("x")
    params = Params.paper_defaults(robot, dtype=jnp.float32)
    rng = np.random.default_rng(0)

    def rows(B, T):  # irregular steps: the steady path does not apply
        dt = jnp.asarray(0.01 + 1e-4 * rng.random((B, T)), jnp.float32).at[:, 0].set(0.0)
        return SensorSeries(dt, jnp.zeros((B, T, 6), jnp.float32),
                            jnp.full((B, T, 2), 1.3, jnp.float32))

    twelve, many = rows(12, 10_000), rows(64, 10_000)
    assert choose_path(params, twelve).path.name == "lanes"
    once = choose_path(params, twelve, path=Auto(runs=1))
    assert once.path.name == "sequential"
    assert "for 1 run(s) its compile costs more than it saves" in once.passed_over["lanes"]
    assert choose_path(params, many, path=Auto(runs=1)).path.name == "lanes"
    assert choose_path(params, twelve, path=Auto(runs=100)).path.name == "lanes"
    hour = jax.tree_util.tree_map(lambda x: x[0], rows(1, 40_000))
    assert choose_path(params, hour).path.name == "segments"
    assert choose_path(params, hour, path=Auto(runs=1)).path.name == "sequential"
    W = Auto().segments.warmup(jnp.float32)
    for gap, expected in ((W // 4, "segments"), (W // 2, "sequential")):
        holed = SensorSeries(hour.dt, hour.gyro, hour.hall_v.at[20_000:20_000 + gap, 0:2].set(
            jnp.nan))
        choice = choose_path(params, holed)
        assert choice.path.name == expected, choice.passed_over
    assert f"for {W // 2} rows (from row 20000)" in choice.passed_over["segments"]
    # One sensor of the pair is enough: the joint still has a reading.
    one_side = SensorSeries(hour.dt, hour.gyro, hour.hall_v.at[20_000:30_000, 0].set(jnp.nan))
    assert choose_path(params, one_side).path.name == "segments"


def test_no_path_is_decided_outside_the_paths_package():
    """No class check of a path and no path's threshold outside ``kckf_jax/_paths``: every
    question goes to the path objects (``AbstractPath``)."""
    import ast
    import pathlib

    import kckf_jax

    root = pathlib.Path(kckf_jax.__file__).parent
    classes = {"Sequential", "Steady", "Lanes", "Segments", "Parallel", "Auto"}
    bad = []
    for f in root.rglob("*.py"):
        if "_paths" in f.parts:
            continue
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Attribute) and node.attr in (
                    "min_trials", "min_rows", "min_segments"):
                bad.append(f"{f.name}:{node.lineno}: .{node.attr}")
            if (isinstance(node, ast.Call) and getattr(node.func, "id", "") == "isinstance"
                    and {n.id for n in ast.walk(node.args[1]) if isinstance(n, ast.Name)}
                    & classes):
                bad.append(f"{f.name}:{node.lineno}: isinstance")
    assert bad == []
