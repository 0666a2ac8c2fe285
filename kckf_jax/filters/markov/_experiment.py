"""The Markovian filter's experiments: the paper's Fig. 9 (mean error of the per-segment KF and
the Markovian KF under 0-20 % parameter uncertainty) and the gradient fit of Table 2, both on
simulated gait (docs/other_filters.md)."""

from __future__ import annotations

import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._fitting._train import AbstractLoss, TrainConfig, train
from ._filter import (
    DEG,
    METHODS,
    N_SEG,
    N_SYSTEM,
    PUBLISHED_KF_DEG,
    PUBLISHED_MKF_DEG,
    SEGMENTS,
    MarkovParams,
    _check_method,
    markov_batch,
    markov_loss,
    mean_error_deg,
    perturb_markov_params,
)
from ._sim import GaitConfig, gait_series, matched_markov_params, simulate_gait

LEVELS = (0, 5, 10, 15, 20)


def uncertainty_factors(rng: np.random.Generator, level_pct: float, runs: int) -> np.ndarray:
    """Factors (runs, ``N_SYSTEM``) uniform in ``[1 - level, 1 + level]``: each run's filter
    parameters deviate from their nominal values by up to ``level_pct`` percent."""
    u = rng.uniform(-1.0, 1.0, size=(runs, N_SYSTEM))
    return 1.0 + level_pct / 100.0 * u


def markov_experiment(runs: int = 20, seed: int = 0, *, levels: Sequence[float] = LEVELS,
                      config: GaitConfig | None = None,
                      params: MarkovParams | None = None) -> dict:
    """The paper's Fig. 9 on simulated gait: mean estimation error (deg) of the per-segment KF
    and of the Markovian KF for each parameter-uncertainty level.

    ``runs`` trials are simulated once (``simulate_gait(runs, seed, config)``, common to every
    level). At level ``L`` each run's filter parameters that form the system matrices
    (``Phi``, ``Q``, ``R``: sigma_g, sigma_bg, sigma_a, tau_g, sigma_enc) deviate from the true
    ones (``params``, default ``matched_markov_params(config)``) by independent uniform factors
    in ``[1 - L, 1 + L]``, the same draw for both filters. Both filters also run once with
    the paper's Table 2 as printed (``details["table2"]``). Every run of every level goes
    through one ``vmap``-ed, jitted scan per filter.

    Returns:
        ``{"levels", "kf_deg", "mkf_deg", "ratio", "published_ratio", "our_ratio",
        "details"}``: mean absolute errors per level, their ratio mkf / kf, the published
        real-data ratio 0.94 / 1.20 (Nogueira et al. 2017) and ours at 0 % uncertainty;
        ``details`` has RMS errors, per-segment errors, update rates, the Table 2 run, the
        nominal parameters and the run time.

    Example:
        >>> out = markov_experiment(runs=2)
        >>> all(m < k for m, k in zip(out["mkf_deg"], out["kf_deg"]))
        True
    """
    if runs < 1:
        raise ValueError(f"markov_experiment: runs must be >= 1, got {runs}")
    t0 = time.perf_counter()
    levels = [int(x) if float(x).is_integer() else float(x) for x in levels]
    trials = simulate_gait(runs, seed, config)
    params = params or matched_markov_params(config)
    dtype = params.log_tau_g.dtype
    rng = np.random.default_rng([seed, 9])
    factors = np.concatenate([uncertainty_factors(rng, lv, runs) for lv in levels])
    n_lv = len(levels)
    n_sets = n_lv + 1  # every level, then Table 2
    batch = jax.vmap(lambda f: perturb_markov_params(params, f))(jnp.asarray(factors, dtype))
    table2 = MarkovParams.table2(dtype)
    batch = jax.tree_util.tree_map(
        lambda b, t: jnp.concatenate([b, jnp.broadcast_to(t, (runs,) + t.shape)]),
        batch, table2)
    series = jax.tree_util.tree_map(lambda a: jnp.tile(a, (n_sets,) + (1,) * (a.ndim - 1)),
                                    gait_series(trials, dtype))
    truth = jnp.tile(jnp.asarray(trials.angles, dtype), (n_sets, 1, 1))
    out: dict = {"levels": levels}
    details: dict = {"runs": runs, "seed": seed, "n_steps": int(trials.dt.shape[1]),
                     "rate_hz": float(1.0 / trials.dt[0, 1]), "table2": {},
                     "nominal_params": params.to_dict()}
    for method in METHODS:
        est = markov_batch(batch, series, method, batched_params=True)
        err = np.asarray(mean_error_deg(est.angles, truth), np.float64).reshape(n_sets, runs)
        rms = np.sqrt(np.asarray(jnp.mean((est.angles - truth) ** 2, axis=(1, 2)),
                                 np.float64)).reshape(n_sets, runs) / DEG
        seg = (np.asarray(jnp.mean(jnp.abs(est.angles - truth), axis=1), np.float64)
               / DEG).reshape(n_sets, runs, N_SEG).mean(axis=1)
        upd = np.asarray(jnp.mean(est.updated[:runs], axis=(0, 1)), np.float64)
        out[f"{method}_deg"] = err[:n_lv].mean(axis=1).tolist()
        details[method] = {
            "rmse_deg": rms[:n_lv].mean(axis=1).tolist(),
            "std_over_runs_deg": err[:n_lv].std(axis=1).tolist(),
            "per_segment_deg": {s: seg[:n_lv, i].tolist() for i, s in enumerate(SEGMENTS)},
            "update_fraction": {s: float(upd[i]) for i, s in enumerate(SEGMENTS)},
        }
        details["table2"][f"{method}_deg"] = float(err[n_lv].mean())
        details["table2"][f"{method}_per_segment_deg"] = {
            s: float(seg[n_lv, i]) for i, s in enumerate(SEGMENTS)}
        if method == "mkf":
            modes = np.asarray(est.mode[:runs])
            details["mode_occupancy"] = {s: float(np.mean(modes == i))
                                         for i, s in enumerate(SEGMENTS)}
            details["no_reliable_fraction"] = float(
                1.0 - np.asarray(est.updated[:runs]).any(axis=-1).mean())
    out["ratio"] = [m / k for m, k in zip(out["mkf_deg"], out["kf_deg"])]
    out["published_ratio"] = PUBLISHED_MKF_DEG / PUBLISHED_KF_DEG
    out["our_ratio"] = out["ratio"][levels.index(0)] if 0 in levels else float(
        np.mean(out["ratio"]))
    details["table2"]["ratio"] = details["table2"]["mkf_deg"] / details["table2"]["kf_deg"]
    details["seconds"] = round(time.perf_counter() - t0, 2)
    out["details"] = details
    return out


class MarkovLoss(AbstractLoss):
    """``markov_loss`` for the training loop; ``batch = (series, truth)``."""

    method: str = eqx.field(static=True)

    def __call__(self, params, batch):
        series, truth = batch
        return markov_loss(params, series, truth, self.method)


def fit_markov(
    method: str = "mkf",
    *,
    train_trials: int = 8,
    test_trials: int = 8,
    steps: int = 150,
    learning_rate: float = 0.05,
    seed: int = 0,
    config: GaitConfig | None = None,
    params: MarkovParams | None = None,
    dtype=None,
) -> dict:
    """Fit the Table 2 parameters (and the encoder noise and initial covariance) of ``method``
    by gradient descent (optax Adam on the log-parameters, the package's one training loop,
    ``_train.train``) on simulated gait, and report the held-out error before and after.

    The loss is the RMS angle error (rad) over ``train_trials`` trials simulated with ``seed``;
    the held-out trials come from another seed; the parameters after the last step are kept.
    ``zeta`` is a threshold (zero gradient) and stays at its starting value; the paper fitted
    the same table with a genetic algorithm.

    Returns:
        ``{"method", "steps", "params" (the fitted MarkovParams), "fitted" (physical values),
        "loss_deg" (training RMS per step), "heldout_table2_deg", "heldout_fitted_deg" (mean
        absolute error, the experiment's figure), "heldout_table2_rmse_deg",
        "heldout_fitted_rmse_deg", "gain" (fraction of the held-out error removed),
        "seconds"}``.

    Example:
        >>> out = fit_markov(train_trials=2, test_trials=2, steps=5, learning_rate=0.1,
        ...                  config=GaitConfig(duration_s=8.0))
        >>> out["heldout_fitted_deg"] < out["heldout_table2_deg"]
        True
    """
    _check_method(method)
    t0 = time.perf_counter()
    dtype = dtype or jnp.asarray(0.0).dtype
    start = (params or MarkovParams.table2()).astype(dtype)
    train_set = simulate_gait(train_trials, seed, config)
    test = simulate_gait(test_trials, seed + 10_000, config)
    s_train, s_test = gait_series(train_set, dtype), gait_series(test, dtype)
    y_train = jnp.asarray(train_set.angles, dtype)
    y_test = jnp.asarray(test.angles, dtype)
    result = train(MarkovLoss(method), start, (s_train, y_train), train_trials,
                   TrainConfig(steps=steps, learning_rate=learning_rate, clip_norm=None,
                               keep="last"))
    p = result.params

    def heldout(q):
        est = markov_batch(q, s_test, method)
        mae = float(jnp.mean(mean_error_deg(est.angles, y_test)))
        rmse = float(jnp.sqrt(jnp.mean((est.angles - y_test) ** 2))) / DEG
        return mae, rmse

    before, before_rmse = heldout(start)
    after, after_rmse = heldout(p)
    return {
        "method": method, "steps": steps, "params": p, "fitted": p.to_dict(),
        "loss_deg": [h["loss_deg"] for h in result.history], "heldout_table2_deg": before,
        "heldout_fitted_deg": after, "heldout_table2_rmse_deg": before_rmse,
        "heldout_fitted_rmse_deg": after_rmse, "gain": 1.0 - after / before,
        "seconds": round(time.perf_counter() - t0, 2),
    }
