"""The paper's extended-use test (Sec. 4.2, Fig. 7) on a simulated one-hour session.

    python training/extended_use.py [--seed 3] [--duration 3600]

Movement for 60 s, then the bench robot held still for the rest of the hour. Runs the KCKF and
the standard KF in float32 and float64 and writes ``training/results/extended_use.json`` (end
errors, float32-float64 agreement, run time) and ``training/results/extended_use.png`` (the
error over time, Fig. 7 style). The README quotes these numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from kckf_jax import (  # noqa: E402
    Params,
    enable_cpu_loops,  # noqa: E402
    run_filter,
    session_series,
    simulate,
)
from kckf_jax.cli.plots import plot_drift  # noqa: E402

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

HERE = os.path.dirname(os.path.abspath(__file__))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--duration", type=float, default=3600.0)
    ap.add_argument("--out", default=os.path.join(HERE, "results"))
    args = ap.parse_args()

    s = simulate("x,y,x,y", "static", seed=args.seed, duration_s=args.duration, move_s=60.0)
    truth = s.truth()
    last = int(np.flatnonzero(np.isfinite(truth).all(axis=1))[-1])
    names = s.robot.angle_names
    res, angles = {}, {}
    for dtype in (jnp.float32, jnp.float64):
        params = Params.paper_defaults(s.robot, s.hall_models, dtype=dtype)
        series = session_series(s, dtype)
        for method in ("kckf", "kf"):
            t0 = time.perf_counter()
            final, est = run_filter(params, series, method)
            a = np.asarray(jax.block_until_ready(est.angles), np.float64)
            elapsed = time.perf_counter() - t0
            angles[jnp.dtype(dtype).name, method] = a
            err = np.degrees(a[last] - truth[last])
            res[f"{method}_{jnp.dtype(dtype).name}"] = {
                "end_error_deg": dict(zip(names, np.round(err, 3).tolist())),
                "rmse_deg": dict(zip(names, np.round(np.degrees(np.sqrt(
                    np.nanmean((a - truth) ** 2, axis=0))), 3).tolist())),
                "seconds_with_compile": round(elapsed, 2),
                "final_cov_min_eig": float(np.linalg.eigvalsh(
                    np.asarray(final.P, np.float64)).min()),
            }
    for method in ("kckf", "kf"):
        d = np.degrees(angles["float32", method] - angles["float64", method])
        res[f"{method}_float32_vs_float64_rmse_deg"] = dict(zip(
            names, np.sqrt(np.mean(d**2, axis=0)).round(6).tolist()))
    doc = {"command": "python training/extended_use.py", "seed": args.seed,
           "duration_s": args.duration, "steps": s.n_steps, "results": res}
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "extended_use.json"), "w") as f:
        json.dump(doc, f, indent=2)
    k = names.index("phi_x")
    t = s.t - s.t[0]
    win = 500  # 5 s moving RMS, so the plot shows the drift rather than the sample noise

    def moving_rms(e):
        e2 = np.nan_to_num(e**2, nan=0.0)
        n = np.convolve(np.isfinite(e).astype(float), np.ones(win), "same")
        return np.sqrt(np.convolve(e2, np.ones(win), "same") / np.maximum(n, 1))

    plot_drift(t, {m: moving_rms(np.degrees(angles["float64", m][:, k] - truth[:, k]))
                   for m in ("kf", "kckf")},
               os.path.join(args.out, "extended_use.png"),
               "Extended use: torso angle phi_x (5 s RMS), 60 s of motion then held still")
    print(f"error at the end of {args.duration:.0f} s (deg):")
    print(f"{'':<16}" + "".join(f"{n:>10}" for n in names))
    for key in ("kckf_float32", "kckf_float64", "kf_float32", "kf_float64"):
        print(f"{key:<16}" + "".join(f"{res[key]['end_error_deg'][n]:>10.2f}" for n in names))
    print("float32 vs float64 RMSE over the run (deg):")
    for method in ("kckf", "kf"):
        d = res[f"{method}_float32_vs_float64_rmse_deg"]
        print(f"{method:<16}" + "".join(f"{d[n]:>10.1e}" for n in names))
    print(f"wrote {args.out}/extended_use.json and extended_use.png")


if __name__ == "__main__":
    main()
