"""The diagnostics a user reads (``kk.diagnostics``, docs/diagnostics.md): the innovations'
whiteness against an independent NumPy reference, the error decomposition on errors built
with known parts, the quantiles against table values, and ``kckf evaluate``'s document and
figure."""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest

import kckf_jax as kk
from kckf_jax._analysis import _diagnostics as D
from kckf_jax._readings import _stats as S
from kckf_jax.cli import main

DEG = np.pi / 180.0


# ------------------------------------------------------------------------------ quantiles
@pytest.mark.parametrize("dof, table", [(20, 31.410), (10, 18.307), (30, 43.773),
                                        (40, 55.758)])
def test_chi2_quantile_is_the_table_value(dof, table):
    assert S.chi2_quantile95(dof) == pytest.approx(table, abs=0.02)


@pytest.mark.parametrize("d1, d2, table", [(1, 10, 4.965), (3, 20, 3.098), (2, 5, 5.786),
                                           (5, 60, 2.368), (1, 1, 161.45), (4, 1e7, 2.372)])
def test_f_quantile_is_the_table_value(d1, d2, table):
    assert S.f_quantile(0.95, d1, d2) == pytest.approx(table, rel=1e-3)


def test_incomplete_beta_closed_forms():
    x = np.linspace(0.01, 0.99, 7)
    for v in x:
        assert S.betainc(1.0, 1.0, v) == pytest.approx(v, abs=1e-12)
        assert S.betainc(2.0, 1.0, v) == pytest.approx(v**2, abs=1e-12)
        assert S.betainc(2.5, 3.5, v) == pytest.approx(1.0 - S.betainc(3.5, 2.5, 1.0 - v),
                                                       abs=1e-12)


# ------------------------------------------------------------------------------ whiteness
def _reference_acf(pieces, lags):
    """The pooled autocorrelation written plainly: the pooled mean off, each lag's mean
    product over the pairs with both values inside one piece, over the pooled variance."""
    values = np.concatenate([x[ok] for x, ok in pieces])
    mean, var, n = values.mean(), values.var(), values.size
    acf, pairs = np.zeros(lags), np.zeros(lags)
    for k in range(1, lags + 1):
        total, count = 0.0, 0
        for x, ok in pieces:
            for t in range(x.size - k):
                if ok[t] and ok[t + k]:
                    total += (x[t] - mean) * (x[t + k] - mean)
                    count += 1
        acf[k - 1], pairs[k - 1] = total / count / var, count
    q = (n + 2) / n * np.sum(pairs * acf**2)
    return acf, pairs, q


def _ar1(rng, rho, n):
    w = rng.standard_normal(n)
    x = np.empty(n)
    x[0] = w[0]
    for t in range(1, n):
        x[t] = rho * x[t - 1] + np.sqrt(1 - rho**2) * w[t]
    return x


def test_acf_and_ljung_box_match_the_reference_with_gaps_and_sessions():
    rng = np.random.default_rng(3)
    pieces = []
    for n in (700, 450):
        x = _ar1(rng, 0.5, n)
        ok = rng.random(n) > 0.1
        pieces.append((np.where(ok, x, 123.0), ok))  # a missing value's number is never read
    acf, pairs, n = S.pooled_acf(pieces, 8)
    ref_acf, ref_pairs, ref_q = _reference_acf(pieces, 8)
    np.testing.assert_allclose(acf, ref_acf, atol=1e-12)
    np.testing.assert_array_equal(pairs, ref_pairs)
    assert S.ljung_box(acf, pairs, n) == pytest.approx(ref_q, rel=1e-12)


def test_ljung_box_of_one_complete_series_is_the_textbook_formula():
    x = _ar1(np.random.default_rng(4), 0.3, 500)
    k = np.arange(1, 11)
    c = x - x.mean()
    r = np.array([np.sum(c[:-j] * c[j:]) for j in k]) / np.sum(c**2)  # textbook r_k
    q_textbook = x.size * (x.size + 2) * np.sum(r**2 / (x.size - k))
    acf, pairs, n = S.pooled_acf([(x, np.ones(x.size, bool))], 10)
    np.testing.assert_allclose(acf, r * x.size / (x.size - k), rtol=1e-12)
    assert S.ljung_box(acf, pairs, n) == pytest.approx(q_textbook, rel=1e-12)


def _innovations(x):
    """One channel's normalised innovations as ``session_innovations`` lays them out."""
    n = x.size
    return (x.reshape(n, 1, 1), np.ones((n, 1, 1)), np.ones((n, 1, 1), bool))


def test_white_noise_is_white_and_ar1_is_not():
    rng = np.random.default_rng(0)
    n = 3000
    (white,) = D.whiteness([_innovations(rng.standard_normal(n))], [[(0, n)]], ["theta1_x"])
    assert white.white and white.q < white.q95 == pytest.approx(31.41, abs=0.02)
    assert white.count == n and abs(white.mean) < 0.1 and white.nis == pytest.approx(1, abs=0.1)
    np.testing.assert_allclose(white.band, 1.96 / np.sqrt(n - np.arange(1, 21)), rtol=1e-3)
    (ar,) = D.whiteness([_innovations(_ar1(rng, 0.5, n))], [[(0, n)]], ["theta1_x"])
    assert not ar.white and ar.q > 10 * ar.q95
    assert ar.acf[0] == pytest.approx(0.5, abs=0.05) and ar.acf[1] == pytest.approx(0.25,
                                                                                   abs=0.06)
    assert ar.outside[:3] == (1, 2, 3)


def test_no_pair_crosses_a_session_or_a_restart():
    """Two white halves at different levels: within each piece the values are white, so
    pooled per piece nothing is flagged; taken as one series they would be."""
    rng = np.random.default_rng(1)
    a, b = rng.standard_normal(1500), rng.standard_normal(1500)
    (split,) = D.whiteness([_innovations(np.r_[a, b])], [[(0, 1500), (1500, 3000)]], ["x"])
    acf, _, _ = S.pooled_acf([(np.r_[a, b], np.ones(3000, bool))], 20)
    ref, _, _ = S.pooled_acf([(a, np.ones(1500, bool)), (b, np.ones(1500, bool))], 20)
    np.testing.assert_allclose(split.acf, ref)
    assert acf[0] != pytest.approx(ref[0], abs=1e-6)


def test_the_effective_sample_is_the_textbook_one_for_ar1():
    """An AR(1) residual's model, and the inflation it gives a slow part (a constant:
    ``(1 + rho) / (1 - rho)``, the brief's ``N (1 - rho1) / (1 + rho1)``) and a part that
    alternates every row (``(1 - rho) / (1 + rho)``, at least 1)."""
    x = _ar1(np.random.default_rng(7), 0.9, 20_000)
    ok = np.ones(x.size, bool)
    a, var = S.noise_model([(x, ok)])
    assert a[0] == pytest.approx(0.9, abs=0.01) and np.all(np.abs(a[1:]) < 0.05)
    assert var == pytest.approx(1 - 0.81, rel=0.05)
    const = [(np.ones(4000), np.ones(4000, bool))]
    tau = S.variance_inflation((np.array([0.9]), 0.19), const)
    assert tau == pytest.approx(19.0 * (1 - 2 * 0.9 / (0.1 * 4000)), rel=0.01)  # finite N
    alternating = [(np.resize([1.0, -1.0], 4000), np.ones(4000, bool))]
    assert S.variance_inflation((np.array([0.9]), 0.19), alternating) == 1.0
    assert S.variance_inflation((np.zeros(0), 1.0), const) == pytest.approx(1.0)


def test_channels_are_named_by_their_joint():
    robot = kk.Robot.from_spec("x,y,x,y")
    assert D.channel_names(robot, "kckf", 2, 2) == ["theta1_x", "theta3_x", "theta2_y",
                                                    "theta4_y"]
    assert D.channel_names(kk.Robot.from_spec("x,y,x"), "kf", 2, 2) == [
        "theta1_x", "theta3_x", "theta2_y", None]
    assert D.channel_names(kk.Robot.from_spec("xyz,xyz"), "kckf3d", 1, 6) == [
        "theta1_x", "theta1_y", "theta1_z", "theta2_x", "theta2_y", "theta2_z"]


# ------------------------------------------------------------------------- decomposition
@pytest.fixture(scope="module")
def cyclic():
    return kk.simulate("x,y", "cyclic", seed=2, duration_s=30)


def _parts(session, est):
    return {p.angle: p for p in D.error_parts([session], [est])}


def _with_truth(session, truth):
    """``session`` with ``truth`` as its motion capture, on its own sensor times."""
    return dataclasses.replace(session, mocap_t=session.t.copy(), mocap=truth,
                               mocap_time_offset_s=0.0)


def test_known_parts_are_attributed_to_their_groups(cyclic):
    """An error made of the regressors themselves (a play of 1 deg on the sign of the rate,
    the estimate 30 ms ahead, a curve, a drift, a bias) is taken apart into them."""
    s = cyclic
    t, est = s.t, s.truth()  # the estimate: a recorded motion; the truth: it minus the error
    rate = D.angle_rate(t, est)  # the estimate's rate, as the decomposition takes it
    direction = np.where(np.abs(rate) < 2 * DEG, 0.0, np.sign(rate))
    u = 2 * (t - t[0]) / (t[-1] - t[0]) - 1
    noise = 0.02 * DEG * np.random.default_rng(0).standard_normal(est.shape)
    rest = 1.0 * DEG * direction + 0.030 * rate + 0.5 * DEG * u[:, None] + 0.3 * DEG + noise
    truth = est - rest
    for _ in range(20):  # the curve is the truth's, and the truth the estimate minus it
        lo, hi = np.nanmin(truth, axis=0), np.nanmax(truth, axis=0)
        x = 2 * (truth - lo) / (hi - lo) - 1
        curve = 0.4 * DEG * (3 * x**2 - 1) / 2  # Legendre P2 of the truth angle
        truth = est - rest - curve
    error = rest + curve
    parts = _parts(_with_truth(s, truth), est)
    for name, p in parts.items():
        k = s.robot.angle_names.index(name)
        ok = np.isfinite(error[:, k])
        assert p.count == ok.sum()
        assert p.play_deg == pytest.approx(1.0, rel=0.1), name
        assert p.clock_offset_ms == pytest.approx(30.0, rel=0.1), name
        c = curve[ok, k] - curve[ok, k].mean()
        assert p.part_deg["angle"] == pytest.approx(np.sqrt(np.mean(c**2)) / DEG, rel=0.1)
        assert p.drift_deg == pytest.approx(0.5 / np.sqrt(3), rel=0.1)
        # The intercept is the mean error: every other regressor is centred.
        assert p.bias_deg == pytest.approx(np.mean(error[ok, k]) / DEG, abs=1e-6)
        assert all(p.significant.values()), (name, p.significant, p.f, p.f95)
        assert p.rest_deg < 0.1 < p.rms_deg


def test_clean_noise_flags_nothing(cyclic):
    """Errors that are noise, strongly correlated in time (an AR(1) of 2 s at 100 Hz plus
    white), leave no group significant: the effective sample size carries the correlation."""
    s = cyclic
    rng = np.random.default_rng(5)
    truth = s.truth()
    noise = np.stack([0.3 * DEG * _ar1(rng, 0.99, s.n_steps)
                      + 0.05 * DEG * rng.standard_normal(s.n_steps)
                      for _ in range(truth.shape[1])], axis=1)
    for name, p in _parts(s, truth + noise).items():
        assert not any(p.significant.values()), (name, p.f, p.f95, p.n_eff)
        assert p.n_eff["bias"] < 0.05 * p.count  # the correlation is seen: a few dozen rows


def test_a_small_play_under_white_noise_is_found_and_nothing_else(cyclic):
    """On white noise the effective sample is every row: a play of 0.1 deg under 0.2 deg of
    noise is found, and nothing else."""
    s = cyclic
    est = s.truth()
    rate = D.angle_rate(s.t, est)
    noise = 0.2 * DEG * np.random.default_rng(6).standard_normal(est.shape)
    error = 0.1 * DEG * np.where(np.abs(rate) < 2 * DEG, 0.0, np.sign(rate)) + noise
    for name, p in _parts(_with_truth(s, est - error), est).items():
        assert p.significant["direction"] and p.play_deg == pytest.approx(0.1, rel=0.1), name
        assert p.n_eff["direction"] > 0.5 * p.count
        assert not (p.significant["bias"] or p.significant["angle"]
                    or p.significant["time"]), (name, p.f, p.f95)


def test_a_backlash_shows_as_a_negative_play(cyclic):
    """The play operator (a backlash of half-width 1 deg between the joint and what reads
    it): the estimate trails the motion, so the play is negative; the regression on the sign
    of the rate takes most of it (not all: inside the dead band the error is in between)."""
    s = cyclic
    truth = s.truth()
    lo = np.where(np.isfinite(truth), truth - DEG, -np.inf)  # a missing row: no push
    hi = np.where(np.isfinite(truth), truth + DEG, np.inf)
    est = np.empty_like(truth)
    p = est[0] = np.nan_to_num(truth[0])
    for k in range(1, truth.shape[0]):
        p = est[k] = np.clip(p, lo[k], hi[k])
    for name, parts in _parts(s, est).items():
        assert -1.0 < parts.play_deg < -0.5 and parts.significant["direction"], name


# --------------------------------------------------------------------------- the command
@pytest.fixture(scope="module")
def session_path(tmp_path_factory, cyclic):
    path = str(tmp_path_factory.mktemp("diag") / "s")
    kk.write_session(cyclic, path)
    return path


@pytest.mark.long
def test_evaluate_json_has_the_diagnostics_and_plot_draws_them(session_path, tmp_path,
                                                               capsys):
    figs = str(tmp_path / "figs")
    assert main(["evaluate", session_path, "--method", "kckf", "--method", "hall_l", "--json",
                 "--plot", figs]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert "diagnostics" not in doc["methods"]["hall_l"]
    d = doc["methods"]["kckf"]["diagnostics"]
    assert set(d) == {"decomposed", "whiteness_of", "lags", "whiteness", "errors"}
    assert d["decomposed"] == "filtered" and d["lags"] == 20
    assert set(d["whiteness"]) == {"theta1_x", "theta2_y"}
    w = d["whiteness"]["theta1_x"]
    assert len(w["acf"]) == 20 and w["q95"] == pytest.approx(31.41, abs=0.02)
    assert w["white"] == (w["q"] <= w["q95"]) and w["count"] > 2000
    assert set(d["errors"]) == set(s for s in doc["methods"]["kckf"]["rmse_deg"])
    e = d["errors"]["theta1_x"]
    assert set(e["groups"]) == set(D.GROUPS)
    assert e["rms_deg"] == pytest.approx(doc["methods"]["kckf"]["rmse_deg"]["theta1_x"],
                                         rel=0.05)
    assert os.path.getsize(os.path.join(figs, "diagnostics_kckf.png")) > 10_000
    assert not os.path.exists(os.path.join(figs, "diagnostics_hall_l.png"))


def test_evaluate_smooth_decomposes_the_smoothed_estimates(session_path, capsys):
    assert main(["evaluate", session_path, "--method", "kckf", "--smooth"]) == 0
    err = capsys.readouterr().err
    assert "kckf: innovations white in" in err
    assert "kckf: smoothed error, significant parts (deg):" in err


def test_the_function_takes_estimates_or_arrays(cyclic):
    est = kk.filter_sessions([cyclic], "kckf")
    d = kk.diagnostics([cyclic], est)
    assert isinstance(d, kk.Diagnostics) and d.decomposed == "filtered"
    assert [w.channel for w in d.whiteness] == ["theta1_x", "theta2_y"]
    assert all(isinstance(w, kk.Whiteness) for w in d.whiteness)
    assert [p.angle for p in d.errors] == list(cyclic.robot.angle_names)
    json.dumps(d.to_json(), allow_nan=False)
    bare = kk.diagnostics([cyclic], [np.asarray(est[0].angles)], method="hall_l")
    assert bare.whiteness == () and bare.decomposed == "estimates"
    assert bare.errors[0].rms_deg == pytest.approx(d.errors[0].rms_deg)
    with pytest.raises(ValueError, match="1 sessions"):
        kk.diagnostics([cyclic], [])
