"""Figures in the style of the KCKF paper's Figs. 5-7 (matplotlib, written to files).

At the edge: the CLI and notebooks call these; nothing in the numerical core imports them.
Every method is named as in the paper's Table 1 (``TABLE_LABELS``, the tables' own names) and
drawn in its own colour (``COLOURS``: Okabe and Ito's palette, which readers with a colour
vision deficiency can tell apart), the same in every figure; motion capture is black.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import numpy as np

from .._analysis._metrics import squared_errors
from .._models._classes import MODELS
from .._sessions._atomic import atomic_write
from .._sessions._session import Session
from ._report import TABLE_LABELS


def _save(fig, path: str) -> None:
    """``fig`` as PNG at ``path``, whole or not at all (``atomic_write``)."""
    with atomic_write(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110)


RAD2DEG = 180.0 / np.pi
#: Each method's colour, in every figure: Okabe and Ito's palette (its black is motion
#: capture's, its pale yellow left out: it is not seen on white), grey for a Hall sensor and
#: Paul Tol's indigo for the 3-D KCKF, which the demo's fitted KCKF (blue) never meets.
COLOURS = {
    "gyro": "#E69F00",               # orange
    "hall_l": "#56B4E9",             # sky blue
    "hall_r": "#999999",             # grey
    "kf": "#CC79A7",                 # reddish purple
    "kckf": "#D55E00",               # vermillion
    "kckf_fit": "#0072B2",           # blue
    "kckf_fit_smoothed": "#009E73",  # bluish green
    "kckf3d": "#332288",             # indigo
}
#: Colours for a method not in ``COLOURS`` (Paul Tol's muted scheme), the first one not taken.
_MORE_COLOURS = ("#882255", "#117733", "#44AA99", "#AA4499", "#999933", "#88CCEE", "#DDCC77",
                 "#CC6677")
TRUTH = dict(color="k", lw=0.9, label="Motion capture")


def label(method: str) -> str:
    """``method``'s name in the tables (``TABLE_LABELS``), else its own."""
    return TABLE_LABELS.get(method, method)


def colours(methods: Sequence[str]) -> dict[str, str]:
    """``{method: colour}``: its own (``COLOURS``), or the first spare one no other of
    ``methods`` has, so no two of them are drawn alike."""
    out = {m: COLOURS[m] for m in methods if m in COLOURS}
    spare = [c for c in (*_MORE_COLOURS, *COLOURS.values()) if c not in out.values()]
    for m in methods:
        if m not in out:
            out[m] = spare.pop(0) if spare else "C" + str(len(out) % 10)
    return out


def _style(method: str, colour: str) -> dict:
    """How ``method``'s line is drawn: a Hall sensor's (noisy) thin and pale, the gyro's
    (smooth, drifting) thin, a filter's full."""
    line = MODELS[method].line if method in MODELS else "filter"  # a fit's column: a filter
    if line == "sensor":
        return dict(color=colour, lw=0.5, alpha=0.7)
    if line == "integrated":
        return dict(color=colour, lw=0.9)
    return dict(color=colour, lw=1.3)


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _broken(t: np.ndarray, y: np.ndarray, rows: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """``t`` and ``y`` with a NaN before each of ``rows``, so a line is not drawn across a gap."""
    if not rows:
        return t, y
    return (np.insert(np.asarray(t, np.float64), rows, np.nan),
            np.insert(np.asarray(y, np.float64), rows, np.nan, axis=0))


def _marks(column: str, angle: str) -> bool:
    """Whether a faulty ``column``'s stretch is marked on ``angle``'s axes: a Hall sensor on
    its joint's (``hall1_x_l`` on ``theta1_x``), a gyro on every angle about its axis."""
    if column.startswith("hall"):
        return angle == "theta" + column[len("hall"):-2]
    return angle.endswith("_" + column[-1])


def _nice(x: float, up: bool = True) -> float:
    """The 1-2-5 number at or above ``x`` (> 0), or with ``up=False`` at or below."""
    k = np.floor(np.log10(x))
    steps = [m * 10.0 ** k for m in (1.0, 2.0, 5.0, 10.0)]
    return float(min(v for v in steps if v >= x) if up else max(v for v in steps if v <= x))


def _linthresh(rmse: Sequence[float]) -> float:
    """The symmetric log scale's linear range for errors of RMSE ``rmse`` (deg): the 1-2-5
    number at or above twice the smallest, so the best method's error, noise and all, is drawn
    linearly and one ten times worse is a decade further out."""
    low = 2.0 * min([r for r in rmse if np.isfinite(r) and r > 0] or [0.5])
    return _nice(min(max(low, 0.01), 100.0))


def _symlog(ax, linthresh: float, top: float) -> None:
    """``ax``'s y axis on a symmetric log scale, linear within ``linthresh``, up to ``top``;
    ticks at 0, the linear range's ends and the powers of ten beyond (at least one), plainly."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator

    top = max(top, 2.0 * linthresh)
    ax.set_yscale("symlog", linthresh=linthresh, linscale=1.0)
    ax.set_ylim(-top, top)
    beyond = [10.0 ** k for k in range(-2, 6) if 3 * linthresh <= 10.0 ** k <= top]
    if not beyond and _nice(top, up=False) >= 3 * linthresh:
        beyond = [_nice(top, up=False)]
    ticks = [linthresh, *beyond]
    ax.yaxis.set_major_locator(FixedLocator(sorted([0.0, *ticks, *(-x for x in ticks)])))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_locator(NullLocator())


def _spans(ax, angle: str, t0: float, gaps: Sequence[dict], faults: Sequence[dict]) -> None:
    """The gaps (grey) and the stretches of faulty readings that bear on ``angle`` (hatched)."""
    for i, g in enumerate(gaps):
        ax.axvspan(g["t_s"] - t0, g["t_s"] - t0 + g["length_s"], color="0.85", lw=0,
                   label=f"gap ({g['action']})" if i == 0 else None)
    shown = set()
    for f in faults:
        if _marks(f["column"], angle):
            key = f"{f['column']} {f['kind']}"
            hall = f["column"].startswith("hall")
            ax.axvspan(f["from_s"] - t0, max(f["to_s"], f["from_s"] + 0.05) - t0,
                       facecolor="0.6" if hall else "0.8", alpha=0.3, edgecolor="0.4",
                       hatch="///" if hall else "...", lw=0,
                       label=None if key in shown else f"not used: {key}")
            shown.add(key)


def session_figures(
    session: Session, angles: Mapping[str, np.ndarray],
    gaps: Sequence[dict] = (), nis: Mapping[str, np.ndarray] | None = None,
    faults: Sequence[dict] = (), title: str = "",
) -> dict:
    """``plot_session``'s figures, drawn and not saved: ``{"joints": fig, "torso": fig}``
    and, given ``nis``, ``"nis"`` (matplotlib figures; the caller closes them)."""
    plt = _plt()
    robot = session.robot
    t0 = session.t[0]
    rows = [int(g["row"]) for g in gaps]
    t, truth = _broken(session.t - t0, session.truth() * RAD2DEG, rows)
    deg = {m: _broken(session.t - t0, np.asarray(a, np.float64) * RAD2DEG, rows)[1]
           for m, a in angles.items()}
    colour = colours(list(angles))
    sse = {m: squared_errors(a, truth) for m, a in deg.items()}  # per angle: (sum, count)
    figs = {}
    groups = (("joints", list(range(robot.n_joint_axes))),
              ("torso", list(range(robot.n_joint_axes, robot.n_angles))))
    for group, idx in groups:
        if not idx:
            continue
        fig, axes = plt.subplots(len(idx), 2, figsize=(15, 2.2 * len(idx) + 1.1), sharex=True,
                                 squeeze=False, layout="constrained")
        for (ax, ex), k in zip(axes, idx):
            name = robot.angle_names[k]
            shown = [m for m in deg if np.isfinite(deg[m][:, k]).any()]
            rmse = {m: float(np.sqrt(sse[m][0][k] / sse[m][1][k])) if sse[m][1][k] else np.nan
                    for m in shown}
            # the worst drawn first, under the better ones; motion capture over them all
            shown.sort(key=lambda m: -rmse[m] if np.isfinite(rmse[m]) else -np.inf)
            # a method whose estimate is another's (the Std KF's torso is the gyro's) dashed
            # over it, and said so in the legend: one line would otherwise hide the other
            same = {}
            for i, m in enumerate(shown):
                for p in shown[:i]:
                    if p not in same and np.allclose(deg[m][:, k], deg[p][:, k], rtol=0,
                                                     atol=1e-9, equal_nan=True):
                        same[m] = p
                        break
            for z, m in enumerate(shown):
                style = _style(m, colour[m]) | ({"ls": "--"} if m in same else {})
                ax.plot(t, deg[m][:, k], label=label(m), zorder=2 + z, **style)
                ex.plot(t, deg[m][:, k] - truth[:, k], label=label(m), zorder=2 + z, **style)
            ax.plot(t, truth[:, k], zorder=3 + len(shown), **TRUTH)
            ex.axhline(0.0, color="k", lw=0.6, zorder=1)
            lim = np.nanmax(np.abs(truth[:, k])) if np.isfinite(truth[:, k]).any() else 30.0
            ax.set_ylim(-1.6 * lim - 5, 1.6 * lim + 5)
            ax.set_ylabel(f"{name} (deg)")
            ex.set_ylabel(f"{name} error (deg)")
            finite = [r for r in rmse.values() if np.isfinite(r)]
            if finite:
                top = max(np.nanmax(np.abs(deg[m][:, k] - truth[:, k])) for m in shown
                          if np.isfinite(rmse[m]))
                _symlog(ex, _linthresh(finite), 1.3 * top)
                best = sorted((m for m in shown if np.isfinite(rmse[m])), key=rmse.get)
                lines = {ln.get_label(): ln for ln in ex.get_lines()}
                ex.legend([lines[label(m)] for m in best],
                          [f"{label(m)}  {rmse[m]:.2f}" + (f" (= {label(same[m])})" if m in
                           same else "") for m in best], title="RMSE, this session (deg)",
                          fontsize=7, title_fontsize=7, loc="upper left",
                          bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
            else:
                ex.text(0.5, 0.5, "no motion capture", transform=ex.transAxes, ha="center")
            for a in (ax, ex):
                a.grid(alpha=0.3, which="major")
                _spans(a, name, t0, gaps, faults)
        axes[0, 0].set_title("angle: each method and motion capture (black)", fontsize=9)
        axes[0, 1].set_title("error: estimate minus motion capture (linear up to the first "
                             "tick, logarithmic beyond)", fontsize=9)
        for a in axes[-1]:
            a.set_xlabel("time (s)")
        handles = {}
        for a in axes[:, 0]:
            for h, lab in zip(*a.get_legend_handles_labels()):
                handles.setdefault(lab, h)
        order = ([label(m) for m in angles if label(m) in handles] + [TRUTH["label"]]
                 + [lab for lab in handles
                    if lab != TRUTH["label"] and lab not in {label(m) for m in angles}])
        # the title heads the legend (a suptitle would lie under a legend outside the axes)
        fig.legend([handles[lab] for lab in order], order, loc="outside upper center",
                   ncol=min(len(order), 9), fontsize=8, title=title or None,
                   title_fontsize=10, frameon=False)
        figs[group] = fig
    if nis:
        fig, ax = plt.subplots(figsize=(9, 2.6), layout="constrained")
        width = max(int(round(session.sample_rate_hz)), 1)
        nis_colour = colours(list(nis))
        for method, x in nis.items():
            x = np.asarray(x, np.float64)
            ok = np.isfinite(x)
            run = (np.convolve(np.where(ok, x, 0.0), np.ones(width), "same")
                   / np.maximum(np.convolve(ok.astype(float), np.ones(width), "same"), 1))
            ax.semilogy(*_broken(session.t - t0, run, rows), label=label(method),
                        **_style(method, nis_colour[method]))
        ax.axhline(1.0, color="k", lw=0.8, ls="--", label="consistent (1)")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("NIS (1 s mean)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
        figs["nis"] = fig
    return figs


def plot_session(
    session: Session, angles: Mapping[str, np.ndarray], out_dir: str, name: str,
    gaps: Sequence[dict] = (), nis: Mapping[str, np.ndarray] | None = None,
    faults: Sequence[dict] = (), title: str = "",
) -> list[str]:
    """Estimates of every method against motion capture, one figure for the joints (Fig. 5
    style) and one for the torso angles (Fig. 6 style): each angle on the left, motion
    capture in black over the estimates, and on the right each method's error against motion
    capture over time (estimate minus truth, deg) on a symmetric log scale (linear up to
    about twice the best method's RMSE, logarithmic beyond: a 0.2 deg error and a 1.7 deg
    one lie visibly apart beside a gyro's 30 deg drift), its legend each method's RMSE over
    this session, best first. Every method is named as in the tables (``TABLE_LABELS``) and
    has its own colour (``COLOURS``). Returns the files written.

    Args:
        session: the session (its ``truth()`` is motion capture).
        angles: ``{method: (T, K) angles in rad}``; NaN columns are skipped.
        out_dir: folder to write into (created if needed).
        name: file name prefix.
        gaps: the gaps of the sensor rows (``Gap.to_json()`` of ``kckf evaluate --json``):
            shaded, and no line is drawn across them.
        nis: ``{method: (T,) mean normalised innovation squared per row}``: a third figure,
            the NIS over time (a 1 s running mean) against its ideal 1.
        faults: the faulty readings' stretches (``"faults"`` of ``kckf evaluate --json``):
            a Hall sensor's marked on its joint's axes, a gyro's on every angle about its
            axis, each with its column and kind.
        title: the figures' title (the session's name, say).
    """
    plt = _plt()
    os.makedirs(out_dir, exist_ok=True)
    files = []
    for group, fig in session_figures(session, angles, gaps, nis, faults, title).items():
        path = os.path.join(out_dir, f"{name}_{group}.png")
        _save(fig, path)
        plt.close(fig)
        files.append(path)
    return files


def plot_drift(t: np.ndarray, errors_deg: Mapping[str, np.ndarray], path: str,
               title: str = "") -> str:
    """Absolute error over time of each method (the paper's Fig. 7), log scale."""
    plt = _plt()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    fig, ax = plt.subplots(figsize=(8, 3.2))
    colour = colours(list(errors_deg))
    for method, e in errors_deg.items():
        ax.semilogy(t / 60.0, np.maximum(np.abs(e), 1e-3), label=label(method),
                    **_style(method, colour[method]))
    ax.set_xlabel("time (min)")
    ax.set_ylabel("|error| (deg)")
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path


def plot_fit_progress(progress: Mapping, best_step: int, path: str) -> str:
    """A fit's progress (``kckf fit --plot``): each step's training loss and the validation
    loss where it was computed, the step whose parameters were kept marked; log scale where
    every loss is positive (RMSE), linear otherwise (a likelihood).

    Args:
        progress: the ``"progress"`` entry of ``kckf fit``'s JSON (``updates``, ``train``,
            ``val``, ``unit``).
        best_step: the updates of the parameters that were kept (``best_step``).
        path: the PNG to write (its folder is created if needed).
    """
    plt = _plt()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    step = np.asarray(progress["updates"], np.float64)
    train = np.asarray(progress["train"], np.float64)
    val = np.array([np.nan if v is None else v for v in progress["val"]], np.float64)
    fig, ax = plt.subplots(figsize=(7, 3.4))
    ax.plot(step, train, "-", color="C0", lw=1.2, label="train (each step's batch)")
    has_val = np.isfinite(val)
    if has_val.any():
        ax.plot(step[has_val], val[has_val], "o-", color="C3", ms=3, lw=1, label="validation")
    ax.axvline(best_step, color="0.3", ls="--", lw=1, label=f"kept: step {best_step}")
    losses = np.concatenate([train, val[has_val]])
    if losses.size and (losses > 0).all():
        ax.set_yscale("log")
    unit = progress["unit"].replace("_plus_", " + ")
    ax.set_xlabel("updates (fitting steps)")
    ax.set_ylabel(f"loss ({unit})")
    ax.set_title("kckf fit: the loss by step", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path


def plot_diagnostics(diag: Mapping, path: str, title: str = "") -> str:
    """Where a Kalman filter's error comes from (docs/diagnostics.md), one figure: above,
    each innovation channel's autocorrelation at lags ``1..k`` against its 95 % band (a
    white channel stays inside); below, each angle's error decomposed: its RMS, each group's
    part and the rest (deg), a group that is not significant drawn pale and hatched.

    Args:
        diag: the ``"diagnostics"`` entry of ``kckf evaluate --json`` (``Diagnostics.to_json()``).
        path: the PNG to write (its folder is created if needed).
        title: the figure's title (the method's name, say).
    """
    plt = _plt()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    white, errors = diag["whiteness"], diag["errors"]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 7.0))
    band, lo, hi = 0.0, 0.0, 0.0
    for i, (name, w) in enumerate(white.items()):
        acf = np.array([np.nan if x is None else x for x in w["acf"]], np.float64)
        lags = np.arange(1, acf.size + 1) + (i - (len(white) - 1) / 2) * 0.08
        verdict = "white" if w["white"] else "not white"
        top.plot(lags, acf, "o-", ms=3, lw=1,
                 label=f"{name}: Q = {w['q']:.4g} (95 %: {w['q95']:.4g}), {verdict}")
        band = max(band, w["band"] or 0.0)
        lo, hi = min(lo, np.nanmin(acf, initial=0.0)), max(hi, np.nanmax(acf, initial=0.0))
    if white:
        top.axhspan(-band, band, color="0.85", label="95 % band of white innovations")
        lo, hi = min(lo, -band), max(hi, band)
        top.set_ylim(lo - 0.1 * (hi - lo), hi + 0.6 * (hi - lo))  # room for the legend
    top.axhline(0.0, color="k", lw=0.6)
    top.set_xticks(np.arange(1, diag["lags"] + 1, max(diag["lags"] // 10, 1)))
    top.set_xlabel("lag (rows)")
    top.set_ylabel("autocorrelation")
    top.set_title(f"normalised innovations ({diag['whiteness_of']})", fontsize=9)
    top.grid(alpha=0.3)
    top.legend(fontsize=7, ncol=2, loc="upper center")
    parts = ["total", "bias", "direction", "angle", "time", "rest"]
    colours = {"total": "0.3", "bias": "C0", "direction": "C3", "angle": "C2", "time": "C1",
               "rest": "0.65"}
    width = 0.8 / len(parts)
    x = np.arange(len(errors))
    for j, part in enumerate(parts):
        heights, pale = [], []
        for p in errors.values():
            if part in ("total", "rest"):
                heights.append(p["rms_deg" if part == "total" else "rest_deg"])
                pale.append(False)
            else:
                heights.append(p["groups"][part]["part_deg"])
                pale.append(not p["groups"][part]["significant"])
        for xi, h, faint in zip(x, heights, pale):
            bottom.bar(xi + (j - (len(parts) - 1) / 2) * width, h or 0.0, width,
                       color=colours[part], alpha=0.3 if faint else 0.9,
                       hatch="//" if faint else None, edgecolor=colours[part])
    bottom.set_xticks(x, list(errors), fontsize=8)
    bottom.set_ylim(0, 1.2 * max([p["rms_deg"] or 0.0 for p in errors.values()] + [0.1]))
    bottom.set_ylabel("RMS (deg)")
    bottom.set_title(f"{diag['decomposed']} error against motion capture, decomposed "
                     "(pale, hatched: not significant)", fontsize=9)
    bottom.grid(alpha=0.3, axis="y")
    bottom.legend([plt.Rectangle((0, 0), 1, 1, color=colours[p]) for p in parts]
                  + [plt.Rectangle((0, 0), 1, 1, facecolor="C0", alpha=0.3, hatch="//")],
                  parts + ["not significant"], fontsize=7, ncol=7)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path
