"""Learned sensor effects (``Params.effects``): the corrections against an independent NumPy
reference, nothing changed when they are off, the same corrections in the batch filter, the
stream and the exported step, the parameter file, and gradients that reach every leaf."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kckf_jax as kk
from kckf_jax._fitting._fit import make_batch
from kckf_jax._models._effects import EFFECTS, SensorEffects, corrected_readings
from kckf_jax.export_loader import ExportedStep

DEG = math.pi / 180.0
ROBOT = kk.Robot.from_spec("x,y")


@pytest.fixture(scope="module")
def session():
    return kk.simulate(ROBOT, "cyclic", seed=3, duration_s=12.0, drop_prob=0.02)


def some_effects(robot: kk.Robot, on=EFFECTS) -> SensorEffects:
    """Effects of realistic sizes: 20 ms, the step's midpoint, 1 % scales, 0.8-1.2 deg of
    play, curves of 0.5 deg, boards turned by up to 5 deg per axis."""
    rng = np.random.default_rng(0)
    G, J, M = 3 * robot.n_links, robot.n_joint_axes, robot.n_hall
    return SensorEffects(jnp.asarray(2.0), jnp.asarray(0.5), jnp.asarray(rng.uniform(-1, 1, G)),
                         jnp.asarray(rng.uniform(0.8, 1.2, J)),
                         jnp.asarray(rng.uniform(-0.5, 0.5, (M, 2))),
                         jnp.asarray(rng.uniform(-5, 5, (robot.n_links, 3))), on=tuple(on))


def reference_correction(params: kk.Params, effects: SensorEffects, gyro, hall_v):
    """The docs' definitions in NumPy float64, inverted with ``hall_voltage`` (its own Newton
    iteration): gyro / (1 + s); theta(V') = theta(V) + h tanh(rate / 5 deg/s) - delta(theta);
    the gyro timing is the step's (``test_gyro_timing_of_a_recording_is_the_streams``)."""
    a, b, c, d, sign = (np.asarray(x, np.float64) for x in params.hall_coeffs)
    gyro = np.asarray(gyro, np.float64) / (1 + np.asarray(effects.gyro_scale, np.float64) / 100)
    # Each board's triad turned back, R g, R = expm([v]_x) (a series, not Rodrigues).
    boards = gyro.reshape(len(gyro), -1, 3)
    for i, v in enumerate(np.asarray(effects.mounting, np.float64) * DEG):
        K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        R, term = np.eye(3), np.eye(3)
        for n in range(1, 20):
            term = term @ K / n
            R = R + term
        boards[:, i] = boards[:, i] @ R.T
    gyro = boards.reshape(gyro.shape)
    theta = sign * (a * np.exp(b * hall_v) - c * np.exp(-d * hall_v))
    plus, minus = ROBOT.rate_pairs
    J = ROBOT.n_joint_axes
    rate = gyro[:, plus[:J]] - gyro[:, minus[:J]]
    rate = np.where(np.isfinite(rate), rate, 0.0)  # a missing gyro: no play correction
    lag = np.asarray(effects.play, np.float64) * DEG * np.tanh(rate / (5 * DEG))
    u = theta / (30 * DEG)
    c2, c3 = (np.asarray(effects.curve, np.float64)[:, k] * DEG for k in (0, 1))
    dev = c2 * 0.5 * (3 * u**2 - 1) + c3 * 0.5 * (5 * u**3 - 3 * u)
    target = theta + lag[:, ROBOT.hall_joint_axis] - dev
    return gyro, kk.hall_voltage(target, a, b, c, d, sign)


def test_corrections_match_an_independent_reference(session):
    params = kk.Params.paper_defaults(ROBOT, session.hall_models)
    effects = some_effects(ROBOT)
    rows = slice(200, 700)  # moving: the joint rates are large and of both signs
    gyro, hall_v = session.gyro[rows], session.hall_v[rows]
    effects = dataclasses.replace(effects, on=tuple(e for e in EFFECTS if e != "gyro_timing"))
    got_g, got_v = corrected_readings(effects, ROBOT, params.hall_coeffs, jnp.asarray(gyro),
                                      jnp.asarray(hall_v))
    ref_g, ref_v = reference_correction(params, effects, gyro, hall_v)
    np.testing.assert_allclose(np.asarray(got_g), ref_g, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(got_v), ref_v, rtol=0, atol=1e-11)  # NaN alike
    moved = np.abs(np.asarray(got_v) - hall_v)
    assert np.nanmax(moved) > 1e-3  # the corrections did something


def test_gyro_timing_of_a_recording_is_the_streams():
    """The recording's transform (``timed_gyro``) against the hold written out as a loop: the
    step into row k + 1 integrates (1 - lambda) H_k + lambda g_{k+1}, with drops."""
    from kckf_jax._models._effects import timed_gyro

    rng = np.random.default_rng(1)
    g = rng.standard_normal((40, 3))
    g[rng.random(g.shape) < 0.2] = np.nan
    g[:3, 0] = np.nan  # no reading yet: the initial hold (0)
    lam = 0.37
    got = np.asarray(timed_gyro(jnp.asarray(lam), jnp.asarray(g)))
    hold = np.zeros(3)
    for k in range(40):
        hold = np.where(np.isfinite(g[k]), g[k], hold)
        nxt = g[k + 1] if k + 1 < 40 else np.full(3, np.nan)
        want = np.where(np.isfinite(nxt), (1 - lam) * hold + lam * np.nan_to_num(nxt), hold)
        np.testing.assert_allclose(got[k], want, rtol=1e-14, atol=1e-15)


@pytest.mark.long  # a heavy check beside a lighter default one (the default run within 4 min)
def test_missing_readings_stay_missing_without_nan_gradients(session):
    params = kk.Params.paper_defaults(ROBOT, session.hall_models)
    effects = some_effects(ROBOT)
    gyro, hall_v = session.gyro[:50].copy(), session.hall_v[:50].copy()
    gyro[5, 3], hall_v[7, 1] = np.nan, np.nan
    g, v = corrected_readings(effects, ROBOT, params.hall_coeffs, jnp.asarray(gyro),
                              jnp.asarray(hall_v))
    assert np.isnan(np.asarray(v)[7, 1])
    assert np.isfinite(np.asarray(g)[5, 3])  # timed: the hold blended with the next reading
    untimed = dataclasses.replace(effects, on=("gyro_scale",))
    g, _ = corrected_readings(untimed, ROBOT, params.hall_coeffs, jnp.asarray(gyro),
                              jnp.asarray(hall_v))
    assert np.isnan(np.asarray(g)[5, 3])
    assert np.isfinite(np.asarray(v)[~np.isnan(hall_v)]).all()

    def total(e):
        g, v = corrected_readings(e, ROBOT, params.hall_coeffs, jnp.asarray(gyro),
                                  jnp.asarray(hall_v))
        return jnp.nansum(v) + jnp.nansum(g**2)

    grads = jax.grad(total)(effects)
    for leaf in (grads.gyro_scale, grads.play, grads.curve, grads.mounting):
        assert np.isfinite(np.asarray(leaf)).all()
    for leaf in (grads.play, grads.curve, grads.mounting):
        assert np.abs(np.asarray(leaf)).max() > 0
    # At zero rotation too (the start of a fit): finite and not zero.
    zero = dataclasses.replace(effects, mounting=jnp.zeros_like(effects.mounting))
    at_zero = np.asarray(jax.grad(total)(zero).mounting)
    assert np.isfinite(at_zero).all() and np.abs(at_zero).max() > 0


def test_effects_off_change_nothing(session):
    """Zero-valued effects, all on, and no effects at all: the same estimates (float64).
    ``gyro_mounting`` makes a triad with a missing axis missing (its correction mixes the
    axes), so with zero rotations it changes nothing on complete readings only."""
    params = kk.Params.paper_defaults(ROBOT, session.hall_models)
    complete = kk.simulate(ROBOT, "cyclic", seed=3, duration_s=12.0)
    for s, on in ((session, tuple(e for e in EFFECTS if e != "gyro_mounting")),
                  (complete, EFFECTS)):
        series = kk.session_series(s)
        base = kk.run_filter(params, series)[1]
        for p in (params.with_effects(on), params.with_effects(())):
            est = kk.run_filter(p, series)[1]
            np.testing.assert_allclose(np.asarray(est.angles), np.asarray(base.angles), rtol=0,
                                       atol=1e-12)
        sm0 = kk.smooth(params, series)
        sm1 = kk.smooth(params.with_effects(on), series)
        np.testing.assert_allclose(np.asarray(sm1.angles), np.asarray(sm0.angles), rtol=0,
                                   atol=1e-12)


def test_a_turned_board_is_turned_back():
    """A session whose boards are tilted (the simulator's ``gyro_mount_deg``, ideal gyros):
    ``gyro_mounting`` at the recorded tilts gives the untilted boards' readings back, and a
    triad with a missing axis is missing."""
    ideal = dict(gyro_noise_density_dps_rthz=0.0, gyro_zero_rate_dps=0.0,
                 gyro_temp_coeff_dps_per_c=0.0, gyro_bias_walk_dps_rts=0.0,
                 gyro_scale_error=0.0, gyro_lsb_dps=1e-9)
    kw = dict(kind="walking", seed=5, duration_s=4.0, kinematics="exact")
    robot = kk.Robot.from_spec("xyz,y")
    plain = kk.simulate(robot, config=kk.SimConfig(**ideal), **kw)
    tilted = kk.simulate(robot, config=kk.SimConfig(**ideal, gyro_mount_deg=10.0), **kw)
    tilt = tilted.extra_meta["simulation"]["effects"]["gyro_mount_deg"]
    effects = SensorEffects.zeros(robot, on=("gyro_mounting",))
    effects = dataclasses.replace(effects, mounting=jnp.asarray(
        [tilt[f"gyro{i + 1}"] for i in range(robot.n_links)]))
    params = kk.Params.paper_defaults(robot, plain.hall_models)
    gyro = tilted.gyro.copy()
    gyro[10, 4] = np.nan
    got, _ = corrected_readings(effects, robot, params.hall_coeffs, jnp.asarray(gyro),
                                jnp.asarray(tilted.hall_v))
    got = np.asarray(got)
    assert np.isnan(got[10, 3:6]).all() and np.isfinite(got[10, :3]).all()
    keep = np.ones(len(gyro), bool)
    keep[10] = False
    np.testing.assert_allclose(got[keep], plain.gyro[keep], atol=1e-7)


@pytest.mark.long
def test_every_path_corrects_alike(session):
    """Regular data with effects on: the steady path and the sequential one agree, and both
    differ from the filter without the effects."""
    s = kk.simulate(ROBOT, "cyclic", seed=4, duration_s=50.0,
                    config=kk.SimConfig(timestamp_jitter_s=0.0))  # steady: over 4096 rows
    params = kk.Params.paper_defaults(ROBOT, s.hall_models).with_effects(
        EFFECTS, some_effects(ROBOT))
    series = kk.session_series(s)
    seq = kk.run_filter(params, series, path="sequential")[1]
    for path in ("steady", "segments", "parallel"):
        other = kk.run_filter(params, series, path=path)[1]
        assert other.path.startswith(path)
        np.testing.assert_allclose(np.asarray(other.angles), np.asarray(seq.angles), atol=1e-7)
    lanes = kk.filter_batch(params, jax.tree_util.tree_map(lambda x: jnp.stack([x] * 4),
                                                           series), path="lanes")
    np.testing.assert_allclose(np.asarray(lanes.angles[2]), np.asarray(seq.angles), atol=1e-7)
    sm_seq = kk.smooth(params, series, path="sequential")
    sm_steady = kk.smooth(params, series, path="steady")
    np.testing.assert_allclose(np.asarray(sm_steady.angles), np.asarray(sm_seq.angles),
                               atol=1e-7)
    plain = kk.run_filter(params.with_effects(()), series, path="sequential")[1]
    assert np.nanmax(np.abs(np.asarray(plain.angles) - np.asarray(seq.angles))) > 1e-3


@pytest.mark.long
def test_stream_and_export_correct_as_the_batch_filter(session, tmp_path):
    params = kk.Params.paper_defaults(ROBOT, session.hall_models).with_effects(
        EFFECTS, some_effects(ROBOT))
    rows = range(300)
    batch = np.asarray(kk.run_filter(params, kk.session_series(session))[1].angles)[:300]
    sf = kk.StreamingFilter(params, host_path=True)
    streamed = []
    for i in rows:
        rec = sf.push(kk.Packet(float(session.t[i]), session.gyro[i], session.hall_v[i], "ok"))
        streamed.append([rec[n] for n in ROBOT.angle_names])
        assert not sf.on_host  # the host map does not carry the corrections
    np.testing.assert_allclose(np.asarray(streamed, np.float64), batch, atol=1e-9)
    for baked in (True, False):
        path = str(tmp_path / f"step_{baked}.jaxexport")
        kk.export_step(params, path, baked=baked)
        step = ExportedStep(path)
        got = [step.push_array(float(session.t[i]),
                               np.r_[session.gyro[i], session.hall_v[i]]) for i in rows]
        np.testing.assert_allclose(np.asarray(got, np.float64), batch, atol=1e-9)
        if not baked:
            names = [n for n, _ in step.header["param_leaves"]]
            assert names[-6:] == ["effects.offset", "effects.timing", "effects.gyro_scale",
                                  "effects.play", "effects.curve", "effects.mounting"]


def test_parameter_file_round_trip(tmp_path):
    params = kk.Params.paper_defaults(ROBOT).with_effects(("play", "offset"),
                                                          some_effects(ROBOT))
    path = str(tmp_path / "p.json")
    kk.save_params(params, path)
    doc = json.loads(Path(path).read_text())
    assert set(doc["effects"]) == {"offset", "play"}
    assert doc["effects"]["offset"]["time_offset_s"] == pytest.approx(0.02)
    back = kk.load_params(path)
    assert back.effects.on == ("offset", "play")
    np.testing.assert_allclose(np.asarray(back.effects.play), np.asarray(params.effects.play))
    mounted = kk.Params.paper_defaults(ROBOT).with_effects(("gyro_mounting",),
                                                           some_effects(ROBOT))
    kk.save_params(mounted, path)
    doc_m = json.loads(Path(path).read_text())
    assert doc_m["effects"]["gyro_mounting"]["gyro2"]["rotation_deg"] == pytest.approx(
        np.asarray(mounted.effects.mounting)[1].tolist())
    np.testing.assert_allclose(np.asarray(kk.load_params(path).effects.mounting),
                               np.asarray(mounted.effects.mounting))
    doc_m["effects"]["gyro_mounting"]["gyro1"]["rotation_deg"] = [1.0, 2.0]
    Path(path).write_text(json.dumps(doc_m))
    with pytest.raises(kk.ParamsFileError, match=r"gyro_mounting\.gyro1\.rotation_deg"):
        kk.load_params(path)
    kk.save_params(kk.Params.paper_defaults(ROBOT), path)
    assert "effects" not in json.loads(Path(path).read_text())  # no effects: the file as before
    doc["effects"]["play"]["theta9_x"] = {"half_width_deg": 1.0}
    Path(path).write_text(json.dumps(doc))
    with pytest.raises(kk.ParamsFileError, match=r"effects\.play\.theta9_x"):
        kk.load_params(path)


def test_clock_offset_moves_the_comparison_not_the_filter(session):
    """The loss compares ``angle - tau * rate`` with the truth: when the motion capture lags
    by 30 ms more, the best tau moves by 30 ms; the filter's estimates do not move."""
    params = kk.Params.paper_defaults(ROBOT, session.hall_models)
    fields = ("robot", "t", "gyro", "hall_v", "sample_rate_hz", "mocap_t", "mocap",
              "hall_models")
    lagged = kk.Session(**{f: getattr(session, f) for f in fields},
                        mocap_time_offset_s=session.mocap_time_offset_s + 0.03)
    taus = np.arange(-0.02, 0.071, 0.005)

    base = params.with_effects(("offset",))
    loss = eqx.filter_jit(lambda offset, batch: kk.loss_fn(
        eqx.tree_at(lambda p: p.effects.offset, base, offset), batch))  # one compile

    def best(s):
        batch = make_batch([s])
        losses = [float(loss(jnp.asarray(tau / 0.01), batch)) for tau in taus]
        return taus[int(np.argmin(losses))]

    assert best(lagged) - best(session) == pytest.approx(0.03, abs=0.0051)
    est0 = kk.run_filter(params, kk.session_series(session))[1].angles
    est1 = kk.run_filter(params.with_effects(("offset",)), kk.session_series(session))[1].angles
    np.testing.assert_array_equal(np.asarray(est0), np.asarray(est1))


@pytest.mark.long
def test_fit_reaches_every_learned_leaf_and_keeps_a_frozen_one(session):
    """One smoothed step of the fit moves every effect it learns and none it does not; a
    frozen leaf (the offset recipe's second step: the timing kept) keeps its starting value;
    freezing a leaf of an effect that is not learned, or learning an unknown effect, is
    refused, naming it."""
    start = kk.Params.paper_defaults(ROBOT, session.hall_models).with_effects(
        ("gyro_timing",), some_effects(ROBOT))
    cfg = kk.FitConfig(steps=1, val_every=1, learn=("gyro_timing", "offset", "play", "curve",
                                                    "gyro_mounting"),
                       freeze=("effects.timing",), smooth=True)
    e = kk.fit([session], (), cfg, init=start).params.effects
    assert e.on == ("offset", "gyro_timing", "play", "curve", "gyro_mounting")
    assert float(e.timing) == float(start.effects.timing)
    for leaf, was in ((e.offset, start.effects.offset), (e.play, start.effects.play),
                      (e.curve, start.effects.curve), (e.mounting, start.effects.mounting)):
        assert np.abs(np.asarray(leaf) - np.asarray(was)).max() > 0
    np.testing.assert_array_equal(np.asarray(e.gyro_scale), np.asarray(start.effects.gyro_scale))
    with pytest.raises(ValueError, match="'effects.play' belongs to the effect 'play'"):
        kk.FitConfig(freeze=("effects.play",))
    with pytest.raises(ValueError, match="unknown effect 'backlash'"):
        kk.FitConfig(learn=("backlash",))


def test_the_mounting_takes_steps_in_its_own_unit(session):
    """A board's rotation (deg, 5-12 where worn) takes Adam steps 10 times the rate and the
    Hall exponents 10 times smaller, the rest the rate: Adam's first step moves every leaf by
    its rate, whatever its gradient's size. A fit that learns no mounting keeps the optimiser
    it had (``leaf_scales`` empty: its steps and a checkpoint's state as before)."""
    from kckf_jax._fitting._fit import EXPONENT_LEAVES
    from kckf_jax._fitting._train import optimizer

    params = kk.Params.paper_defaults(ROBOT, session.hall_models).with_effects(
        ("gyro_mounting",), some_effects(ROBOT))
    cfg = kk.FitConfig(learn=("gyro_mounting",))._train_config()
    assert cfg.leaf_scales == (("mounting", 10.0),)
    assert kk.FitConfig(learn=("play",))._train_config().leaf_scales == ()
    opt = optimizer(0.03, None, EXPONENT_LEAVES, cfg.leaf_scales)
    grads = jax.tree_util.tree_map(lambda x: 1e-3 * jnp.ones_like(x), params)
    step, _ = opt.update(grads, opt.init(params), params)
    np.testing.assert_allclose(np.asarray(step.effects.mounting), -0.3, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(step.log_hall_b), -0.003, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(step.effects.play), -0.03, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(step.log_q), -0.03, rtol=1e-4)


def test_a_fit_that_makes_the_filter_lag_says_so():
    """On motion capture 30 ms late, the timing learned from the RMSE goes below 0 (the filter
    learns to lag): the fit warns, naming the remedy; on motion capture on time it does not."""
    import warnings

    def fit_on(sync):
        s = kk.simulate(ROBOT, "cyclic", seed=5, duration_s=8.0,
                        config=kk.SimConfig(mocap_sync_error_s=sync))
        with warnings.catch_warnings(record=True) as got:
            warnings.simplefilter("always")
            res = kk.fit([s], (), kk.FitConfig(steps=30, learning_rate=0.1,
                                               learn=("gyro_timing",)))
        return float(res.params.effects.timing), [str(w.message) for w in got]

    lam, said = fit_on(0.03)
    assert lam < 0 and any("now lag" in m and "--loss nll" in m for m in said), (lam, said)
    lam, said = fit_on(0.0)
    assert lam > 0 and not any("now lag" in m for m in said), (lam, said)
