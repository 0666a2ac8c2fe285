"""Figures in the style of the KCKF paper's Figs. 5-7 (matplotlib, written to files).

At the edge: the CLI and notebooks call these; nothing in the numerical core imports them.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np

from ._atomic import atomic_write
from ._session import Session


def _save(fig, path: str) -> None:
    """``fig`` as PNG at ``path``, whole or not at all (``atomic_write``)."""
    with atomic_write(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110)

RAD2DEG = 180.0 / np.pi
LABELS = {"kckf": "KCKF", "kf": "Std KF", "gyro": "Gyro", "hall_l": "Hall l", "hall_r": "Hall r"}
STYLES = {
    "kckf": dict(color="C3", lw=1.6), "kf": dict(color="C2", lw=1.0),
    "gyro": dict(color="C1", lw=0.8, alpha=0.8), "hall_l": dict(color="C0", lw=0.6, alpha=0.6),
    "hall_r": dict(color="C4", lw=0.6, alpha=0.6),
}


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


def plot_session(
    session: Session, angles: Mapping[str, np.ndarray], out_dir: str, name: str,
    gaps: list[dict] = (), nis: Mapping[str, np.ndarray] | None = None,
    faults: list[dict] = (),
) -> list[str]:
    """Estimates of every method against motion capture, one figure for the joints (Fig. 5
    style) and one for the torso angles (Fig. 6 style). Returns the files written.

    Args:
        session: the session (its ``truth()`` is drawn in black).
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
    """
    plt = _plt()
    os.makedirs(out_dir, exist_ok=True)
    robot = session.robot
    t0 = session.t[0]
    rows = [int(g["row"]) for g in gaps]
    t, truth = _broken(session.t - t0, session.truth(), rows)
    angles = {m: _broken(session.t - t0, a, rows)[1] for m, a in angles.items()}
    files = []
    groups = (("joints", list(range(robot.n_joint_axes))),
              ("torso", list(range(robot.n_joint_axes, robot.n_angles))))
    for group, idx in groups:
        fig, axes = plt.subplots(len(idx), 1, figsize=(9, 2.0 * len(idx) + 0.6), sharex=True,
                                 squeeze=False)
        for ax, k in zip(axes[:, 0], idx):
            ax.plot(t, truth[:, k] * RAD2DEG, color="k", lw=1.2, label="Mocap")
            for method, a in angles.items():
                col = np.asarray(a)[:, k]
                if np.isfinite(col).any():
                    ax.plot(t, col * RAD2DEG, label=LABELS.get(method, method),
                            **STYLES.get(method, {}))
            lim = np.nanmax(np.abs(truth[:, k] * RAD2DEG)) if np.isfinite(truth[:, k]).any() else 30
            ax.set_ylim(-1.6 * lim - 5, 1.6 * lim + 5)
            ax.set_ylabel(f"{robot.angle_names[k]} (deg)")
            ax.grid(alpha=0.3)
            for i, g in enumerate(gaps):
                ax.axvspan(g["t_s"] - t0, g["t_s"] - t0 + g["length_s"], color="0.85",
                           label=f"gap ({g['action']})" if i == 0 else None)
            shown = set()
            for f in faults:
                if _marks(f["column"], robot.angle_names[k]):
                    key = f"{f['column']} {f['kind']}"
                    hall = f["column"].startswith("hall")
                    ax.axvspan(f["from_s"] - t0, max(f["to_s"], f["from_s"] + 0.05) - t0,
                               color="C1" if hall else "C4", alpha=0.3 if hall else 0.12,
                               lw=0, label=None if key in shown else f"not used: {key}")
                    shown.add(key)
            if shown and k != idx[0]:
                ax.legend(loc="lower right", fontsize=7)
        axes[0, 0].legend(loc="upper right", ncol=6, fontsize=8)
        axes[-1, 0].set_xlabel("time (s)")
        fig.tight_layout()
        path = os.path.join(out_dir, f"{name}_{group}.png")
        _save(fig, path)
        plt.close(fig)
        files.append(path)
    if nis:
        fig, ax = plt.subplots(figsize=(9, 2.6))
        width = max(int(round(session.sample_rate_hz)), 1)
        for method, x in nis.items():
            x = np.asarray(x, np.float64)
            ok = np.isfinite(x)
            run = (np.convolve(np.where(ok, x, 0.0), np.ones(width), "same")
                   / np.maximum(np.convolve(ok.astype(float), np.ones(width), "same"), 1))
            ax.semilogy(*_broken(session.t - t0, run, rows), label=LABELS.get(method, method),
                        **STYLES.get(method, {}))
        ax.axhline(1.0, color="k", lw=0.8, ls="--", label="consistent (1)")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("NIS (1 s mean)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = os.path.join(out_dir, f"{name}_nis.png")
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
    for method, e in errors_deg.items():
        ax.semilogy(t / 60.0, np.maximum(np.abs(e), 1e-3), label=LABELS.get(method, method),
                    **STYLES.get(method, {}))
    ax.set_xlabel("time (min)")
    ax.set_ylabel("|error| (deg)")
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    ax.legend()
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
