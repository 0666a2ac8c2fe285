"""What a one-shot command waits for: each path's compile and first run, and its next run, in
a fresh process per case (no compile cache), on recorded-like data (the simulator's jittered
stamps, 1 % of readings missing, the voltage noise model), bench robot, float32. The
constants of ``AbstractPath.cost`` (``Auto(runs=1)``, the command's policy) come from here.

    python benchmarks/one_shot.py [--json] [--quick]  # every case, a table (or JSON)
    python benchmarks/one_shot.py CASE PATH           # one case in this process

Cases: ``hour`` (360,000 rows), ``hour_dropout`` (the same with every reading lost for 100 s),
``trials:B:T`` (B trials of T rows). ``--json``: the results as one JSON document, last on
stdout. ``--quick``: a smoke run on tiny sizes that the long tests execute (an "hour" of
16,000 rows, trials of 1,000 rows; a representative subset of the cases: every kind of case
and every path once, each still in a fresh process), the figures meaningless.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import kckf_jax as kk

CASES = [("hour", "segments"), ("hour", "sequential"), ("hour", "auto"),
         ("hour_dropout", "segments"), ("hour_dropout", "sequential"), ("hour_dropout", "auto"),
         ("trials:4:10000", "lanes"), ("trials:4:10000", "sequential"),
         ("trials:12:10000", "lanes"), ("trials:12:10000", "sequential"),
         ("trials:64:10000", "lanes"), ("trials:64:10000", "sequential")]
#: ``--quick``: every kind of case and every path once (the hours are 16,000 rows).
QUICK_CASES = [("hour", "auto"), ("hour_dropout", "segments"), ("trials:4:1000", "lanes"),
               ("trials:4:1000", "sequential")]


def one(case: str, path: str, quick: bool = False) -> dict:
    kk.enable_cpu_loops()
    robot = kk.Robot.from_spec("x,y,x,y")
    if case.startswith("hour"):
        T = 16_000 if quick else 360_000
        s = kk.simulate(robot, "static", seed=3, duration_s=T / 100.0, drop_prob=0.01)
        p = kk.initial_params([s], kk.FitConfig(), jnp.float32)
        ser = kk.session_series(s, jnp.float32)
        if case == "hour_dropout":
            n, r0 = T // 36, T * 5 // 18
            gyro, hall = np.array(ser.gyro), np.array(ser.hall_v)
            gyro[r0:r0 + n] = np.nan
            hall[r0:r0 + n] = np.nan
            ser = kk.SensorSeries(ser.dt, jnp.asarray(gyro), jnp.asarray(hall))
        ser, _ = kk.screened(p, ser)
        jax.block_until_ready(ser.dt)
        t0 = time.perf_counter()
        est = kk.run_filter(p, ser, "kckf", path=_policy(path))[1]
        jax.block_until_ready(est.angles)
        t1 = time.perf_counter()
        est = kk.run_filter(p, ser, "kckf", path=_policy(path))[1]
        jax.block_until_ready(est.angles)
        t2 = time.perf_counter()
    else:  # "trials:B:T"
        _, B, T = case.split(":")
        B, T = int(B), int(T)
        sess = [kk.simulate(robot, "cyclic", seed=i, duration_s=T / 100.0, drop_prob=0.01,
                            device_seed=1) for i in range(B)]
        p = kk.initial_params(sess, kk.FitConfig(), jnp.float32)
        b = kk.pad_series([kk.session_series(x, np.float64) for x in sess])
        b = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), b)
        b, _ = kk.screened(p, b)
        jax.block_until_ready(b.dt)
        t0 = time.perf_counter()
        est = kk.filter_batch(p, b, "kckf", path=_policy(path))
        jax.block_until_ready(est.angles)
        t1 = time.perf_counter()
        est = kk.filter_batch(p, b, "kckf", path=_policy(path))
        jax.block_until_ready(est.angles)
        t2 = time.perf_counter()
    print(f"{case} {path}: first call {t1 - t0:.3f} s, second {t2 - t1:.3f} s, ran {est.path}",
          flush=True)
    return {"case": case, "path": path, "first_s": t1 - t0, "second_s": t2 - t1,
            "ran": str(est.path)}


def _policy(path: str):
    return kk.Auto(runs=1) if path == "auto" else path


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", nargs="?", help="run this one case in this process (with PATH)")
    ap.add_argument("path", nargs="?", help="the path of the one case")
    ap.add_argument("--json", action="store_true",
                    help="the results as JSON (last on stdout)")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing; a representative subset of the cases (every kind of case "
                         "and every path once)")
    args = ap.parse_args(argv)
    if args.case is not None:
        if args.path is None:
            ap.error("a case needs its path: CASE PATH")
        row = one(args.case, args.path, args.quick)
        if args.json:
            print(json.dumps(row))
        return 0
    flags = (["--quick"] if args.quick else []) + (["--json"] if args.json else [])
    rows = []
    for case, path in QUICK_CASES if args.quick else CASES:
        r = subprocess.run([sys.executable, __file__, case, path, *flags], capture_output=True,
                           text=True)
        if r.returncode != 0:
            sys.exit(f"{case} {path} failed ({r.returncode}):\n{r.stderr[-3000:]}")
        lines = r.stdout.strip().splitlines()
        if args.json:
            rows.append(json.loads(lines[-1]))
            print(lines[-2], file=sys.stderr, flush=True)
        else:
            print(lines[-1], flush=True)
    if args.json:
        print(json.dumps({"benchmark": "one_shot", "quick": args.quick, "cases": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
