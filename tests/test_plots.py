"""The session figures (``kckf demo``'s and ``kckf evaluate --plot``'s): every method named
as in the tables, in a colour of its own, motion capture over the estimates, and each
method's error against motion capture over time on a scale where 0.2 and 1.7 deg differ.

Small synthetic estimates (motion capture plus known errors), no filter run."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.colors import to_rgb

import kckf_jax as kk
from kckf_jax.cli import plots
from kckf_jax.cli._report import PAPER_TABLE_METHODS, TABLE_LABELS

METHODS = [*PAPER_TABLE_METHODS, "kckf_fit", "kckf_fit_smoothed"]  # the demo's columns
#: Each method's error on every angle it estimates (deg): the gyro drifts, the rest are off
#: by a constant, the smoothed fit by 0.2 deg and the Std KF by 1.7 deg.
OFFSET_DEG = {"hall_l": 3.0, "hall_r": -2.5, "kf": 1.7, "kckf": 0.6, "kckf_fit": -0.4,
              "kckf_fit_smoothed": 0.2}


@pytest.fixture(scope="module")
def session():
    return kk.simulate("x,y", "human", seed=1, duration_s=6.0)


@pytest.fixture(scope="module")
def angles(session):
    truth = np.nan_to_num(session.truth())  # an estimate where motion capture has none too
    t = session.t - session.t[0]
    out = {}
    for m in METHODS:
        err = 5.0 * t[:, None] if m == "gyro" else np.full((t.size, 1), OFFSET_DEG[m])
        a = truth + np.radians(err)
        if m.startswith("hall"):  # the Hall sensors see the joints only
            a[:, session.robot.n_joint_axes:] = np.nan
        out[m] = a
    return out


@pytest.fixture(scope="module")
def figures(session, angles):
    gaps = [{"row": 200, "t_s": float(session.t[200]), "length_s": 0.3, "action": "reset"}]
    faults = [{"column": "hall1_x_l", "kind": "stuck", "from_s": float(session.t[300]),
               "to_s": float(session.t[350]), "count": 51}]
    figs = plots.session_figures(session, angles, gaps=gaps, faults=faults, title="synthetic")
    yield figs
    import matplotlib.pyplot as plt

    for fig in figs.values():
        for fig in figs.values():
            plt.close(fig)


def _rgb(line) -> tuple:
    return to_rgb(line.get_color())


def test_plot_session_writes_a_png_per_group(session, angles, tmp_path):
    files = plots.plot_session(session, angles, str(tmp_path), "s1")
    assert [f.rsplit("/", 1)[-1] for f in files] == ["s1_joints.png", "s1_torso.png"]
    for f in files:
        with open(f, "rb") as fh:
            assert fh.read(8) == b"\x89PNG\r\n\x1a\n"


def test_every_legend_names_the_methods_as_the_table_does(figures):
    names = {TABLE_LABELS[m] for m in METHODS}
    for group, fig in figures.items():
        (legend,) = fig.legends
        texts = [t.get_text() for t in legend.get_texts()]
        shown = METHODS if group == "joints" else [m for m in METHODS if "hall" not in m]
        assert texts[:len(shown) + 1] == [TABLE_LABELS[m] for m in shown] + ["Motion capture"]
        for ax in fig.axes:
            for line in ax.get_lines():
                if not line.get_label().startswith("_"):
                    assert line.get_label() in names | {"Motion capture"}, line.get_label()
        for ax in fig.axes[1::2]:  # the error panels: each method's name and its RMSE
            for text in ax.get_legend().get_texts():
                name, rmse = text.get_text().split("  ")
                assert name in names and float(rmse) >= 0
        everything = " ".join(t.get_text() for leg in [legend, *(a.get_legend() for a in
                              fig.axes[1::2])] for t in leg.get_texts())
        assert "kckf_fit" not in everything and "kf" not in everything


def test_no_two_lines_of_a_panel_share_a_colour_and_each_method_keeps_its_own(figures):
    colour_of = {}
    for fig in figures.values():
        for ax in fig.axes:
            lines = [ln for ln in ax.get_lines() if not ln.get_label().startswith("_")]
            colours = [_rgb(ln) for ln in lines]
            assert len(set(colours)) == len(colours), [ln.get_label() for ln in lines]
            for ln in lines:
                assert colour_of.setdefault(ln.get_label(), _rgb(ln)) == _rgb(ln)
    assert colour_of["Motion capture"] == (0.0, 0.0, 0.0)
    assert len(set(colour_of.values())) == len(colour_of) == len(METHODS) + 1
    assert set(plots.colours(["kckf", "a", "b", "c"]).values()).__len__() == 4


def test_motion_capture_is_drawn_over_the_estimates(figures):
    for fig in figures.values():
        for ax in fig.axes[0::2]:
            lines = ax.get_lines()
            truth = [ln for ln in lines if ln.get_label() == "Motion capture"]
            assert len(truth) == 1
            assert truth[0].get_zorder() > max(ln.get_zorder() for ln in lines
                                               if ln is not truth[0])


def test_the_error_panel_has_each_methods_error_on_a_scale_where_0p2_and_1p7_differ(
        session, angles, figures):
    truth = np.degrees(session.truth())
    fig = figures["torso"]
    k0 = session.robot.n_joint_axes
    for row, ax in enumerate(fig.axes[1::2]):
        k = k0 + row
        lines = {ln.get_label(): ln for ln in ax.get_lines() if not ln.get_label().startswith("_")}
        assert set(lines) == {TABLE_LABELS[m] for m in METHODS if "hall" not in m}
        for m in METHODS:
            if "hall" in m:
                continue
            y = np.asarray(lines[TABLE_LABELS[m]].get_ydata(), np.float64)
            expect = np.degrees(angles[m][:, k]) - truth[:, k]
            # a gap adds a NaN row (the line is broken there): compare the rows drawn
            drawn = np.isfinite(y)
            assert drawn.sum() == np.isfinite(expect).sum()
            np.testing.assert_allclose(y[drawn], expect[np.isfinite(expect)], atol=1e-9)
        # the smoothed fit's 0.2 deg and the Std KF's 1.7 deg at least a tenth of the panel
        # apart (on the linear scale of the gyro's 30 deg they would be 3 % apart)
        to_px = ax.transData.transform
        height = ax.bbox.height
        y02, y17 = (to_px((0.0, v))[1] for v in (0.2, 1.7))
        assert abs(y17 - y02) > 0.1 * height
        legend = [t.get_text() for t in ax.get_legend().get_texts()]
        assert legend[0] == "smoothed  0.20" and legend[-1].startswith("Gyro")


def test_gaps_and_faults_are_marked(figures):
    (legend,) = figures["joints"].legends
    texts = [t.get_text() for t in legend.get_texts()]
    assert "gap (reset)" in texts and "not used: hall1_x_l stuck" in texts


def test_a_method_that_is_another_is_drawn_dashed_and_said_so(session, angles):
    same = {"gyro": angles["gyro"], "kf": angles["gyro"].copy(), "kckf": angles["kckf"]}
    figs = plots.session_figures(session, same)
    try:
        ax = figs["torso"].axes[1]
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        assert lines["Std KF"].get_linestyle() == "--"
        assert lines["Gyro"].get_linestyle() == "-" == lines["KCKF"].get_linestyle()
        texts = [t.get_text() for t in ax.get_legend().get_texts()]
        assert any(t.startswith("Std KF") and t.endswith("(= Gyro)") for t in texts), texts
    finally:
        import matplotlib.pyplot as plt

        for fig in figs.values():
            plt.close(fig)
