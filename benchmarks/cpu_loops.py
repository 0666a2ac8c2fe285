"""XLA's CPU while loops as one kernel each (``kk.enable_cpu_loops()``) against XLA's
default, on every path.

    python benchmarks/cpu_loops.py [--json] [--quick] [--rounds 2] [--cases a,b,...]
                                   [--bounds BYTES,...] [--ynn]

Each setting runs in processes of its own (XLA reads its flags once per process), the
settings alternating (off, on, off, on, ...: ``--rounds`` of each); every case reports the
compile and first call and the median of the calls after it, and the table the medians over
rounds. "off" is ``KCKF_XLA_LOOPS=0`` (XLA's default: on jax 0.10 each loop iteration run
kernel by kernel); "on" is ``kk.enable_cpu_loops()``, the call the command and the
documented API make (``kk.cpu_loops()``); ``--bounds`` adds a setting per bound
(``KCKF_XLA_LOOPS=<bytes>``: loops touching more per iteration stay kernel by kernel), as for
the choice of the default (``--cases lanes_1024,lanes_4096 --bounds 1048576,16777216``);
``--ynn`` adds "ynn": the loops' bound set but XLA's library (YNNPACK) fusions left on, as
the call left them before issue 49 (``XLA_FLAGS`` naming the bound, which the call keeps).
Data: simulated bench sessions (x, y, x, y) as ``kckf simulate`` writes them (jittered
stamps, 1 % of the readings missing), the ``voltage`` noise model of a fit's starting point,
float32, except the regular hour (constant step, every reading, the ``angle`` noise model: the
steady path, whose chunks are matrix products that XLA does not fold into one kernel).

``--quick``: a smoke run on tiny sizes that the long tests execute (8 trials x 2,000 rows,
hours of 16,000 rows, one timed call per case, one round), the figures meaningless; every
case in one setting only, so the table has no ratios ("off": ``lanes_64`` and
``sequential_64``; "on": the others), and a representative subset of the cases: not
``gradient_64`` (``gradient_3``'s code on another batch) nor ``hour_sequential`` (``hour``'s
on another path), unless ``--cases`` names them. Every case in both settings would take two
minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
CASES = ("fit_step", "gradient_64", "gradient_3", "lanes_64", "lanes_1024", "sequential_64",
         "hour", "hour_sequential", "hour_smooth", "smooth_batch_64", "regular_hour")
MORE = ("lanes_4096",)  # run only when named
QUICK_SKIP = ("gradient_64", "hour_sequential")  # --quick: unless named
QUICK_OFF = ("lanes_64", "sequential_64")  # --quick: these in "off" (and --bounds), the rest "on"
#: ``--ynn``'s flags: the call's bound, preset (so the call keeps them, fusions and all).
YNN_KEPT = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1099511627776"


def worker(cases: list[str], quick: bool) -> dict:
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    import kckf_jax as kk

    kk.enable_cpu_loops()  # "off": KCKF_XLA_LOOPS=0 makes it leave XLA's default
    sys.path.insert(0, HERE)
    import recorded as R

    robot = kk.Robot.from_spec("x,y,x,y")
    B, T = (8, 2000) if quick else (64, 10_000)
    L = 16_000 if quick else 360_000
    out = {"cpu_loops": kk.cpu_loops()._asdict()}

    def timed(name, fn, repeats=5, path=None):
        repeats = 1 if quick else repeats
        t0 = time.perf_counter()
        first = jax.block_until_ready(fn())
        first_s = time.perf_counter() - t0
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            times.append(time.perf_counter() - t0)
        path = path or getattr(first, "path", None)
        out[name] = {"first_s": round(first_s, 3), "median_s": round(float(np.median(times)), 4),
                     "path": path}
        print(f"  {name}: {out[name]}", file=sys.stderr, flush=True)

    batch_sessions = R.trials(robot, B, T)
    params = R.params_of(robot, batch_sessions, jnp.float32)
    series = R.batch_of(batch_sessions, jnp.float32)

    def gradient(sessions):
        batch = kk.make_batch(sessions, jnp.float32)
        p = kk.initial_params(sessions, kk.FitConfig(), jnp.float32)
        path = kk.choose_path(p, batch.series, "kckf", kk.Auto(lanes=kk.Lanes(min_trials=1),
                                                               segments=None)).path
        diff, static = eqx.partition(p, eqx.is_array)
        f = jax.jit(lambda d, b: eqx.filter_value_and_grad(
            lambda d: kk.loss_fn(eqx.combine(d, static), b, "kckf", path=path))(d))
        return (lambda: f(diff, batch)), path.name  # the batch an argument, as in fit

    hour = None
    for case in cases:
        if case == "fit_step":  # through fit itself: 6 steps, the first compiles
            stamps = []
            t0 = time.perf_counter()
            kk.fit(batch_sessions, (), kk.FitConfig(steps=3 if quick else 6),
                   dtype=jnp.float32,
                   callback=lambda r: stamps.append(time.perf_counter()))
            out[case] = {"first_s": round(stamps[0] - t0, 3),
                         "median_s": round(float(np.median(np.diff(stamps))), 4),
                         "path": "lanes"}
        elif case == "gradient_64":
            fn, name = gradient(batch_sessions)
            timed(case, fn, path=name)
        elif case == "gradient_3":  # the size of kckf demo's fits
            fn, name = gradient(R.trials(robot, 3, 4000, seed0=300))
            timed(case, fn, path=name)
        elif case == "lanes_64":
            timed(case, lambda: kk.filter_batch(params, series, "kckf"))
        elif case in ("lanes_1024", "lanes_4096"):
            n, rows = (1024, 2000) if case == "lanes_1024" else (4096, 500)
            big = R.trials(robot, n // 8 if quick else n, rows)
            bs = R.batch_of(big, jnp.float32)
            timed(case, lambda bs=bs: kk.filter_batch(params, bs, "kckf"), repeats=3)
        elif case == "sequential_64":
            timed(case, lambda: kk.filter_batch(params, series, "kckf", path="sequential"),
                  repeats=3)
        elif case.startswith("hour"):
            if hour is None:  # one recorded-like hour for the three cases
                hour = kk.simulate(robot, "static", seed=3, duration_s=L / 100.0,
                                   drop_prob=0.01)
                hp = kk.initial_params([hour], kk.FitConfig(), jnp.float32)
                hs = kk.session_series(hour, jnp.float32)
            if case == "hour":
                timed(case, lambda: kk.run_filter(hp, hs, "kckf")[1], repeats=3)
            elif case == "hour_sequential":
                timed(case, lambda: kk.run_filter(hp, hs, "kckf", path="sequential")[1],
                      repeats=3)
            else:
                timed(case, lambda: kk.smooth(hp, hs, "kckf"), repeats=3)
        elif case == "smooth_batch_64":
            timed(case, lambda: kk.smooth_batch(params, series, "kckf"), repeats=3)
        elif case == "regular_hour":
            reg = kk.simulate(robot, "static", seed=3, duration_s=L / 100.0)
            reg.t = np.arange(reg.n_steps) * 0.01
            rp = kk.Params.paper_defaults(robot, reg.hall_models).astype(jnp.float32)
            rs = kk.session_series(reg, jnp.float32)
            timed(case, lambda: kk.run_filter(rp, rs, "kckf")[1], repeats=3)
        else:
            raise SystemExit(f"unknown case {case!r}; cases: {', '.join(CASES + MORE)}")
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing; one round, each case in one setting only (no ratios), "
                         f"not {' nor '.join(QUICK_SKIP)} unless named")
    ap.add_argument("--rounds", type=int, help="default 2 (--quick: 1)")
    ap.add_argument("--cases", help=f"default {','.join(CASES)}")
    ap.add_argument("--bounds", default="", help="more settings: bounds in bytes, comma-separated")
    ap.add_argument("--ynn", action="store_true",
                    help='one more setting, "ynn": the bound set, the YNNPACK fusions left on')
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.cases is None:
        args.cases = ",".join(c for c in CASES if not (args.quick and c in QUICK_SKIP))
    cases = [c for c in args.cases.split(",") if c]
    if args.worker:
        print(json.dumps(worker(cases, args.quick)))
        return
    args.rounds = args.rounds or (1 if args.quick else 2)
    settings = (["off", "on"] + [b for b in args.bounds.split(",") if b]
                + (["ynn"] if args.ynn else []))
    runs = {s: [] for s in settings}
    # --quick: each case in one setting only.
    of = {s: ",".join(c for c in cases if (c in QUICK_OFF) == (s != "on")) if args.quick
          else args.cases for s in settings}
    for r in range(args.rounds):
        for setting in settings:
            env = dict(os.environ)
            env.pop("KCKF_XLA_LOOPS", None)
            if setting == "ynn":  # a preset bound: the call keeps XLA_FLAGS as they are
                env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {YNN_KEPT}".strip()
            elif setting != "on":
                env["KCKF_XLA_LOOPS"] = "0" if setting == "off" else setting
            print(f"round {r + 1}, {setting}", file=sys.stderr, flush=True)
            cmd = [sys.executable, os.path.abspath(__file__), "--worker", "--cases", of[setting]]
            got = subprocess.run(cmd + (["--quick"] if args.quick else []), env=env,
                                 check=True, capture_output=True, text=True)
            runs[setting].append(json.loads(got.stdout))
    import numpy as np

    sys.path.insert(0, HERE)
    from _machine import machine

    table = {}
    for case in cases:
        row = {}
        for setting in settings:
            r = [run[case] for run in runs[setting] if case in run]
            if not r:  # --quick: not run in this setting
                continue
            row[setting] = {"median_s": round(float(np.median([x["median_s"] for x in r])), 4),
                            "first_s": round(float(np.median([x["first_s"] for x in r])), 2),
                            "runs_s": [x["median_s"] for x in r], "path": r[0]["path"]}
        row["ratio_on_over_off"] = (round(row["on"]["median_s"] / row["off"]["median_s"], 3)
                                    if "on" in row and "off" in row else None)
        if "ynn" in row and "on" in row:
            row["ratio_on_over_ynn"] = round(row["on"]["median_s"] / row["ynn"]["median_s"], 3)
        table[case] = row
    doc = {"benchmark": "cpu_loops", "machine": machine(), "date": time.strftime("%Y-%m-%d"),
           "rounds": args.rounds, "quick": args.quick,
           "settings": {s: runs[s][0]["cpu_loops"] for s in runs}, "cases": table}
    try:
        doc["commit"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE,
                                       capture_output=True, text=True).stdout.strip()
    except OSError:
        pass
    if args.json:
        print(json.dumps(doc, indent=2))
        return
    print(f"{'case':18s} {'path':>16s} " + " ".join(f"{s + ' (s)':>14s}" for s in settings)
          + f" {'on/off':>7s} {'first off':>9s} {'first on':>9s}")
    def cell(row, s, key, width, digits):
        return f"{row[s][key]:{width}.{digits}f}" if s in row else f"{'-':>{width}s}"

    for case, row in table.items():
        ratio = row["ratio_on_over_off"]
        path = (row.get("on") or row.get("off") or {}).get("path")
        print(f"{case:18s} {str(path):>16s} "
              + " ".join(cell(row, s, "median_s", 14, 4) for s in settings)
              + (f" {ratio:7.2f}" if ratio is not None else f" {'-':>7s}")
              + f" {cell(row, 'off', 'first_s', 9, 2)} {cell(row, 'on', 'first_s', 9, 2)}")


if __name__ == "__main__":
    main()
