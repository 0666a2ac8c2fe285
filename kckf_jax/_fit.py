"""Learned tuning: fit the filter's parameters by gradient descent on the mocap RMSE.

The loss runs the jitted ``lax.scan`` filter over recorded sessions (``vmap`` over trials padded
to one length), compares the angles with motion capture where there is truth, and optax moves
the unconstrained parameter leaves (noise scales, initial covariance, every Hall sensor's Eq. 1
coefficients) downhill. One jitted training step computes the loss, its gradient and the optax
update. Trials are sharded over all visible devices (``jax.sharding``), long trials are
checkpointed in chunks, and a fit can be interrupted and resumed with nothing lost.
"""

from __future__ import annotations

import functools
import json
import math
import os
import signal
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Bool, Float

from ._fast import CONVERGING_METHODS, STEADY_STEPS, steady_batch
from ._filter import SensorSeries, pad_series, scan_filter
from ._params import _LEAVES, Params, params_to_dict, with_floors
from ._session import Session

RAD2DEG = 180.0 / math.pi


# ----------------------------------------------------------------------------- data
class Batch(eqx.Module):
    """Padded trials for the loss: inputs, ground truth (0 where missing) and its mask.

    ``regular`` (static) records that every trial has the same constant time step, the same
    length and no missing reading: the loss may then take the steady path (``_fast.py``).
    """

    series: SensorSeries
    truth: Float[Array, "B T K"]
    mask: Bool[Array, "B T K"]
    regular: bool = eqx.field(static=True, default=False)


def _is_regular(series: Sequence[SensorSeries], robot) -> bool:
    used = np.asarray(robot.rate_pairs).ravel()
    n = {int(np.shape(s.dt)[0]) for s in series}
    if len(n) != 1:
        return False
    dts = [np.asarray(s.dt, np.float64) for s in series]
    step = dts[0][1] if dts[0].shape[0] > 1 else 0.0
    return bool(step > 0 and all(
        np.max(np.abs(dt[1:] - step)) <= 1e-9 and not np.isnan(np.asarray(s.gyro)[:, used]).any()
        and not np.isnan(np.asarray(s.hall_v)).any() for dt, s in zip(dts, series)))


def make_batch(sessions: Sequence[Session], dtype=None, burn_in_s: float = 0.0,
               multiple_of: int = 1) -> Batch:
    """Stack ``sessions`` into a ``Batch``; the trial count is padded to ``multiple_of``
    (for sharding) with copies of the first trial that have no truth, so they add nothing to
    the loss (and keep a regular batch regular)."""
    if not sessions:
        raise ValueError("no sessions to fit on")
    dtype = dtype or jnp.asarray(0.0).dtype
    series = [SensorSeries(s.dt(), s.gyro, s.hall_v) for s in sessions]
    truths = []
    for s in sessions:
        if not s.has_truth:
            raise ValueError(f"{s.path or 'session'}: no motion capture to fit against")
        tr = s.truth().copy()
        if burn_in_s > 0:
            tr[s.t - s.t[0] < burn_in_s] = np.nan
        truths.append(tr)
    T = max(s.n_steps for s in sessions)
    K = sessions[0].robot.n_angles
    n_pad = (-len(sessions)) % multiple_of
    batch = pad_series(series + [series[0]] * n_pad, length=T)
    truth = np.full((len(series) + n_pad, T, K), np.nan)
    for b, tr in enumerate(truths):
        truth[b, : tr.shape[0]] = tr
    mask = np.isfinite(truth)
    return Batch(
        series=jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), batch),
        truth=jnp.asarray(np.where(mask, truth, 0.0), dtype),
        mask=jnp.asarray(mask),
        regular=_is_regular(series, sessions[0].robot),
    )


#: Above this many trial-steps in one gradient, the scan is checkpointed in chunks: a plain
#: gradient keeps about 2.7 kB per step (x, y, x, y robot), 135 MB at this size.
REMAT_ABOVE_STEPS = 50_000


def auto_chunk(T: int, trials: int = 1) -> int | None:
    """Remat chunk for a gradient through ``trials`` scans of ``T`` steps: about sqrt(T), or
    none when everything fits comfortably in memory (no recomputation, faster to compile)."""
    return None if T * trials <= REMAT_ABOVE_STEPS else int(math.ceil(math.sqrt(T)))


# ----------------------------------------------------------------------------- loss
def per_angle_rmse(params: Params, batch: Batch, method: str = "kckf",
                   remat_chunk: int | None = None) -> tuple[Array, Array]:
    """Pooled RMSE (rad) of every angle over all trials and steps with truth, and the counts.

    A regular batch with the constant Hall noise model takes the steady path (the same
    estimates, ``_fast.py``) for a filter whose covariance converges; anything else the
    sequential scan.

    NaN-free by construction: missing truth is masked before it is subtracted, and the square
    root is guarded, so neither the loss nor its gradient is NaN when truth is missing.
    """
    if (batch.regular and params.hall_noise == "angle" and method in CONVERGING_METHODS
            and batch.truth.shape[1] > STEADY_STEPS):
        est = steady_batch(params, batch.series, method, remat_chunk)
    else:
        est = jax.vmap(lambda s: scan_filter(params, s, method, remat_chunk=remat_chunk)[1])(
            batch.series)
    err = jnp.where(batch.mask, est.angles - batch.truth, 0.0)
    n = jnp.sum(batch.mask, axis=(0, 1))
    mse = jnp.sum(err**2, axis=(0, 1)) / jnp.maximum(n, 1)
    return jnp.sqrt(mse + 1e-18), n


def loss_fn(params: Params, batch: Batch, method: str = "kckf",
            remat_chunk: int | None = None) -> Array:
    """Mean over angles (joints and torso) of the pooled RMSE, rad: the quantity
    ``kckf evaluate`` reports as ``mean_rmse_deg``. Angles without truth are left out."""
    rmse, n = per_angle_rmse(params, batch, method, remat_chunk)
    has = n > 0
    return jnp.sum(jnp.where(has, rmse, 0.0)) / jnp.maximum(jnp.sum(has), 1)


# ----------------------------------------------------------------------------- sharding
def trial_mesh() -> jax.sharding.Mesh:
    """A 1-D mesh over every visible device, axis ``"trials"``."""
    return jax.sharding.Mesh(np.asarray(jax.devices()), ("trials",))


def shard_batch(batch: Batch, mesh: jax.sharding.Mesh | None = None) -> Batch:
    """Place the trials of ``batch`` across the devices of ``mesh`` (parameters stay
    replicated); the trial count must be a multiple of the device count (``make_batch``'s
    ``multiple_of``). On one device this is a no-op placement."""
    mesh = mesh or trial_mesh()
    spec = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("trials"))
    n_dev = mesh.devices.size
    if batch.truth.shape[0] % n_dev:
        raise ValueError(f"shard_batch: {batch.truth.shape[0]} trials do not split over "
                         f"{n_dev} devices; build the batch with make_batch(multiple_of={n_dev})")
    return jax.device_put(batch, spec)


# ----------------------------------------------------------------------------- config
@dataclass(frozen=True)
class FitConfig:
    """How to fit. Defaults: Adam with gradient clipping, early stopping on validation.

    Attributes:
        steps: maximum number of gradient steps.
        learning_rate: Adam step size on the log-parameters.
        clip_norm: global gradient-norm clip (``optax.clip_by_global_norm``).
        hall_noise: noise model of the fitted filter: ``"voltage"`` (measured better on data
            with saturation, see docs/fitting.md) or ``"angle"`` (the paper's constant).
        freeze: names of ``Params`` leaves to keep fixed (e.g. ``("log_p0_angle",)``).
        burn_in_s: leave the first seconds of every trial out of the loss.
        val_every: validate every this many steps (and at the last step).
        patience: stop after this many validations without improvement.
        batch_size: trials per step (default: all), drawn with ``seed``.
        remat_chunk: chunk length for checkpointing the scan (default: about sqrt(T)).
        checkpoint_every: steps between checkpoints (when a checkpoint path is given).
        seed: makes minibatch draws deterministic.
        method: the filter to fit (``"kckf"`` or ``"kf"``).
    """

    steps: int = 200
    learning_rate: float = 0.03
    clip_norm: float = 1.0
    hall_noise: str = "voltage"
    freeze: tuple[str, ...] = ()
    burn_in_s: float = 0.0
    val_every: int = 10
    patience: int = 5
    batch_size: int | None = None
    remat_chunk: int | None = None
    checkpoint_every: int = 10
    seed: int = 0
    method: str = "kckf"

    def __post_init__(self):
        unknown = sorted(set(self.freeze) - set(_LEAVES))
        if unknown:
            raise ValueError(f"FitConfig.freeze: unknown leaf {unknown[0]!r}; expected names "
                             f"from {', '.join(_LEAVES)}")
        if self.steps < 0 or self.val_every < 1 or self.patience < 1:
            raise ValueError("FitConfig: steps must be >= 0, val_every and patience >= 1")
        if self.method not in ("kckf", "kf"):
            raise ValueError(f"FitConfig.method: expected 'kckf' or 'kf', got {self.method!r}")


#: Leaves that sit in an exponent (Eq. 1's ``b`` and ``d``: ``d V`` is about 10, so a 1 %
#: change moves the curve by 10 %) take steps this much smaller than the others.
EXPONENT_LEAVES = ("log_hall_b", "log_hall_d")
EXPONENT_LR_SCALE = 0.1


def _param_labels(params) -> object:
    """``"exponent"`` for the leaves in ``EXPONENT_LEAVES``, ``"default"`` for the others."""
    def label(path, _):
        names = {getattr(k, "name", None) for k in path}
        return "exponent" if names & set(EXPONENT_LEAVES) else "default"

    return jax.tree_util.tree_map_with_path(label, params)


@functools.lru_cache(maxsize=16)
def optimizer(learning_rate: float, clip_norm: float) -> optax.GradientTransformation:
    """Adam after global-norm clipping; smaller steps for the Hall curves' exponents.

    Cached, so that fits with the same settings share one compiled training step."""
    return optax.chain(
        optax.clip_by_global_norm(clip_norm),
        optax.multi_transform(
            {"default": optax.adam(learning_rate),
             "exponent": optax.adam(learning_rate * EXPONENT_LR_SCALE)},
            _param_labels),
    )


def initial_params(sessions: Sequence[Session], config: FitConfig, dtype=None) -> Params:
    """The starting point: the paper defaults with the first session's Hall calibration, the
    configured noise model, and small floors on terms the paper sets to zero."""
    s = sessions[0]
    p = Params.paper_defaults(s.robot, s.hall_models, dtype=dtype)
    p = replace(p, hall_noise=config.hall_noise)
    return with_floors(p)


def _filter_spec(params: Params, freeze: Sequence[str]) -> Params:
    spec = jax.tree_util.tree_map(lambda _: True, params)
    for name in freeze:
        spec = eqx.tree_at(lambda p, n=name: getattr(p, n), spec, False)
    return spec


# ----------------------------------------------------------------------------- training
@dataclass
class FitResult:
    """What a fit gives back: the best parameters and the history of the run."""

    params: Params
    best_step: int
    best_loss_deg: float
    history: list[dict] = field(default_factory=list)
    steps_done: int = 0
    stopped_early: bool = False
    seconds: float = 0.0

    def info(self) -> dict:
        return {"best_step": self.best_step, "best_loss_deg": self.best_loss_deg,
                "steps_done": self.steps_done, "stopped_early": self.stopped_early,
                "seconds": round(self.seconds, 2), "history": self.history}


class FitInterrupted(Exception):
    """The fit was interrupted (Ctrl-C, SIGTERM); its checkpoint holds the last full step."""

    def __init__(self, step: int, checkpoint: str | None):
        self.step, self.checkpoint = step, checkpoint
        where = f"; checkpoint {checkpoint}, continue with --resume" if checkpoint else ""
        super().__init__(f"fit interrupted after step {step}{where}")


@eqx.filter_jit
def _train_step(diff, static, opt_state, batch, idx, opt, method, chunk):
    sub = jax.tree_util.tree_map(lambda x: x[idx], batch) if idx is not None else batch

    def f(d):
        return loss_fn(eqx.combine(d, static), sub, method, chunk)

    loss, grads = eqx.filter_value_and_grad(f)(diff)
    updates, opt_state = opt.update(grads, opt_state, diff)
    return eqx.apply_updates(diff, updates), opt_state, loss


@eqx.filter_jit
def _eval_loss(params, batch, method, chunk):
    return loss_fn(params, batch, method, chunk)


def _ckpt_header(config: FitConfig, step: int, best: dict, history: list, fingerprint: str):
    return {"kind": "kckf-fit-checkpoint/1", "config": asdict(config), "step": step,
            "best": best, "history": history, "fingerprint": fingerprint}


def _save_checkpoint(path: str, header: dict, tree) -> None:
    tmp = f"{path}.tmp"
    with open(tmp, "wb") as f:
        head = json.dumps(header).encode()
        f.write(len(head).to_bytes(8, "little"))
        f.write(head)
        eqx.tree_serialise_leaves(f, tree)
    os.replace(tmp, path)


def _load_checkpoint(path: str, like):
    with open(path, "rb") as f:
        n = int.from_bytes(f.read(8), "little")
        header = json.loads(f.read(n).decode())
        tree = eqx.tree_deserialise_leaves(f, like)
    return header, tree


def fingerprint(sessions: Sequence[Session], val: Sequence[Session]) -> str:
    """Identifies the data of a fit (so ``--resume`` refuses a different set of sessions)."""
    import hashlib

    h = hashlib.sha256()
    for s in list(sessions) + ["|"] + list(val):
        if isinstance(s, str):
            h.update(s.encode())
            continue
        h.update(np.ascontiguousarray(s.t).tobytes())
        h.update(np.ascontiguousarray(s.hall_v[:50]).tobytes())
    return h.hexdigest()[:16]


def fit(
    sessions: Sequence[Session],
    val_sessions: Sequence[Session] = (),
    config: FitConfig = FitConfig(),
    *,
    init: Params | None = None,
    dtype=None,
    checkpoint: str | None = None,
    resume: bool = False,
    callback: Callable[[dict], None] | None = None,
    pad_trials_to: int | None = None,
) -> FitResult:
    """Fit the filter's parameters to motion capture.

    Args:
        sessions: training sessions (one robot layout, with motion capture).
        val_sessions: validation sessions for early stopping and for choosing the best
            parameters (default: the training loss decides).
        config: optimisation settings.
        init: starting parameters (default ``initial_params``).
        dtype: float32 (default without x64) or float64.
        checkpoint: file to checkpoint to; written every ``config.checkpoint_every`` steps and
            when interrupted (Ctrl-C, SIGTERM) or on an error.
        resume: continue from ``checkpoint`` (same data and configuration) with nothing lost:
            the result equals that of an uninterrupted fit.
        callback: called after every step with ``{"step", "loss_deg", "val_deg"}``.
        pad_trials_to: pad the trial count to a multiple of this (with empty trials), so fits
            on data sets of different sizes can share one compiled training step.

    Returns:
        A ``FitResult`` with the best parameters found.
    """
    t0 = time.perf_counter()
    n_dev = jax.device_count()
    multiple = math.lcm(n_dev, pad_trials_to or 1)
    batch = shard_batch(make_batch(sessions, dtype, config.burn_in_s, multiple_of=multiple))
    val = (shard_batch(make_batch(val_sessions, dtype, config.burn_in_s, multiple_of=multiple))
           if val_sessions else None)
    B, T = batch.truth.shape[:2]
    chunk = config.remat_chunk or auto_chunk(T, config.batch_size or B)
    vchunk = None  # the validation loss is not differentiated: no remat needed
    params = init if init is not None else initial_params(sessions, config, dtype)
    if params.robot != sessions[0].robot:
        raise ValueError(f"initial parameters are for joints {params.robot.spec!r}, the "
                         f"sessions have {sessions[0].robot.spec!r}")
    # Parameters live replicated on every device (committed, so that the first and later
    # steps see identically placed inputs and compile once).
    replicated = jax.sharding.NamedSharding(trial_mesh(), jax.sharding.PartitionSpec())
    params = jax.device_put(params, replicated)
    spec = _filter_spec(params, config.freeze)
    diff, static = eqx.partition(params, spec)
    opt = optimizer(config.learning_rate, config.clip_norm)
    opt_state = jax.device_put(opt.init(diff), replicated)
    best = {"step": 0, "loss": math.inf}
    best_params = params
    history: list[dict] = []
    start = 0
    fp = fingerprint(sessions, val_sessions)
    if resume:
        if not checkpoint or not os.path.exists(checkpoint):
            raise ValueError(f"--resume: no checkpoint at {checkpoint}; start the fit without "
                             "--resume")
        header, (diff, opt_state, best_params) = _load_checkpoint(
            checkpoint, (diff, opt_state, best_params))
        if header.get("fingerprint") != fp or header.get("config") != json.loads(
                json.dumps(asdict(config))):
            raise ValueError(f"{checkpoint}: the checkpoint belongs to a fit with other "
                             "sessions or settings; resume with the same command line")
        start, best, history = header["step"], header["best"], header["history"]
    n_trials = len(sessions)
    key = jax.random.PRNGKey(config.seed)
    since_best = sum(1 for h in history if h.get("val_deg") is not None
                     and h["step"] > best["step"])
    stopped_early = False
    step = start

    def save(step_done: int):
        if checkpoint:
            _save_checkpoint(checkpoint, _ckpt_header(config, step_done, best, history, fp),
                             (diff, opt_state, best_params))

    previous = signal.getsignal(signal.SIGTERM)

    def on_term(signum, frame):
        raise KeyboardInterrupt

    in_main = _in_main_thread()
    if in_main:
        signal.signal(signal.SIGTERM, on_term)
    try:
        for step in range(start, config.steps):
            idx = None
            if config.batch_size and config.batch_size < n_trials:
                idx = jax.random.choice(jax.random.fold_in(key, step), n_trials,
                                        (config.batch_size,), replace=False)
            new_diff, new_opt_state, loss = _train_step(diff, static, opt_state, batch, idx,
                                                        opt, config.method, chunk)
            loss_deg = float(loss) * RAD2DEG  # the loss of the parameters before this update
            record = {"step": step + 1, "loss_deg": loss_deg, "val_deg": None}
            # Score the parameters the loss was computed with (those before the update).
            current = eqx.combine(diff, static)
            score = loss_deg
            last = step + 1 == config.steps
            if val is not None and ((step % config.val_every) == 0 or last):
                score = float(_eval_loss(current, val, config.method, vchunk)) * RAD2DEG
                record["val_deg"] = score
            diff, opt_state = new_diff, new_opt_state
            if val is None or record["val_deg"] is not None:
                if score < best["loss"]:
                    best = {"step": step, "loss": score}
                    best_params = current
                    since_best = 0
                elif val is not None:
                    since_best += 1
            history.append(record)
            if callback:
                callback(record)
            if checkpoint and (step + 1) % config.checkpoint_every == 0:
                save(step + 1)
            if val is not None and since_best >= config.patience:
                stopped_early = True
                step += 1
                break
        else:
            step = config.steps
        # The parameters after the last update have not been scored yet.
        final = eqx.combine(diff, static)
        fin = (float(_eval_loss(final, val, config.method, vchunk)) if val is not None
               else float(_eval_loss(final, batch, config.method, chunk))) * RAD2DEG
        if fin < best["loss"]:
            best, best_params = {"step": step, "loss": fin}, final
    except KeyboardInterrupt:
        save(len(history))
        raise FitInterrupted(len(history), checkpoint) from None
    except Exception:
        save(len(history))
        raise
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)
    save(step)
    return FitResult(params=best_params, best_step=int(best["step"]),
                     best_loss_deg=float(best["loss"]), history=history, steps_done=step,
                     stopped_early=stopped_early, seconds=time.perf_counter() - t0)


def _in_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def fit_info(result: FitResult, sessions: Sequence[Session], val: Sequence[Session],
             config: FitConfig) -> dict:
    """Metadata stored with fitted parameters (the ``fit`` entry of the JSON file)."""
    from . import __version__

    return {"kckf_jax": __version__, "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
            "sessions": [s.path for s in sessions], "val_sessions": [s.path for s in val],
            "config": {k: v for k, v in asdict(replace(config)).items()},
            **{k: v for k, v in result.info().items() if k != "history"}}


__all__ = ["Batch", "FitConfig", "FitInterrupted", "FitResult", "auto_chunk", "fit", "fit_info",
           "loss_fn", "make_batch", "params_to_dict", "per_angle_rmse", "shard_batch",
           "trial_mesh"]
