"""The one training loop: any filter's parameters fitted by optax on any loss.

``train`` takes a loss object (``AbstractLoss``: ``loss(params, batch) -> scalar``, traceable,
and ``refresh(params)`` to re-decide, on the concrete parameters after each step, anything
the loss decided on concrete inputs, such as its path), the starting parameters (an
``eqx.Module`` of unconstrained leaves) and the data. One jitted training step computes the
loss, its gradient and the optax update; validation, early stopping, checkpoints, interruption
and resumption are the same for every filter. ``kckf_jax.fit`` (the KCKF) and
``filters.markov.fit_markov`` (the Markovian filter) both call it.
"""

from __future__ import annotations

import abc
import functools
import json
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import equinox as eqx
import jax
import optax
from jaxtyping import Array, Float

from .._models._params import get_leaf
from .._sessions._atomic import atomic_write

RAD2DEG = 180.0 / math.pi


class AbstractLoss(eqx.Module):
    """A fitting loss: ``__call__(params, batch)`` (traceable) and ``refresh(params)``.

    ``refresh`` gets the concrete parameters before every step and returns the loss to use for
    it: ``self``, or another loss when a decision made on concrete values (the path) no longer
    holds; the training step recompiles for the new one. ``unit`` names what the history
    reports (``"loss_" + unit``, ``"val_" + unit``), ``scale`` turns the value into it (an
    RMSE in rad is reported in deg)."""

    unit: ClassVar[str] = "deg"
    scale: ClassVar[float] = RAD2DEG

    @abc.abstractmethod
    def __call__(self, params, batch) -> Float[Array, ""]:
        raise NotImplementedError

    def refresh(self, params) -> AbstractLoss:
        return self


@dataclass(frozen=True)
class TrainConfig:
    """The optimiser and the loop (``FitConfig`` holds these and the KCKF's own settings).

    Attributes:
        steps: maximum number of gradient steps.
        learning_rate: Adam step size on the unconstrained leaves.
        clip_norm: global gradient-norm clip (``optax.clip_by_global_norm``); ``None``: none.
        exponent_leaves: leaves that take steps ``EXPONENT_LR_SCALE`` times smaller.
        leaf_scales: ``(name, factor)`` pairs: the named leaves take steps ``factor`` times
            the learning rate (a leaf whose typical size is far from 1 in its unit).
        freeze: names of leaves to keep fixed.
        val_every: validate every this many steps (and at the last step).
        patience: stop after this many validations without improvement.
        batch_size: trials per step (default: all), drawn with ``seed``.
        checkpoint_every: steps between checkpoints (when a checkpoint path is given).
        seed: makes minibatch draws deterministic.
        keep: ``"best"`` (the parameters with the lowest validation, or training, loss) or
            ``"last"`` (those after the last step).
    """

    steps: int = 200
    learning_rate: float = 0.03
    clip_norm: float | None = 1.0
    exponent_leaves: tuple[str, ...] = ()
    leaf_scales: tuple[tuple[str, float], ...] = ()
    freeze: tuple[str, ...] = ()
    val_every: int = 10
    patience: int = 5
    batch_size: int | None = None
    checkpoint_every: int = 10
    seed: int = 0
    keep: str = "best"

    def __post_init__(self):
        if self.steps < 0 or self.val_every < 1 or self.patience < 1:
            raise ValueError("FitConfig: steps must be >= 0, val_every and patience >= 1")
        if self.keep not in ("best", "last"):
            raise ValueError(f"TrainConfig.keep: expected 'best' or 'last', got {self.keep!r}")


#: Leaves that sit in an exponent (Eq. 1's ``b`` and ``d``: ``d V`` is about 10, so a 1 %
#: change moves the curve by 10 %) take steps this much smaller than the others.
EXPONENT_LR_SCALE = 0.1


@functools.lru_cache(maxsize=16)
def optimizer(learning_rate: float, clip_norm: float | None,
              exponent_leaves: tuple[str, ...] = (),
              leaf_scales: tuple[tuple[str, float], ...] = ()) -> optax.GradientTransformation:
    """Adam after global-norm clipping; ``EXPONENT_LR_SCALE`` times smaller steps for
    ``exponent_leaves``, ``factor`` times the rate for each ``(name, factor)`` of
    ``leaf_scales`` (a leaf named in both takes the latter).

    Cached, so that fits with the same settings share one compiled training step."""
    groups = {n: "exponent" for n in exponent_leaves} | {n: n for n, _ in leaf_scales}
    if not groups:
        adam = optax.adam(learning_rate)
    else:
        def labels(params):
            def label(path, _):
                names = [getattr(k, "name", None) for k in path]
                return next((groups[n] for n in reversed(names) if n in groups), "default")

            return jax.tree_util.tree_map_with_path(label, params)

        rates = {"default": learning_rate, "exponent": learning_rate * EXPONENT_LR_SCALE}
        rates |= {n: learning_rate * f for n, f in leaf_scales}
        adam = optax.multi_transform(
            {g: optax.adam(rates[g]) for g in ["default", *dict.fromkeys(groups.values())]},
            labels)
    return adam if clip_norm is None else optax.chain(optax.clip_by_global_norm(clip_norm),
                                                      adam)


def filter_spec(params, freeze: Sequence[str]):
    """``eqx.partition`` spec: ``True`` for every leaf but the ``freeze``d ones."""
    spec = jax.tree_util.tree_map(lambda _: True, params)
    for name in freeze:  # a leaf's name, or a dotted path into a sub-module ("effects.timing")
        spec = eqx.tree_at(lambda p, n=name: get_leaf(p, n), spec, False)
    return spec


@dataclass
class FitResult:
    """What a fit gives back: the chosen parameters and the history of the run."""

    params: object
    best_step: int
    best_loss_deg: float
    history: list[dict] = field(default_factory=list)
    steps_done: int = 0
    stopped_early: bool = False
    seconds: float = 0.0
    unit: str = "deg"

    def info(self) -> dict:
        return {"best_step": self.best_step, "best_loss_deg": self.best_loss_deg,
                "unit": self.unit,
                "steps_done": self.steps_done, "stopped_early": self.stopped_early,
                "seconds": round(self.seconds, 2), "history": self.history}


class FitInterrupted(Exception):
    """The fit was interrupted (Ctrl-C, SIGTERM); its checkpoint holds the last full step."""

    def __init__(self, step: int, checkpoint: str | None):
        self.step, self.checkpoint = step, checkpoint
        where = f"; checkpoint {checkpoint}, continue with --resume" if checkpoint else ""
        super().__init__(f"fit interrupted after step {step}{where}")


@eqx.filter_jit
def _train_step(loss: AbstractLoss, diff, static, opt_state, batch, idx, opt):
    sub = jax.tree_util.tree_map(lambda x: x[idx], batch) if idx is not None else batch

    def f(d):
        return loss(eqx.combine(d, static), sub)

    value, grads = eqx.filter_value_and_grad(f)(diff)
    updates, opt_state = opt.update(grads, opt_state, diff)
    return eqx.apply_updates(diff, updates), opt_state, value


@eqx.filter_jit
def _eval(loss: AbstractLoss, params, batch):
    return loss(params, batch)


def _save_checkpoint(path: str, header: dict, tree) -> None:
    with atomic_write(path, "wb") as f:
        head = json.dumps(header).encode()
        f.write(len(head).to_bytes(8, "little"))
        f.write(head)
        eqx.tree_serialise_leaves(f, tree)


def _load_checkpoint(path: str, like):
    with open(path, "rb") as f:
        n = int.from_bytes(f.read(8), "little")
        header = json.loads(f.read(n).decode())
        tree = eqx.tree_deserialise_leaves(f, like)
    return header, tree


def train(
    loss: AbstractLoss,
    params,
    batch,
    n_trials: int,
    config: TrainConfig,
    *,
    val_batch=None,
    val_loss: AbstractLoss | None = None,
    checkpoint: str | None = None,
    resume: bool = False,
    identity: dict | None = None,
    callback: Callable[[dict], None] | None = None,
    place: Callable | None = None,
) -> FitResult:
    """Fit ``params`` by ``config``'s optimiser on ``loss`` over ``batch``.

    Args:
        loss: the training loss; ``val_loss`` (default ``loss``) scores ``val_batch``.
        params: the starting parameters (every inexact array leaf not frozen is fitted).
        batch: the training data, any pytree with the trials on the leading axis of every
            leaf (``n_trials`` real trials; minibatches draw from those).
        config: the optimiser and the loop.
        val_batch: validation data for early stopping and for choosing the best step.
        checkpoint: file to checkpoint to; written every ``config.checkpoint_every`` steps
            and when interrupted (Ctrl-C, SIGTERM) or on an error.
        resume: continue from ``checkpoint`` with nothing lost: the result equals that of an
            uninterrupted fit. ``identity`` (the data's fingerprint and the settings) must
            equal the checkpoint's.
        callback: called after every step with ``{"step", "loss_deg", "val_deg"}`` (the
            loss's ``unit``: ``"loss_nats"`` for the likelihood) and ``"refreshed"`` when
            ``refresh`` gave a new loss for that step.
        place: applied to the starting parameters and optimiser state (e.g. replicate them
            on every device).

    Returns:
        A ``FitResult``.
    """
    t0 = time.perf_counter()
    place = place or (lambda x: x)
    val_loss = val_loss or loss
    params = place(params)
    diff, static = eqx.partition(params, filter_spec(params, config.freeze))
    opt = optimizer(config.learning_rate, config.clip_norm, config.exponent_leaves,
                    config.leaf_scales)
    opt_state = place(opt.init(diff))
    best = {"step": 0, "loss": math.inf}
    best_params = params
    history: list[dict] = []
    start = 0
    identity = json.loads(json.dumps(identity or {}))
    if resume:
        if not checkpoint or not os.path.exists(checkpoint):
            raise ValueError(f"--resume: no checkpoint at {checkpoint}; start the fit without "
                             "--resume")
        header, (diff, opt_state, best_params) = _load_checkpoint(
            checkpoint, (diff, opt_state, best_params))
        if header.get("identity") != identity:
            raise ValueError(f"{checkpoint}: the checkpoint belongs to a fit with other "
                             "sessions or settings; resume with the same command line")
        start, best, history = header["step"], header["best"], header["history"]
    key = jax.random.PRNGKey(config.seed)
    since_best = sum(1 for h in history if h.get(f"val_{loss.unit}") is not None
                     and h["step"] > best["step"])
    stopped_early = False
    step = start

    def save(step_done: int):
        if checkpoint and jax.process_index() == 0:  # one writer under jax.distributed
            header = {"kind": "kckf-fit-checkpoint/2", "identity": identity,
                      "step": step_done, "best": best, "history": history}
            _save_checkpoint(checkpoint, header, (diff, opt_state, best_params))

    previous = signal.getsignal(signal.SIGTERM)

    def on_term(signum, frame):
        raise KeyboardInterrupt

    in_main = threading.current_thread() is threading.main_thread()
    if in_main:
        signal.signal(signal.SIGTERM, on_term)
    try:
        for step in range(start, config.steps):
            current = eqx.combine(diff, static)
            record = {"step": step + 1}
            loss, val_loss = _refresh(loss, val_loss, current, record)
            idx = None
            if config.batch_size and config.batch_size < n_trials:
                idx = jax.random.choice(jax.random.fold_in(key, step), n_trials,
                                        (config.batch_size,), replace=False)
            new_diff, new_opt_state, value = _train_step(loss, diff, static, opt_state, batch,
                                                         idx, opt)
            # The loss of the parameters before this update, which are the ones scored.
            lk, vk = f"loss_{loss.unit}", f"val_{loss.unit}"
            record[lk] = float(value) * loss.scale
            record[vk] = None
            score = record[lk]
            last = step + 1 == config.steps
            if val_batch is not None and ((step % config.val_every) == 0 or last):
                score = float(_eval(val_loss, current, val_batch)) * loss.scale
                record[vk] = score
            diff, opt_state = new_diff, new_opt_state
            if val_batch is None or record[vk] is not None:
                if score < best["loss"]:
                    best = {"step": step, "loss": score}
                    best_params = current
                    since_best = 0
                elif val_batch is not None:
                    since_best += 1
            history.append(record)
            if callback:
                callback(record)
            if checkpoint and (step + 1) % config.checkpoint_every == 0:
                save(step + 1)
            if val_batch is not None and since_best >= config.patience:
                stopped_early = True
                step += 1
                break
        else:
            step = config.steps
        # The parameters after the last update have not been scored yet.
        final = eqx.combine(diff, static)
        loss, val_loss = _refresh(loss, val_loss, final, {})
        fin = (float(_eval(val_loss, final, val_batch)) if val_batch is not None
               else float(_eval(loss, final, batch))) * loss.scale
        if config.keep == "last":
            best, best_params = {"step": step, "loss": fin}, final
        elif fin < best["loss"]:
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
                     stopped_early=stopped_early, seconds=time.perf_counter() - t0,
                     unit=loss.unit)


def _refresh(loss: AbstractLoss, val_loss: AbstractLoss, params, record: dict):
    """Both losses re-decided on ``params``; a change is noted in ``record["refreshed"]``
    (the new loss's ``repr``)."""
    new, new_val = loss.refresh(params), val_loss.refresh(params)
    if new is not loss or new_val is not val_loss:
        record["refreshed"] = repr(new)
    return new, new_val
