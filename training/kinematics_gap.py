"""What the paper's linear model costs on a robot with finite rotations (issue 35's baseline).

    python training/kinematics_gap.py [--steps 60] [--sessions 3] [--duration 60]
        [--methods kckf,kckf3d] [--merge]

For each layout (``xyz,xyz,xyz``, ``x,y,x,y``) and kind (``walking``, ``human``): training,
validation and ``--sessions`` test sessions of one device, each simulated twice with every
random draw the same, once with the paper's linear kinematics and once with exact rotations
(``simulate(..., kinematics=...)``). The linear KCKF (``kckf``) with the paper's defaults and
fitted on each data's own training sessions (RMSE loss, ``--steps`` steps) is scored on each
data's test sessions: mean RMSE over every angle and over the torso angles alone, deg. The
rotation-aware KCKF (``kckf3d``) is scored the same way on the exact data (``--methods``).
Writes ``training/results/kinematics_gap.json`` (``--merge``: keeps the cases it did not run).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from kckf_jax import FitConfig, Robot, enable_cpu_loops, filter_sessions, fit, rmse_table, simulate

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

HERE = os.path.dirname(os.path.abspath(__file__))


def sessions(spec: str, kind: str, kinematics: str, seeds, duration: float):
    return [simulate(spec, kind, seed=s, duration_s=duration, device_seed=11, drop_prob=0.01,
                     kinematics=kinematics) for s in seeds]


def score(robot, test, params, method="kckf"):
    est = filter_sessions(test, method, params)
    table = rmse_table(test, [e.angles for e in est])
    rmse = table["rmse_deg"]
    torso = [rmse[n] for n in robot.torso_angle_names]
    return {"mean_rmse_deg": round(float(table["mean_rmse_deg"]), 3),
            "torso_rmse_deg": round(float(np.mean(torso)), 3),
            "torso_rmse_per_axis_deg": [round(float(rmse[n]), 2) for n in robot.torso_angle_names]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--sessions", type=int, default=3)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--layouts", default="xyz,xyz,xyz;x,y,x,y")
    ap.add_argument("--kinds", default="walking,human")
    ap.add_argument("--methods", default="kckf,kckf3d")
    ap.add_argument("--merge", action="store_true")
    args = ap.parse_args()
    path = os.path.join(HERE, "results", "kinematics_gap.json")
    cases = {}
    if args.merge and os.path.exists(path):
        with open(path) as f:
            cases = json.load(f)["cases"]
    out = {"date": time.strftime("%Y-%m-%d"), "steps": args.steps, "duration_s": args.duration,
           "test_sessions": args.sessions, "cases": cases}
    methods = args.methods.split(",")
    for spec in args.layouts.split(";"):
        robot = Robot.from_spec(spec)
        for kind in args.kinds.split(","):
            for kin in ("linear", "exact"):
                train = sessions(spec, kind, kin, (1, 2), args.duration)
                val = sessions(spec, kind, kin, (3,), args.duration)
                test = sessions(spec, kind, kin, range(100, 100 + args.sessions),
                                args.duration)
                for method in methods:
                    if kin == "linear" and method != "kckf":
                        continue  # the exact model is for exact data
                    t0 = time.perf_counter()
                    fitted = fit(train, val, FitConfig(steps=args.steps, method=method)).params
                    row = {"paper": score(robot, test, None, method),
                           "fitted": score(robot, test, fitted, method),
                           "fit_s": round(time.perf_counter() - t0, 1)}
                    key = f"{spec} {kind} {kin}" + ("" if method == "kckf" else f" {method}")
                    out["cases"][key] = row
                    print(f"{spec:12s} {kind:8s} {kin:6s} {method:6s} paper "
                          f"{row['paper']['mean_rmse_deg']:6.2f} "
                          f"(torso {row['paper']['torso_rmse_deg']:6.2f})  fitted "
                          f"{row['fitted']['mean_rmse_deg']:6.2f} (torso "
                          f"{row['fitted']['torso_rmse_deg']:6.2f})", flush=True)
    with open(path, "w") as f:
        json.dump(out, f, indent=1)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
