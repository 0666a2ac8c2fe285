"""Are a refactor's numbers the same? float64 estimates and gradients of every path, saved to
compare with another commit's.

    python benchmarks/same_numbers.py save OUT.npz          # at one commit
    python benchmarks/same_numbers.py compare A.npz B.npz   # largest difference per entry
    python benchmarks/same_numbers.py --quick [--json]      # the smoke run

To take the numbers of an older commit, run its checkout's package with this script:
``git worktree add /tmp/old COMMIT`` and ``PYTHONPATH=/tmp/old python
benchmarks/same_numbers.py save old.npz`` (only public names that every commit since issue 30
exports are used). The data: the simulator's recorded-like sessions (jittered stamps, 1 % of
readings missing, the voltage noise model) and a regular one; every path that applies
(``sequential``, ``lanes``, ``segments``, ``steady``, ``parallel``), the smoother's layouts,
and the RMSE loss with its gradient on the sequential and lanes paths. Issue 34's criterion:
every entry within 1e-12 (``compare`` exits 1 otherwise).

``--quick``: a smoke run on tiny sizes that the long tests execute (every entry, on sessions
of 5 s, a long recording of 170 s, a regular one of 45 s); without a command it saves the
numbers to a temporary file, reads them back and compares them with the ones it computed
(exit 1 if any entry differs by more than 1e-12; computing them twice would cost another
10 s). ``save --quick`` saves the small numbers (compare them only with other ``--quick``
numbers). ``--json``: ``compare``'s result as one JSON document, last on stdout.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import kckf_jax as kk  # noqa: E402


def numbers(quick: bool = False) -> dict[str, np.ndarray]:
    robot = kk.Robot.from_spec("x,y,x,y")
    f64 = jnp.float64
    out: dict[str, np.ndarray] = {}
    # --quick: the same entries on small inputs (the long one still 2 float64 segments).
    rec_s, long_s, reg_s = (5.0, 170.0, 45.0) if quick else (30.0, 400.0, 60.0)
    rec = [kk.simulate(robot, "cyclic", seed=40 + i, duration_s=rec_s, drop_prob=0.01,
                       device_seed=1) for i in range(3)]
    p = kk.initial_params(rec, kk.FitConfig(), f64)
    batch = kk.pad_series([kk.session_series(s, f64) for s in rec])
    for path in ("sequential", "lanes", "parallel"):
        est = kk.filter_batch(p, batch, "kckf", path=path)
        out[f"filter_{path}"] = np.stack([np.asarray(est.angles), np.asarray(est.angle_std),
                                          np.asarray(est.bias)])
    for method in ("kf", "hall_l", "gyro"):
        out[f"filter_{method}"] = np.asarray(kk.filter_batch(p, batch, method).angles)
    for layout in ("sequential", "lanes"):
        est = kk.smooth_batch(p, batch, "kckf", path=layout)
        out[f"smooth_{layout}"] = np.stack([np.asarray(est.angles), np.asarray(est.angle_std)])
    # One long recording: the segments path (float64: 8,192 warm-up rows, 4 segments or more).
    long = kk.simulate(robot, "cyclic", seed=7, duration_s=long_s, drop_prob=0.01,
                       device_seed=1)
    pl = kk.initial_params([long], kk.FitConfig(), f64)
    ser = kk.session_series(long, f64)
    for path in ("segments", "sequential"):
        _, est = kk.run_filter(pl, ser, "kckf", path=path)
        out[f"long_{path}"] = np.stack([np.asarray(est.angles), np.asarray(est.angle_std)])
    # A regular recording: the steady path and the steady smoother.
    reg = kk.simulate(robot, "cyclic", seed=9, duration_s=reg_s, config=kk.SimConfig(
        timestamp_jitter_s=0.0))
    pr = kk.initial_params([reg], kk.FitConfig(hall_noise="angle"), f64)
    sr = kk.session_series(reg, f64)
    sr = kk.SensorSeries(jnp.full_like(sr.dt, 0.01).at[0].set(0.0), sr.gyro, sr.hall_v)
    for path in ("steady", "sequential"):
        _, est = kk.run_filter(pr, sr, "kckf", path=path)
        out[f"regular_{path}"] = np.stack([np.asarray(est.angles), np.asarray(est.angle_std)])
    for layout in ("steady", "sequential"):
        est = kk.smooth_batch(pr, kk.pad_series([sr]), "kckf", path=layout)
        out[f"regular_smooth_{layout}"] = np.asarray(est.angles)
    # The RMSE loss and its gradient (the fit's), on two paths.
    fit_batch = kk.make_batch(rec, f64)
    for path in ("sequential", "lanes"):
        loss, grad = jax.value_and_grad(lambda q, path=path: kk.loss_fn(
            q, fit_batch, "kckf", path=path))(p)
        leaves = [np.ravel(np.asarray(x)) for x in jax.tree_util.tree_leaves(grad)
                  if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating)]
        out[f"loss_{path}"] = np.asarray([loss])
        out[f"grad_{path}"] = np.concatenate(leaves)
    return out


def compare(a, b, as_json: bool = False) -> int:
    """The largest difference per entry of two saved sets of numbers: 0 when every entry is
    within 1e-12, else 1."""
    worst = 0.0
    rows: dict = {}
    for k in sorted(set(a) | set(b)):
        if k not in a or k not in b:
            rows[k] = {"only_in": "A" if k in a else "B"}
            print(f"{k}: only in {'A' if k in a else 'B'}", file=sys.stderr if as_json else None)
            continue
        x, y = a[k], b[k]
        both = np.isfinite(x) & np.isfinite(y)
        same_nan = bool(np.all(np.isfinite(x) == np.isfinite(y)))
        d = float(np.max(np.abs(x[both] - y[both]), initial=0.0))
        worst = max(worst, d)
        rows[k] = {"max_diff": d, "same_nan": same_nan}
        print(f"{k:28s} {d:9.2e}{'' if same_nan else '  (NaN where the other is not)'}",
              file=sys.stderr if as_json else None)
    print(f"largest difference: {worst:.2e}", file=sys.stderr if as_json else None)
    ok = worst <= 1e-12
    if as_json:
        print(json.dumps({"benchmark": "same_numbers", "entries": rows,
                          "largest_difference": worst, "within_1e-12": ok}))
    return 0 if ok else 1


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("command", nargs="?", choices=("save", "compare"),
                    help="save OUT.npz, or compare A.npz B.npz")
    ap.add_argument("files", nargs="*", help="save: OUT.npz; compare: A.npz B.npz")
    ap.add_argument("--json", action="store_true",
                    help="compare's result as JSON (last on stdout)")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing; without a command: save, read back, compare")
    args = ap.parse_args(argv)
    if args.command == "save" or (args.command is None and args.quick):
        kk_enable = getattr(kk, "enable_cpu_loops", None)
        if kk_enable is not None:
            kk_enable()
    if args.command == "save" and len(args.files) == 1:
        np.savez(args.files[0], **numbers(args.quick))
        print(f"saved {args.files[0]}", file=sys.stderr if args.json else None)
        if args.json:
            print(json.dumps({"benchmark": "same_numbers", "saved": args.files[0],
                              "quick": args.quick}))
        return 0
    if args.command == "compare" and len(args.files) == 2:
        return compare(np.load(args.files[0]), np.load(args.files[1]), args.json)
    if args.command is None and args.quick and not args.files:
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "quick.npz")
            got = numbers(quick=True)
            np.savez(path, **got)
            return compare(np.load(path), got, args.json)
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
