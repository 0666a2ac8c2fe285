"""Time per gradient step and memory of learned tuning; time to convergence of the demo's fit.

    python benchmarks/fit_speed.py [--json] [--trials 64] [--steps 10000] [--quick]

Part 1: one training step (loss, gradient, Adam update) for ``--trials`` simulated bench trials
(x, y, x, y) of ``--steps`` steps each, float32, the scan checkpointed in chunks of about
sqrt(T) (``fit``'s default), timed through ``kckf_jax.fit`` itself (6 steps; the first
compiles). Reports compile time, the median step time over the other 5, XLA's temporary buffer
size for the loss and gradient (with and without chunked checkpointing) and the process's peak
resident memory.

Part 2: the fit ``kckf demo`` runs (80 Adam steps on the shipped training sessions): wall time
and the step after which the training loss stays within 2 % of its final value.

``--quick``: a smoke run on tiny sizes that the long tests run (part 1 with 2 trials x 300
steps and 2 fitting steps, part 2 with 2 Adam steps on each data set): the figures mean nothing.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import resource
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
    Sequential,
    choose_path,
    enable_cpu_loops,  # noqa: E402
    fit,
    initial_params,
    loss_fn,
    make_batch,
    read_session,
    simulate,
)

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

ROOT = os.path.join(os.path.dirname(__file__), "..")


def gradient_step(trials: int, steps: int, fit_steps: int = 6) -> dict:
    sessions = [simulate("x,y,x,y", "cyclic", seed=i, duration_s=steps / 100.0, device_seed=1,
                         drop_prob=0.01) for i in range(trials)]
    batch = make_batch(sessions, jnp.float32)
    cfg = FitConfig(steps=fit_steps)
    params = initial_params(sessions, cfg, jnp.float32)
    diff, static = eqx.partition(params, eqx.is_array)
    chunk = int(np.ceil(np.sqrt(steps)))  # fit's chunk length above REMAT_ABOVE_STEPS trial-steps
    mem = {}
    for name, c in (("chunked", chunk), ("plain", None)):
        path = choose_path(params, batch.series, "kckf", Auto(sequential=Sequential(c))).path
        f = jax.jit(lambda d, b, path=path: eqx.filter_value_and_grad(
            lambda d: loss_fn(eqx.combine(d, static), b, "kckf", path=path))(d))
        mem[name] = f.lower(diff, batch).compile().memory_analysis().temp_size_in_bytes
    del batch
    stamps = []
    t0 = time.perf_counter()
    fit(sessions, (), cfg, dtype=jnp.float32,
        callback=lambda r: stamps.append(time.perf_counter()))
    compile_s = stamps[0] - t0
    times = np.diff(stamps).tolist()
    return {"trials": trials, "steps": steps, "dtype": "float32", "remat_chunk": chunk,
            "path": path.name,
            "compile_and_first_s": round(compile_s, 2),
            "step_s_median": round(float(np.median(times)), 3),
            "step_s_all": [round(t, 3) for t in times],
            "filter_steps_per_s_fwd_bwd": round(trials * steps / float(np.median(times))),
            "xla_temp_mb_chunked": round(mem["chunked"] / 1e6, 1),
            "xla_temp_mb_plain": round(mem["plain"] / 1e6, 1),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3, 1)}


def demo_convergence(steps: int | None = None) -> dict:
    from kckf_jax.cli import DEMO_FIT_LR, DEMO_FIT_STEPS

    out = {}
    for ds in ("bench", "human"):
        train = [read_session(p) for p in sorted(glob.glob(os.path.join(ROOT, "data", ds,
                                                                          "train*")))]
        t0 = time.perf_counter()
        stamps = []
        res = fit(train, (), FitConfig(steps=steps or DEMO_FIT_STEPS, learning_rate=DEMO_FIT_LR),
                  pad_trials_to=3, callback=lambda r: stamps.append(time.perf_counter()))
        losses = np.array([h["loss_deg"] for h in res.history])
        final = losses[-1]
        within = np.abs(losses - final) <= 0.02 * final
        conv = int(len(losses) - np.argmin(within[::-1]) if not within.all() else 0)
        out[ds] = {"steps": len(losses), "seconds": round(time.perf_counter() - t0, 2),
                   "first_step_s": round(stamps[0] - t0, 2),
                   "within_2pct_of_final_from_step": conv,
                   "seconds_to_that_step": round(stamps[max(conv - 1, 0)] - t0, 2),
                   "loss_first_deg": round(float(losses[0]), 3),
                   "loss_final_deg": round(float(final), 3)}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--trials", type=int, default=64)
    ap.add_argument("--steps", type=int, default=10_000)
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing")
    args = ap.parse_args()
    if args.quick:
        args.trials, args.steps = 2, 300
    doc = {"benchmark": "fit_speed", "machine": machine(), "date": time.strftime("%Y-%m-%d"),
           "gradient_step": gradient_step(args.trials, args.steps, 2 if args.quick else 6),
           "demo_fit": demo_convergence(2 if args.quick else None)}
    if args.quick:
        doc["quick"] = True
    if args.json:
        print(json.dumps(doc, indent=2))
        return
    g = doc["gradient_step"]
    print(f"gradient step, {g['trials']} trials x {g['steps']} steps, float32, remat chunk "
          f"{g['remat_chunk']}: {g['step_s_median']:.3f} s median (compile + first "
          f"{g['compile_and_first_s']:.1f} s); XLA temp {g['xla_temp_mb_chunked']} MB chunked vs "
          f"{g['xla_temp_mb_plain']} MB plain; peak RSS {g['peak_rss_mb']} MB")
    for ds, d in doc["demo_fit"].items():
        print(f"demo fit {ds}: {d['steps']} steps in {d['seconds']} s (first step "
              f"{d['first_step_s']} s incl. compile); loss {d['loss_first_deg']} -> "
              f"{d['loss_final_deg']} deg, within 2 % of final from step "
              f"{d['within_2pct_of_final_from_step']} ({d['seconds_to_that_step']} s)")


if __name__ == "__main__":
    main()
