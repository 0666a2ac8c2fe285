"""One ``fit --smooth`` step against one ``fit`` step (issue 37).

    python benchmarks/smooth_fit.py [--json] [--trials 64] [--steps 2000] [--learn A,B]
                                    [--quick]

``--trials`` recorded-like bench trials (x, y, x, y; ``kckf simulate``'s jittered stamps, 1 %
dropped readings, the voltage noise model) of ``--steps`` rows each, float32, fitted through
``kckf_jax.fit`` itself for 4 steps (the first compiles), once on the filtered estimates and
once on the smoothed ones (``FitConfig.smooth``), with the sensor effects ``--learn`` learned in
both (the offline recipe's). Reports each one's compile-and-first-step time, the median of the
other steps, the path the loss took (the filter's; the smoother's layout under the gradient)
and XLA's temporary buffers for the loss and its gradient. ``--quick``: a smoke run on tiny sizes
that the long tests execute (2 trials of 500 rows, 3 fitting steps; both fits, the figures
meaningless).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _machine import machine  # noqa: E402

from kckf_jax import (  # noqa: E402
    Auto,
    FitConfig,
    choose_path,
    enable_cpu_loops,
    fit,
    initial_params,
    loss_fn,
    make_batch,
    simulate,
)

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation


def one(sessions, smooth: bool, learn: tuple[str, ...], steps: int = 4) -> dict:
    cfg = FitConfig(steps=steps, smooth=smooth, learn=learn)
    params = initial_params(sessions, cfg, jnp.float32)
    batch = make_batch(sessions, jnp.float32)
    path = choose_path(params, batch.series, "kckf", Auto().for_loss()).path  # as fit's
    diff, static = eqx.partition(params, eqx.is_array)
    f = jax.jit(lambda d, b: eqx.filter_value_and_grad(
        lambda d: loss_fn(eqx.combine(d, static), b, "kckf", path=path, smooth=smooth))(d))
    mem = f.lower(diff, batch).compile().memory_analysis().temp_size_in_bytes
    del batch
    stamps = []
    t0 = time.perf_counter()
    fit(sessions, (), cfg, dtype=jnp.float32,
        callback=lambda r: stamps.append(time.perf_counter()))
    times = np.diff(stamps)
    return {"smooth": smooth, "path": path.name,
            "smoother_under_gradient": (path.batch_layout(len(sessions), "kckf") if smooth
                                        else None),
            "compile_and_first_s": round(stamps[0] - t0, 2),
            "step_s_median": round(float(np.median(times)), 3),
            "step_s_all": [round(float(t), 3) for t in times],
            "xla_temp_mb": round(mem / 1e6, 1)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=64)
    ap.add_argument("--steps", type=int, default=2000, help="rows per trial")
    ap.add_argument("--learn", default="gyro_timing,gyro_scale")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing")
    args = ap.parse_args()
    fit_steps = 4
    if args.quick:
        args.trials, args.steps, fit_steps = 2, 500, 3
    learn = tuple(x for x in args.learn.split(",") if x)
    sessions = [simulate("x,y,x,y", "cyclic", seed=i, duration_s=args.steps / 100.0,
                         device_seed=1, drop_prob=0.01) for i in range(args.trials)]
    runs = [one(sessions, False, learn, fit_steps), one(sessions, True, learn, fit_steps)]
    out = {"machine": machine(), "trials": args.trials, "rows": args.steps, "learn": learn,
           "dtype": "float32", "fit": runs[0], "fit_smooth": runs[1],
           "step_ratio": round(runs[1]["step_s_median"] / runs[0]["step_s_median"], 1)}
    if args.quick:
        out["quick"] = True
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        for r in runs:
            print(f"{'fit --smooth' if r['smooth'] else 'fit':>12}: compile+first "
                  f"{r['compile_and_first_s']} s, step {r['step_s_median']} s "
                  f"(path {r['path']}, XLA temporaries {r['xla_temp_mb']} MB)")
        print(f"ratio {out['step_ratio']}x")


if __name__ == "__main__":
    main()
