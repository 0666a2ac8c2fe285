"""The filter's pass gives the innovations too (issue 48, item 3): ``filter_sessions(...,
innovations=True)`` carries the same fused Hall innovations as the second pass it replaces
(``session_innovations``), across a gap the filter restarts at, and ``kckf evaluate``
filters each recording once where the path allows."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np
import pytest

import kckf_jax as kk
from kckf_jax._analysis._diagnostics import session_innovations


@pytest.mark.parametrize("method", ["kckf", "kf", "kckf3d"])
def test_the_pass_innovations_are_the_second_pass(method):
    s = kk.simulate("x,y,x,y", "cyclic", 3, 12.0, drop_prob=0.01)
    t = s.t.copy()
    t[500:] += 2.0  # a 2 s gap in the sensor rows: the filter restarts after it
    s = dataclasses.replace(s, t=t)
    gaps = kk.GapPolicy(on_gap="restart")
    plain = kk.filter_sessions([s], method, gaps=gaps, dtype=np.float64)[0]
    est = kk.filter_sessions([s], method, gaps=gaps, dtype=np.float64, innovations=True)[0]
    # (kckf3d: its own lanes step, from one trial on; the linear filters: sequential)
    assert est.path == plain.path == ("lanes" if method == "kckf3d" else "sequential")
    # The same steps in a program that also returns the innovations: the same estimates (to
    # the bit for the linear filters; kckf3d's to float64 rounding, its program fused otherwise).
    np.testing.assert_allclose(est.angles, plain.angles, rtol=0, atol=1e-12)
    want = session_innovations([s], method, kk.Params.paper_defaults(s.robot, s.hall_models,
                                                                     dtype=np.float64), gaps)[0]
    for got, ref in zip(est.innovations, want):
        np.testing.assert_allclose(np.asarray(got, np.float64), ref, rtol=1e-12, atol=1e-12)
    assert plain.innovations is None


def test_the_lanes_pass_gives_them_too():
    """Three sessions of uneven length as one lanes batch: each session's innovations from the
    lanes scan equal the second pass's, and the estimates those of the lanes run without
    them."""
    sessions = [kk.simulate("x,y,x,y", "cyclic", k, d, drop_prob=0.01)
                for k, d in ((1, 6.0), (2, 8.0), (3, 7.0))]
    plain = kk.filter_sessions(sessions, "kckf", path="lanes", dtype=np.float64)
    est = kk.filter_sessions(sessions, "kckf", path="lanes", dtype=np.float64,
                             innovations=True)
    params = kk.Params.paper_defaults(sessions[0].robot, sessions[0].hall_models,
                                      dtype=np.float64)
    want = session_innovations(sessions, "kckf", params)
    for e, p, w in zip(est, plain, want):
        assert e.path == p.path == "lanes"
        np.testing.assert_allclose(e.angles, p.angles, rtol=0, atol=1e-12)
        for got, ref in zip(e.innovations, w):
            np.testing.assert_allclose(np.asarray(got, np.float64), ref, rtol=1e-10,
                                       atol=1e-10)


def test_the_segments_pass_gives_them_too():
    """A long recording on the segments path (cut into warmed-up segments run as lanes): the
    innovations of the pass that passed its check equal the second pass's."""
    s = kk.simulate("x,y", "cyclic", 2, 200.0, drop_prob=0.01)
    path = kk.Segments(lanes=4, min_segments=2)  # float64: two segments, 8,192 rows warm-up
    plain = kk.filter_sessions([s], "kckf", path=path, dtype=np.float64)[0]
    est = kk.filter_sessions([s], "kckf", path=path, dtype=np.float64, innovations=True)[0]
    assert est.path == plain.path == "segments"
    np.testing.assert_allclose(est.angles, plain.angles, rtol=0, atol=1e-12)
    params = kk.Params.paper_defaults(s.robot, s.hall_models, dtype=np.float64)
    want = session_innovations([s], "kckf", params)[0]
    for got, ref in zip(est.innovations, want):
        np.testing.assert_allclose(np.asarray(got, np.float64), ref, rtol=1e-9, atol=1e-9)


@pytest.mark.long  # a heavy check beside a lighter default one (the default run within 4 min)
def test_the_steady_pass_gives_them_too():
    """A regular recording on the steady path (the converged map after the head rows): each
    row's innovations, read back from its new joint angles, equal the second pass's; ``x,x,y``
    pads its second block, whose padding slot must stay out of the other joints'."""
    s = kk.simulate("x,x,y", "cyclic", 4, 60.0, config=kk.SimConfig(timestamp_jitter_s=0.0))
    est = kk.filter_sessions([s], "kckf", path="steady", dtype=np.float64, innovations=True)[0]
    plain = kk.filter_sessions([s], "kckf", path="steady", dtype=np.float64)[0]
    assert est.path == plain.path == "steady"
    np.testing.assert_allclose(est.angles, plain.angles, rtol=0, atol=1e-12)
    params = kk.Params.paper_defaults(s.robot, s.hall_models, dtype=np.float64)
    want = session_innovations([s], "kckf", params)[0]
    assert want[2].sum() > 0.7 * want[2].size
    # The converged rows use the head's last covariance: as close as the steady estimates are.
    for got, ref in zip(est.innovations, want):
        np.testing.assert_allclose(np.asarray(got, np.float64), ref, rtol=1e-9, atol=1e-9)


def test_the_parallel_pass_gives_them_too():
    """The parallel path (every row's own affine map, dropped readings included): each row's
    innovations read back by its entering covariance equal the second pass's."""
    s = kk.simulate("x,x,y", "cyclic", 5, 12.0, drop_prob=0.02)
    est = kk.filter_sessions([s], "kckf", path="parallel", dtype=np.float64,
                             innovations=True)[0]
    assert est.path == "parallel"
    params = kk.Params.paper_defaults(s.robot, s.hall_models, dtype=np.float64)
    want = session_innovations([s], "kckf", params)[0]
    assert not want[2].all()  # some readings dropped: their innovations are not valid
    for got, ref in zip(est.innovations, want):
        np.testing.assert_allclose(np.asarray(got, np.float64), ref, rtol=1e-11, atol=1e-11)


class _Plain(kk.AbstractPath):
    """A caller's path that computes no innovations in its pass."""

    name: ClassVar[str] = "plain"

    def applies(self, params, series, method, state=None):
        return None

    def run(self, params, series, method, state):
        return kk.Sequential().run(params, series, method, state)


def test_a_baseline_or_a_path_without_them_carries_none():
    s = kk.simulate("x,y", "cyclic", 1, 4.0)
    assert kk.filter_sessions([s], "hall_l", innovations=True)[0].innovations is None
    est = kk.filter_sessions([s], "kckf", path=_Plain(), innovations=True)[0]
    assert est.path == "plain" and est.innovations is None


@pytest.mark.parametrize("layout", ["sequential", pytest.param("lanes", marks=pytest.mark.long),
                                    pytest.param("steady", marks=pytest.mark.long)])
def test_the_smoother_forward_pass_gives_them_too(layout):
    """``kckf evaluate --smooth``: the smoother's forward pass is the filter, and each layout
    keeps its innovations (the sequential one from its moments, the lanes' scan, the steady
    smoother read back as the steady path): equal to the second pass's, and the smoothed
    estimates unchanged by asking."""
    config = kk.SimConfig(timestamp_jitter_s=0.0) if layout == "steady" else None
    sessions = [kk.simulate("x,x,y", "cyclic", k, 60.0 if layout == "steady" else 6.0,
                            config=config) for k in (1, 2)]
    params = kk.Params.paper_defaults(sessions[0].robot, sessions[0].hall_models,
                                      dtype=np.float64)
    batch = kk.pad_series([kk.session_series(s, np.float64) for s in sessions])
    plain = kk.smooth_batch(params, batch, "kckf", path=layout)
    est = kk.smooth_batch(params, batch, "kckf", path=layout, innovations=True)
    assert est.path == plain.path == ("smoothed" if layout == "sequential"
                                      else f"smoothed:{layout}")
    assert plain.innovations is None
    np.testing.assert_allclose(est.angles, plain.angles, rtol=0, atol=1e-12)
    want = session_innovations(sessions, "kckf", params)
    tol = 1e-9 if layout == "steady" else 1e-11
    for b, w in enumerate(want):
        for got, ref in zip(est.innovations, w):
            np.testing.assert_allclose(np.asarray(got[b], np.float64), ref, rtol=tol, atol=tol)
