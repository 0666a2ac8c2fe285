"""Learned tuning of the KCKF: its parameters fitted by gradient descent on the mocap RMSE.

The loss runs the filter over recorded sessions (trials padded to one length, one batch),
compares the angles with motion capture where there is truth, and the one training loop
(``_train.train``) moves the unconstrained parameter leaves (noise scales, initial covariance,
every Hall sensor's Eq. 1 coefficients) downhill. The path that computes the filter is chosen
once on the concrete data and starting parameters (``choose_path``: the steady path on a
regular batch), and re-checked on the concrete parameters before every step. Trials are
sharded over all visible devices (``jax.sharding``), long trials are checkpointed in chunks,
and a fit can be interrupted and resumed with nothing lost.
"""

from __future__ import annotations

import importlib.metadata
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._models._classes import (
    KALMAN_METHODS,
    MODELS,
    AbstractModel,
    init_state,
    method_name,
    register_model,
)
from .._models._effects import EFFECT_OF_LEAF, EFFECTS, STEP_SCALES, angle_rates
from .._models._fault_policy import FaultPolicy
from .._models._kernel import SensorSeries
from .._models._params import ALL_LEAVES, Params, with_floors
from .._paths import AbstractPath, Auto, Sequential, as_path, regular_step
from .._paths._likelihood import hall_nll
from .._paths._run import choose_path, screened
from .._paths._smooth import smooth_batch
from .._readings._batching import pad_series
from .._readings._gaps import GapPolicy
from .._sessions._session import Session, split_at_gaps
from ._mounting import estimate_mounting
from ._train import (
    AbstractLoss,
    FitInterrupted,
    FitResult,
    TrainConfig,
    train,
)

RAD2DEG = 180.0 / math.pi
EXPONENT_LEAVES = ("log_hall_b", "log_hall_d")  # in Eq. 1's exponents: smaller Adam steps


# ----------------------------------------------------------------------------- data
class Batch(eqx.Module):
    """Padded trials for the loss: inputs, ground truth (0 where missing) and its mask."""

    series: SensorSeries
    truth: Float[Array, "B T K"]
    mask: Bool[Array, "B T K"]


def package_version() -> str:
    """kckf-jax's version as installed (``pyproject.toml``), stamped on every checkpoint."""
    try:
        return importlib.metadata.version("kckf-jax")
    except importlib.metadata.PackageNotFoundError:  # a source tree on ``sys.path``
        return "0+unknown"


def make_batch(sessions: Sequence[Session], dtype=None, burn_in_s: float = 0.0,
               multiple_of: int = 1, gaps: GapPolicy = GapPolicy(), length: int | None = None,
               trials: int | None = None, need_truth: bool = True) -> Batch:
    """Stack ``sessions`` into a ``Batch``; the trial count is padded to ``multiple_of``
    (for sharding), or to ``trials``, with copies of the first trial that have no truth, so
    they add nothing to the loss (and keep a regular batch regular), and the rows to the
    longest trial, or to ``length``. A session with a gap where ``gaps`` restarts the filter
    becomes one trial per stretch (``split_at_gaps``), as every command filters it;
    ``len(trial_sessions(sessions, gaps))`` counts them. ``need_truth=False`` accepts
    sessions without motion capture (the likelihood loss)."""
    if not sessions:
        raise ValueError("no sessions to fit on")
    dtype = dtype or jnp.asarray(0.0).dtype
    for s in sessions:
        if need_truth and not s.has_truth:
            raise ValueError(f"{s.path or 'session'}: no motion capture to fit against (the "
                             "likelihood loss, --loss nll, needs none)")
    pieces = trial_sessions(sessions, gaps)
    series = [SensorSeries(s.dt(), s.gyro, s.hall_v) for s in pieces]
    truths = []
    for s, whole in zip(pieces, _origins(sessions, gaps)):
        tr = s.truth().copy()
        if burn_in_s > 0:
            tr[s.t - whole.t[0] < burn_in_s] = np.nan
        truths.append(tr)
    sessions = pieces
    T = max(s.n_steps for s in sessions) if length is None else length
    K = sessions[0].robot.n_angles
    n_pad = (-len(sessions)) % multiple_of if trials is None else trials - len(sessions)
    if n_pad < 0:
        raise ValueError(f"make_batch: {len(sessions)} trials, more than trials={trials}")
    batch = pad_series(series + [series[0]] * n_pad, length=T)
    truth = np.full((len(series) + n_pad, T, K), np.nan)
    for b, tr in enumerate(truths):
        truth[b, : tr.shape[0]] = tr
    mask = np.isfinite(truth)
    return Batch(
        series=jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), batch),
        truth=jnp.asarray(np.where(mask, truth, 0.0), dtype),
        mask=jnp.asarray(mask),
    )


def trial_sessions(sessions: Sequence[Session], gaps: GapPolicy = GapPolicy()) -> list[Session]:
    """The trials of a batch: every session, cut where ``gaps`` restarts the filter."""
    return [p for s in sessions for p in split_at_gaps(s, gaps)]


def _origins(sessions: Sequence[Session], gaps: GapPolicy) -> list[Session]:
    return [s for s in sessions for _ in split_at_gaps(s, gaps)]


#: Above this many trial-steps in one gradient, the sequential scan is checkpointed in chunks.
#: Unchunked, it already checkpoints every row and keeps about 445 B per trial-step (x, y, x, y
#: robot, float32: XLA temporaries 133 MB at 3 x 100,000 rows), the same bound as the 2.7 kB of
#: every intermediate gave at the old 50,000; chunks halve it and cost 14 to 47 % more time.
REMAT_ABOVE_STEPS = 300_000


def auto_chunk(T: int, trials: int = 1) -> int | None:
    """Remat chunk for a gradient through ``trials`` scans of ``T`` steps: about sqrt(T), or
    none when everything fits comfortably in memory (no recomputation, faster to compile)."""
    return None if T * trials <= REMAT_ABOVE_STEPS else int(math.ceil(math.sqrt(T)))


# ----------------------------------------------------------------------------- loss
def per_angle_rmse(params: Params, batch: Batch, method: str | AbstractModel = "kckf",
                   remat_chunk: int | None = None, path: str | AbstractPath | None = None,
                   smooth: bool = False) -> tuple[Array, Array]:
    """Pooled RMSE (rad) of every angle over all trials and steps with truth, and the counts.

    ``path`` computes the filter (default ``Auto`` with ``Sequential(remat_chunk)``: on
    concrete inputs the fastest that applies, under a transformation the sequential scan;
    ``fit`` chooses it on the concrete data beforehand, and so can a caller:
    ``choose_path(params, batch.series).path``). ``smooth``: the fixed-interval smoothed
    estimates are scored (``smooth_batch``, laid out as ``path`` lays out its smoother), the
    output an offline user reads.

    A learned clock offset (``Params.effects``, ``"offset"``: the motion capture lags the
    sensors by ``tau``) compares each estimate, moved back by ``tau`` along the gyros' rate,
    with the truth: ``angle(t - tau) ~ angle(t) - tau * rate(t)``.

    NaN-free by construction: missing truth is masked before it is subtracted, and the square
    root is guarded, so neither the loss nor its gradient is NaN when truth is missing.
    """
    method = method_name(method)
    path = Auto().for_loss(remat_chunk, gradient=False) if path is None else as_path(path)
    if smooth:
        angles = smooth_batch(params, batch.series, method, path=path).angles
    else:
        n_trials = batch.truth.shape[0]
        state = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n_trials,) + x.shape),
                                       init_state(params, method))
        angles = path.run(params, batch.series, method, state)[1].angles
    if params.effects is not None and params.effects.uses("offset"):
        rate = angle_rates(params.robot, jnp.asarray(batch.series.gyro))
        rate = jnp.where(jnp.isfinite(rate), rate, 0.0).astype(angles.dtype)
        angles = angles - params.effects.time_offset_s * rate
    err = jnp.where(batch.mask, angles - batch.truth, 0.0)
    n = jnp.sum(batch.mask, axis=(0, 1))
    mse = jnp.sum(err**2, axis=(0, 1)) / jnp.maximum(n, 1)
    return jnp.sqrt(mse + 1e-18), n


def loss_fn(params: Params, batch: Batch, method: str | AbstractModel = "kckf",
            remat_chunk: int | None = None, path: str | AbstractPath | None = None,
            smooth: bool = False) -> Array:
    """Mean over angles (joints and torso) of the pooled RMSE, rad: the quantity
    ``kckf evaluate`` reports as ``mean_rmse_deg``. Angles without truth are left out.
    ``path`` and ``smooth`` as for ``per_angle_rmse``."""
    method = method_name(method)
    rmse, n = per_angle_rmse(params, batch, method, remat_chunk, path, smooth)
    has = n > 0
    return jnp.sum(jnp.where(has, rmse, 0.0)) / jnp.maximum(jnp.sum(has), 1)


class RmseLoss(AbstractLoss):
    """``loss_fn`` on a fixed path, for the training loop. ``refresh`` re-checks the steady
    path's convergence on the concrete parameters before every step (they move during a fit)
    and falls back to the sequential path, for good, when it no longer holds."""

    method: str = eqx.field(static=True)
    path: AbstractPath = eqx.field(static=True)
    step_s: float | None = eqx.field(static=True, default=None)
    fallback: AbstractPath = eqx.field(static=True, default=Sequential())
    smooth: bool = eqx.field(static=True, default=False)

    def __call__(self, params, batch):
        return loss_fn(params, batch, self.method, path=self.path, smooth=self.smooth)

    def refresh(self, params) -> RmseLoss:
        if self.path.recheck(params, self.method, self.step_s) is not None:
            return replace(self, path=self.fallback, step_s=None)
        return self


#: ``rmse+nll``'s weight on the likelihood (nats per reading against deg of RMSE); measured in
#: docs/fitting.md ("The weight of rmse+nll").
NLL_WEIGHT = 0.1


class NllLoss(AbstractLoss):
    """The negative log-likelihood of every Hall reading given the earlier ones (nats per
    reading; ``_likelihood.hall_nll``): needs no motion capture."""

    method: str = eqx.field(static=True)
    path: AbstractPath = eqx.field(static=True, default=Auto())  # lays out the innovations
    unit: ClassVar[str] = "nats"
    scale: ClassVar[float] = 1.0

    def __call__(self, params, batch):
        return hall_nll(params, batch.series, self.method, path=self.path)


class RmseNllLoss(AbstractLoss):
    """Both: the RMSE against motion capture in deg plus ``nll_weight`` times the likelihood in
    nats per reading (``unit`` "deg+nats")."""

    rmse: RmseLoss
    nll: NllLoss
    nll_weight: float = eqx.field(static=True, default=NLL_WEIGHT)
    unit: ClassVar[str] = "deg_plus_nats"
    scale: ClassVar[float] = 1.0

    def __call__(self, params, batch):
        return self.rmse(params, batch) * RAD2DEG + self.nll_weight * self.nll(params, batch)

    def refresh(self, params) -> RmseNllLoss:
        new = self.rmse.refresh(params)
        return self if new is self.rmse else replace(self, rmse=new)


LOSSES = ("rmse", "nll", "rmse+nll")


def make_loss(kind: str, params: Params, batch: Batch, method: str,
              remat_chunk: int | None, nll_weight: float = NLL_WEIGHT,
              gradient: bool = True, smooth: bool = False) -> AbstractLoss:
    """The training loss ``kind`` (``LOSSES``) on ``batch``; ``gradient``: it will be
    differentiated (the validation loss is not), which decides its path (``rmse_loss``);
    ``smooth``: the RMSE of the smoothed estimates (the likelihood of the readings is the
    filter's either way: smoothing changes the estimates, not the data's likelihood)."""
    nll = NllLoss(method, Auto().for_loss(remat_chunk, gradient))
    if kind == "nll":
        return nll
    rmse = rmse_loss(params, batch, method, remat_chunk, gradient, smooth)
    return rmse if kind == "rmse" else RmseNllLoss(rmse, nll, nll_weight)


def rmse_loss(params: Params, batch: Batch, method: str, remat_chunk: int | None,
              gradient: bool = True, smooth: bool = False) -> RmseLoss:
    """The training loss on ``batch``, its path chosen on the concrete data and ``params``
    by the policy for a fitting loss (``Auto.for_loss``)."""
    policy = Auto().for_loss(remat_chunk, gradient)
    path = choose_path(params, batch.series, method, policy).path
    return RmseLoss(method, path, regular_step(params, batch.series)[0], policy.sequential,
                    smooth)


# ----------------------------------------------------------------------------- sharding
def trial_mesh() -> jax.sharding.Mesh:
    """A 1-D mesh over every visible device, axis ``"trials"``."""
    return jax.sharding.Mesh(np.asarray(jax.devices()), ("trials",))


def shard_batch(batch: Batch, mesh: jax.sharding.Mesh | None = None) -> Batch:
    """Place the trials of ``batch`` across the devices of ``mesh`` (parameters stay
    replicated); the trial count must be a multiple of the device count (``make_batch``'s
    ``multiple_of``). On one device this is a no-op placement.

    Under ``jax.distributed`` (several processes) ``batch`` holds this process's trials only,
    the same count in every process (a multiple of its local devices): the global batch is
    every process's, in process order (``jax.make_array_from_process_local_data``)."""
    mesh = mesh or trial_mesh()
    spec = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("trials"))
    if jax.process_count() > 1:
        n_local = jax.local_device_count()
        if batch.truth.shape[0] % n_local:
            raise ValueError(f"shard_batch: {batch.truth.shape[0]} trials do not split over "
                             f"{n_local} local devices")
        return jax.tree_util.tree_map(
            lambda x: jax.make_array_from_process_local_data(spec, np.asarray(x)), batch)
    n_dev = mesh.devices.size
    if batch.truth.shape[0] % n_dev:
        raise ValueError(f"shard_batch: {batch.truth.shape[0]} trials do not split over "
                         f"{n_dev} devices; build the batch with make_batch(multiple_of={n_dev})")
    return jax.device_put(batch, spec)


def _process_max(*values: int) -> list[int]:
    """Each value's largest over every process (``jax.distributed``; itself in one process)."""
    if jax.process_count() == 1:
        return list(values)
    from jax.experimental import multihost_utils

    got = multihost_utils.process_allgather(np.asarray(values, np.int64))
    return [int(x) for x in np.asarray(got).reshape(-1, len(values)).max(axis=0)]


def _local_batch(sessions, dtype, burn_in_s, multiple, gaps, need_truth=True) -> Batch:
    """This process's part of a batch: in several processes, every process's part has the
    same rows (the longest trial of any) and trials (the most of any, in whole multiples of
    the local devices), so that the parts make one global batch."""
    pieces = trial_sessions(sessions, gaps)
    T, n = _process_max(max(p.n_steps for p in pieces), len(pieces))
    if jax.process_count() == 1:
        return make_batch(sessions, dtype, burn_in_s, multiple, gaps, need_truth=need_truth)
    n = -(-n // jax.local_device_count()) * jax.local_device_count()
    return make_batch(sessions, dtype, burn_in_s, gaps=gaps, length=T, trials=n,
                      need_truth=need_truth)


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
        method: the filter to fit: a Kalman model of ``_models`` (``KCKF``, ``KF``,
            ``ExactKCKF``, one registered) or its name (``"kckf"``, ``"kf"``, ``"kckf3d"``).
        loss: ``"rmse"`` (the mean RMSE against motion capture), ``"nll"`` (the negative
            log-likelihood of the Hall readings: no motion capture needed) or ``"rmse+nll"``.
        nll_weight: ``rmse+nll``'s weight on the likelihood, in deg of RMSE per nat per
            reading (docs/fitting.md says how the default was chosen).
        smooth: fit the fixed-interval smoothed estimates (the offline output) instead of
            the filtered ones; the validation loss is smoothed too.
        learn: the sensor effects to learn with the rest (``EFFECTS``: ``"offset"``,
            ``"gyro_scale"``, ``"play"``, ``"curve"``; docs/fitting.md); none by default.
        faults: the fault policy the training and validation readings are judged by
            (``FaultPolicy``'s names: ``"isolate"``, the default; ``"report"``; ``"off"``).
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
    method: str | AbstractModel = "kckf"
    loss: str = "rmse"
    nll_weight: float = NLL_WEIGHT
    smooth: bool = False
    learn: tuple[str, ...] = ()
    faults: str = "isolate"

    def __post_init__(self):
        FaultPolicy(self.faults)  # a name it knows
        unknown = sorted(set(self.learn) - set(EFFECTS))
        if unknown:
            raise ValueError(f"FitConfig.learn: unknown effect {unknown[0]!r}; expected some "
                             f"of {', '.join(EFFECTS)}")
        model = self.method
        if isinstance(model, AbstractModel):  # the object for its name (``_models``)
            object.__setattr__(self, "method", register_model(model))
        else:
            model = MODELS.get(model) if isinstance(model, str) else None
        kalman = model is not None and model.kalman
        if self.smooth and not kalman:
            raise ValueError(f"FitConfig.smooth: smoothing needs a Kalman method, got "
                             f"{self.method!r}")
        unknown = sorted(set(self.freeze) - set(ALL_LEAVES))
        if unknown:
            raise ValueError(f"FitConfig.freeze: unknown leaf {unknown[0]!r}; expected names "
                             f"from {', '.join(ALL_LEAVES)}")
        effect = {f"effects.{n}": e for n, e in EFFECT_OF_LEAF.items()}
        off = [n for n in self.freeze if n in effect and effect[n] not in self.learn]
        if off:
            raise ValueError(f"FitConfig.freeze: {off[0]!r} belongs to the effect "
                             f"{effect[off[0]]!r}, which is not learned: add it to learn (its "
                             "value then comes from the starting parameters) or leave it out")
        if not kalman:
            raise ValueError(f"FitConfig.method: expected one of {', '.join(KALMAN_METHODS)}, "
                             f"got {self.method!r}")
        if self.loss not in LOSSES:
            raise ValueError(f"FitConfig.loss: expected one of {', '.join(LOSSES)}, got "
                             f"{self.loss!r}")
        if not (math.isfinite(self.nll_weight) and self.nll_weight > 0):
            raise ValueError(f"FitConfig.nll_weight: expected a positive number, got "
                             f"{self.nll_weight!r}")
        self._train_config()  # the loop's own checks

    def _train_config(self) -> TrainConfig:
        """The settings of the one training loop."""
        return TrainConfig(
            steps=self.steps, learning_rate=self.learning_rate, clip_norm=self.clip_norm,
            exponent_leaves=EXPONENT_LEAVES, leaf_scales=tuple(
                (n, f) for n, f in STEP_SCALES if EFFECT_OF_LEAF[n] in self.learn),
            freeze=self.freeze, val_every=self.val_every, patience=self.patience,
            batch_size=self.batch_size, checkpoint_every=self.checkpoint_every, seed=self.seed)


def initial_params(sessions: Sequence[Session], config: FitConfig, dtype=None) -> Params:
    """The starting point: the paper defaults with the first session's Hall calibration, the
    configured noise model, and small floors on terms the paper sets to zero; learning
    ``gyro_mounting``, each board's rotation estimated from the gyros alone
    (``estimate_mounting``: the hinges' axes as the boards see them)."""
    s = sessions[0]
    p = Params.paper_defaults(s.robot, s.hall_models, dtype=dtype)
    p = replace(p, hall_noise=config.hall_noise)
    p = with_floors(p)
    if not config.learn:
        return p
    p = p.with_effects(config.learn)
    if "gyro_mounting" in config.learn:
        rot, _ = estimate_mounting(s.robot, sessions)
        p = replace(p, effects=replace(p.effects, mounting=jnp.asarray(
            rot, p.effects.mounting.dtype)))
    return p


# ----------------------------------------------------------------------------- training
def fingerprint_of(data: bytes) -> str:
    import hashlib

    return hashlib.sha256(data).hexdigest()[:16]


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
    gaps: GapPolicy = GapPolicy(),
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
        gaps: what a gap in the sensor rows does (``GapPolicy``; as every command).

    Under ``jax.distributed`` (``jax.distributed.initialize()`` in every process, then the
    same ``fit`` call in each) every process passes only its own ``sessions`` and
    ``val_sessions``; the trials of all of them form one batch sharded over every device, the
    loss and its gradient are reduced over all of them (XLA's collectives), and every process
    gets the same parameters. Minibatches (``batch_size``) are for one process; process 0
    writes the checkpoint, which every process reads to resume (a shared file system).

    Returns:
        A ``FitResult`` with the best parameters found.
    """
    t0 = time.perf_counter()
    n_dev = jax.device_count()
    multiple = math.lcm(n_dev, pad_trials_to or 1)
    n_proc = jax.process_count()
    if n_proc > 1 and config.batch_size:
        raise ValueError("fit: batch_size (minibatches) needs one process; under "
                         "jax.distributed every step uses every process's trials")
    need = config.loss != "nll"
    batch = shard_batch(_local_batch(sessions, dtype, config.burn_in_s, multiple, gaps, need))
    has_val = _process_max(len(val_sessions))[0] > 0
    if has_val and not val_sessions:
        raise ValueError("fit: under jax.distributed every process needs val_sessions when "
                         "any has them")
    val = (shard_batch(_local_batch(val_sessions, dtype, config.burn_in_s, multiple, gaps, need))
           if has_val else None)
    B, T = batch.truth.shape[:2]
    chunk = config.remat_chunk or auto_chunk(T, config.batch_size or B)
    params = init if init is not None else initial_params(sessions, config, dtype)
    if params.robot != sessions[0].robot:
        raise ValueError(f"initial parameters are for joints {params.robot.spec!r}, the "
                         f"sessions have {sessions[0].robot.spec!r}")
    if config.learn and (params.effects is None or set(params.effects.on) != set(config.learn)):
        params = params.with_effects(config.learn)  # a starting file's values are kept
    params = params.with_faults(config.faults)
    # The readings are judged once, with the starting parameters (``_run.screened``: every
    # reading alone and each sensor over time), not in every step's loss: faulty readings do
    # not enter the fit, and the health monitor's scan is not paid per step.
    batch = _screen_batch(params, batch, config.method)
    val = None if val is None else _screen_batch(params, val, config.method)
    loss = make_loss(config.loss, params, batch, config.method, chunk, config.nll_weight,
                     smooth=config.smooth)
    # The validation loss is not differentiated: no remat needed, and the filter's own path.
    val_loss = (None if val is None else
                make_loss(config.loss, params, val, config.method, None, config.nll_weight,
                          gradient=False, smooth=config.smooth))
    # Parameters live replicated on every device (committed, so that the first and later
    # steps see identically placed inputs and compile once).
    replicated = jax.sharding.NamedSharding(trial_mesh(), jax.sharding.PartitionSpec())
    identity = {"config": asdict(config), "fingerprint": fingerprint(sessions, val_sessions),
                "processes": n_proc}
    if n_proc > 1:  # every process's data, so that each accepts process 0's checkpoint
        from jax.experimental import multihost_utils

        fps = multihost_utils.process_allgather(
            np.frombuffer(identity["fingerprint"].encode(), np.uint8))
        identity["fingerprint"] = fingerprint_of(np.asarray(fps).tobytes())
    n_trials = len(trial_sessions(sessions, gaps))
    result = train(loss, params, batch, n_trials, config._train_config(), val_batch=val,
                   val_loss=val_loss, checkpoint=checkpoint, resume=resume, identity=identity,
                   callback=callback, place=lambda x: jax.device_put(x, replicated))
    result.seconds = time.perf_counter() - t0
    _warn_lagging_timing(result.params, config, sessions[0].sample_rate_hz)
    return result


def _warn_lagging_timing(params: Params, config: FitConfig, rate_hz: float) -> None:
    """A learned gyro timing below 0 makes the filter's angles lag (the gyros would read
    ahead of the Hall sensors by more than half a step, which no sensor does): what a fit on
    motion capture that lags the sensors learns from the RMSE (docs/fitting.md, "offset").
    Said, not refused: the fit did what it was asked."""
    e = params.effects
    if e is None or "gyro_timing" not in e.on or config.loss == "nll":
        return
    lam = float(e.timing)
    if lam >= 0.0:
        return
    import warnings

    warnings.warn(
        f"the learned gyro timing is {lam:.2f} of a step: the filter's angles now lag by about "
        f"{1000 * (0.5 - lam) / rate_hz:.0f} ms, as motion capture that lags the sensors "
        "would teach; learn the timing from the likelihood (--loss nll) and the clock offset "
        "from the RMSE with the timing frozen (docs/fitting.md, 'offset')", stacklevel=3)


def _screen_batch(params: Params, batch: Batch, method: str) -> Batch:
    """``batch`` with its series as ``method`` uses it (``_run.screened``), in place."""
    series, _ = screened(params, batch.series, method)
    return replace(batch, series=series)


def fit_info(result: FitResult, sessions: Sequence[Session], val: Sequence[Session],
             config: FitConfig) -> dict:
    """Metadata stored with fitted parameters (the ``fit`` entry of the JSON file)."""
    return {"kckf_jax": package_version(), "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
            "sessions": [s.path for s in sessions], "val_sessions": [s.path for s in val],
            "config": {k: v for k, v in asdict(replace(config)).items()},
            **{k: v for k, v in result.info().items() if k != "history"}}


__all__ = ["Batch", "FitConfig", "FitInterrupted", "FitResult", "RmseLoss", "auto_chunk", "fit",
           "fit_info", "loss_fn", "make_batch", "per_angle_rmse", "rmse_loss", "shard_batch",
           "trial_mesh"]
