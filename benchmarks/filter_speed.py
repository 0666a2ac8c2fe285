"""Steps per second of the KCKF: one long session and 64 vmapped trials, float32 and float64.

    python benchmarks/filter_speed.py [--json] [--repeats 5] [--quick]

Data are simulated bench sessions (x, y, x, y) with 1 % of readings missing, so every trial's
covariance differs (a vmapped filter cannot share one covariance across trials, see
../shared/notes/jax-cpu-hazards.md, item 4). Times are the median of ``--repeats`` runs after a
compile-and-warm-up run; compile time is reported separately. ``--quick``: a smoke run on
tiny sizes (a 10 s session, two trials of 300 steps, one repeat; both cases, both dtypes) that
the long tests run: the figures mean nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _machine import machine  # noqa: E402

from kckf_jax import (  # noqa: E402
    Params,
    enable_cpu_loops,  # noqa: E402
    filter_batch,
    pad_series,
    run_filter,
    session_series,
    simulate,
)

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation


def _time(fn, repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return first, float(np.median(times))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--method", default="kckf")
    ap.add_argument("--long-s", type=float, default=3600.0, help="long session length, s")
    ap.add_argument("--trials", type=int, default=64)
    ap.add_argument("--trial-steps", type=int, default=10_000)
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing")
    args = ap.parse_args()
    if args.quick:
        args.repeats, args.long_s, args.trials, args.trial_steps = 1, 10.0, 2, 300

    long_s = simulate("x,y,x,y", "cyclic", seed=1, duration_s=args.long_s, drop_prob=0.01)
    trials = [simulate("x,y,x,y", "cyclic", seed=100 + i, drop_prob=0.01,
                       duration_s=args.trial_steps / 100.0) for i in range(args.trials)]
    rows = []
    for dtype in (jnp.float32, jnp.float64):
        params = Params.paper_defaults(long_s.robot, long_s.hall_models, dtype=dtype)
        series = session_series(long_s, dtype)
        T = series.dt.shape[0]
        first, med = _time(lambda: run_filter(params, series, args.method)[1].angles,
                           args.repeats)
        rows.append(dict(case=f"one session, {T} steps", dtype=jnp.dtype(dtype).name,
                         seconds=med, compile_and_first_s=first, steps_per_s=T / med))
        batch = pad_series([session_series(s, np.float64) for s in trials])
        batch = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), batch)
        B, T = batch.dt.shape
        first, med = _time(lambda: filter_batch(params, batch, args.method).angles, args.repeats)
        rows.append(dict(case=f"{B} vmapped trials x {T} steps", dtype=jnp.dtype(dtype).name,
                         seconds=med, compile_and_first_s=first, steps_per_s=B * T / med))
    doc = {"benchmark": "filter_speed", "method": args.method, "machine": machine(),
           "date": time.strftime("%Y-%m-%d"), "results": rows}
    if args.quick:
        doc["quick"] = True
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        print(f"{args.method} on {doc['machine']['cpu']} ({doc['machine']['cores']} cores), "
              f"jax {doc['machine']['jax']} {doc['machine']['backend']}")
        print(f"{'case':<34}{'dtype':>9}{'time (s)':>11}{'steps/s':>13}{'compile+1st':>13}")
        for r in rows:
            print(f"{r['case']:<34}{r['dtype']:>9}{r['seconds']:>11.3f}{r['steps_per_s']:>13,.0f}"
                  f"{r['compile_and_first_s']:>13.2f}")


if __name__ == "__main__":
    main()
