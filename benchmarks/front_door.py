"""The front door: what a one-shot command costs against the floor of reading its data, side by
side in one run (issue 36, item 3).

    python benchmarks/front_door.py [--runs 3] [--json] [--demo] [--work DIR] [--quick]

On a recorded-like hour (``kckf simulate --kind human --duration 3600 --drop-prob 0.01``: the
simulator's jittered stamps, 1 % of readings missing, its voltage noise; bench robot
``x,y,x,y``; 360,000 sensor rows, 432,000 motion-capture rows at 120 Hz), each in a fresh
process, the median of ``--runs``:

* **floor**: ``import jax`` and ``np.loadtxt`` of the two CSV files (a copy whose missing
  cells are written ``nan``, which ``np.loadtxt`` reads; the command reads the original, with
  empty cells);
* ``kckf evaluate HOUR --json``: **cold** (an empty compile cache, ``KCKF_CACHE_DIR``) and
  **warm** (the cache the cold run filled);
* ``kckf filter HOUR -o est.csv``: cold and warm likewise;
* ``--demo``: ``kckf demo`` (cold and warm: its fit dominates; one run each).

The aim: warm at most 1.5x the floor, cold at most 2.5x. ``--python-path DIR`` runs the
command from another checkout (``python -m kckf_jax`` with ``PYTHONPATH=DIR``), for a before
and after on the same machine.

``--quick``: a smoke run on tiny sizes that the long tests execute: the same commands with
this interpreter on a simulated session of 20 s, once each (floor, evaluate and filter cold
and warm, and ``kckf demo --steps 1`` cold only: 20 s), in a temporary work folder removed
afterwards (not ``--work``); ``front_door_latest.json`` is not written. The figures mean
nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

FLOOR = """
import sys
import jax  # noqa: F401
import numpy as np
np.loadtxt(sys.argv[1], delimiter=",", skiprows=1)
np.loadtxt(sys.argv[2], delimiter=",", skiprows=1)
"""


def _timed(cmd: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    # In the work folder: ``python -m`` puts the current folder first on the path, which
    # would shadow ``--python-path``'s checkout when run from a checkout.
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=WORK[0])
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({r.returncode}): {r.stderr.strip()[-400:]}")
    if "Warning" in r.stderr:
        raise SystemExit(f"{' '.join(cmd)}: a raw Python warning reached stderr:\n{r.stderr}")
    return dt


WORK = [tempfile.gettempdir()]


def _hour(work: str, kckf: list[str], env: dict, duration_s: int = 3600) -> str:
    hour = os.path.join(work, "hour")
    if not os.path.exists(os.path.join(hour, "mocap.csv")):
        subprocess.run([*kckf, "simulate", hour, "--kind", "human", "--seed", "1",
                        "--duration", str(duration_s), "--drop-prob", "0.01", "--quiet"],
                       env=env, check=True, cwd=work)
    floor = os.path.join(work, "floor")
    if not os.path.exists(os.path.join(floor, "mocap.csv")):
        os.makedirs(floor, exist_ok=True)
        for name in ("sensors.csv", "mocap.csv"):
            with open(os.path.join(hour, name)) as f, open(os.path.join(floor, name), "w") as g:
                for line in f:
                    cells = line.rstrip("\n").split(",")
                    g.write(",".join(c if c else "nan" for c in cells) + "\n")
    return hour


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--json", action="store_true", help="also write front_door_latest.json")
    ap.add_argument("--demo", action="store_true", help="also time kckf demo")
    ap.add_argument("--work", default=os.path.join(tempfile.gettempdir(), "kckf-front-door"))
    ap.add_argument("--python-path", help="run kckf from this checkout (PYTHONPATH)")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing; a 20 s session, one run of each command, the demo too "
                         "(cold only), in a temporary work folder")
    args = ap.parse_args(argv)
    if not args.quick:
        return _run(args)
    # Never the full run's work folder: its hour would be reused (or replaced by 20 s).
    args.work = tempfile.mkdtemp(prefix="kckf-front-door-quick-")
    args.runs, args.demo = 1, True
    try:
        return _run(args)
    finally:
        shutil.rmtree(args.work, ignore_errors=True)


def _run(args) -> int:
    os.makedirs(args.work, exist_ok=True)
    WORK[0] = args.work
    env = dict(os.environ)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    if args.python_path:
        env["PYTHONPATH"] = args.python_path
    kckf = [sys.executable, "-m", "kckf_jax"]
    hour = _hour(args.work, kckf, env, 20 if args.quick else 3600)
    floor = os.path.join(args.work, "floor")
    cache = os.path.join(args.work, "cache")
    out_csv = os.path.join(args.work, "est.csv")

    def cold_warm(label: str, cmd: list[str], runs: int, with_warm: bool = True) -> dict:
        cold, warm = [], []
        for _ in range(runs):
            shutil.rmtree(cache, ignore_errors=True)
            cold.append(_timed(cmd, {**env, "KCKF_CACHE_DIR": cache}))
            if with_warm:
                warm.append(_timed(cmd, {**env, "KCKF_CACHE_DIR": cache}))
        row = {"cold_s": statistics.median(cold),
               "warm_s": statistics.median(warm) if warm else None,
               "cold_runs": cold, "warm_runs": warm}
        print(f"{label:<22} cold {row['cold_s']:6.2f} s"
              + (f"  warm {row['warm_s']:6.2f} s" if warm else ""), file=sys.stderr, flush=True)
        return row

    floor_runs = [_timed([sys.executable, "-c", FLOOR, os.path.join(floor, "sensors.csv"),
                          os.path.join(floor, "mocap.csv")], env) for _ in range(args.runs)]
    result = {"floor_s": statistics.median(floor_runs), "floor_runs": floor_runs}
    print(f"{'floor (jax + loadtxt)':<22} {result['floor_s']:6.2f} s", file=sys.stderr)
    result["evaluate"] = cold_warm("kckf evaluate --json", [*kckf, "evaluate", hour, "--json"],
                                   args.runs)
    result["filter"] = cold_warm("kckf filter -o", [*kckf, "filter", hour, "-o", out_csv],
                                 args.runs)
    if args.demo:
        result["demo"] = cold_warm("kckf demo", [*kckf, "demo", "--out",
                                                 os.path.join(args.work, "demo")]
                                   + (["--steps", "1"] if args.quick else []), 1,
                                   with_warm=not args.quick)
    for key in ("evaluate", "filter"):
        row = result[key]
        row["cold_ratio"] = row["cold_s"] / result["floor_s"]
        row["warm_ratio"] = row["warm_s"] / result["floor_s"]
        print(f"{key}: cold {row['cold_ratio']:.2f}x the floor (aim 2.5x), warm "
              f"{row['warm_ratio']:.2f}x (aim 1.5x)", file=sys.stderr)
    if args.quick:
        result["quick"] = True
    if args.json and not args.quick:
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        from _machine import machine

        result["machine"] = machine()
        result["python_path"] = args.python_path
        with open(os.path.join(os.path.dirname(os.path.abspath(__file__)),
                               "front_door_latest.json"), "w") as f:
            json.dump(result, f, indent=1)
    print(json.dumps({k: (v if not isinstance(v, dict) else
                          {a: b for a, b in v.items() if not a.endswith("runs")})
                      for k, v in result.items() if k != "floor_runs"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
