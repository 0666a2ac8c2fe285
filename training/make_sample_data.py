"""Write the sample sessions shipped in ``data/`` (deterministic: same files every run).

    python training/make_sample_data.py [--out data]

* ``data/bench``: the paper's bench test (Sec. 4.1), 4 joints x, y, x, y, gait-like cyclic
  motion by hand, 40 s each, 1 % of readings dropped; 2 training and 2 test sessions.
* ``data/human``: a person bending and extending (Sec. 4.3), 30 deg range, 40 s each;
  3 training and 2 test sessions.
"""

import argparse
import os
import shutil

from kckf_jax import (
    enable_cpu_loops,  # noqa: E402
    simulate,
    write_session,
)

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

# One exoshell per data set (device_seed): train and test sessions are trials of the same
# robot, so a fitted Hall calibration carries over to the test sessions.
SETS = {
    "bench": dict(kind="cyclic", device=1, train=(101, 102), test=(201, 202)),
    "human": dict(kind="human", device=2, train=(301, 302, 303), test=(401, 402)),
}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "..", "data"))
    ap.add_argument("--duration", type=float, default=40.0)
    args = ap.parse_args()
    for name, cfg in SETS.items():
        for split in ("train", "test"):
            for i, seed in enumerate(cfg[split], start=1):
                path = os.path.join(args.out, name, f"{split}{i}")
                shutil.rmtree(path, ignore_errors=True)
                s = simulate("x,y,x,y", cfg["kind"], seed=seed, duration_s=args.duration,
                             drop_prob=0.01, device_seed=cfg["device"])
                write_session(s, path, digits=7)
                print("wrote", os.path.normpath(path))


if __name__ == "__main__":
    main()
