"""Sensor faults: what each does to the KCKF's error, and whether it is named.

    python benchmarks/faults.py [--seeds 1,2,3] [--steps 60] [--json]
    python benchmarks/faults.py --exact [--seeds 1,2] [--json]
    python benchmarks/faults.py --quick [--json]

Sessions: ``kckf simulate --kind cyclic --duration 60 --joints x,y,x,y`` for each seed (its
own robot: ``device_seed`` = seed), each fault of issue 33 written onto a copy with
``kk.inject_faults`` (``kckf simulate --fault``). Parameters: the paper's defaults, and a fit
(``--steps`` Adam steps, the default ``FitConfig`` otherwise) on two other clean trials of
the same robot, and the same fit on copies of those trials with faults in them
(``TRAIN_FAULTS``), scored on the clean session. Float32, the default gap policy. Per fault
and parameter set: the mean RMSE (deg) clean and faulty, averaged over the seeds, the largest
estimated angle (deg), on how many seeds both stay within the issue's bound (1.3 x clean + 0.1
deg), and whether every faulty column was named (``"faults"`` of ``kckf evaluate --json``)
or, for the set-up mistakes, by ``kk.setup_check``.

``--quick``: a smoke run that the long tests run: one seed, 2 Adam steps per fit, every fault,
then ``--exact``'s section on one seed (its lines on stderr, its rows under ``"exact"`` of the
JSON): the figures mean nothing. ``--exact --json`` prints those rows as JSON (the lines on
stderr).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

import kckf_jax as kk
from kckf_jax import enable_cpu_loops  # noqa: E402

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

FAULTS = {
    "Hall disconnected (0 V) for 10 s": ["disconnect:hall1_x_l@20-30"],
    "2 s of 0.5 V noise on one Hall sensor": ["noise:hall1_x_l@20-22=0.5"],
    "2 s of 0.5 V noise on all eight Hall sensors": [
        f"noise:hall{i}_{a}_{s}@20-22=0.5" for i, a in zip(range(1, 5), "xyxy") for s in "lr"],
    "gyro clipped at +-2 rad/s": ["clip:gyro5_x=2.0"],
    "gyro bias steps by 0.2 rad/s at 30 s": ["bias_step:gyro3_x@30=0.2"],
    "Hall stuck at 1.65 V for 20 s": ["stuck:hall1_x_l@20-40=1.65"],
    "Hall coefficient a 10x in meta.json": ["coeff:hall1_x_l=10"],
    "left and right Hall columns swapped": ["swap:hall1_x"],
    "10-minute gap": ["gap@30-630"],  # on a 660 s session (below)
    "gyro4_x blanked where |rate| >= 1.2 rad/s": ["blank:gyro4_x=1.2"],
    # Issue 45's held-out cases: two faults of different joints at once, and a slow drift.
    "Hall disconnected on one joint while another joint's sticks": [
        "disconnect:hall1_x_l@20-30", "stuck:hall3_x_r@20-40=1.65"],
    "a Hall sensor drifting by 0.25 V over the minute": ["drift:hall2_y_r=0.25"],
}


#: The faults in the two training sessions of the fit that must not be wrecked by them.
TRAIN_FAULTS = (["disconnect:hall1_x_l@10-15", "noise:hall2_y_r@20-22=0.5",
                 "bias_step:gyro3_x@25=0.2"],
                ["stuck:hall3_x_r@5-15=1.65", "clip:gyro5_x=2.0", "flicker:hall4_y_l@20-30"])


def mean_rmse(session, params):
    est = kk.filter_sessions([session], "kckf", params)[0]
    table = kk.rmse_table([session], [est.angles])
    return table["mean_rmse_deg"], float(np.nanmax(np.abs(np.degrees(est.angles)))), est


def named(session, est, specs, params):
    robot = session.robot
    found = {f["column"] for f in kk.fault_stretches(session.t, est.faults,
                                                      robot.gyro_names + robot.hall_names)}
    drifting = {c for f in kk.hall_drift(session, params, est.faults) for c in f["columns"]}
    setup = {c for f in kk.setup_check(session) for c in f.columns}
    want = set()
    for spec in specs:
        f = kk.Fault.parse(spec)
        if f.column and f.kind != "gap":
            want.add(f.column if f.kind != "swap" else f.column + "_l")
    if not want:
        return "as a gap"  # every command names a gap and what it did (stderr, JSON)
    if want <= found:
        return "yes"
    if want <= drifting:
        return "as a slow drift (the pair)"
    if want <= setup | {c[:-2] + "_l" for c in setup if c.endswith("_r")}:
        return "set-up check"
    return "no"


#: Issue 45: the faults on exact-rotation sessions, filtered by kckf3d (``--exact``).
EXACT_FAULTS = {
    "Hall disconnected for 10 s": ["disconnect:hall1_x_l@10-20"],
    "2 s of 0.5 V noise on one Hall sensor": ["noise:hall1_x_l@10-12=0.5"],
    "gyro clipped at +-2 rad/s": ["clip:gyro5_x=2.0"],
    "gyro bias steps by 0.2 rad/s": ["bias_step:gyro3_x@15=0.2"],
    "Hall stuck at 1.65 V for 10 s": ["stuck:hall1_x_l@10-20=1.65"],
    "two joints' Hall sensors at once": ["disconnect:hall1_x_l@10-20",
                                          "stuck:hall3_x_r@10-20=1.65"],
    "a Hall sensor drifting by 0.25 V": ["drift:hall2_y_r=0.25"],
}


def exact(seeds, file=None):
    """``--exact``: each of ``EXACT_FAULTS`` on a 30 s exact-rotation walking session of
    ``x,y,x,y`` per seed, kckf3d with paper defaults, float32: the mean RMSE (deg) clean and
    faulty, whether within 1.3 x clean + 0.1, and what was named. Prints a line each (to
    ``file``, default stdout) and returns the same per seed."""
    file = file or sys.stdout
    out = {}
    for seed in seeds:
        s = kk.simulate("x,y,x,y", "walking", seed, 30.0, kinematics="exact", device_seed=seed)
        clean = kk.rmse_table([s], [kk.filter_sessions([s], "kckf3d")[0].angles])[
            "mean_rmse_deg"]
        print(f"seed {seed}: clean {clean:.2f} deg", file=file)
        out[str(seed)] = row = {"clean": float(clean), "faults": {}}
        for name, specs in EXACT_FAULTS.items():
            bad = kk.inject_faults(s, [kk.Fault.parse(x) for x in specs])
            est = kk.filter_sessions([bad], "kckf3d")[0]
            r = kk.rmse_table([bad], [est.angles])["mean_rmse_deg"]
            names = bad.robot.gyro_names + bad.robot.hall_names
            found = sorted({f"{f['column']} {f['kind']}" for f in kk.fault_stretches(
                bad.t, est.faults, names)})
            params = kk.Params.paper_defaults(bad.robot, bad.hall_models)
            found += [f"{'/'.join(d['columns'])} drift" for d in kk.hall_drift(
                bad, params, est.faults)]
            found += [f"{' or '.join(d['columns'])} bias step at {d['t_s']:.1f} s"
                      for d in kk.bias_steps(bad, est)]
            print(f"  {name:40s} {r:5.2f} deg, within {r <= 1.3 * clean + 0.1}, named: "
                  f"{', '.join(found) or 'nothing'}", file=file)
            row["faults"][name] = {"rmse_deg": float(r), "within": bool(r <= 1.3 * clean + 0.1),
                                   "named": found}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--exact", action="store_true",
                    help="the faults on exact-rotation sessions with kckf3d (paper defaults)")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing; one seed, 2 fitting steps, then --exact's section too")
    args = ap.parse_args(argv)
    if args.quick:
        args.seeds, args.steps = "1", 2
    if args.exact:
        rows = exact([int(x) for x in args.seeds.split(",")],
                     sys.stderr if args.json else sys.stdout)
        if args.json:
            print(json.dumps(rows, indent=1))
        return
    robot = kk.Robot.from_spec("x,y,x,y")
    rows = {name: {"paper": [], "fitted": [], "max_deg": [], "named": [], "within": []}
            for name in FAULTS}
    clean = {"paper": [], "fitted": [], "fitted on faulty sessions": []}
    for seed in (int(s) for s in args.seeds.split(",")):
        s = kk.simulate(robot, "cyclic", seed=seed, duration_s=60.0, device_seed=seed)
        train = [kk.simulate(robot, "cyclic", seed=1000 + 10 * seed + k, duration_s=40.0,
                             device_seed=seed) for k in range(2)]
        fitted = kk.fit(train, config=kk.FitConfig(steps=args.steps)).params
        # The same fit on training sessions with faults in them: a fit is not wrecked by them.
        faulty_train = [kk.inject_faults(x, [kk.Fault.parse(f) for f in TRAIN_FAULTS[k]],
                                         seed=seed) for k, x in enumerate(train)]
        fitted_faulty = kk.fit(faulty_train, config=kk.FitConfig(steps=args.steps)).params
        paper = kk.Params.paper_defaults(robot, s.hall_models)
        c_paper = mean_rmse(s, paper)[0]
        clean["paper"].append(c_paper)
        assert not kk.fault_stretches(s.t, mean_rmse(s, paper)[2].faults,
                                      robot.gyro_names + robot.hall_names), "clean: a fault"
        c_fit = mean_rmse(s, fitted)[0]
        clean["fitted"].append(c_fit)
        clean["fitted on faulty sessions"].append(mean_rmse(s, fitted_faulty)[0])
        long = kk.simulate(robot, "cyclic", seed=seed, duration_s=660.0, device_seed=seed)
        for name, specs in FAULTS.items():
            base = long if "gap" in name else s
            bad = kk.inject_faults(base, [kk.Fault.parse(x) for x in specs], seed=seed)
            p_paper = kk.Params.paper_defaults(robot, bad.hall_models)
            a, mx, est = mean_rmse(bad, p_paper)
            b, mx2, _ = mean_rmse(bad, fitted)
            rows[name]["paper"].append(a)
            rows[name]["fitted"].append(b)
            # The bound, per seed: faulty <= 1.3 x clean + 0.1 deg (the gap's clean
            # is the same 660 s session without it).
            ca, cb = (mean_rmse(base, paper)[0], mean_rmse(base, fitted)[0]) if base is long \
                else (c_paper, c_fit)
            rows[name]["within"].append(bool(a <= 1.3 * ca + 0.1 and b <= 1.3 * cb + 0.1))
            rows[name]["max_deg"].append(max(mx, mx2))
            rows[name]["named"].append(named(bad, est, specs, p_paper))
        print(f"seed {seed} done", file=sys.stderr)
    out = {"clean": {k: float(np.mean(v)) for k, v in clean.items()},
           "faults": {n: {"paper": float(np.mean(r["paper"])),
                          "fitted": float(np.mean(r["fitted"])),
                          "max_deg": float(np.max(r["max_deg"])),
                          "named": sorted(set(r["named"])),
                          "seeds_within_bound": f"{sum(r['within'])} of {len(r['within'])}"}
                      for n, r in rows.items()}}
    if args.quick:
        out["exact"] = exact([int(s) for s in args.seeds.split(",")], sys.stderr)
        out["quick"] = True
    if args.json:
        print(json.dumps(out, indent=1))
        return
    c = out["clean"]
    print(f"clean: paper {c['paper']:.2f} deg, fitted {c['fitted']:.2f} deg, fitted on "
          f"training sessions with faults {c['fitted on faulty sessions']:.2f} deg")
    print("| fault | paper defaults | fitted | largest estimate (deg) | seeds within "
          "1.3x clean + 0.1 | named |")
    print("| --- | ---: | ---: | ---: | ---: | --- |")
    for n, r in out["faults"].items():
        print(f"| {n} | {r['paper']:.2f} | {r['fitted']:.2f} | {r['max_deg']:.0f} | "
              f"{r['seeds_within_bound']} | {', '.join(r['named'])} |")


if __name__ == "__main__":
    main()
