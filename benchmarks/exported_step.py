"""The exported step's cost per packet, this checkout against others in alternation (issue 46).

    python benchmarks/exported_step.py [--python-path DIR ...] [--rounds 5] [--json] [--quick]

Each round runs, for every checkout in turn (this one, then each ``--python-path``), a fresh
process that calls ``low_latency()`` before any computation (as ``kckf stream`` and
``stream_latency.py`` do), writes a 50 s recorded-like session of the bench robot (``x,y,x,y``,
1 % of readings missing), exports its step with ``kckf export`` and times
``ExportedStep.push_array`` (that checkout's ``export_loader.py``) on every packet: one median
per process. The best median of each checkout over the rounds is the figure (this machine's
runs vary by up to 1.5x from process to process). ``--quick``: one round, a 5 s session, this
checkout only: the smoke run the long tests execute.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

CHILD = r"""
import os, sys, tempfile, time
import numpy as np
import kckf_jax as kk
if hasattr(kk, "enable_cpu_loops"):
    kk.enable_cpu_loops()
kk.low_latency()
from kckf_jax.cli import main as kckf
s = kk.simulate(kk.Robot.from_spec("x,y,x,y"), "cyclic", seed=1, duration_s=float(sys.argv[1]),
                drop_prob=0.01)
tmp = tempfile.mkdtemp(prefix="kckf-exported-")
kk.write_session(s, os.path.join(tmp, "s"))
path = os.path.join(tmp, "step.jaxexport")
assert kckf(["export", "--meta", os.path.join(tmp, "s", "meta.json"), "-o", path,
             "--quiet"]) == 0
sys.path.insert(0, os.path.dirname(kk.__file__))
import export_loader
ex = export_loader.ExportedStep(path)
x = np.concatenate([s.gyro, s.hall_v], axis=1)
ex.push_array(0.0, x[0])
ex.reset()
out = []
for i in range(s.n_steps):
    t0 = time.perf_counter()
    ex.push_array(float(s.t[i]), x[i])
    out.append((time.perf_counter() - t0) * 1e6)
print(f"{np.median(out):.3f}")
"""


def one(path: str, duration_s: float) -> float:
    env = dict(os.environ, PYTHONPATH=path)
    out = subprocess.run([sys.executable, "-c", CHILD, str(duration_s)], env=env, check=True,
                         capture_output=True, text=True, cwd=path)
    return float(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--python-path", action="append", default=[],
                    help="another checkout's root, timed in alternation with this one")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    checkouts = [ROOT] + ([] if args.quick else list(args.python_path))
    rounds, duration = (1, 5.0) if args.quick else (args.rounds, 50.0)
    medians: dict[str, list[float]] = {c: [] for c in checkouts}
    for r in range(rounds):
        for c in checkouts:
            medians[c].append(one(c, duration))
        print(f"round {r + 1}: " + "  ".join(f"{os.path.basename(c.rstrip('/')) or c} "
                                             f"{medians[c][-1]:.2f} us" for c in checkouts),
              flush=True)
    for c in checkouts:
        print(f"{c}: best median {min(medians[c]):.2f} us over {rounds} process(es)")
    if args.json:
        print(json.dumps({"medians_us": medians,
                          "best_us": {c: min(v) for c, v in medians.items()}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
