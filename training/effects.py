"""Learned sensor effects (issue 37): does each one show in the diagnostics, is it recovered,
and what does it gain, filtered and smoothed?

    python training/effects.py [--config training/configs/effects.json] [--only play,curve]

Per effect (``cases``): sessions of one simulated robot with the effect on (the simulator's
option, ``SimConfig``; docs/simulator.md "Sensor effects"), fitted on training sessions three
ways: without the effect (``base_learn`` only), learning it, and learning it fitted for
smoothing (``FitConfig.smooth``). On held-out sessions: the mean RMSE filtered and smoothed of
each; the learned value against the simulator's true one; and the diagnostics' verdict on the
effect's group (``kk.diagnostics``: significant or not) with the effect absent (the fit without
it on sessions without it), present and unmodelled (the fit without it on sessions with it)
and modelled (the fit that learns it). Then every effect at once (``all``), per kind of
motion: today's fitted filter (no effect, filtered) against the offline recipe (every kept
effect learned, fitted for smoothing, smoothed). Writes ``training/results/effects.json`` and
``training/results/effects.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import numpy as np

import kckf_jax as kk

kk.enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

HERE = os.path.dirname(os.path.abspath(__file__))


def simulated(cfg: dict, sim: dict, kind: str, seeds) -> list:
    robot = kk.Robot.from_spec(cfg["joints"])
    return [kk.simulate(robot, kind, seed=s, duration_s=cfg["duration_s"],
                        device_seed=cfg["device_seed"], drop_prob=cfg["drop_prob"],
                        config=kk.SimConfig(**sim)) for s in seeds]


def on_mocap_clock(sessions, params) -> list:
    """The sessions' motion capture aligned by a learned clock offset (as ``kckf evaluate``)."""
    e = params.effects if params is not None else None
    if e is None or "offset" not in e.on:
        return list(sessions)
    tau = float(e.time_offset_s)
    return [dataclasses.replace(s, mocap_time_offset_s=s.mocap_time_offset_s - tau)
            for s in sessions]


def fitted(cfg: dict, train, learn, smooth=False):
    t0 = time.perf_counter()
    res = kk.fit(train, (), kk.FitConfig(steps=cfg["steps"], learning_rate=cfg["learning_rate"],
                                         learn=tuple(learn), smooth=smooth))
    return res.params, round(time.perf_counter() - t0, 1)


def scores(test, params) -> dict:
    scored = on_mocap_clock(test, params)
    out = {}
    for name, smooth in (("filtered", False), ("smoothed", True)):
        est = kk.filter_sessions(test, "kckf", params, smooth=smooth)
        out[name] = round(kk.rmse_table(scored, [e.angles for e in est])["mean_rmse_deg"], 4)
    return out


def verdict(test, params, group: str) -> dict:
    """The diagnostics of the filtered estimates of ``params`` on ``test``: how many angles
    have ``group`` significant, and the clock offset and play they read."""
    scored = on_mocap_clock(test, params)
    d = kk.diagnostics(scored, kk.filter_sessions(test, "kckf", params), params=params)
    flagged = [p.angle for p in d.errors if p.significant[group]]
    return {"flagged": len(flagged), "of": len(d.errors), "angles": flagged,
            "part_deg": round(float(np.mean([p.part_deg[group] for p in d.errors])), 3),
            "clock_offset_ms": round(float(np.median([p.clock_offset_ms for p in d.errors])), 2),
            "play_deg": round(float(np.median([p.play_deg for p in d.errors])), 3),
            "white_channels": sum(w.white for w in d.whiteness),
            "channels": len(d.whiteness)}


def recovery(name: str, params, session) -> dict:
    """The learned value against the simulator's (``extra_meta["simulation"]["effects"]``):
    each item's relative error, and whether all are within 25 %."""
    e, truth, robot = params.effects, session.extra_meta["simulation"]["effects"], session.robot
    step = 1.0 / session.sample_rate_hz
    if name in ("gyro_timing", "delay"):
        true = [0.5 + truth.get("gyro_delay_s", 0.0) / step]
        got = [float(e.timing)]
        items = ["lambda"]
    elif name == "play":
        items = list(truth["hall_play_deg"])
        true = [truth["hall_play_deg"][n] for n in items]
        got = np.asarray(e.play, np.float64).tolist()
    elif name == "curve":
        items = robot.hall_names
        c = np.asarray(e.curve, np.float64)
        w = np.array([1 / 5, 1 / 7])  # P2 and P3's mean squares over u in [-1, 1]
        tr = np.array([[truth["hall_curve_deg"][n]["p2"], truth["hall_curve_deg"][n]["p3"]]
                       for n in items])
        err = np.sqrt(((c - tr) ** 2 * w).sum(1)) / np.sqrt((tr**2 * w).sum(1))
        return {"items": list(items), "true_rms_deg": np.sqrt((tr**2 * w).sum(1)).round(3).tolist(),
                "learned_rms_deg": np.sqrt((c**2 * w).sum(1)).round(3).tolist(),
                "relative_error": err.round(3).tolist(), "within_25": bool(np.all(err <= 0.25))}
    elif name == "offset":
        items, true, got = ["tau_s"], [truth["mocap_sync_error_s"]], [float(e.time_offset_s)]
    else:  # gyro_scale: the channels the filter reads
        used = robot.used_gyro_index
        items = [robot.gyro_names[i] for i in used]
        true = [truth["gyro_scale"][n] for n in items]
        got = np.asarray(e.gyro_scale_error, np.float64)[used].tolist()
    rel = np.abs(np.asarray(got) - np.asarray(true)) / np.abs(np.asarray(true))
    return {"items": list(items), "true": np.round(true, 5).tolist(),
            "learned": np.round(got, 5).tolist(), "relative_error": rel.round(3).tolist(),
            "within_25": bool(np.all(rel <= 0.25))}


def run_case(cfg: dict, name: str, case: dict) -> dict:
    base = case.get("base_learn", cfg["base_learn"])
    learn = sorted(set(base) | set(case["learn"]), key=kk.EFFECTS.index)
    kind = cfg["kind"]
    train = simulated(cfg, case["sim"], kind, cfg["train_seeds"])
    test = simulated(cfg, case["sim"], kind, cfg["test_seeds"])
    clean_train = simulated(cfg, {}, kind, cfg["train_seeds"])
    clean_test = simulated(cfg, {}, kind, cfg["test_seeds"])
    p_base, s_base = fitted(cfg, train, base)
    p_learn, s_learn = fitted(cfg, train, learn)
    p_smooth, s_smooth = fitted(cfg, train, learn, smooth=True)
    p_clean = p_base if not case["sim"] else fitted(cfg, clean_train, base)[0]
    out = {
        "sim": case["sim"], "learn": learn, "base_learn": base, "group": case["group"],
        "fit_seconds": {"base": s_base, "learn": s_learn, "learn_smooth": s_smooth},
        "heldout_mean_rmse_deg": {"base": scores(test, p_base), "learn": scores(test, p_learn),
                                  "learn_fitted_for_smoothing": scores(test, p_smooth)},
        "diagnostics": {
            "absent": None if name == "gyro_timing" else verdict(clean_test, p_clean,
                                                                  case["group"]),
            "present_unmodelled": verdict(test, p_base, case["group"]),
            "modelled": verdict(test, p_learn, case["group"]),
        },
        "recovery": recovery(name, p_learn, test[0]),
        "recovery_fitted_for_smoothing": recovery(name, p_smooth, test[0]),
    }
    return out


def run_all(cfg: dict) -> dict:
    keep = [e for e in kk.EFFECTS if e in cfg.get("keep", kk.EFFECTS)]
    out = {"learn": keep, "kinds": {}}
    for label, kind in cfg["all"]["kinds"].items():
        train = simulated(cfg, cfg["all"]["sim"], kind, cfg["train_seeds"])
        test = simulated(cfg, cfg["all"]["sim"], kind, cfg["test_seeds"])
        p_today, s_today = fitted(cfg, train, [])
        p_off, s_off = fitted(cfg, train, keep, smooth=True)
        out["kinds"][label] = {
            "today_fitted": scores(test, p_today), "offline_recipe": scores(test, p_off),
            "fit_seconds": {"today": s_today, "offline": s_off},
            "diagnostics_today": verdict(test, p_today, "time"),
            "diagnostics_offline": verdict(test, p_off, "time"),
        }
    return out


def markdown(res: dict) -> str:
    lines = ["### Each effect (bench, held-out mean RMSE, deg)", "",
             "| effect | simulated | not modelled: filtered / smoothed | learned: filtered / "
             "smoothed | learned, fitted for smoothing: smoothed | recovered (within 25 %) | "
             "diagnostics: absent / unmodelled / modelled (angles flagged) |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, c in res["cases"].items():
        h = c["heldout_mean_rmse_deg"]
        d = c["diagnostics"]

        def f(v):
            return "-" if v is None else f"{v['flagged']}/{v['of']}"

        rec = c["recovery"]
        lines.append(
            f"| {name} | {json.dumps(c['sim']) if c['sim'] else 'default'} | "
            f"{h['base']['filtered']:.3f} / {h['base']['smoothed']:.3f} | "
            f"{h['learn']['filtered']:.3f} / {h['learn']['smoothed']:.3f} | "
            f"{h['learn_fitted_for_smoothing']['smoothed']:.3f} | "
            f"{'yes' if rec['within_25'] else 'no'} (max {max(rec['relative_error']):.0%}) | "
            f"{f(d['absent'])} / {f(d['present_unmodelled'])} / {f(d['modelled'])} "
            f"({c['group']}) |")
    if "all" in res:
        lines += ["", f"### Every effect at once (learned: {', '.join(res['all']['learn'])})", "",
                  "| motion | today's fit, filtered | offline recipe, smoothed | ratio |",
                  "| --- | ---: | ---: | ---: |"]
        for label, k in res["all"]["kinds"].items():
            a, b = k["today_fitted"]["filtered"], k["offline_recipe"]["smoothed"]
            lines.append(f"| {label} | {a:.3f} | {b:.3f} | {b / a:.2f} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=os.path.join(HERE, "configs", "effects.json"))
    ap.add_argument("--out", default=os.path.join(HERE, "results", "effects.json"))
    ap.add_argument("--only", help="comma-separated cases (and 'all') to run")
    args = ap.parse_args()
    with open(args.config) as f:
        cfg = json.load(f)
    only = set(args.only.split(",")) if args.only else None
    res = {"config": cfg, "cases": {}}
    for name, case in cfg["cases"].items():
        if only is None or name in only:
            t0 = time.perf_counter()
            res["cases"][name] = run_case(cfg, name, case)
            print(f"{name}: {time.perf_counter() - t0:.0f} s", json.dumps(
                res["cases"][name]["heldout_mean_rmse_deg"]), flush=True)
    if only is None or "all" in only:
        res["all"] = run_all(cfg)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(res, f, indent=2)
    md = markdown(res)
    with open(os.path.splitext(args.out)[0] + ".md", "w") as f:
        f.write(md)
    print(md)


if __name__ == "__main__":
    main()
