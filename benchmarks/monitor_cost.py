"""What the health monitor costs: the filter with ``--faults isolate`` against ``off`` in one run.

    python benchmarks/monitor_cost.py [--quick] [--json]

Data: recorded-like sessions of the bench robot (``x,y,x,y``; ``kckf simulate``'s jittered
stamps, 1 % of readings missing, the voltage noise model of a fit's starting point),
float32. Cases: 64 trials x 10,000 rows through ``filter_batch`` (the path ``Auto`` picks:
lanes) and one recorded-like hour (360,000 rows) through ``run_filter``; each with the
fault policy ``isolate`` (the plausibility screen, then the monitor's scan, then the filter)
and ``off`` (the screen, then the filter), best of 3 after a compiled first call, and the
monitor's scan alone with the screen (``kk.screened``, no filter). Issue 45's aim:
``isolate`` at most 1.15x ``off``. ``--quick``: 4 trials x 2,000 rows and a 2-minute
"hour", the smoke run the long tests execute.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import kckf_jax as kk
from kckf_jax import enable_cpu_loops

enable_cpu_loops()


def best_of(fn, repeats=3):
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    B, T, hour_s = (4, 2000, 120.0) if args.quick else (64, 10000, 3600.0)
    robot = kk.Robot.from_spec("x,y,x,y")
    base = [kk.simulate(robot, "cyclic", seed=i, duration_s=T / 100.0, drop_prob=0.01,
                        device_seed=1) for i in range(min(B, 16))]
    sessions = [base[i % len(base)] for i in range(B)]
    params = kk.initial_params(sessions, kk.FitConfig(), jnp.float32)
    batch = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), kk.pad_series(
        [kk.session_series(s, np.float64) for s in sessions]))
    hour = kk.simulate(robot, "static", seed=3, duration_s=hour_s, drop_prob=0.01)
    hour_series = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32),
                                         kk.session_series(hour, np.float64))
    rows = {}
    for name, run, series in (
            ("batch", lambda p: kk.filter_batch(p, batch, "kckf").angles, batch),
            ("hour", lambda p: kk.run_filter(p, hour_series, "kckf")[1].angles, hour_series)):
        t = {f: best_of(lambda f=f: run(params.with_faults(f))) for f in ("off", "isolate")}
        # The readings judged alone and over time, without the filter (``kk.screened``: the
        # monitor's scan and the per-reading screen).
        t["monitor_scan"] = best_of(lambda: kk.screened(params, series)[0].gyro)
        t["ratio"] = t["isolate"] / t["off"]
        rows[name] = {k: round(v, 4) for k, v in t.items()}
        print(f"{name:6s} off {t['off']:.3f} s  isolate {t['isolate']:.3f} s  "
              f"ratio {t['ratio']:.2f}  (the monitor's scan alone {t['monitor_scan']:.3f} s)",
              flush=True)
    if args.json:
        print(json.dumps({"B": B, "T": T, "hour_s": hour_s, "rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
