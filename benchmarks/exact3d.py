"""The rotation-aware KCKF (``kckf3d``) against the linear KCKF in the same run: a batch of
recorded-like trials, one fitting step, one trial, and an hour in float32.

    python benchmarks/exact3d.py [--json] [--trials 64] [--rows 10000] [--hour] [--quick]

Data: the project's simulator, exact-rotation walking of the 3D layout ``xyz,xyz,xyz``,
recorded-like (jittered stamps, 1 % of readings missing, the voltage noise model of
``FitConfig()``'s initial parameters), float32. Each filter on the path ``Auto`` chooses
(the linear KCKF: lanes for the batch, sequential for one trial; ``kckf3d``: its own lanes
step for both, and the sequential path in the fitting step's gradient), named in the
output. Times: compile and first call, then the median of three calls. The fitting
step is ``fit``'s own (RMSE loss, gradient, Adam update; 4 steps, the first compiles; the
median of the other 3). ``--hour``: one hour of walking in float32 and float64: finite, the
covariance's smallest eigenvalue, the largest float32 - float64 difference and the RMSE.
``--quick``: a smoke run on tiny sizes that the long tests run (one trial of 300 rows, one timed
call, 2 fitting steps of the linear KCKF only, as ``kckf3d``'s gradient takes about a minute to
compile on two cores, and ``--hour``'s section on 5 s): the figures mean nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _machine import machine  # noqa: E402

from kckf_jax import (  # noqa: E402
    FitConfig,
    enable_cpu_loops,
    filter_batch,
    fit,
    initial_params,
    pad_series,
    rmse_table,
    run_filter,
    session_series,
    simulate,
)

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation
SPEC = "xyz,xyz,xyz"


def sessions(n: int, rows: int):
    return [simulate(SPEC, "walking", seed=i, duration_s=rows / 100.0, device_seed=1,
                     drop_prob=0.01, kinematics="exact") for i in range(n)]


def timed(f, repeats: int = 3) -> tuple[float, float]:
    t0 = time.perf_counter()
    jax.block_until_ready(f())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(f())
        times.append(time.perf_counter() - t0)
    return first, float(np.median(times))


def batch_case(trials: int, rows: int, repeats: int = 3) -> dict:
    ss = sessions(trials, rows)
    params = initial_params(ss, FitConfig(), jnp.float32)
    series = pad_series([session_series(s, np.float64) for s in ss])
    series = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), series)
    out = {}
    for method in ("kckf", "kckf3d"):
        est = filter_batch(params, series, method)
        first, med = timed(lambda m=method: filter_batch(params, series, m).angles, repeats)
        out[method] = {"path": est.path, "compile_and_first_s": round(first, 2),
                       "run_s": round(med, 3)}
    out["ratio"] = round(out["kckf3d"]["run_s"] / out["kckf"]["run_s"], 1)
    return out


def fit_case(trials: int, rows: int, steps: int = 4,
             methods: tuple[str, ...] = ("kckf", "kckf3d")) -> dict:
    ss = sessions(trials, rows)
    out = {}
    for method in methods:
        stamps = []
        t0 = time.perf_counter()
        fit(ss, (), FitConfig(steps=steps, method=method), dtype=jnp.float32,
            callback=lambda r, stamps=stamps: stamps.append(time.perf_counter()))
        out[method] = {"compile_and_first_s": round(stamps[0] - t0, 2),
                       "step_s": round(float(np.median(np.diff(stamps))), 3)}
    if len(methods) == 2:
        out["ratio"] = round(out["kckf3d"]["step_s"] / out["kckf"]["step_s"], 1)
    return out


def hour_case(duration_s: float = 3600.0) -> dict:
    (s,) = [simulate(SPEC, "walking", seed=7, duration_s=duration_s, drop_prob=0.01,
                     kinematics="exact")]
    out, angles = {}, {}
    jax.config.update("jax_enable_x64", True)  # the last case: float64 for the reference run
    for dtype in (jnp.float32, jnp.float64):
        params = initial_params([s], FitConfig(), dtype)
        t0 = time.perf_counter()
        final, est = run_filter(params, session_series(s, dtype), "kckf3d")
        jax.block_until_ready(est.angles)
        secs = time.perf_counter() - t0
        a = np.asarray(est.angles, np.float64)
        P = np.asarray(final.P[0], np.float64)
        angles[str(np.dtype(dtype))] = a
        out[str(np.dtype(dtype))] = {
            "finite": bool(np.isfinite(a).all()),
            "min_eig_P": float(np.linalg.eigvalsh(0.5 * (P + P.T)).min()),
            "symmetric": bool(np.array_equal(P, P.T)),
            "mean_rmse_deg": round(rmse_table([s], [a])["mean_rmse_deg"], 3),
            "seconds": round(secs, 1)}
    out["max_f32_f64_deg"] = round(float(np.degrees(np.abs(angles["float32"]
                                                            - angles["float64"]).max())), 4)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--trials", type=int, default=64)
    ap.add_argument("--rows", type=int, default=10_000)
    ap.add_argument("--hour", action="store_true")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing; every section, but the fitting step of the linear KCKF only "
                         "(kckf3d's gradient takes about a minute to compile)")
    args = ap.parse_args()
    repeats, fit_steps, fit_methods, hour_s = 3, 4, ("kckf", "kckf3d"), 3600.0
    if args.quick:
        args.trials, args.rows, args.hour = 1, 300, True
        repeats, fit_steps, fit_methods, hour_s = 1, 2, ("kckf",), 5.0
    out = {"machine": machine(), "layout": SPEC, "trials": args.trials, "rows": args.rows,
           "filter": batch_case(args.trials, args.rows, repeats),
           "fit_step": fit_case(args.trials, args.rows, fit_steps, fit_methods)}
    out["one_trial"] = batch_case(1, args.rows, repeats)
    if args.hour:
        out["hour"] = hour_case(hour_s)
    if args.quick:
        out["quick"] = True
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        for k, v in out.items():
            print(f"{k}: {v}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
