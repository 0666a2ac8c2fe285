"""Offline analysis and tuning without motion capture (issue #18): the smoother and the losses.

    python training/offline.py [--config training/configs/offline.json]

For each data set (bench cyclic motion, human bending) of one simulated robot: fit the KCKF on
training sessions with each loss (``rmse``: against motion capture; ``nll``: the likelihood of
the Hall readings, no motion capture; ``rmse+nll``), then score the paper-default and every
fitted filter on test sessions the fits never saw, filtered and smoothed (the RTS smoother),
with the mean NIS of the Hall innovations and a consistent filter's 95 % interval.

The fixed-lag trade-off (what a live controller would gain from waiting): the estimate of row
``t`` given the readings up to ``t + lag``, for rows sampled over the test sessions (each
sampled row a copy of its session whose rows after ``t + lag`` carry nothing: no time step,
no reading, which the smoother passes through unchanged), smoothed, against motion capture;
lag 0 is the filter. Writes ``training/results/offline.json`` and
``training/results/offline.md``.
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from kckf_jax import (
    FitConfig,
    Robot,
    SensorSeries,
    consistency_figures,
    enable_cpu_loops,  # noqa: E402
    filter_sessions,
    fit,
    pad_series,
    rmse_table,
    session_series,
    simulate,
    smooth_batch,
)

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

HERE = os.path.dirname(os.path.abspath(__file__))


def score(test, params) -> dict:
    out = {}
    for smoothed in (False, True):
        est = filter_sessions(test, "kckf", params, smooth=smoothed)
        out["smoothed" if smoothed else "filtered"] = rmse_table(
            test, [e.angles for e in est])["mean_rmse_deg"]
        if not smoothed:
            out["nis"] = consistency_figures(test, "kckf", est, params)[0]["nis"]
    out["smoothed_over_filtered"] = out["smoothed"] / out["filtered"]
    return out


def fixed_lag(test, params, lags_rows, per_session: int, burn_in_rows: int, seed: int) -> dict:
    """Mean over angles of the RMSE (deg) of row ``t``'s estimate given the readings up to
    ``t + lag``, per lag, at ``per_session`` rows drawn from each test session."""
    rng = np.random.default_rng(seed)
    err = {lag: [] for lag in lags_rows}
    for s in test:
        base = session_series(s, np.float64)
        parts = (base.dt, base.gyro, base.hall_v)
        truth = s.truth()
        ok = np.flatnonzero(np.isfinite(truth).all(axis=1))
        ok = ok[(ok >= burn_in_rows) & (ok < s.n_steps - max(lags_rows) - 1)]
        rows = rng.choice(ok, size=min(per_session, ok.size), replace=False)
        for lag in lags_rows:
            cut = []
            for t in rows:
                end = t + lag + 1
                dt, gyro, hall = (np.array(x, np.float64) for x in parts)
                dt[end:], gyro[end:], hall[end:] = 0.0, np.nan, np.nan
                cut.append(SensorSeries(dt, gyro, hall))
            est = np.asarray(smooth_batch(params, pad_series(cut)).angles, np.float64)
            err[lag].append(est[np.arange(len(rows)), rows] - truth[rows])
    return {int(lag): float(np.mean(np.sqrt(np.mean(np.concatenate(e) ** 2, axis=0))) * 180
                            / np.pi) for lag, e in err.items()}


def run(cfg: dict) -> dict:
    robot = Robot.from_spec(cfg["joints"])
    out = {"config": cfg, "datasets": {}}
    for name, ds in cfg["datasets"].items():
        def sim(seed, ds=ds):
            return simulate(robot, ds["kind"], seed=seed, duration_s=cfg["duration_s"],
                            device_seed=ds["device_seed"], drop_prob=cfg["drop_prob"])

        train = [sim(s) for s in ds["train_seeds"]]
        test = [sim(s) for s in ds["test_seeds"]]
        rows = {"paper": score(test, None)}
        fits = {}
        for loss in cfg["losses"]:
            res = fit(train, (), FitConfig(steps=cfg["steps"], learning_rate=cfg["learning_rate"],
                                           loss=loss))
            rows[loss] = score(test, res.params)
            if loss == "rmse":
                fitted_rmse = res.params
            fits[loss] = {"seconds": round(res.seconds, 1),
                          "sigma_v_mv": (np.asarray(res.params.sigma_hall_v, np.float64)
                                         * 1e3).round(1).tolist()}
        paper = rows["paper"]["filtered"]
        for r in rows.values():
            r["filtered_over_paper"] = r["filtered"] / paper
        lag = cfg["fixed_lag"]
        rate = 1.0 / float(np.median(test[0].dt()[1:]))
        lags = [int(round(ms * 1e-3 * rate)) for ms in lag["lags_ms"]]
        lag_rmse = fixed_lag(test, fitted_rmse, lags, lag["rows_per_session"],
                             int(lag["burn_in_s"] * rate), lag["seed"])
        out["datasets"][name] = {"scores": rows, "fits": fits, "fixed_lag": {
            "params": "fitted (rmse)", "rows_scored": lag["rows_per_session"] * len(test),
            "mean_rmse_deg_by_lag_ms": {str(ms): lag_rmse[r] for ms, r in
                                        zip(lag["lags_ms"], lags)}}}
    return out


def markdown(res: dict) -> str:
    lines = []
    for name, ds in res["datasets"].items():
        lines += [f"### {name}", "",
                  "| parameters | filtered mean RMSE (deg) | smoothed (deg) | smoothed / filtered "
                  "| filtered / paper's | NIS (95 % interval) |",
                  "| --- | ---: | ---: | ---: | ---: | --- |"]
        for k, r in ds["scores"].items():
            n = r["nis"]
            lines.append(f"| {k} | {r['filtered']:.3f} | {r['smoothed']:.3f} | "
                         f"{r['smoothed_over_filtered']:.2f} | {r['filtered_over_paper']:.2f} | "
                         f"{n['mean']:.2f} ({n['lo95']:.2f}-{n['hi95']:.2f}) |")
        lines.append("")
        for k, f in ds["fits"].items():
            lines.append(f"- fit `{k}`: {f['seconds']} s; sigma_V {f['sigma_v_mv']} mV")
        fl = ds["fixed_lag"]
        lines += ["", f"Fixed lag ({fl['params']} parameters, {fl['rows_scored']} rows): "
                  "mean RMSE (deg) by lag: " + ", ".join(
                      f"{ms} ms {v:.3f}" for ms, v in fl["mean_rmse_deg_by_lag_ms"].items()), ""]
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=os.path.join(HERE, "configs", "offline.json"))
    ap.add_argument("--out", default=os.path.join(HERE, "results", "offline.json"))
    args = ap.parse_args()
    with open(args.config) as f:
        cfg = json.load(f)
    res = run(cfg)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(res, f, indent=2)
    md = markdown(res)
    with open(os.path.splitext(args.out)[0] + ".md", "w") as f:
        f.write(md + "\n")
    print(md)


if __name__ == "__main__":
    main()
