"""Recovery of known parameters by fitting (issue #3).

    python training/recovery.py [--config training/configs/recovery.json]

Simulates sessions of one robot whose Hall sensors have known true curves (every coefficient
of every sensor perturbed by up to +-10 % from the paper's Eq. 1), fits from the paper
defaults, and compares with the filter that uses the true parameters: held-out RMSE, the fused
Hall measurement per joint (the identifiable part of the calibration), the individual
coefficients and the noise scales. Writes ``training/results/recovery.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from kckf_jax import (
    FitConfig,
    Params,
    Robot,
    filter_sessions,
    fit,
    fused_hall_error,
    rmse_table,
    simulate,
)

DEG = np.pi / 180.0

HERE = os.path.dirname(os.path.abspath(__file__))

#: The simulator's truth, in the filter's terms (docs/simulator.md): a gyro difference has
#: sqrt(2) times one gyro's white noise (3.8 mdps/sqrt(Hz)) and bias random walk (2e-4
#: dps/sqrt(s)); Hall noise is 30 mV; the paper's Eq. 13 term is absent (q -> 0).
TRUE_ANGLE_RW = np.sqrt(2) * 3.8e-3 * DEG
TRUE_BIAS_RW = np.sqrt(2) * 2e-4 * DEG
TRUE_SIGMA_V = 0.03


def perturbed_models(robot: Robot, frac: float, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    models = {}
    for name, sign in zip(robot.hall_names, robot.hall_side_sign):
        f = 1 + rng.uniform(-frac, frac, 4)
        models[name] = {"a": 0.07 * f[0], "b": 2.87 * f[1], "c": 2.22e5 * f[2],
                        "d": 8.43 * f[3], "sign": sign, "unit": "deg"}
    return models


def true_params(robot: Robot, models: dict) -> Params:
    return Params.from_physical(robot, hall_models=models, hall_noise="voltage",
                                sigma_hall_v=TRUE_SIGMA_V, sigma_hall=0.05 * DEG, q=1e-12,
                                angle_rw=TRUE_ANGLE_RW, bias_rw=TRUE_BIAS_RW)


def run(cfg: dict) -> dict:
    robot = Robot.from_spec(cfg["joints"])
    models = perturbed_models(robot, cfg["perturbation"], cfg["perturbation_seed"])

    def sim(seed):
        return simulate(robot, cfg["kind"], seed=seed, duration_s=cfg["duration_s"],
                        device_seed=cfg["device_seed"], drop_prob=cfg["drop_prob"],
                        true_hall_models=models)

    train = [sim(s) for s in cfg["train_seeds"]]
    test = [sim(s) for s in cfg["test_seeds"]]
    truth = true_params(robot, models)
    paper = Params.paper_defaults(robot)
    t0 = time.perf_counter()
    res = fit(train, (), FitConfig(steps=cfg["steps"], learning_rate=cfg["learning_rate"]))
    fitted = res.params

    def score(p):
        return rmse_table(test, [e.angles for e in filter_sessions(test, "kckf", p)])

    scores = {k: score(p) for k, p in (("paper", paper), ("true", truth), ("fitted", fitted))}
    a, b, c, d, _ = (np.asarray(x, np.float64) for x in fitted.hall_coeffs)
    fit_coef = np.stack([a / DEG, b, c / DEG, d], axis=1)
    true_coef = np.array([[models[n][k] for k in "abcd"] for n in robot.hall_names])
    rel = 100 * (fit_coef / true_coef - 1)
    return {
        "config": cfg,
        "fit_seconds": round(time.perf_counter() - t0, 1),
        "heldout_mean_rmse_deg": {k: v["mean_rmse_deg"] for k, v in scores.items()},
        "heldout_rmse_deg": {k: v["rmse_deg"] for k, v in scores.items()},
        "fitted_over_true": scores["fitted"]["mean_rmse_deg"] / scores["true"]["mean_rmse_deg"],
        "fused_hall_error_deg": {
            "fitted": dict(zip(robot.joint_angle_names,
                               fused_hall_error(fitted, truth, test).round(3).tolist())),
            "paper": dict(zip(robot.joint_angle_names,
                              fused_hall_error(paper, truth, test).round(3).tolist())),
        },
        "coefficient_error_percent": {
            "max_abs": {k: float(np.max(np.abs(rel[:, i]))) for i, k in enumerate("abcd")},
            "median_abs": {k: float(np.median(np.abs(rel[:, i]))) for i, k in enumerate("abcd")},
        },
        "noise": {
            "sigma_v_fitted": np.asarray(fitted.sigma_hall_v, np.float64).round(4).tolist(),
            "sigma_v_true": TRUE_SIGMA_V,
            "angle_rw_fitted_deg_rts": (np.asarray(fitted.angle_rw, np.float64) / DEG).round(
                5).tolist(),
            "angle_rw_true_deg_rts": TRUE_ANGLE_RW / DEG,
            "bias_rw_fitted_deg_s_rts": (np.asarray(fitted.bias_rw, np.float64) / DEG).round(
                6).tolist(),
            "bias_rw_true_deg_s_rts": TRUE_BIAS_RW / DEG,
        },
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=os.path.join(HERE, "configs", "recovery.json"))
    ap.add_argument("--out", default=os.path.join(HERE, "results", "recovery.json"))
    args = ap.parse_args()
    with open(args.config) as f:
        cfg = json.load(f)
    out = run(cfg)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(out, f, indent=2)
    m = out["heldout_mean_rmse_deg"]
    print(f"held-out mean RMSE (deg): paper {m['paper']:.3f}, true parameters {m['true']:.3f}, "
          f"fitted {m['fitted']:.3f} ({100 * out['fitted_over_true']:.0f} % of true)")
    print("fused Hall error per joint (deg):", out["fused_hall_error_deg"])
    print("coefficient error (%):", out["coefficient_error_percent"])
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
