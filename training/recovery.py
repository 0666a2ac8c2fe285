"""Recovery of known parameters by fitting (issue #3).

    python training/recovery.py [--config training/configs/recovery.json] [--loss nll]

Simulates sessions of one robot whose Hall sensors have known true curves (every coefficient
of every sensor perturbed by up to +-10 % from the paper's Eq. 1), fits from the paper
defaults, and compares with the filter that uses the true parameters: held-out RMSE, the fused
Hall measurement per joint (the identifiable part of the calibration), the individual
coefficients, the noise scales and the fitted filter's consistency (the mean NIS of its Hall
innovations on the held-out sessions, with a consistent filter's 95 % interval). ``--loss``:
the fitting loss (``rmse``, ``nll``: no motion capture used, ``rmse+nll``). Writes
``training/results/recovery.json`` (``recovery_<loss>.json`` for another loss).

``--config training/configs/recovery_effects.json``: the sessions also carry sensor effects
(``"effects": {"sim": SimConfig fields, "learn": effects to learn}``; docs/simulator.md
"Sensor effects"), and the fit learns them: each learned effect's value against the
simulator's (``effects_recovery``, as ``training/effects.py`` judges it). Writes
``training/results/recovery_effects.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
from effects import recovery as effect_recovery  # training/effects.py, beside this one

from kckf_jax import (
    FitConfig,
    Params,
    Robot,
    SimConfig,
    consistency_figures,
    enable_cpu_loops,  # noqa: E402
    filter_sessions,
    fit,
    fused_hall_error,
    hall_angle,
    rmse_table,
    simulate,
)

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

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


def scale_and_offset(params: Params, truth: Params, sessions) -> dict:
    """Per Hall sensor, the straight line that maps its true Eq. 1 angle onto ``params``'s over
    every reading of ``sessions`` (``angle = k true + o``): what of a curve was recovered as a
    scale error ``|k - 1|`` (%) and an offset ``|o|`` (deg). Medians and maxima over sensors."""
    v = np.concatenate([s.hall_v for s in sessions])
    fit_c = [np.asarray(x, np.float64) for x in params.hall_coeffs]
    true_c = [np.asarray(x, np.float64) for x in truth.hall_coeffs]
    k, o = [], []
    for j in range(v.shape[1]):
        x = v[np.isfinite(v[:, j]), j]
        a_true = np.asarray(hall_angle(x, *(c[j] for c in true_c)), np.float64)
        a_fit = np.asarray(hall_angle(x, *(c[j] for c in fit_c)), np.float64)
        kj, oj = np.polyfit(a_true, a_fit, 1)
        k.append(abs(kj - 1) * 100)
        o.append(abs(oj) / DEG)
    return {"scale_error_percent": {"median": float(np.median(k)), "max": float(np.max(k))},
            "offset_error_deg": {"median": float(np.median(o)), "max": float(np.max(o))}}


def run(cfg: dict) -> dict:
    robot = Robot.from_spec(cfg["joints"])
    models = perturbed_models(robot, cfg["perturbation"], cfg["perturbation_seed"])

    effects = cfg.get("effects", {})

    def sim(seed):
        return simulate(robot, cfg["kind"], seed=seed, duration_s=cfg["duration_s"],
                        device_seed=cfg["device_seed"], drop_prob=cfg["drop_prob"],
                        true_hall_models=models, config=SimConfig(**effects.get("sim", {})))

    train = [sim(s) for s in cfg["train_seeds"]]
    test = [sim(s) for s in cfg["test_seeds"]]
    truth = true_params(robot, models)
    paper = Params.paper_defaults(robot)
    t0 = time.perf_counter()
    loss = cfg.get("loss", "rmse")
    res = fit(train, (), FitConfig(steps=cfg["steps"], learning_rate=cfg["learning_rate"],
                                   loss=loss, learn=tuple(effects.get("learn", ()))))
    fitted = res.params

    def score(p):
        est = filter_sessions(test, "kckf", p)
        out = rmse_table(test, [e.angles for e in est])
        out["nis"] = consistency_figures(test, "kckf", est, p)[0]["nis"]
        return out

    scores = {k: score(p) for k, p in (("paper", paper), ("true", truth), ("fitted", fitted))}
    a, b, c, d, _ = (np.asarray(x, np.float64) for x in fitted.hall_coeffs)
    fit_coef = np.stack([a / DEG, b, c / DEG, d], axis=1)
    true_coef = np.array([[models[n][k] for k in "abcd"] for n in robot.hall_names])
    rel = 100 * (fit_coef / true_coef - 1)
    out = {
        "config": cfg,
        "fit_seconds": round(time.perf_counter() - t0, 1),
        "loss": loss,
        "heldout_mean_rmse_deg": {k: v["mean_rmse_deg"] for k, v in scores.items()},
        "heldout_nis": {k: v["nis"] for k, v in scores.items()},
        "heldout_rmse_deg": {k: v["rmse_deg"] for k, v in scores.items()},
        "fitted_over_true": scores["fitted"]["mean_rmse_deg"] / scores["true"]["mean_rmse_deg"],
        "fused_hall_error_deg": {
            "fitted": dict(zip(robot.joint_angle_names,
                               fused_hall_error(fitted, truth, test).round(3).tolist())),
            "paper": dict(zip(robot.joint_angle_names,
                              fused_hall_error(paper, truth, test).round(3).tolist())),
        },
        "hall_scale_offset": {"fitted": scale_and_offset(fitted, truth, test),
                              "paper": scale_and_offset(paper, truth, test)},
        "coefficient_error_percent": {
            "max_abs": {k: float(np.max(np.abs(rel[:, i]))) for i, k in enumerate("abcd")},
            "median_abs": {k: float(np.median(np.abs(rel[:, i]))) for i, k in enumerate("abcd")},
        },
        "noise": {
            "sigma_v_fitted": np.asarray(fitted.sigma_hall_v, np.float64).round(4).tolist(),
            "sigma_v_true": TRUE_SIGMA_V,
            "sigma_v_fitted_over_true_range": [
                float(np.min(fitted.sigma_hall_v) / TRUE_SIGMA_V),
                float(np.max(fitted.sigma_hall_v) / TRUE_SIGMA_V)],
            "angle_rw_fitted_deg_rts": (np.asarray(fitted.angle_rw, np.float64) / DEG).round(
                5).tolist(),
            "angle_rw_true_deg_rts": TRUE_ANGLE_RW / DEG,
            "bias_rw_fitted_deg_s_rts": (np.asarray(fitted.bias_rw, np.float64) / DEG).round(
                6).tolist(),
            "bias_rw_true_deg_s_rts": TRUE_BIAS_RW / DEG,
        },
    }
    if effects.get("learn"):
        out["effects_recovery"] = {e: effect_recovery(e, fitted, test[0])
                                   for e in effects["learn"]}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=os.path.join(HERE, "configs", "recovery.json"))
    ap.add_argument("--out", default=None, help="default training/results/recovery[_LOSS].json")
    ap.add_argument("--loss", choices=("rmse", "nll", "rmse+nll"), default=None,
                    help="the fitting loss (default the config's, else rmse)")
    args = ap.parse_args()
    with open(args.config) as f:
        cfg = json.load(f)
    if args.loss:
        cfg["loss"] = args.loss
    loss = cfg.get("loss", "rmse")
    suffix = "" if loss == "rmse" else "_" + loss.replace("+", "_")
    suffix += "_effects" if cfg.get("effects") else ""
    args.out = args.out or os.path.join(HERE, "results", f"recovery{suffix}.json")
    out = run(cfg)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(out, f, indent=2)
    m = out["heldout_mean_rmse_deg"]
    print(f"held-out mean RMSE (deg): paper {m['paper']:.3f}, true parameters {m['true']:.3f}, "
          f"fitted {m['fitted']:.3f} ({100 * out['fitted_over_true']:.0f} % of true)")
    print("fused Hall error per joint (deg):", out["fused_hall_error_deg"])
    print(f"fitted sigma_V / true: {out['noise']['sigma_v_fitted_over_true_range']}; held-out "
          f"NIS {out['heldout_nis']['fitted']}")
    print("coefficient error (%):", out["coefficient_error_percent"])
    print("Hall curves, scale and offset error:", out["hall_scale_offset"])
    for name, r in out.get("effects_recovery", {}).items():
        print(f"effect {name}: within 25 %: {r['within_25']}; relative errors "
              f"{r['relative_error']}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
