"""Recorded-like data at full speed: kckf-jax's paths against dynamax and filterpy.

    python benchmarks/recorded.py [--json] [--quick] [--robots bench,3d]
                                  [--no-peers] [--cases batch,trials,hour,fit]

Data: what ``kckf simulate`` writes and what a recording has: jittered timestamps (the
microcontroller's sampling jitter), 1 % of the readings missing, channel by channel, and the
``voltage`` Hall noise model that fitted filters use (its noise varies with every reading).
Every library filters the same rows with the same model: the paper's KCKF with the default
parameters of a fit's starting point, float32 unless said.

How the peers are given what they cannot express:

* dynamax ``lgssm_filter``: the time-varying F, B and Q of every row (from its time step) and R
  of every row (the voltage model); a missing Hall reading gets the value 0 and a variance of
  1e12 rad^2 (dynamax cannot drop one channel of a measurement), a missing gyro reading holds
  the last one (as kckf-jax does); the constraint rows a (1e-3 deg)^2 noise;
* filterpy ``KalmanFilter``: the same F, B, Q per row, and per row an update with only the Hall
  rows that are present (exact masking), in a Python loop (timed on the first 5,000 rows).

Cases: 64 trials x 10,000 rows; trial counts 1 to 1,024 at 5,000 rows (kckf-jax); one
recorded-like hour (360,000 rows: the segments path, against the sequential one and the lanes
layout with one lane), and the same hour with a 100 s dropout of every reading (the segments'
repair passes, against the sequential fallback they replace); one fitting step on 64 x
10,000 rows through ``fit`` with the default ``FitConfig``, its compile and the peak
memory, and the fitting step on regular data (the steady path's gradient compile).
Accuracy: the largest angle difference from kckf-jax's float64 sequential filter on the same
rows.

``--quick``: a smoke run on tiny sizes that the long tests execute, the figures meaningless:
every case on 8 trials x 2,000 rows (the trial counts: 1 and 8, of 2,000 rows), an "hour" of
24,000 rows, fits of 3 steps, one timed call each; a representative subset: the bench robot
unless ``--robots`` says otherwise (the 3D robot runs the same code, another two minutes).
Without dynamax or filterpy installed it goes on as ``--no-peers``, saying so on stderr and
in the JSON document (``peers``).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _machine import machine, require_peers  # noqa: E402

import kckf_jax as kk  # noqa: E402
from kckf_jax import enable_cpu_loops  # noqa: E402
from kckf_jax._models._blocks import full_state, paper_matrices  # noqa: E402 (internals)

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

ROBOTS = {"bench": "x,y,x,y", "3d": "xyz,xyz,xyz,xyz"}
MISSING_VAR = 1e12
CONSTRAINT_VAR = (1e-3 * np.pi / 180) ** 2


_T0 = time.perf_counter()


def log(msg):
    """Progress on stderr: the case, the seconds since start and the peak memory so far."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(f"[{time.perf_counter() - _T0:7.1f} s, peak {rss:5.1f} GB] {msg}", file=sys.stderr,
          flush=True)


QUICK = [False]  # --quick: every timing one call after the first


def timed(fn, repeats=3):
    repeats = 1 if QUICK[0] else repeats
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return out, best, first


def trials(robot, n, steps, seed0=0):
    """Recorded-like sessions: the simulator's jittered stamps, 1 % of readings missing."""
    base = [kk.simulate(robot, "cyclic", seed=seed0 + i, duration_s=steps / 100.0,
                        drop_prob=0.01, device_seed=1) for i in range(min(n, 16))]
    return [base[i % len(base)] for i in range(n)]


REFERENCE = """
import sys, numpy as np, jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
sys.path.insert(0, sys.argv[1])
import recorded as R
import kckf_jax as kk
robot = kk.Robot.from_spec(sys.argv[2])
sess = R.trials(robot, int(sys.argv[3]), int(sys.argv[4]))
p = R.params_of(robot, sess, jnp.float64)
b = R.batch_of(sess, jnp.float64)
np.savez(sys.argv[5], ref=np.asarray(kk.filter_batch(p, b, "kckf", path="sequential").angles),
         lanes=np.asarray(kk.filter_batch(p, b, "kckf", path="lanes").angles))
"""


def reference(spec, B, T):
    """The float64 sequential filter's angles (and the lanes path's in float64) on the same
    trials, in a process of its own (float64 enabled)."""
    import tempfile

    out = os.path.join(tempfile.mkdtemp(), "ref.npz")
    subprocess.run([sys.executable, "-c", REFERENCE, os.path.dirname(os.path.abspath(__file__)),
                    spec, str(B), str(T), out], check=True)
    d = np.load(out)
    return d["ref"], d["lanes"]


HOUR_REFERENCE = """
import sys, numpy as np, jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import kckf_jax as kk
robot = kk.Robot.from_spec(sys.argv[1])
L = int(sys.argv[2])
hour = kk.simulate(robot, "static", seed=3, duration_s=L / 100.0, drop_prob=0.01)
p = kk.initial_params([hour], kk.FitConfig(), jnp.float64)
ser = kk.session_series(hour, jnp.float64)
seg = kk.run_filter(p, ser, "kckf", path="segments")[1]
ref = kk.run_filter(p, ser, "kckf", path="sequential")[1]
np.savez(sys.argv[3], ref=np.asarray(ref.angles), seg=np.asarray(seg.angles),
         seg_path=seg.path)
"""


def hour_reference(spec, L):
    """The float64 sequential filter's angles on the recorded-like hour (and how far the
    float64 segments path is from them, printed), in a process of its own."""
    import tempfile

    out = os.path.join(tempfile.mkdtemp(), "hour.npz")
    subprocess.run([sys.executable, "-c", HOUR_REFERENCE, spec, str(L), out], check=True)
    d = np.load(out)
    log(f"float64 hour: {d['seg_path']} path, max |segments - sequential| = "
        f"{np.nanmax(np.abs(d['seg'] - d['ref'])):.2e} rad")
    HOUR_FLOAT64[spec] = {"path_that_ran": str(d["seg_path"]),
                          "max_err_rad": float(np.nanmax(np.abs(d["seg"] - d["ref"])))}
    return d["ref"]


HOUR_FLOAT64: dict = {}


def batch_of(sessions, dtype):
    b = kk.pad_series([kk.session_series(s, np.float64) for s in sessions])
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), b)


def params_of(robot, sessions, dtype):
    p = kk.initial_params(sessions, kk.FitConfig(), dtype)  # voltage noise model
    return p


# --------------------------------------------------------------------------- peers
def peer_rows(params, s):
    """Per row, the stacked model a peer needs: F, B, Q (time step), R (voltage model), the
    measurements (Hall angles and the constraint's zeros), their mask, the held inputs."""
    robot = params.robot
    p64 = params.astype(jnp.float64)
    dt = s.dt()
    T = s.n_steps
    base = paper_matrices(robot, p64, ts=1.0)
    A1 = base.A - np.eye(base.A.shape[0])  # A = I + ts A1
    N = base.A.shape[0]
    F = np.eye(N)[None] + dt[:, None, None] * A1[None]
    Bu = base.B
    B = dt[:, None, None] * Bu[None]
    q = np.asarray(p64.q)
    arw, brw = np.asarray(p64.angle_rw), np.asarray(p64.bias_rw)
    K = robot.n_angles
    Q = np.zeros((T, N, N))
    a = q * dt[:, None] ** 4 / 4 + arw**2 * dt[:, None]
    b = q * dt[:, None] ** 3 / 2
    g = q * dt[:, None] ** 2 + brw**2 * dt[:, None]
    idx = np.arange(K)
    Q[:, idx, idx], Q[:, idx, K + idx], Q[:, K + idx, idx], Q[:, K + idx, K + idx] = a, b, b, g
    coeffs = p64.hall_coeffs
    v = np.nan_to_num(s.hall_v)
    ang = np.asarray(kk.hall_angle(v, *coeffs))
    slope = np.asarray(kk.hall_slope(v, *coeffs))
    r = (slope * np.asarray(p64.sigma_hall_v)) ** 2 + np.asarray(p64.sigma_hall) ** 2
    present = np.isfinite(s.hall_v)
    M, P = robot.n_hall, robot.n_torso_axes
    y = np.concatenate([np.where(present, ang, 0.0), np.zeros((T, P))], axis=1)
    R = np.zeros((T, M + P, M + P))
    R[:, np.arange(M), np.arange(M)] = np.where(present, r, MISSING_VAR)
    R[:, M + np.arange(P), M + np.arange(P)] = CONSTRAINT_VAR
    H = np.vstack([base.C, base.D])
    held = np.array(s.gyro)
    for t in range(T):
        bad = ~np.isfinite(held[t])
        held[t, bad] = held[t - 1, bad] if t else 0.0
    u = np.concatenate([np.zeros((1, held.shape[1])), held[:-1]], axis=0)
    st = kk.KCKF().structure(robot)
    P0b = np.asarray(kk.init_state(p64).P)
    _, P0 = full_state(st, np.zeros(P0b.shape[:2]), P0b)
    return dict(F=F, B=B, Q=Q, H=H, R=R, y=y, u=u, present=present, x0=np.zeros(N), P0=P0)


def dynamax_run(rows_list, dtype):
    from dynamax.linear_gaussian_ssm import lgssm_filter
    from dynamax.linear_gaussian_ssm.inference import (
        ParamsLGSSM,
        ParamsLGSSMDynamics,
        ParamsLGSSMEmissions,
        ParamsLGSSMInitial,
    )

    def params(r):
        T, m, n = r["y"].shape[0], r["H"].shape[0], r["H"].shape[1]
        return ParamsLGSSM(
            initial=ParamsLGSSMInitial(mean=r["x0"], cov=r["P0"]),
            dynamics=ParamsLGSSMDynamics(weights=r["F"], bias=jnp.zeros((T, n), dtype),
                                         input_weights=r["B"], cov=r["Q"]),
            emissions=ParamsLGSSMEmissions(weights=r["H"], bias=jnp.zeros(m, dtype),
                                           input_weights=jnp.zeros((m, r["B"].shape[2]), dtype),
                                           cov=r["R"]))

    stacked = {k: jnp.asarray(np.stack([r[k] for r in rows_list]), dtype)
               for k in ("F", "B", "Q", "R", "y", "u")}
    shared = {k: jnp.asarray(rows_list[0][k], dtype) for k in ("H", "x0", "P0")}

    def one(F, B, Q, R, y, u):
        return lgssm_filter(params(dict(shared, F=F, B=B, Q=Q, R=R, y=y)), y, u).filtered_means

    f = jax.jit(jax.vmap(one))
    return timed(lambda: f(*(stacked[k] for k in ("F", "B", "Q", "R", "y", "u"))), repeats=1)


def filterpy_run(r, steps):
    from filterpy.kalman import KalmanFilter

    n, m = r["H"].shape[1], r["H"].shape[0]
    kf = KalmanFilter(dim_x=n, dim_z=m, dim_u=r["u"].shape[1])
    kf.x, kf.P = r["x0"].copy(), r["P0"].copy()
    M = r["present"].shape[1]
    out = np.empty((steps, n))
    t0 = time.perf_counter()
    for t in range(steps):
        if t > 0:
            kf.predict(u=r["u"][t], B=r["B"][t], F=r["F"][t], Q=r["Q"][t])
        keep = np.r_[np.flatnonzero(r["present"][t]), M + np.arange(m - M)]
        kf.update(r["y"][t, keep], R=r["R"][t][np.ix_(keep, keep)], H=r["H"][keep])
        out[t] = kf.x
    return out, time.perf_counter() - t0


def angles_of_x(x, robot):
    return np.asarray(x)[..., : robot.n_angles]


# --------------------------------------------------------------------------- cases
def run_robot(name, spec, args):
    robot = kk.Robot.from_spec(spec)
    cases = args.cases.split(",")
    B, T = (8, 2000) if args.quick else (64, 10_000)
    sess = trials(robot, B, T)
    p32 = params_of(robot, sess, jnp.float32)
    res = {}
    if "batch" in cases:
        res["batch"] = batch_case(name, spec, robot, sess, p32, args, B, T)
    if "trials" in cases:
        res["trials"] = trials_case(name, robot, p32, args)
    if "hour" in cases:
        res["hour"] = hour_case(name, spec, robot, p32, args)
    if name == "bench" and "fit" in cases:
        res["fit"] = fit_steps(robot, args)
    return res


def batch_case(name, spec, robot, sess, p32, args, B, T):
    """The B x T batch: kckf-jax's paths, dynamax and filterpy."""
    b32 = batch_of(sess, jnp.float32)
    ref, lanes64 = reference(spec, B, T)

    def err(a):
        return float(np.nanmax(np.abs(np.asarray(a, np.float64) - ref[..., : a.shape[-1]])))

    log(f"{name}: {B} x {T} batch")
    batch = {}
    for label, path in (("kckf-jax auto", "auto"), ("kckf-jax lanes", "lanes"),
                        ("kckf-jax sequential", "sequential")):
        out, t, first = timed(lambda path=path: kk.filter_batch(p32, b32, "kckf", path=path).angles)
        batch[label] = {"trial_steps_per_s": B * T / t, "seconds": t, "compile_s": first - t,
                        "max_err_rad": err(out),
                        "path": kk.choose_path(p32, b32, "kckf").path.name if path == "auto"
                        else path}
    batch["kckf-jax lanes"]["max_err_rad_float64"] = float(np.abs(lanes64 - ref).max())
    if not args.no_peers:
        # dynamax gets every row's matrices: 16 trials (the distinct ones) keep them in memory
        # (the 3D robot's F, B, Q and R for 64 x 10,000 rows would be 10 GB).
        nd = min(B, 16)
        log(f"{name}: dynamax and filterpy")
        rows = [peer_rows(p32, s) for s in sess[:nd]]
        out, t, first = dynamax_run(rows, jnp.float32)
        batch[f"dynamax vmapped lgssm_filter ({nd} trials)"] = {
            "trial_steps_per_s": nd * T / t, "seconds": t, "compile_s": first - t,
            "max_err_rad": float(np.nanmax(np.abs(angles_of_x(out, robot) - ref[:nd])))}
        n = min(5000, T)
        out, t = filterpy_run(rows[0], n)
        batch["filterpy loop (1 trial, float64)"] = {
            "trial_steps_per_s": n / t, "max_err_rad": float(np.abs(angles_of_x(out, robot)
                                                                     - ref[0, :n]).max())}
    return batch


def trials_case(name, robot, p32, args):
    """Trial counts (kckf-jax): per-trial throughput from 1 to 1,024 trials."""
    scaling = {}
    Ts = 2000 if args.quick else 5000  # --quick: 8 x 2,000 compiled already (batch_case)
    for n in ((1, 8) if args.quick else (1, 8, 16, 64, 256, 1024)):
        log(f"{name}: {n} trials x {Ts}")
        ss = trials(robot, n, Ts, seed0=100)
        bb = batch_of(ss, jnp.float32)
        row = {}
        for path in ("auto", "sequential"):
            _, t, _ = timed(lambda path=path: kk.filter_batch(p32, bb, "kckf", path=path).angles,
                            repeats=2)
            row[path] = n * Ts / t
        row["auto_path"] = kk.choose_path(p32, bb, "kckf").path.name
        scaling[n] = row
    return scaling


def hour_case(name, spec, robot, p32, args):
    """One recorded-like hour: the segments path against the sequential one and one lane."""
    L = 24_000 if args.quick else 360_000
    log(f"{name}: one hour")
    hour = kk.simulate(robot, "static", seed=3, duration_s=L / 100.0, drop_prob=0.01)
    ser = kk.session_series(hour, jnp.float32)
    ref_hour = hour_reference(spec, L)
    long = {}
    for label, path in (("kckf-jax auto", "auto"), ("kckf-jax segments", "segments"),
                        ("kckf-jax sequential", "sequential"),
                        ("kckf-jax lanes (1 lane)", "lanes")):
        est, t, first = timed(lambda path=path: kk.run_filter(p32, ser, "kckf", path=path)[1],
                              repeats=3)
        long[label] = {"steps_per_s": L / t, "seconds": t, "compile_s": first - t,
                       "path_that_ran": est.path,
                       "max_err_rad": float(np.nanmax(np.abs(np.asarray(est.angles, np.float64)
                                                             - ref_hour)))}
    long["kckf-jax auto"]["path"] = kk.choose_path(p32, ser, "kckf").path.name
    long["kckf-jax segments, float64"] = HOUR_FLOAT64[spec]
    # The same hour with every reading lost for 100 s (a cable pulled out, 10,000 rows from
    # row 100,000; the quick hour loses 6.7 s from row 6,666): the warm-ups inside the gap
    # cannot forget, so the segments' check fails; the repair passes make it exact, where the
    # old path (repairs=0) fell back to the sequential one. Errors against the float32 sequential
    # path (through the gap both are dead reckoning, 1.5e-4 rad from float64 there). The
    # quick hour's 6.7 s gap is shorter than a warm-up: its check passes at once.
    n, r0 = L // 36, L * 5 // 18
    gyro, hall = np.array(ser.gyro), np.array(ser.hall_v)
    gyro[r0: r0 + n] = np.nan
    hall[r0: r0 + n] = np.nan
    holed = kk.SensorSeries(ser.dt, jnp.asarray(gyro), jnp.asarray(hall))
    seq = None
    gap = {}
    for label, path in (("kckf-jax sequential", "sequential"),
                        ("kckf-jax segments (repairs=2, default)", kk.Segments()),
                        ("kckf-jax segments (repairs=0)", kk.Segments(repairs=0))):
        est, t, first = timed(lambda path=path: kk.run_filter(p32, holed, "kckf", path=path)[1],
                              repeats=3)
        seq = np.asarray(est.angles) if seq is None else seq
        gap[label] = {"steps_per_s": L / t, "seconds": t, "compile_s": first - t,
                      "path_that_ran": est.path,
                      "max_diff_from_sequential_rad": float(np.abs(np.asarray(est.angles)
                                                                   - seq).max())}
    long[f"with a {n / 100:.0f} s dropout"] = gap
    return long


def fit_steps(robot, args):
    """One fitting step through ``fit`` (default FitConfig: voltage noise model), 6 steps: the
    first compiles; the median of the other 5. Regular data too (its path's compile)."""
    B, T = (8, 2000) if args.quick else (64, 10_000)
    out = {}
    for label, regular in (("recorded-like", False), ("regular, angle noise", True)):
        sess = trials(robot, B, T, seed0=200)
        steps = 3 if args.quick else 6
        cfg = kk.FitConfig(steps=steps)
        if regular:
            sess = [kk.simulate(robot, "cyclic", seed=200 + i, duration_s=T / 100.0)
                    for i in range(min(B, 16))]
            for s in sess:
                s.t = np.arange(s.n_steps) * 0.01
                s._truth = None
            sess = [sess[i % len(sess)] for i in range(B)]
            cfg = kk.FitConfig(steps=steps, hall_noise="angle")
        log(f"fit step, {label}")
        stamps = []
        t0 = time.perf_counter()
        kk.fit(sess, (), cfg, dtype=jnp.float32,
               callback=lambda r: stamps.append(time.perf_counter()))
        steps = np.diff(stamps)
        batch = kk.make_batch(sess, jnp.float32)
        path = kk.choose_path(kk.initial_params(sess, cfg, jnp.float32), batch.series).path
        out[label] = {"trials": B, "rows": T, "path": path.name,
                      "compile_and_first_step_s": round(stamps[0] - t0, 2),
                      "step_s_median": round(float(np.median(steps)), 3),
                      "step_s_all": [round(float(x), 3) for x in steps]}
    out["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3, 1)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing; the bench robot only; without dynamax or filterpy "
                         "installed, as --no-peers")
    ap.add_argument("--robots", help="default bench,3d (--quick: bench)")
    ap.add_argument("--no-peers", action="store_true")
    ap.add_argument("--cases", default="batch,trials,hour,fit",
                    help="which cases to run (comma-separated; default all)")
    args = ap.parse_args()
    QUICK[0] = args.quick
    args.robots = args.robots or ("bench" if args.quick else "bench,3d")
    peers = "skipped: --no-peers" if args.no_peers else "run"
    if args.quick and not args.no_peers:  # a smoke run goes on without them
        import importlib.util

        missing = [m for m in ("dynamax", "filterpy") if importlib.util.find_spec(m) is None]
        if missing:
            peers = f"skipped: {', '.join(missing)} not installed"
            log(f"recorded.py --quick: the peers (dynamax, filterpy) {peers}; kckf-jax alone")
            args.no_peers = True
    if not args.no_peers:
        require_peers("benchmarks/recorded.py")
    doc = {"benchmark": "recorded", "machine": machine(), "date": time.strftime("%Y-%m-%d"),
           "jax": jax.__version__, "backend": jax.default_backend(), "quick": args.quick,
           "peers": peers,
           "robots": {n: run_robot(n, ROBOTS[n], args) for n in args.robots.split(",")}}
    try:
        doc["commit"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"],
                                       capture_output=True, text=True).stdout.strip()
    except OSError:
        pass
    print(json.dumps(doc, indent=2, default=float))


if __name__ == "__main__":
    main()
