"""Gyros as worn (issue 50): boards tilted on their links and moving on soft mounts, fitted
with and without the learned mounting (``gyro_mounting``).

    python training/mounting.py [--joints x,y,z] [--kind walking] [--devices 7,8,9]
                                [--steps 300] [--tilt 10] [--soft 0] [--train 2]
                                [--also gyro_scale] [--fits ...,truth] [--quick]
    python training/mounting.py --table [--also gyro_scale]

Per device (``--devices``: each its own tilts; ``--train`` training sessions and one held-out
of 40 s, exact kinematics, 1 % dropped readings, ``kckf3d``) three fits on the training
sessions, each learning the effects ``--also`` names (default ``gyro_scale``: without it the
mounting stands in for the gyros' scale, docs/fitting.md):
the same sessions with rigid, aligned boards (``rigid``); the tilted (and, with ``--soft HZ``,
softly mounted) boards without the mounting (``not modelled``); and learning it (``learned``).
Reports the held-out RMSE (deg, the fit's kept step), the held-out mean RMSE of the kept
parameters filtered and smoothed (``kk.filter_sessions``, ``kk.rmse_table``), the kept step
against the steps run, each board's learned rotation against the simulator's (deg: the norm of
the difference of the rotation vectors; zero is the truth with ``--tilt 0``), and each hinge's
axis as each of its two boards sees it, learned against true (deg: what the filter reads of a
board is its rate along the hinge axes beside it, so a board's turn about its one hinge is
neither seen nor needed), and the validation curve (every 10 steps) with its last quarter's
worst over its best. Writes ``training/results/mounting_<joints>_<kind>[_tilt<deg>]
[_soft<hz>][_train<n>][_<also>].json`` (no ``_tilt`` part at the default 10 deg, no
``_train`` part at 2). ``--fits
learned`` runs only the named fits and keeps the others' figures from that file (the rigid and
not-modelled fits learn no mounting, so a change to how it is learned leaves them as they
were). ``--fits learned,truth`` adds a fit that learns everything else with the mounting kept
at the simulator's, and scores the learned fit's parameters with the true mounting put in:
their training RMSE says whether the data prefer the true axes to the learned ones.
``--quick``: a smoke run (one device, 10 s sessions, 5 steps) that writes nothing;
``--table``: docs/fitting.md's three tables (each effect alone and together on ``x,y,z``
walking; tilt and soft mount on every robot and motion run; learned against the truth kept,
where it was run) from the result files.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import kckf_jax as kk

kk.enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

HERE = os.path.dirname(os.path.abspath(__file__))
#: The fits a run can make: ``truth`` learns as ``learned`` does with the mounting kept at the
#: simulator's (what the data say of the learned axes: its training RMSE against the
#: learned fit's); run by ``--fits``, not by default.
FITS = ("rigid", "not_modelled", "learned", "truth")


def sessions(joints: str, kind: str, device: int, duration: float, sim: dict,
             n_train: int = 2) -> tuple:
    """``n_train`` training sessions and one held-out of ``device``; the first two and the
    held-out are the same whatever ``n_train``."""
    def one(seed):
        return kk.simulate(joints, kind, seed=seed, duration_s=duration, device_seed=device,
                           kinematics="exact", drop_prob=0.01, config=kk.SimConfig(**sim))

    more = [one(100 * device + 10 + i) for i in range(n_train - 2)]
    return [one(100 * device + 1), one(100 * device + 2)] + more, [one(100 * device + 3)]


def held_out(val, params) -> dict:
    """The held-out mean RMSE (deg) of ``params``, filtered and smoothed."""
    out = {}
    for name, smooth in (("filtered", False), ("smoothed", True)):
        est = kk.filter_sessions(val, "kckf3d", params, smooth=smooth)
        out[name] = round(kk.rmse_table(val, [e.angles for e in est])["mean_rmse_deg"], 3)
    return out


def rotation_matrices(v: np.ndarray) -> np.ndarray:
    """The rotations (``... 3 3``) of rotation vectors ``v`` (``... 3``, rad), Rodrigues'
    formula: the simulator's and the learned mounting's convention (a board reads ``R' w``)."""
    angle = np.linalg.norm(v, axis=-1)[..., None, None]
    k = v / np.maximum(angle[..., 0], 1e-300)
    K = np.zeros(v.shape + (3,))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def axis_errors(joints: str, got: np.ndarray, want: np.ndarray) -> list:
    """Per one-axis joint, the angle (deg) between its axis as each of its two boards sees it
    under the learned (``got``) and the true (``want``) mountings (``L 3``, deg): ``R' e``.
    Joint ``i + 1`` joins boards ``i`` and ``i + 1``."""
    Rg, Rw = (rotation_matrices(np.radians(np.asarray(v, np.float64))) for v in (got, want))
    out = []
    for i, axes in enumerate(kk.Robot.from_spec(joints).joints):
        if len(axes) != 1:
            continue
        e = np.eye(3)["xyz".index(axes[0])]
        for b in (i, i + 1):
            c = float(np.clip((Rg[b].T @ e) @ (Rw[b].T @ e), -1.0, 1.0))
            out.append(round(float(np.degrees(np.arccos(c))), 2))
    return out


def train_rmse(train, params) -> float:
    """The training sessions' mean RMSE (deg, filtered) of ``params``."""
    est = kk.filter_sessions(train, "kckf3d", params)
    return round(kk.rmse_table(train, [e.angles for e in est])["mean_rmse_deg"], 4)


def with_mounting(params, mounting):
    """``params`` with the boards' rotations (``L 3``, deg) set to ``mounting``."""
    return eqx.tree_at(lambda p: p.effects.mounting, params,
                       jnp.asarray(mounting, params.effects.mounting.dtype))


def fitted(train, val, steps: int, learn: tuple, mounting=None) -> dict:
    """One fit and its held-out scores. ``tail``: the last quarter's worst validation over the
    best (1 where the fit still improves at its end; how far it wanders off otherwise).
    ``mounting`` (``L 3``, deg): learning ``gyro_mounting``, start it there and keep it."""
    # One rate for every fit: the mounting's leaf (deg) takes steps 10 times it
    # (``_effects.STEP_SCALES``), the rest the default 0.03.
    cfg = kk.FitConfig(steps=steps, method="kckf3d", learn=learn, val_every=10,
                       patience=steps,
                       freeze=("effects.mounting",) if mounting is not None else ())
    init = (None if mounting is None else
            with_mounting(kk.initial_params(train, cfg, jnp.float32), mounting))
    t0 = time.time()
    res = kk.fit(train, val, cfg, init=init, dtype=jnp.float32)
    seconds = round(time.time() - t0, 1)
    curve = [(h["step"], h["val_deg"]) for h in res.history if h.get("val_deg") is not None]
    tail = max(v for k, v in curve if k > 0.75 * res.steps_done) / float(res.best_loss_deg)
    return {"val_rmse_deg": round(float(res.best_loss_deg), 3), **held_out(val, res.params),
            "train_rmse_deg": train_rmse(train, res.params),
            "best_step": res.best_step, "steps": res.steps_done, "tail": round(tail, 3),
            "val_curve": [[k, round(v, 4)] for k, v in curve], "seconds": seconds,
            "result": res}


def _mean(rows, fit, key):
    return sum(r[fit][key] for r in rows) / len(rows)


def _span(xs, fmt="{:.2f}"):
    lo, hi = fmt.format(min(xs)), fmt.format(max(xs))
    return lo if lo == hi else f"{lo}-{hi}"


def _learned(rows) -> str:
    """Both tables' last four cells: learned over rigid (filtered, per device), the kept
    steps, the last quarter's worst validation over the best, and the learned mounting against
    the truth."""
    ratio = [r["learned"]["filtered"] / r["rigid"]["filtered"] for r in rows]
    return (f"{_span(ratio)} | {_span([r['learned']['best_step'] for r in rows], '{}')} | "
            f"{_tail(rows, 'learned')} | {_axes(rows)}")


def _tail(rows, fit):
    """The last quarter's worst validation over the best, or ``-`` in a file from before it
    was recorded."""
    tails = [r[fit].get("tail") for r in rows]
    return "-" if None in tails else _span(tails)


def _axes(rows):
    """The learned hinge axes (or, without hinges, board rotations) within 1 deg of the truth,
    of all, and the largest error."""
    key = "hinge_axis_error_deg" if rows[0].get("hinge_axis_error_deg") else "mounting_error_deg"
    errs = [e for r in rows for e in r[key]]
    what = "hinge axes" if key == "hinge_axis_error_deg" else "boards"
    return f"{sum(e <= 1.0 for e in errs)} of {len(errs)} {what}; worst {max(errs):.1f} deg"


def effects(also: str) -> tuple:
    """``--also``'s effects (``''``: none)."""
    return tuple(x for x in also.split(",") if x)


def result_path(joints: str, kind: str, tilt: float = 10.0, soft: float = 0.0,
                train: int = 2, also: tuple = ()) -> str:
    """The result file of one run (see the module's docstring for the name's parts)."""
    name = f"mounting_{joints.replace(',', '-')}_{kind}"
    if tilt != 10.0:
        name += f"_tilt{tilt:g}"
    if soft:
        name += f"_soft{soft:g}"
    if train != 2:
        name += f"_train{train}"
    if also:
        name += "_" + "-".join(also)
    return os.path.join(HERE, "results", name + ".json")


def tables(also: str = "gyro_scale") -> str:
    """The two tables of docs/fitting.md ("Gyros as worn") from the result files of the fits
    that learned ``also`` besides the mounting."""
    def path(joints="x,y,z", kind="walking", **run):
        return result_path(joints, kind, also=effects(also), **run)

    def load(path):
        with open(path) as f:
            return json.load(f)["rows"]

    def pair(rows, k):
        return f"{_mean(rows, k, 'filtered'):.3f} / {_mean(rows, k, 'smoothed'):.3f}"

    out = ["| effect simulated (x,y,z walking, devices 7-9) | not modelled: filtered / smoothed "
           "| learned: filtered / smoothed | learned / rigid, filtered | kept steps (of 300) "
           "| last quarter: worst / best validation | learned mounting against the truth |",
           "| --- | --- | --- | --- | --- | --- | --- |"]
    base = load(path())
    out.append(f"| none (rigid, aligned boards) | {pair(base, 'rigid')} | - | - | "
               f"{_span([r['rigid']['best_step'] for r in base], '{}')} | "
               f"{_tail(base, 'rigid')} | - |")
    for label, run in (("tilt 5-10 deg", {}),
                       ("soft mount (8 Hz), no tilt", {"tilt": 0.0, "soft": 8.0}),
                       ("tilt and soft mount", {"soft": 8.0})):
        rows = load(path(**run))
        out.append(f"| {label} | {pair(rows, 'not_modelled')} | {pair(rows, 'learned')} | "
                   f"{_learned(rows)} |")
    # Every robot and motion run with tilt and soft mount, each file read once for both tables.
    runs = [(f"`{joints}` {kind} | {n}", load(file))
            for joints in ("x,y,z", "x,y,x,y", "xyz,xyz")
            for kind in ("walking", "cyclic", "human") for n in (2, 6)
            if os.path.exists(file := path(joints, kind, soft=8.0, train=n))]
    out += ["", "| robot, motion (tilt and soft mount, devices 7-9) | training sessions | rigid: "
            "filtered / smoothed | not modelled | learned | learned / rigid, filtered | kept "
            "steps (of 300) | last quarter: worst / best validation | learned mounting against "
            "the truth |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for label, rows in runs:
        cells = " | ".join(pair(rows, k) for k in ("rigid", "not_modelled", "learned"))
        out.append(f"| {label} | {cells} | {_learned(rows)} |")
    out += ["", "| robot, motion (tilt and soft mount, devices 7-9) | training sessions | "
            "learned hinge axes against the truth | training RMSE: learned / mounting kept at "
            "the truth | the same, per device: truth / learned | held-out, filtered: learned / "
            "truth | training RMSE, learned with the true mounting put in (not refitted) |",
            "| --- | --- | --- | --- | --- | --- | --- |"]
    for label, rows in runs:
        if "truth" not in rows[0]:
            continue
        ratio = [r["truth"]["train_rmse_deg"] / r["learned"]["train_rmse_deg"] for r in rows]
        swap = sum(r["learned_true_mounting"]["train_rmse_deg"] for r in rows) / len(rows)
        out.append(
            f"| {label} | {_axes(rows)} | {_mean(rows, 'learned', 'train_rmse_deg'):.3f} / "
            f"{_mean(rows, 'truth', 'train_rmse_deg'):.3f} | {_span(ratio, '{:.3f}')} | "
            f"{_mean(rows, 'learned', 'filtered'):.3f} / {_mean(rows, 'truth', 'filtered'):.3f} "
            f"| {swap:.3f} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--joints", default="x,y,z")
    ap.add_argument("--kind", default="walking")
    ap.add_argument("--devices", default="7,8,9")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--tilt", type=float, default=10.0, help="SimConfig.gyro_mount_deg")
    ap.add_argument("--soft", type=float, default=0.0, help="SimConfig.soft_mount_hz")
    ap.add_argument("--fits", default="rigid,not_modelled,learned",
                    help="the fits to run (and truth: the mounting kept at the simulator's); "
                    "the others' figures are kept from the result file")
    ap.add_argument("--also", default="gyro_scale",
                    help="effects every fit learns besides the mounting ('' for none)")
    ap.add_argument("--train", type=int, default=2, help="training sessions per device")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--table", action="store_true",
                    help="print docs/fitting.md's tables from the result files, run nothing")
    args = ap.parse_args()
    if args.table:
        print(tables(args.also))
        return
    fits = args.fits.split(",")
    unknown = sorted(set(fits) - set(FITS))
    if unknown:
        ap.error(f"--fits: unknown fit {unknown[0]!r}; expected some of {', '.join(FITS)}")
    also = effects(args.also)
    out_path = result_path(args.joints, args.kind, args.tilt, args.soft, args.train, also)
    kept = {}
    if not set(FITS[:3]) <= set(fits) and not args.quick:
        with open(out_path) as f:
            kept = {r["device"]: r for r in json.load(f)["rows"]}
    devices = [int(x) for x in args.devices.split(",")]
    duration, steps = 40.0, args.steps
    if args.quick:
        devices, duration, steps = devices[:1], 10.0, 5
    worn = {"gyro_mount_deg": args.tilt, "soft_mount_hz": args.soft}
    rows = []
    for device in devices:
        rigid = sessions(args.joints, args.kind, device, duration, {}, args.train)
        tilted = sessions(args.joints, args.kind, device, duration, worn, args.train)
        truth = tilted[0][0].extra_meta["simulation"]["effects"].get(
            "gyro_mount_deg", {n: [0.0, 0.0, 0.0] for n in range(kk.Robot.from_spec(
                args.joints).n_links)})
        row = {"device": device}
        truth_rot = np.array(list(truth.values()))
        for k, data, learn, mount in (
                ("rigid", rigid, also, None), ("not_modelled", tilted, also, None),
                ("learned", tilted, ("gyro_mounting",) + also, None),
                ("truth", tilted, ("gyro_mounting",) + also, truth_rot)):
            if k in fits:
                row[k] = fitted(*data, steps, learn, mount)
            elif k in kept.get(device, {}):
                row[k] = dict(kept[device][k])
        if truth and "learned" in fits:  # what the learned fit's mounting gives
            learned = row["learned"]["result"].params
            got = np.asarray(learned.effects.mounting, np.float64)
            row["mounting_error_deg"] = np.round(np.linalg.norm(got - truth_rot, axis=1),
                                                 2).tolist()
            row["mounting_true_deg"] = np.round(np.linalg.norm(truth_rot, axis=1), 2).tolist()
            row["mounting_learned_deg"] = np.round(got, 2).tolist()
            row["hinge_axis_error_deg"] = axis_errors(args.joints, got, truth_rot)
            # Its parameters with the true mounting put in, not refitted.
            swapped = with_mounting(learned, truth_rot)
            row["learned_true_mounting"] = {"train_rmse_deg": train_rmse(tilted[0], swapped),
                                            **held_out(tilted[1], swapped)}
        else:
            for k in ("mounting_error_deg", "mounting_true_deg", "mounting_learned_deg",
                      "hinge_axis_error_deg", "learned_true_mounting"):
                if k in kept[device]:
                    row[k] = kept[device][k]
        for k in fits:
            row[k].pop("result")
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = {"joints": args.joints, "kind": args.kind, "tilt_deg": args.tilt,
           "soft_hz": args.soft, "steps": steps, "method": "kckf3d",
           "learning_rate": "0.03, the mounting's leaf 10x (_effects.STEP_SCALES)",
           "also_learned": list(also), "training_sessions": args.train,
           "fits_run": fits, "rows": rows}
    if not args.quick:
        with open(out_path, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
