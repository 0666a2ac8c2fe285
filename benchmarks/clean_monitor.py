"""The health monitor on clean data: what it isolates, and what that costs the estimates.

    python benchmarks/clean_monitor.py [--sessions 20] [--duration 30] [--steps 30]
                                       [--cases all|quick] [--only WORDS] [--method M]
                                       [--json [OUT]] [--quick]

A monitor exists to make the estimates better; on a clean session it must take nothing out
for more than a moment and cost nothing. Per case (kinematics, joint layout, kind of motion,
joint range, method, parameters) ``--sessions`` clean simulated sessions of one robot
(``device_seed`` fixed per case, ``seed`` 1..N), each filtered with ``--faults isolate`` and
``--faults off`` (float32, the default gap policy); parameters: the paper's defaults, and a
fit (``--steps`` Adam steps, ``FitConfig`` defaults otherwise) on two other trials of the
same robot. Reported per case: the monitor's findings per hour (readings it would isolate,
by kind), the mean RMSE with ``isolate`` over ``off`` (mean and the worst session), and the
model-mismatch warnings (``pair_mismatch``) the report gives, and for ``kckf3d`` the gyro
bias steps named from its bias estimate (``kk.bias_steps``: ``bias_steps_named``, any is a
false alarm on clean data). ``--json OUT`` writes the rows
to ``OUT`` (after each case); ``--json`` alone prints them as one line of JSON at the end of
stdout (the per-case lines go to stderr then). ``--quick`` is the smoke run the long tests
execute: ``--cases quick`` (three small cases that between them take every value of each of
the case's parts but one, a fit of ``kckf3d``, whose gradient takes about a minute to compile on
two cores; two 10 s sessions each) with 2 Adam steps per fit; the figures mean nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
import time
import zlib

import numpy as np

import kckf_jax as kk
from kckf_jax import enable_cpu_loops

enable_cpu_loops()


def cases(which: str):
    """``(kinematics, joints, kind, range_deg, method, params)`` per case."""
    if which == "quick":
        yield ("exact", "x,y,x,y", "walking", None, "kckf", "paper")
        yield ("linear", "x,y,z", "human", 140.0, "kckf", "fitted")
        yield ("exact", "xyz,xyz,xyz", "cyclic", 140.0, "kckf3d", "paper")
        return
    for reach, kin, joints, kind in itertools.product(
            (140.0, None), ("exact", "linear"), ("x,y,x,y", "x,y,z", "xyz,xyz,xyz"),
            ("walking", "human", "cyclic")):
        methods = ("kckf", "kckf3d") if kin == "exact" else ("kckf",)
        for method in methods:
            for params in ("paper", "fitted"):
                yield kin, joints, kind, reach, method, params


def sessions_of(kin, joints, kind, reach, seeds, duration, device_seed):
    cfg = kk.SimConfig()
    if reach is not None:
        cfg = dataclasses.replace(cfg, motion_range_deg=reach)
    return [kk.simulate(joints, kind, seed, duration, config=cfg, kinematics=kin,
                        device_seed=device_seed) for seed in seeds]


def mean_rmse(sessions, ests):
    return [kk.rmse_table([s], [e.angles])["mean_rmse_deg"] for s, e in zip(sessions, ests)]


def run_case(case, n, duration, steps):
    kin, joints, kind, reach, method, which = case
    dev = 1000 + zlib.crc32(repr(case[:4]).encode()) % 1000  # one robot per case
    sessions = sessions_of(kin, joints, kind, reach, range(1, n + 1), duration, dev)
    params = None
    if which == "fitted":
        train = sessions_of(kin, joints, kind, reach, (901, 902), duration, dev)
        params = kk.fit(train, (), kk.FitConfig(steps=steps, method=method)).params
    out = {}
    for policy in ("isolate", "off"):
        ests = kk.filter_sessions(sessions, method, params, faults=policy)
        out[policy] = (mean_rmse(sessions, ests), ests)
    iso, off = np.array(out["isolate"][0]), np.array(out["off"][0])
    ratio = iso / off
    hours = sum(s.t[-1] - s.t[0] for s in sessions) / 3600.0
    kinds: dict[str, int] = {}
    for e in out["isolate"][1]:
        codes = np.asarray(e.faults)
        for k in np.unique(codes[codes > 0]):
            kinds[kk.FAULT_KINDS[int(k) - 1]] = kinds.get(kk.FAULT_KINDS[int(k) - 1], 0) + int(
                (codes == k).sum())
    mismatch = sum(bool(kk.model_mismatch(s, method)) for s in sessions)
    # kckf3d's bias steps (no gyro pairs: named from its bias estimate, ``kk.bias_steps``).
    steps = (sum(len(kk.bias_steps(s, e)) for s, e in zip(sessions, out["isolate"][1]))
             if method == "kckf3d" else 0)
    worst = int(np.argmax(ratio))
    return {"kinematics": kin, "joints": joints, "kind": kind,
            "range_deg": reach or "default", "method": method, "params": which,
            "sessions": n, "isolated_per_hour": {k: round(v / hours) for k, v in kinds.items()},
            "rmse_off_deg": round(float(off.mean()), 3),
            "rmse_isolate_deg": round(float(iso.mean()), 3),
            "ratio_mean": round(float(ratio.mean()), 4),
            "ratio_worst": round(float(ratio[worst]), 4), "worst_seed": worst + 1,
            "sessions_with_mismatch_warning": mismatch, "bias_steps_named": steps}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=20)
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--cases", choices=("all", "quick"), default="all")
    ap.add_argument("--only", help="words of the case's label (all of them) to run only those")
    ap.add_argument("--method", choices=("kckf", "kckf3d"), help="only this method's cases")
    ap.add_argument("--json", nargs="?", const="-",
                    help="write the rows to this file; without one, print them as JSON (one "
                         "line, the last on stdout)")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing; --cases quick (three cases, not a fit of kckf3d), 2 Adam "
                         "steps")
    args = ap.parse_args(argv)
    if args.quick:
        args.cases, args.steps = "quick", 2
    to_stdout = args.json == "-"
    log = sys.stderr if to_stdout else sys.stdout
    n = 2 if args.cases == "quick" else args.sessions
    duration = 10.0 if args.cases == "quick" else args.duration
    rows = []
    for case in cases(args.cases):
        label = " ".join(str(c) for c in case)
        if args.only and not all(w in label.split() for w in args.only.split()):
            continue
        if args.method and case[4] != args.method:
            continue
        t0 = time.perf_counter()
        row = run_case(case, n, duration, args.steps)
        row["seconds"] = round(time.perf_counter() - t0, 1)
        rows.append(row)
        print(f"{label:50s} per h {row['isolated_per_hour']} off {row['rmse_off_deg']:.3f} "
              f"isolate/off mean {row['ratio_mean']:.4f} worst {row['ratio_worst']:.4f} "
              f"(seed {row['worst_seed']}) mismatch {row['sessions_with_mismatch_warning']}/"
              f"{n} bias steps {row['bias_steps_named']} [{row['seconds']} s]", file=log,
              flush=True)
        if args.json and not to_stdout:
            with open(args.json, "w") as f:
                json.dump(rows, f, indent=1)
    if rows:
        worst = max(r["ratio_worst"] for r in rows)
        print(f"worst session isolate/off over every case: {worst:.4f}", file=log)
    else:
        print("no case matches --only/--method", file=log)
    if to_stdout:
        print(json.dumps(rows), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
