"""Held-out gain of learned tuning, and the choice of the Hall noise model (issue #3).

    python training/heldout_gain.py [--config training/configs/heldout_gain.json]

For each data set (bench cyclic motion, human bending) of one simulated robot: fit the KCKF on
training sessions with each Hall noise model ("voltage": angle noise = |d theta/dV| sigma_V,
"angle": the paper's constant), then score the paper-default and the fitted filters per joint
on test sessions the fit never saw. Writes ``training/results/heldout_gain.json`` and
``training/results/heldout_gain.md``.
"""

from __future__ import annotations

import argparse
import json
import os

from kckf_jax import (
    FitConfig,
    Robot,
    enable_cpu_loops,  # noqa: E402
    filter_sessions,
    fit,
    rmse_table,
    simulate,
)

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

HERE = os.path.dirname(os.path.abspath(__file__))


def run(cfg: dict) -> dict:
    robot = Robot.from_spec(cfg["joints"])
    out = {"config": cfg, "datasets": {}}
    for name, ds in cfg["datasets"].items():
        def sim(seed, ds=ds):
            return simulate(robot, ds["kind"], seed=seed, duration_s=cfg["duration_s"],
                            device_seed=ds["device_seed"], drop_prob=cfg["drop_prob"])

        train = [sim(s) for s in ds["train_seeds"]]
        test = [sim(s) for s in ds["test_seeds"]]
        rows = {"paper": rmse_table(test, [e.angles for e in filter_sessions(test, "kckf")])}
        fits = {}
        for noise in cfg["noise_models"]:
            res = fit(train, (), FitConfig(steps=cfg["steps"], learning_rate=cfg["learning_rate"],
                                           hall_noise=noise))
            rows[f"fitted_{noise}"] = rmse_table(
                test, [e.angles for e in filter_sessions(test, "kckf", res.params)])
            fits[noise] = {"seconds": round(res.seconds, 1), "train_rmse_deg": res.best_loss_deg}
        paper = rows["paper"]["mean_rmse_deg"]
        out["datasets"][name] = {
            "rmse_deg": {k: v["rmse_deg"] for k, v in rows.items()},
            "mean_rmse_deg": {k: v["mean_rmse_deg"] for k, v in rows.items()},
            "ratio_to_paper": {k: v["mean_rmse_deg"] / paper for k, v in rows.items()},
            "fits": fits,
        }
    return out


def markdown(res: dict) -> str:
    lines = []
    for name, ds in res["datasets"].items():
        cols = list(ds["rmse_deg"])
        lines += [f"### {name}", "", "| angle | " + " | ".join(cols) + " |",
                  "| --- |" + " ---: |" * len(cols)]
        for angle in ds["rmse_deg"]["paper"]:
            lines.append(f"| {angle} | " + " | ".join(
                f"{ds['rmse_deg'][c][angle]:.3f}" for c in cols) + " |")
        lines.append("| mean | " + " | ".join(f"{ds['mean_rmse_deg'][c]:.3f}" for c in cols)
                     + " |")
        lines.append("| ratio to paper | " + " | ".join(
            f"{100 * ds['ratio_to_paper'][c]:.0f} %" for c in cols) + " |")
        lines.append("")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=os.path.join(HERE, "configs", "heldout_gain.json"))
    ap.add_argument("--out", default=os.path.join(HERE, "results", "heldout_gain.json"))
    args = ap.parse_args()
    with open(args.config) as f:
        cfg = json.load(f)
    res = run(cfg)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(res, f, indent=2)
    md = markdown(res)
    with open(os.path.splitext(args.out)[0] + ".md", "w") as f:
        f.write(md)
    print(md)


if __name__ == "__main__":
    main()
