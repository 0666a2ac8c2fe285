"""The segments path (one long recording cut into warmed-up segments run as lanes) equals the
sequential filter wherever its check passes (at once or after a repair pass), falls back to
it where the repairs fail too, says which ran, and ``Auto`` takes it for long recordings only.

Most tests use small constants (``SMALL``: warm-ups of 800 rows, a few lanes) and noise that
makes the filter forget its start within ~800 rows, so each property is checked on a few
thousand rows; one checks the defaults at full size in float32.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kckf_jax import (
    Auto,
    Lanes,
    Params,
    Robot,
    Segments,
    SensorSeries,
    Sequential,
    choose_path,
    filter_batch,
    init_state,
    pad_series,
    run_filter,
    simulate,
)
from kckf_jax._fitting._fit import Batch, rmse_loss

DEG = np.pi / 180
SMALL = Segments(lanes=6, warmup_float64=800, warmup_float32=800, min_segments=2)


def recorded_like(robot, seed, n, drop=0.05):
    """The simulator's jittered stamps, ``drop`` of the readings missing channel by channel."""
    s = simulate(robot, "human", seed=seed, duration_s=n / 100.0, drop_prob=drop)
    return s, SensorSeries(s.dt(), s.gyro, s.hall_v)


def fast(robot, s, dtype=jnp.float64):
    """The voltage noise model and process noise that make the filter forget fast."""
    return Params.from_physical(robot, q=1e4 * DEG**2, hall_models=s.hall_models,
                                hall_noise="voltage", dtype=dtype)


def close(a, b, atol, rtol=0.0):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=atol, rtol=rtol)


@pytest.mark.parametrize("spec", ["x,y,x,y", "xz,y,xyz"])
def test_segments_equal_sequential_on_recorded_like_data(spec):
    """Jittered steps, 5 % missing readings, the voltage model and one overflowing update:
    angles, biases, their standard deviations, the skipped step and the final state equal
    the sequential path's (1e-9 rad in float64); ``Estimate.path`` says the segments ran."""
    robot = Robot.from_spec(spec)
    s, series = recorded_like(robot, 1, 4801)
    dt = np.asarray(series.dt).copy()
    dt[3700] = 1e200  # an overflowing prediction: skipped, the state kept
    series = SensorSeries(dt, series.gyro, series.hall_v)
    params = fast(robot, s)
    ref_final, ref = run_filter(params, series, "kckf", path="sequential")
    final, est = run_filter(params, series, "kckf", path=SMALL)
    assert est.path == "segments"
    assert SMALL.segments_of(1, 4801, jnp.float64) == 6  # all six lanes, 801 rows each
    close((est.angles, est.bias, final.z), (ref.angles, ref.bias, ref_final.z), 1e-9)
    close((est.angle_std, final.P), (ref.angle_std, ref_final.P), 1e-12, 1e-8)
    np.testing.assert_array_equal(np.asarray(est.skipped), np.asarray(ref.skipped))
    assert np.asarray(est.skipped)[3700] and np.asarray(est.skipped).sum() == 1
    np.testing.assert_array_equal(final.gyro_hold, ref_final.gyro_hold)
    # The standard KF: nothing observes its torso angle, so it never forgets its start and
    # no warm-up could converge: the path does not apply, and says why.
    with pytest.raises(ValueError, match="path='segments' does not apply: the standard KF"):
        run_filter(params, series, "kf", path=SMALL)
    assert choose_path(params, series, "kf", Auto(segments=SMALL)).passed_over[
        "segments"].startswith("the standard KF's torso angle and bias are unobservable")


def test_segments_batch_of_uneven_trials_and_an_entering_state():
    """A padded batch of two trials (each cut into three segments) and a recording entered
    from another state equal the sequential path's."""
    robot = Robot.from_spec("x,y")
    trials = [recorded_like(robot, seed, n) for seed, n in ((2, 2400), (3, 1900))]
    params = fast(robot, trials[0][0])
    batch = pad_series([t[1] for t in trials])
    ref = filter_batch(params, batch, "kckf", path="sequential")
    got = filter_batch(params, batch, "kckf", path=SMALL)
    assert got.path == "segments"
    close((got.angles, got.bias), (ref.angles, ref.bias), 1e-9)
    close(got.angle_std, ref.angle_std, 1e-12, 1e-8)
    state = init_state(params, "kckf")
    state = type(state)(state.z + 0.1, state.P * 2.0, state.gyro_hold + 0.01)
    one = trials[0][1]
    (f_ref, e_ref), (f_got, e_got) = (run_filter(params, one, "kckf", state, path=p)
                                      for p in ("sequential", SMALL))
    assert e_got.path == "segments"
    close((e_got.angles, f_got.z, f_got.gyro_hold), (e_ref.angles, f_ref.z, f_ref.gyro_hold),
          1e-9)


@pytest.mark.long
def test_a_failed_check_is_repaired_else_falls_back_to_the_sequential_path():
    """Warm-ups too short to forget the start (or a gyro channel missing through a whole
    warm-up): the check fails; a repair pass (every segment's rows again from where the one
    before ended) makes the segments exact, and ``run_filter`` says the segments ran. Where
    the segments are too short for the repair to converge as well, ``run_filter`` runs and
    names the sequential path, and under ``jit`` (no host check) ``Segments.run`` gives the
    sequential result too."""
    robot = Robot.from_spec("x,y")
    s, series = recorded_like(robot, 4, 4800)
    params = fast(robot, s)
    st = init_state(params, "kckf")
    one = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], (series, st))
    checked = eqx.filter_jit(lambda path, *a: path.run_checked(params, *a)[1:])
    _, ref = run_filter(params, series, "kckf", path="sequential")
    # Six segments of 800 rows, warm-ups of 5 rows: the first pass is wrong by degrees ...
    short = Segments(lanes=6, warmup_float64=5, min_segments=2)
    est, ok = checked(dataclasses.replace(short, repairs=0), one[0], "kckf", one[1])
    assert not bool(ok) and np.abs(np.asarray(est.angles[0] - ref.angles)).max() > 1e-3
    # ... and one repair pass makes it exact: each segment ran 800 rows from its start.
    est, ok = checked(short, one[0], "kckf", one[1])
    assert bool(ok)
    close(est.angles[0], ref.angles, 1e-9)
    # Forty-eight segments of 100 rows: neither repair pass (the default two) converges.
    tiny = Segments(lanes=48, warmup_float64=5, min_segments=2)
    _, est = run_filter(params, series, "kckf", path=tiny)
    assert est.path == "sequential"
    np.testing.assert_array_equal(np.asarray(est.angles), np.asarray(ref.angles))
    jitted = jax.jit(lambda p, x, s0: tiny.run(p, x, "kckf", s0)[1].angles)
    close(jitted(params, *one)[0], ref.angles, 1e-12)
    # A gyro channel missing through the whole warm-up of the fourth segment (rows 1600 to
    # 2399): it enters holding the starting value, not the reading before the gap, so the
    # check fails; the repair enters it with the hold the third segment ended with.
    gyro = np.asarray(series.gyro).copy()
    gyro[1000:2500, 0] = np.nan
    gap = SensorSeries(series.dt, gyro, series.hall_v)
    _, ref = run_filter(params, gap, "kckf", path="sequential")
    gap1 = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], gap)
    assert not bool(checked(dataclasses.replace(SMALL, repairs=0), gap1, "kckf", one[1])[1])
    _, est = run_filter(params, gap, "kckf", path=SMALL)
    assert est.path == "segments"
    close(est.angles, ref.angles, 1e-9)


@pytest.mark.long  # a heavy check beside a lighter default one (the default run within 4 min)
def test_auto_takes_segments_for_long_recordings_only():
    """``Auto``: segments for one recording long enough to cut into ``min_segments``
    segments, with the reason otherwise; never for a fit's loss (its gradient); the
    defaults at full size in float32 pass their check and agree with the sequential path
    to float32's rounding."""
    robot = Robot.from_spec("x,y,x,y")
    s, series = recorded_like(robot, 5, 40_000, drop=0.01)
    p32 = Params.from_physical(robot, hall_models=s.hall_models, hall_noise="voltage",
                               dtype=jnp.float32)
    s32 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), series)
    choice = choose_path(p32, s32, "kckf")
    assert choice.path == Segments() and "fewer than 12" in choice.passed_over["lanes"]
    short = jax.tree_util.tree_map(lambda x: x[:9000], s32)
    why = choose_path(p32, short, "kckf").passed_over["segments"]
    assert why == "9000 rows make 2 segment(s) of 3072 rows or more, fewer than 4"
    assert choose_path(p32, s32, "kckf", Auto(segments=None)).path == Sequential()
    _, ref = run_filter(p32, s32, "kckf", path="sequential")
    _, est = run_filter(p32, s32, "kckf")
    assert est.path == "segments"
    assert np.isfinite(np.asarray(est.angles)).all()
    close(est.angles, ref.angles, 1e-5)
    # The fitting loss is never computed on segments (its Auto offers none): its gradient
    # takes the lanes path from one trial on, unless it is chunked for memory; a validation
    # loss (not differentiated) takes the filter's own choice.
    batch = Batch(jax.tree_util.tree_map(lambda x: x[None], s32),
                  jnp.zeros((1, 40_000, robot.n_angles), jnp.float32),
                  jnp.ones((1, 40_000, robot.n_angles), bool))
    # (kckf3d's own lanes step too: its reverse pass is written by hand, _exact_adjoint)
    assert rmse_loss(p32, batch, "kckf", None).path == Lanes(min_trials=1)
    assert rmse_loss(p32, batch, "kckf", 200).path == Sequential(200)
    assert rmse_loss(p32, batch, "kckf", None, gradient=False).path == Sequential()
