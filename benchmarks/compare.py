"""kckf-jax against the libraries a user would pick instead, on the same model and data.

    python benchmarks/compare.py [--json] [--robots bench,3d] [--quick] [--no-peers]

Model: the paper's KCKF (Eqs. 3-20, Q of Eq. 13, sigma_hall = 3.2 deg) with its paper-default
parameters. Peers get the literal stacked model: full state x = [theta, phi, b, b_phi], the
Hall angles (Eq. 1 applied to the voltages beforehand) and the forward-kinematics rows as
measurements with a tiny noise (1e-3 deg)^2 in place of the paper's zero (dynamax and filterpy
need a positive definite innovation covariance). Data: simulated sessions with an exactly
constant 100 Hz time step and no missing reading (dynamax has no missing-data handling), so
kckf-jax's automatic path choice takes its steady path; its sequential path is measured too.

Peers: dynamax's ``lgssm_filter`` (sequential) and ``parallel_lgssm_filter`` (associative scan;
run in a subprocess with a time limit, because batched LAPACK solves have deadlocked on 2-core
machines with jax 0.10.2), filterpy's ``KalmanFilter`` in a Python loop, and a plain NumPy loop.
Cases: one long session (1 h at 100 Hz), 64 vmapped trials of 10,000 steps, the gradient of the
fitting loss (mean RMSE against mocap) over those trials, per-packet streaming latency; robots:
the paper's bench layout (x, y, x, y) and a 3D layout (xyz x 4); float32 and float64.
Every figure is a rate measured in this run; ratios are taken within the run. Accuracy of every
path: the largest angle difference from kckf-jax's float64 sequential filter on the same steps.

The arithmetic limit: flops and bytes of one step of the structured model (counted from the
filter's block structure), and this machine's measured matmul rate and memory bandwidth.

``--no-peers``: kckf-jax alone (and the plain NumPy loop), without dynamax and filterpy.
``--quick``: a smoke run on tiny sizes that the long tests execute, the figures meaningless:
every case on a 20,000-step session and 8 trials, a representative subset (the bench robot
unless ``--robots`` says otherwise; the gradient on the sequential path only: the steady
path's compile alone takes 20 s; dynamax's parallel filter given 30 s); where dynamax or
filterpy is not installed it goes on without the peers (``--no-peers``), saying so on stderr
and in the JSON document (``peers``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import textwrap
import time

import jax

# Each precision runs in its own worker process: dynamax's float32 filter needs x64 off.
_WORKER = sys.argv[sys.argv.index("--worker") + 1] if "--worker" in sys.argv else None
jax.config.update("jax_enable_x64", _WORKER == "float64")
if _WORKER == "float32":  # streaming is measured here: settings before the first computation
    from kckf_jax import low_latency

    low_latency()

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _machine import machine, require_peers  # noqa: E402

from kckf_jax import (  # noqa: E402
    KCKF,
    PacketParser,
    Params,
    Robot,
    SensorSeries,
    Sequential,
    Steady,
    StreamingFilter,
    enable_cpu_loops,  # noqa: E402
    filter_batch,
    hall_angle,
    init_state,
    loss_fn,
    make_batch,
    run_filter,
    simulate,
)
from kckf_jax._models._blocks import full_state, paper_matrices  # noqa: E402 (internals)

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

ROBOTS = {"bench": "x,y,x,y", "3d": "xyz,xyz,xyz,xyz"}
DT = 0.01
CONSTRAINT_VAR = (1e-3 * np.pi / 180) ** 2


# --------------------------------------------------------------------------- data and models
def regular_session(robot, seed, steps):
    s = simulate(robot, "cyclic", seed=seed, duration_s=steps * DT, device_seed=1)
    s.t = np.arange(s.n_steps) * DT
    s._truth = None
    return s


def series_of(s, dtype):
    dt = np.r_[0.0, np.full(s.n_steps - 1, DT)]
    return SensorSeries(jnp.asarray(dt, dtype), jnp.asarray(s.gyro, dtype),
                        jnp.asarray(s.hall_v, dtype))


def peer_model(params: Params):
    """The literal stacked model (float64 NumPy): F, B, Q, H, R, x0, P0 and Hall angle maps."""
    robot = params.robot
    pm = paper_matrices(robot, params, ts=DT)
    H = np.vstack([pm.C, pm.D])
    R = np.zeros((H.shape[0], H.shape[0]))
    R[: robot.n_hall, : robot.n_hall] = pm.R
    R[robot.n_hall:, robot.n_hall:] = CONSTRAINT_VAR * np.eye(robot.n_torso_axes)
    st = KCKF().structure(robot)
    K = robot.n_angles
    x0 = np.zeros(2 * K)
    # The KCKF's prior satisfies the constraint: P0 = T diag(p0) T^T in the paper's order.
    P0b = np.asarray(init_state(params.astype(jnp.float64)).P)
    _, P0 = full_state(st, np.zeros(P0b.shape[:2]), P0b)
    return dict(F=pm.A, B=pm.B, Q=pm.Q, H=H, R=R, x0=x0, P0=P0)


def peer_emissions(params, s):
    """Hall angles through Eq. 1 (rad) plus the constraint's zeros, (T, M + P)."""
    ang = hall_angle(jnp.asarray(s.hall_v), *params.astype(jnp.float64).hall_coeffs)
    return np.concatenate([np.asarray(ang), np.zeros((s.n_steps, params.robot.n_torso_axes))], 1)


def peer_inputs(s):
    """dynamax and filterpy predict into row t with input t: our rows' previous gyro."""
    return np.concatenate([np.zeros((1, s.gyro.shape[1])), s.gyro[:-1]], axis=0)


def angles_of_x(x, robot):
    return np.asarray(x)[..., : robot.n_angles]


# --------------------------------------------------------------------------- timing
def timed(fn, repeats=3):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    best = np.inf
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return out, best, first


# --------------------------------------------------------------------------- dynamax
def dynamax_params(model, dtype):
    from dynamax.linear_gaussian_ssm import ParamsLGSSM
    from dynamax.linear_gaussian_ssm.inference import (
        ParamsLGSSMDynamics,
        ParamsLGSSMEmissions,
        ParamsLGSSMInitial,
    )

    c = {k: jnp.asarray(v, dtype) for k, v in model.items()}
    n, m = c["H"].shape[1], c["H"].shape[0]
    return ParamsLGSSM(
        initial=ParamsLGSSMInitial(mean=c["x0"], cov=c["P0"]),
        dynamics=ParamsLGSSMDynamics(weights=c["F"], bias=jnp.zeros(n, dtype),
                                     input_weights=c["B"], cov=c["Q"]),
        emissions=ParamsLGSSMEmissions(weights=c["H"], bias=jnp.zeros(m, dtype),
                                       input_weights=jnp.zeros((m, c["B"].shape[1]), dtype),
                                       cov=c["R"]),
    )


def dynamax_filter(dtype):
    from dynamax.linear_gaussian_ssm import lgssm_filter

    return jax.jit(lambda p, y, u: lgssm_filter(p, y, u).filtered_means)


PARALLEL_SCRIPT = textwrap.dedent("""
    import sys, time, json, numpy as np, jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    sys.path.insert(0, sys.argv[1])
    import compare as C
    from dynamax.linear_gaussian_ssm import parallel_lgssm_filter
    d = np.load(sys.argv[2], allow_pickle=True).item()
    dtype = jnp.float32 if sys.argv[3] == "float32" else jnp.float64
    p = C.dynamax_params(d["model"], dtype)
    y, u = jnp.asarray(d["y"], dtype), jnp.asarray(d["u"], dtype)
    f = jax.jit(lambda p, y, u: parallel_lgssm_filter(p, y, u).filtered_means)
    out, best, first = C.timed(lambda: f(p, y, u), repeats=1)
    np.save(sys.argv[4], np.asarray(out, np.float64))
    print(json.dumps({"seconds": best, "first": first}))
""")


def dynamax_parallel(model, y, u, dtype_name, tmp, timeout_s):
    path = os.path.join(tmp, "par.npy")
    np.save(path, {"model": model, "y": y, "u": u}, allow_pickle=True)
    out = os.path.join(tmp, "par_out.npy")
    try:
        r = subprocess.run([sys.executable, "-c", PARALLEL_SCRIPT, os.path.dirname(__file__),
                            path, dtype_name, out], capture_output=True, text=True,
                           timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return None, f"no result within {timeout_s} s (hung or too slow)"
    if r.returncode != 0:
        return None, "failed: " + r.stderr.strip().splitlines()[-1][:200]
    return (json.loads(r.stdout.strip().splitlines()[-1]), np.load(out)), ""


# --------------------------------------------------------------------------- filterpy, numpy
def filterpy_run(model, y, u, steps):
    from filterpy.kalman import KalmanFilter

    n, m = model["H"].shape[1], model["H"].shape[0]
    kf = KalmanFilter(dim_x=n, dim_z=m, dim_u=u.shape[1])
    kf.F, kf.B, kf.Q, kf.H, kf.R = (model[k].copy() for k in ("F", "B", "Q", "H", "R"))
    kf.x, kf.P = model["x0"].copy(), model["P0"].copy()
    out = np.empty((steps, n))
    lat = np.empty(steps)
    for t in range(steps):
        t0 = time.perf_counter()
        if t > 0:
            kf.predict(u=u[t])
        kf.update(y[t])
        lat[t] = time.perf_counter() - t0
        out[t] = kf.x
    return out, lat


def numpy_run(model, y, u, steps):
    F, B, Q, H, R = (model[k] for k in ("F", "B", "Q", "H", "R"))
    x, P = model["x0"].copy(), model["P0"].copy()
    n = x.shape[0]
    eye = np.eye(n)
    out = np.empty((steps, n))
    lat = np.empty(steps)
    for t in range(steps):
        t0 = time.perf_counter()
        if t > 0:
            x = F @ x + B @ u[t]
            P = F @ P @ F.T + Q
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        x = x + K @ (y[t] - H @ x)
        IKH = eye - K @ H
        P = IKH @ P @ IKH.T + K @ R @ K.T
        lat[t] = time.perf_counter() - t0
        out[t] = x
    return out, lat


# --------------------------------------------------------------------------- the limit
def flops_bytes(robot: Robot, dtype_bytes: int) -> dict:
    """Floating-point operations and bytes of one step of the structured model.

    Counted from the block structure: per axis block the sparse prediction of the mean and of
    the (symmetric) covariance, the constraint's scalar Joseph update and one scalar Joseph
    update per joint, plus the Hall model (two exponentials per sensor, counted as 20 flops
    each) and the fusion of each joint's two readings; the steady path: the affine map of the
    mean only. Bytes: the row read (dt, gyro, Hall) and the estimate written (angles, std,
    bias); the state stays in cache.
    """
    st = KCKF().structure(robot)
    nz, ny, m = st.n_z, st.n_z + st.n_e, st.m
    F = (st.F0 != 0) | (st.F1 != 0)
    nnzF = int(F.sum())
    predict = 2 * (nnzF + int((st.G1 != 0).sum())) + 2 * nnzF * nz + nnzF * (ny + 1) + 3 * int(
        ((st.Qa != 0) | (st.Qab != 0) | (st.Qb != 0)).sum() // (m + 1))

    def upd(n):
        return 2 + n + 2 * n + 3 * n * (n + 1)

    per_block = predict + upd(ny) * st.n_e + m * upd(nz)
    blocks = robot.n_torso_axes
    hall = robot.n_hall * 2 * 20 + robot.n_joint_axes * 8
    full = blocks * per_block + hall
    steady = blocks * (2 * nz * nz + 2 * nz * (2 * m + 1)) + hall + 2 * robot.n_angles * nz
    row = (1 + 3 * robot.n_links + robot.n_hall) * dtype_bytes
    out = 3 * robot.n_angles * dtype_bytes
    return {"full_step_flops": int(full), "steady_step_flops": int(steady),
            "bytes_per_step": int(row + out)}


def machine_rates() -> dict:
    """Measured float32 matmul rate and memory bandwidth of this machine (via XLA).

    Two bandwidths: ``copy_inplace`` (read and write a 256 MB array in place, its buffer
    donated: the memory system's rate, used for the limit) and ``copy_fresh`` (the same into
    a newly allocated output, as every jitted call returns; on this VM the first touch of
    fresh pages costs most of that time)."""
    n = 2048
    a = jnp.ones((n, n), jnp.float32)
    mm = jax.jit(lambda a: a @ a)
    _, t, _ = timed(lambda: mm(a), repeats=5)
    nbytes = 256 << 20
    big = jnp.ones(nbytes // 4, jnp.float32)
    cp = jax.jit(lambda x: x * 1.0001)
    _, tc, _ = timed(lambda: cp(big), repeats=5)
    ip = jax.jit(lambda x: x * 1.0001, donate_argnums=0)
    buf = [jnp.ones(nbytes // 4, jnp.float32)]

    def inplace():
        buf[0] = ip(buf[0])
        return buf[0]

    _, ti, _ = timed(inplace, repeats=5)
    return {"matmul_gflops_f32": 2 * n**3 / t / 1e9, "copy_inplace_gbytes_per_s": 2 * nbytes / ti
            / 1e9, "copy_fresh_gbytes_per_s": 2 * nbytes / tc / 1e9}


# --------------------------------------------------------------------------- cases
def run_robot(name: str, spec: str, args, tmp: str, dtype) -> dict:
    """Every case for one robot in one precision (this process's x64 setting). The float64
    worker runs first and leaves kckf-jax's float64 sequential estimates as the reference."""
    robot = Robot.from_spec(spec)
    dn = jnp.dtype(dtype).name
    L = args.long_steps
    s = regular_session(robot, 11, L)
    B, T = args.trials, args.trial_steps
    trials = [regular_session(robot, 100 + i, T) for i in range(B)]
    params = Params.paper_defaults(robot, s.hall_models, dtype=dtype)
    model = peer_model(Params.paper_defaults(robot, s.hall_models))  # NumPy float64 matrices
    y = peer_emissions(params, s)
    u = peer_inputs(s)
    ref_file = os.path.join(tmp, f"ref_{name}.npz")
    ser_long = series_of(s, dtype)
    batch_ser = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[series_of(t, dtype)
                                                                for t in trials])
    if dn == "float64":
        ref = np.asarray(run_filter(params, ser_long, "kckf", path="sequential")[1].angles)
        ref_b = np.asarray(filter_batch(params, batch_ser, "kckf", path="sequential").angles)
        np.savez(ref_file, long=ref, batch=ref_b)
    else:
        refs = np.load(ref_file)
        ref, ref_b = refs["long"], refs["batch"]

    def err(a, r):
        a = np.asarray(a, np.float64)
        return float(np.max(np.abs(a - r[: a.shape[0]])))

    cases = {}
    # ---- one long session
    long = {}
    for path in ("auto", "sequential"):
        out, t, first = timed(lambda path=path: run_filter(params, ser_long, "kckf",
                                                           path=path)[1].angles)
        long[f"kckf-jax {path}"] = {"steps_per_s": L / t, "seconds": t, "compile_s": first - t,
                                    "max_err_rad": err(out, ref)}
    if args.peers:
        dp = dynamax_params(model, dtype)
        f = dynamax_filter(dtype)
        yy, uu = jnp.asarray(y, dtype), jnp.asarray(u, dtype)
        out, t, first = timed(lambda: f(dp, yy, uu), repeats=1)
        long["dynamax sequential"] = {"steps_per_s": L / t, "seconds": t,
                                      "compile_s": first - t,
                                      "max_err_rad": err(angles_of_x(out, robot), ref)}
        par, why = dynamax_parallel(model, y, u, dn, tmp, args.parallel_timeout)
        if par is None:
            long["dynamax parallel"] = {"steps_per_s": None, "note": why}
        else:
            info, out = par
            long["dynamax parallel"] = {"steps_per_s": L / info["seconds"], "seconds":
                                        info["seconds"],
                                        "max_err_rad": err(angles_of_x(out, robot), ref)}
    if dn == "float64":
        n = args.loop_steps
        if args.peers:
            out, lat_fp = filterpy_run(model, y, u, n)
            long["filterpy loop"] = {"steps_per_s": n / lat_fp.sum(), "steps": n,
                                     "max_err_rad": err(angles_of_x(out, robot), ref)}
        out, lat_np = numpy_run(model, y, u, n)
        long["numpy loop"] = {"steps_per_s": n / lat_np.sum(), "steps": n,
                              "max_err_rad": err(angles_of_x(out, robot), ref)}
    cases["long_session"] = long

    # ---- vmapped trials
    batch = {}
    for path in ("auto", "sequential"):
        out, t, first = timed(lambda path=path: filter_batch(params, batch_ser, "kckf",
                                                             path=path).angles)
        batch[f"kckf-jax {path}"] = {"trial_steps_per_s": B * T / t, "seconds": t,
                                     "compile_s": first - t, "max_err_rad": err(out, ref_b)}
    if args.peers:
        from dynamax.linear_gaussian_ssm import lgssm_filter

        ys = jnp.asarray(np.stack([peer_emissions(params, t) for t in trials]), dtype)
        us = jnp.asarray(np.stack([peer_inputs(t) for t in trials]), dtype)
        fv = jax.jit(jax.vmap(lambda y, u: lgssm_filter(dp, y, u).filtered_means))
        out, t, first = timed(lambda: fv(ys, us), repeats=1)
        batch["dynamax vmapped"] = {"trial_steps_per_s": B * T / t, "seconds": t,
                                    "compile_s": first - t,
                                    "max_err_rad": err(angles_of_x(out, robot), ref_b)}
    cases["vmapped_trials"] = batch

    if dn == "float32":
        # ---- gradient of the fitting loss
        grad = {}
        b = make_batch(trials, dtype)
        for path in (Sequential(100),) if args.quick else (Steady(), Sequential(100)):
            g = eqx.filter_jit(eqx.filter_value_and_grad(
                lambda q, b, path=path: loss_fn(q, b, "kckf", path=path)))
            (lv, _), t, first = timed(lambda g=g, b=b: g(params, b), repeats=2)
            grad["kckf-jax " + path.name] = {
                "seconds_per_gradient": t, "compile_s": first - t,
                "loss_deg": float(lv) * 180 / np.pi}
        if args.dynamax_grad and args.peers:
            base = {k: jnp.asarray(v, dtype) for k, v in model.items()}

            def dyn_loss(logs):
                mdl = dict(base, Q=base["Q"] * jnp.exp(logs[0]),
                           R=base["R"].at[: robot.n_hall, : robot.n_hall].multiply(
                               jnp.exp(logs[1])))
                d = dynamax_params(mdl, dtype)
                xs = jax.vmap(lambda y, u: lgssm_filter(d, y, u).filtered_means)(ys, us)
                e = jnp.where(b.mask, xs[..., : robot.n_angles] - b.truth, 0.0)
                return jnp.mean(jnp.sqrt(jnp.sum(e**2, (0, 1)) / jnp.sum(b.mask, (0, 1))))

            gd = jax.jit(jax.value_and_grad(dyn_loss))
            (lv, _), t, first = timed(lambda: gd(jnp.zeros(2, dtype)), repeats=1)
            grad["dynamax (w.r.t. 2 noise scales)"] = {
                "seconds_per_gradient": t, "compile_s": first - t,
                "loss_deg": float(lv) * 180 / np.pi}
        cases["gradient"] = grad

        # ---- streaming latency (low_latency() ran at import, before any computation)
        # A live stream at a constant rate: the first host_after packets (20 s
        # at 100 Hz) go untimed, while the covariance converges; the next ones are timed.
        warm = StreamingFilter(params).host_after
        n_lat = min(5000, L - warm)
        parser = PacketParser(robot)
        pk = []
        for i in range(warm + n_lat):
            obj = {"t": float(s.t[i])}
            obj.update(dict(zip(robot.gyro_names, s.gyro[i].tolist())))
            obj.update(dict(zip(robot.hall_names, s.hall_v[i].tolist())))
            pk.append(parser.parse(json.dumps(obj).encode()))
        lat_cases = {}
        for label, host in (("kckf-jax StreamingFilter.push", True),
                            ("kckf-jax StreamingFilter.push, device step only", False)):
            sf = StreamingFilter(params, host_path=host)
            sf.warmup()
            for q in pk[:warm]:
                sf.push(q)
            lat, on_host = [], 0
            for q in pk[warm:]:
                t0 = time.perf_counter()
                sf.push(q)
                lat.append(time.perf_counter() - t0)
                on_host += sf.on_host
            lat = np.asarray(lat) * 1e6
            lat_cases[label] = {"median": float(np.median(lat)),
                                "p99": float(np.percentile(lat, 99)),
                                "fraction_on_host": on_host / len(lat), "packets": len(lat)}
        cases["streaming_latency_us"] = lat_cases
    else:
        cases["streaming_latency_us"] = {
            "numpy loop step": {"median": float(np.median(lat_np) * 1e6),
                                "p99": float(np.percentile(lat_np, 99) * 1e6)}}
        if args.peers:
            cases["streaming_latency_us"] = {
                "filterpy predict+update": {"median": float(np.median(lat_fp) * 1e6),
                                            "p99": float(np.percentile(lat_fp, 99) * 1e6)},
                **cases["streaming_latency_us"]}
    return {"robot": spec, "n_states_paper": 2 * robot.n_angles, "cases": cases,
            "limit": flops_bytes(robot, 4 if dn == "float32" else 8)}


def merge(f64: dict, f32: dict) -> dict:
    """One document per robot: ``cases[case][path][dtype] = figures``."""
    out = {"robot": f64["robot"], "n_states_paper": f64["n_states_paper"], "cases": {},
           "limit": {"float32": f32["limit"], "float64": f64["limit"]}}
    for dn, res in (("float64", f64), ("float32", f32)):
        for case, rows in res["cases"].items():
            for path, figures in rows.items():
                out["cases"].setdefault(case, {}).setdefault(path, {})[dn] = figures
    return out


def ratios(res: dict) -> dict:
    """kckf-jax's rate over each peer's, per case and dtype (measured in this run)."""
    out = {}
    long, batch = res["cases"]["long_session"], res["cases"]["vmapped_trials"]
    for dn in ("float32", "float64"):
        ours = long["kckf-jax auto"][dn]["steps_per_s"]
        for peer in ("dynamax sequential", "dynamax parallel", "filterpy loop", "numpy loop"):
            v = long.get(peer, {}).get(dn if peer.startswith("dynamax") else "float64", {})
            v = v.get("steps_per_s")
            out[f"long {dn}: kckf-jax / {peer}"] = ours / v if v else None
        out[f"vmapped {dn}: kckf-jax / dynamax"] = (
            batch["kckf-jax auto"][dn]["trial_steps_per_s"]
            / batch["dynamax vmapped"][dn]["trial_steps_per_s"]
            if "dynamax vmapped" in batch else None)  # None: --no-peers
    lat = res["cases"]["streaming_latency_us"]
    ours = lat["kckf-jax StreamingFilter.push"]["float32"]["median"]
    fp = lat.get("filterpy predict+update", {}).get("float64", {}).get("median")
    out["streaming: filterpy median / kckf-jax median"] = fp / ours if fp else None
    out["streaming: filterpy median / kckf-jax device-step median"] = (
        fp / lat["kckf-jax StreamingFilter.push, device step only"]["float32"]["median"]
        if fp else None)
    out["streaming: numpy median / kckf-jax median"] = (
        lat["numpy loop step"]["float64"]["median"] / ours)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--robots", help="default bench,3d (--quick: bench)")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing; the bench robot, the sequential gradient; without "
                         "dynamax or filterpy installed, as --no-peers")
    ap.add_argument("--no-peers", dest="peers", action="store_false",
                    help="kckf-jax alone (and the NumPy loop): no dynamax, no filterpy")
    ap.add_argument("--parallel-timeout", type=int,
                    help="seconds for dynamax's parallel filter (default 90; --quick: 30)")
    ap.add_argument("--no-dynamax-grad", dest="dynamax_grad", action="store_false")
    ap.add_argument("--worker", choices=("float32", "float64"), help=argparse.SUPPRESS)
    ap.add_argument("--tmp", help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.robots = args.robots or ("bench" if args.quick else "bench,3d")
    args.parallel_timeout = args.parallel_timeout or (30 if args.quick else 90)
    skipped = ""
    if not args.worker and args.peers and args.quick:  # a smoke run goes on without them
        import importlib.util

        missing = [m for m in ("dynamax", "filterpy") if importlib.util.find_spec(m) is None]
        if missing:
            skipped = f"skipped: {', '.join(missing)} not installed"
            print(f"compare.py --quick: the peers (dynamax, filterpy) {skipped}; kckf-jax "
                  "alone", file=sys.stderr, flush=True)
            args.peers = False
    if not args.worker and args.peers:  # the peers are the point of this benchmark
        require_peers("benchmarks/compare.py")
    args.long_steps = 20_000 if args.quick else 360_000
    args.trials, args.trial_steps = ((8, Steady().min_rows + 1000) if args.quick
                                     else (64, 10_000))
    args.loop_steps = 2_000 if args.quick else 20_000
    if args.worker:
        dtype = jnp.float32 if args.worker == "float32" else jnp.float64
        out = {name: run_robot(name, ROBOTS[name], args, args.tmp, dtype)
               for name in args.robots.split(",")}
        if args.worker == "float32":
            out["_rates"] = machine_rates()
        print("RESULT " + json.dumps(out, default=float))
        return
    import shutil
    import tempfile

    tmp = tempfile.mkdtemp(prefix="kckf-compare-")
    worker = {}
    for dn in ("float64", "float32"):
        cmd = [sys.executable, __file__, "--worker", dn, "--tmp", tmp, "--robots", args.robots,
               "--parallel-timeout", str(args.parallel_timeout)]
        cmd += (["--quick"] if args.quick else []) + ([] if args.dynamax_grad else
                                                       ["--no-dynamax-grad"])
        cmd += [] if args.peers else ["--no-peers"]
        r = subprocess.run(cmd, capture_output=True, text=True)
        lines = [x for x in r.stdout.splitlines() if x.startswith("RESULT ")]
        if r.returncode != 0 or not lines:
            sys.exit(f"the {dn} worker failed:\n{r.stderr[-3000:]}")
        worker[dn] = json.loads(lines[-1][len("RESULT "):])
    shutil.rmtree(tmp, ignore_errors=True)  # the reference and the peers' inputs
    rates = worker["float32"].pop("_rates")
    doc = {"benchmark": "compare", "machine": machine(), "date": time.strftime("%Y-%m-%d"),
           "command": "python benchmarks/compare.py" + (" --quick" if args.quick else "")
           + ("" if args.peers else " --no-peers"),
           "peers": skipped or ("run" if args.peers else "skipped: --no-peers"),
           "rates": rates, "robots": {}}
    for name in args.robots.split(","):
        res = merge(worker["float64"][name], worker["float32"][name])
        res["ratios"] = ratios(res)
        lim = res["limit"]["float32"]
        peak, bw = rates["matmul_gflops_f32"] * 1e9, rates["copy_inplace_gbytes_per_s"] * 1e9
        lim["full_step_limit_steps_per_s"] = min(peak / lim["full_step_flops"],
                                                 bw / lim["bytes_per_step"])
        lim["steady_step_limit_steps_per_s"] = min(peak / lim["steady_step_flops"],
                                                   bw / lim["bytes_per_step"])
        long = res["cases"]["long_session"]
        lim["auto_fraction_of_steady_limit"] = (
            long["kckf-jax auto"]["float32"]["steps_per_s"] / lim["steady_step_limit_steps_per_s"])
        lim["vmapped_auto_fraction_of_steady_limit"] = (
            res["cases"]["vmapped_trials"]["kckf-jax auto"]["float32"]["trial_steps_per_s"]
            / lim["steady_step_limit_steps_per_s"])
        lim["sequential_fraction_of_full_limit"] = (
            long["kckf-jax sequential"]["float32"]["steps_per_s"]
            / lim["full_step_limit_steps_per_s"])
        doc["robots"][name] = res
    if args.json:
        print(json.dumps(doc, indent=2, default=float))
        return
    print(f"{doc['machine']['cpu']}, {doc['machine']['cores']} cores, jax {doc['machine']['jax']}"
          f"; matmul {rates['matmul_gflops_f32']:.0f} GFLOP/s, copy in place "
          f"{rates['copy_inplace_gbytes_per_s']:.1f} GB/s, into a fresh buffer "
          f"{rates['copy_fresh_gbytes_per_s']:.1f} GB/s")
    for name, res in doc["robots"].items():
        print(f"\n== {name} ({res['robot']}, {res['n_states_paper']} states) ==")
        for case, rows in res["cases"].items():
            print(f"-- {case}")
            for path, by_dtype in rows.items():
                for dn, v in by_dtype.items():
                    print(f"   {path + ' ' + dn:<48} " + ", ".join(
                        f"{a}={b:.4g}" if isinstance(b, float) else f"{a}={b}"
                        for a, b in v.items()))
        print("-- ratios (measured in this run)")
        for k, v in res["ratios"].items():
            print(f"   {k:<58} {'n/a' if v is None else f'{v:.1f}x'}")
        print("-- limit (float32)", {k: (round(v, 4) if isinstance(v, float) else v)
                                     for k, v in res["limit"]["float32"].items()})


if __name__ == "__main__":
    main()
