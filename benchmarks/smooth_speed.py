"""Offline analysis speed: the RTS smoother and one step of the likelihood loss.

    python benchmarks/smooth_speed.py [--json] [--quick]

Data: recorded-like bench sessions (x, y, x, y) as ``kckf simulate`` writes them (jittered
timestamps, 1 % of the readings missing) and the ``voltage`` Hall noise model of a fit's
starting point, float32.

Cases: ``smooth`` of one recorded-like hour (360,000 rows), with ``run_filter`` on the same
rows for comparison and the float32 health of the smoothed hour (NaN count, the smallest
smoothed standard deviation, the largest violation of the constraint ``phi = sum theta``);
``smooth`` of one regular hour (constant 10 ms step, every reading, the paper's parameters:
the steady filter and the steady smoother) beside ``run_filter``; ``smooth_batch`` of 64
trials x 10,000 rows beside ``filter_batch`` (lanes, and the vmapped sequential smoother for
comparison); one fitting step through
``fit`` with ``loss="nll"`` and with ``loss="rmse"`` on 64 x 10,000 rows (6 steps, the first
compiles; the median of the other 5).

``--quick``: a smoke run on tiny sizes that the long tests execute (hours of 16,000 rows, 8
trials x 2,000 rows, fits of 3 steps; every case), the figures meaningless.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _machine import machine  # noqa: E402
from recorded import timed, trials  # noqa: E402  (the same data and timing)

import kckf_jax as kk  # noqa: E402
from kckf_jax import enable_cpu_loops  # noqa: E402

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

SPEC = "x,y,x,y"


def log(msg):
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(f"[peak {rss:5.1f} GB] {msg}", file=sys.stderr, flush=True)


def constraint_violation(est, robot) -> float:
    """The largest ``|phi - sum theta|`` over every torso axis and row (rad)."""
    cols = est.columns()
    worst = 0.0
    for axis in robot.torso_axes:
        joints = [v for k, v in cols.items() if k.startswith("theta") and k.endswith(axis)]
        worst = max(worst, float(np.nanmax(np.abs(cols[f"phi_{axis}"] - sum(joints)))))
    return worst


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing")
    args = ap.parse_args()
    robot = kk.Robot.from_spec(SPEC)
    res = {}

    L = 16_000 if args.quick else 360_000
    log(f"one recorded-like hour, {L} rows")
    hour = kk.simulate(robot, "static", seed=3, duration_s=L / 100.0, drop_prob=0.01)
    p32 = kk.initial_params([hour], kk.FitConfig(), jnp.float32)
    ser = kk.session_series(hour, jnp.float32)
    est, t, first = timed(lambda: kk.smooth(p32, ser), repeats=2)
    _, tf, _ = timed(lambda: kk.run_filter(p32, ser)[1].angles, repeats=2)
    std = np.asarray(est.angle_std)
    res["hour"] = {
        "rows": L, "smooth_s": round(t, 3), "smooth_steps_per_s": round(L / t),
        "smooth_compile_s": round(first - t, 2), "filter_s": round(tf, 3),
        "filter_path": kk.choose_path(p32, ser, "kckf").path.name,
        "smooth_over_filter_time": round(t / tf, 2),
        "nan_count": int(np.isnan(np.asarray(est.angles)).sum() + np.isnan(std).sum()),
        "min_angle_std_rad": float(np.nanmin(std)),
        "max_constraint_violation_rad": constraint_violation(est, robot)}
    log(str(res["hour"]))

    log(f"one regular hour, {L} rows")
    clean = kk.simulate(robot, "static", seed=3, duration_s=L / 100.0, drop_prob=0.0)
    dt = np.full(len(clean.gyro), 0.01)
    dt[0] = 0.0
    reg = kk.SensorSeries(jnp.asarray(dt, jnp.float32), jnp.asarray(clean.gyro, jnp.float32),
                          jnp.asarray(clean.hall_v, jnp.float32))
    p_reg = kk.Params.paper_defaults(robot, dtype=jnp.float32)
    est, t, first = timed(lambda: kk.smooth(p_reg, reg), repeats=2)
    _, tf, _ = timed(lambda: kk.run_filter(p_reg, reg)[1].angles, repeats=2)
    res["regular_hour"] = {
        "rows": L, "smooth_path": est.path, "smooth_s": round(t, 3),
        "smooth_steps_per_s": round(L / t), "smooth_compile_s": round(first - t, 2),
        "filter_s": round(tf, 3), "filter_path": kk.choose_path(p_reg, reg, "kckf").path.name,
        "smooth_over_filter_time": round(t / tf, 2),
        "nan_count": int(np.isnan(np.asarray(est.angles)).sum()),
        "max_constraint_violation_rad": constraint_violation(est, robot)}
    _, ts, _ = timed(lambda: kk.smooth(p_reg, reg, path="sequential").angles, repeats=1)
    res["regular_hour"]["sequential_smooth_s"] = round(ts, 3)
    log(str(res["regular_hour"]))

    B, T = (8, 2000) if args.quick else (64, 10_000)
    log(f"{B} trials x {T} rows")
    sess = trials(robot, B, T)
    batch = kk.pad_series([kk.session_series(s, np.float32) for s in sess])
    pb = kk.initial_params(sess, kk.FitConfig(), jnp.float32)
    est, t, first = timed(lambda: kk.smooth_batch(pb, batch), repeats=2)
    _, tf, _ = timed(lambda: kk.filter_batch(pb, batch, "kckf").angles, repeats=2)
    _, tseq, _ = timed(lambda: kk.smooth_batch(pb, batch, path="sequential").angles,
                       repeats=1)
    res["batch"] = {"trials": B, "rows": T, "smooth_path": est.path, "smooth_s": round(t, 3),
                    "sequential_smooth_s": round(tseq, 3),
                    "smooth_trial_steps_per_s": round(B * T / t),
                    "smooth_compile_s": round(first - t, 2), "filter_s": round(tf, 3),
                    "filter_path": kk.choose_path(pb, batch, "kckf").path.name,
                    "smooth_over_filter_time": round(t / tf, 2)}
    log(str(res["batch"]))

    res["fit_step"] = {}
    for loss in ("nll", "rmse"):
        log(f"fit step, loss {loss}")
        stamps = []
        t0 = time.perf_counter()
        kk.fit(sess, (), kk.FitConfig(steps=3 if args.quick else 6, loss=loss),
               dtype=jnp.float32,
               callback=lambda r: stamps.append(time.perf_counter()))
        steps = np.diff(stamps)
        res["fit_step"][loss] = {"trials": B, "rows": T,
                                 "compile_and_first_step_s": round(stamps[0] - t0, 2),
                                 "step_s_median": round(float(np.median(steps)), 3)}
        log(str(res["fit_step"][loss]))
    res["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3, 1)

    doc = {"benchmark": "smooth", "machine": machine(), "date": time.strftime("%Y-%m-%d"),
           "results": res}
    try:
        doc["commit"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"],
                                       capture_output=True, text=True).stdout.strip()
    except OSError:
        pass
    print(json.dumps(doc, indent=2, default=float) if args.json else doc)


if __name__ == "__main__":
    main()
