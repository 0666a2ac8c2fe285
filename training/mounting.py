"""Gyros as worn (issue 50): boards tilted on their links and moving on soft mounts, fitted
with and without the learned mounting (``gyro_mounting``).

    python training/mounting.py [--joints x,y,z] [--kind walking] [--devices 7,8,9]
                                [--steps 300] [--tilt 10] [--soft 0] [--fits ...] [--quick]

Per device (``--devices``: each its own tilts; two training sessions and one held-out of 40
s, exact kinematics, 1 % dropped readings, ``kckf3d``) three fits on the training sessions:
the same sessions with rigid, aligned boards (``rigid``); the tilted (and, with ``--soft HZ``,
softly mounted) boards without the mounting (``not modelled``); and learning it (``learned``).
Reports the held-out RMSE (deg, the fit's kept step), the kept step against the steps run, and
each board's learned rotation against the simulator's (deg: the norm of the difference of the
rotation vectors). Writes ``training/results/mounting_<joints>_<kind>.json``. ``--fits
learned`` runs only the named fits and keeps the others' figures from that file (the rigid and
not-modelled fits learn no mounting, so a change to how it is learned leaves them as they
were); ``--quick``: a smoke run (one device, 10 s sessions, 5 steps) that writes nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax.numpy as jnp
import numpy as np

import kckf_jax as kk

kk.enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

HERE = os.path.dirname(os.path.abspath(__file__))


def sessions(joints: str, kind: str, device: int, duration: float, sim: dict) -> tuple:
    def one(seed):
        return kk.simulate(joints, kind, seed=seed, duration_s=duration, device_seed=device,
                           kinematics="exact", drop_prob=0.01, config=kk.SimConfig(**sim))

    return [one(100 * device + 1), one(100 * device + 2)], [one(100 * device + 3)]


def fitted(train, val, steps: int, learn: tuple) -> dict:
    # One rate for every fit: the mounting's leaf (deg) takes steps 10 times it
    # (``_effects.STEP_SCALES``), the rest the default 0.03.
    cfg = kk.FitConfig(steps=steps, method="kckf3d", learn=learn, val_every=10,
                       patience=steps)
    t0 = time.time()
    res = kk.fit(train, val, cfg, dtype=jnp.float32)
    return {"val_rmse_deg": round(float(res.best_loss_deg), 3), "best_step": res.best_step,
            "steps": res.steps_done, "seconds": round(time.time() - t0, 1), "result": res}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--joints", default="x,y,z")
    ap.add_argument("--kind", default="walking")
    ap.add_argument("--devices", default="7,8,9")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--tilt", type=float, default=10.0, help="SimConfig.gyro_mount_deg")
    ap.add_argument("--soft", type=float, default=0.0, help="SimConfig.soft_mount_hz")
    ap.add_argument("--fits", default="rigid,not_modelled,learned",
                    help="the fits to run; the others' figures are kept from the result file")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    fits = args.fits.split(",")
    unknown = sorted(set(fits) - {"rigid", "not_modelled", "learned"})
    if unknown:
        ap.error(f"--fits: unknown fit {unknown[0]!r}; expected rigid, not_modelled, learned")
    name = f"mounting_{args.joints.replace(',', '-')}_{args.kind}"
    if args.soft:
        name += f"_soft{args.soft:g}"
    out_path = os.path.join(HERE, "results", name + ".json")
    kept = {}
    if len(fits) < 3 and not args.quick:
        with open(out_path) as f:
            kept = {r["device"]: r for r in json.load(f)["rows"]}
    devices = [int(x) for x in args.devices.split(",")]
    duration, steps = 40.0, args.steps
    if args.quick:
        devices, duration, steps = devices[:1], 10.0, 5
    worn = {"gyro_mount_deg": args.tilt, "soft_mount_hz": args.soft}
    rows = []
    for device in devices:
        rigid = sessions(args.joints, args.kind, device, duration, {})
        tilted = sessions(args.joints, args.kind, device, duration, worn)
        truth = tilted[0][0].extra_meta["simulation"]["effects"].get("gyro_mount_deg")
        row = {"device": device}
        for k, data, learn in (("rigid", rigid, ()), ("not_modelled", tilted, ()),
                               ("learned", tilted, ("gyro_mounting",))):
            row[k] = fitted(*data, steps, learn) if k in fits else dict(kept[device][k])
        if truth and "learned" in fits:
            got = np.asarray(row["learned"]["result"].params.effects.mounting, np.float64)
            want = np.array(list(truth.values()))
            row["mounting_error_deg"] = np.round(np.linalg.norm(got - want, axis=1), 2).tolist()
            row["mounting_true_deg"] = np.round(np.linalg.norm(want, axis=1), 2).tolist()
        elif truth:
            for k in ("mounting_error_deg", "mounting_true_deg"):
                row[k] = kept[device][k]
        for k in fits:
            row[k].pop("result")
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = {"joints": args.joints, "kind": args.kind, "tilt_deg": args.tilt,
           "soft_hz": args.soft, "steps": steps, "method": "kckf3d",
           "learning_rate": "0.03, the mounting's leaf 10x (_effects.STEP_SCALES)",
           "fits_run": fits, "rows": rows}
    if not args.quick:
        with open(out_path, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
