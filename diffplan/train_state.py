"""The training state of the denoiser and what makes it: hyper-parameters, optimiser, keys.

Optimisation (paper appendix A): AdamW, learning rate 0 -> ``lr`` linearly over
``warmup_steps`` then cosine decay to 0 at ``steps`` (``optax.warmup_cosine_decay_schedule``),
gradient clipping by global norm, and an exponential moving average of the params (used for
evaluation).

Keys: every random number of a run is a function of ``TrainConfig.seed`` only:
``root_keys(seed) = (init key, data root, validation root)``, and the key of (0-based) step
``i`` is ``step_key(seed, i) = fold_in(data root, i)``, so a resumed run sees exactly the data
(and noise) an uninterrupted one would.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Mapping, Optional

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

__all__ = ["PREDICTIONS", "TrainConfig", "TrainState", "lr_schedule", "make_optimizer",
           "init_train_state", "root_keys", "step_key", "hashable"]

PREDICTIONS = ("eps", "x0")
"""What the network predicts for the generated channels: the noise (the paper's objective) or
the clean plan x0 (whose loss weighs every noise level alike, so the model must infer the
goal from the conditions even when the noisy channels carry no information)."""


OBJECTIVES = ("diffusion", "goal")
"""What ``TrainConfig.objective`` may name: the denoiser's loss, or the learned-goal
baseline's."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (defaults follow the paper's appendix where it says).

    Attributes:
      seed: the root of every random number (init, data, noise, timesteps).
      steps: total optimisation steps (also the end of the cosine decay).
      batch_size: global batch size (paper: 64), divisible by the number of devices.
      lr: peak learning rate (paper: 2e-4).
      warmup_steps: linear warm-up from 0 (paper: 5 of 200 epochs, i.e. 2.5% of training).
      weight_decay: AdamW decoupled weight decay (on kernels/embeddings, not biases/norms).
      grad_clip: max global gradient norm (0 disables clipping).
      ema_decay: EMA decay; the effective decay is min(ema_decay, (1 + n) / (10 + n)) at
        update n, so early EMA params follow the model.
      num_train_timesteps: diffusion steps T of the cosine schedule (paper: 100).
      timestep_power: how a training example's timestep is drawn: t = floor(T * u ** (1 /
        timestep_power)), u ~ U[0, 1). 1 is the paper's uniform draw; a larger power draws the
        noisier timesteps more often (the noisiest fifth gets 1 - 0.8 ** power of the examples),
        where a planner's choices are made (``diffplan.losses.draw_timesteps``).
      num_gen_channels: G, the number of trailing generated channels of x0 (2: path, goal).
      prediction: "eps" (the paper) or "x0": the network's target (see PREDICTIONS).
      checkpoint_every: save a checkpoint every this many steps (and at the end).
      log_every: append metrics every this many steps (and at the end).
      val_every: evaluate the EMA params' loss on fixed validation batches every this many
        steps (0: never).
      val_batches: number of validation batches.
      objective: "diffusion" (the denoising loss, ``diffplan.losses.diffusion_loss``) or
        "goal" (the learned-goal baseline: cross-entropy over cells of the generated channels'
        +1 cells, ``diffplan.losses.goal_loss``, for a model with a ``logits`` method such as
        ``diffplan.baselines.goal.GoalClassifier``).
    """

    seed: int = 0
    steps: int = 20_000
    batch_size: int = 64
    lr: float = 2e-4
    warmup_steps: int = 500
    weight_decay: float = 1e-2
    grad_clip: float = 1.0
    ema_decay: float = 0.999
    num_train_timesteps: int = 100
    timestep_power: float = 1.0
    num_gen_channels: int = 2
    prediction: str = "eps"
    checkpoint_every: int = 1000
    log_every: int = 50
    val_every: int = 0
    val_batches: int = 4
    objective: str = "diffusion"

    def __post_init__(self):
        ints = {f.name for f in dataclasses.fields(self) if f.type in ("int", int)}
        if self.prediction not in PREDICTIONS:
            raise ValueError(f"TrainConfig.prediction must be one of {PREDICTIONS}, "
                             f"got {self.prediction!r}")
        if self.objective not in OBJECTIVES:
            raise ValueError(f"TrainConfig.objective must be one of {OBJECTIVES}, "
                             f"got {self.objective!r}")
        for f in dataclasses.fields(self):
            if f.name in ("prediction", "objective"):
                continue
            v = getattr(self, f.name)
            if f.name in ints:
                if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                    raise ValueError(f"TrainConfig.{f.name} must be an int, got {v!r}")
            else:
                if isinstance(v, bool) or not isinstance(v, (int, float, np.floating,
                                                             np.integer)):
                    raise ValueError(f"TrainConfig.{f.name} must be a number, got {v!r}")
                if not math.isfinite(float(v)):
                    raise ValueError(f"TrainConfig.{f.name} must be finite, got {v!r}")
        positive = ("steps", "batch_size", "num_train_timesteps", "num_gen_channels",
                    "checkpoint_every", "log_every", "val_batches")
        for name in positive:
            if getattr(self, name) < 1:
                raise ValueError(f"TrainConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("warmup_steps", "weight_decay", "grad_clip", "val_every"):
            if getattr(self, name) < 0:
                raise ValueError(f"TrainConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not self.lr > 0:
            raise ValueError(f"TrainConfig.lr must be > 0, got {self.lr}")
        if self.warmup_steps >= self.steps:
            raise ValueError(f"TrainConfig.warmup_steps ({self.warmup_steps}) must be < steps "
                             f"({self.steps})")
        if not self.timestep_power > 0:
            raise ValueError(f"TrainConfig.timestep_power must be > 0, got "
                             f"{self.timestep_power}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"TrainConfig.ema_decay must be in [0, 1), got {self.ema_decay}")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        if d["timestep_power"] == 1.0:  # absent at 1, as in checkpoints from before it
            del d["timestep_power"]
        if d["objective"] == "diffusion":  # likewise absent at its default
            del d["objective"]
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "TrainConfig":
        from diffplan.models import config_from_dict

        return config_from_dict(cls, d)


@flax.struct.dataclass
class TrainState:
    """The whole optimisation state (a pytree; what ``diffplan.train.fit`` runs and
    checkpoints, for the denoiser and the baselines alike).

    Attributes:
      params: the model's ``params`` collection.
      ema_params: the parameters evaluated and exported: the exponential moving average of
        ``params`` for the denoiser (a copy of ``params``, or CQL's target network, for the
        baselines).
      opt_state: the optax state.
      step: int32 scalar, the number of completed optimisation steps.
    """

    params: Any
    ema_params: Any
    opt_state: Any
    step: jax.Array


# ------------------------------------------------------------------------------- optimiser

def lr_schedule(config: TrainConfig) -> optax.Schedule:
    """0 -> ``lr`` linearly over ``warmup_steps``, then cosine decay to 0 at ``steps``."""
    return optax.warmup_cosine_decay_schedule(
        init_value=0.0, peak_value=config.lr, warmup_steps=config.warmup_steps,
        decay_steps=config.steps, end_value=0.0)


FROZEN_PREFIX = "frozen_"
"""A parameter whose name starts with this is a constant the model reads under stop_gradient
(e.g. ``Denoiser``'s ``frozen_cell_features``), written once before training
(:func:`init_train_state`'s ``fixed``): its gradient is zero, so Adam leaves it as it is, and
weight decay is not applied to it."""


def is_frozen(path) -> bool:
    """Whether a parameter's pytree path names a constant (:data:`FROZEN_PREFIX`)."""
    return any(str(getattr(k, "key", "")).startswith(FROZEN_PREFIX) for k in path)


def _decay_mask(params):
    return jax.tree_util.tree_map_with_path(
        lambda path, p: jnp.ndim(p) > 1 and not is_frozen(path), params)


def make_optimizer(config: TrainConfig) -> optax.GradientTransformation:
    """Global-norm clipping then AdamW on ``lr_schedule(config)``."""
    adamw = optax.adamw(lr_schedule(config), b1=0.9, b2=0.999, eps=1e-8,
                        weight_decay=config.weight_decay, mask=_decay_mask)
    if config.grad_clip > 0:
        return optax.chain(optax.clip_by_global_norm(config.grad_clip), adamw)
    return adamw


def _with_fixed(params, fixed: Mapping[str, Any]):
    """params with the named top-level constants replaced (checked: name, shape)."""
    if not fixed:
        return params
    params = dict(params)
    for name, value in fixed.items():
        if not name.startswith(FROZEN_PREFIX):
            raise ValueError(f"only constants ({FROZEN_PREFIX}* parameters) can be fixed before "
                             f"training, not {name!r}")
        if name not in params:
            raise ValueError(f"the model has no parameter {name!r} to fix (it has "
                             f"{sorted(params)})")
        value = jnp.asarray(value, params[name].dtype)
        if value.shape != params[name].shape:
            raise ValueError(f"{name} must have shape {params[name].shape}, got {value.shape}")
        params[name] = value
    return params


# ------------------------------------------------------------------------------- keys

def root_keys(seed) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(init key, data root, validation root), all functions of ``seed`` only."""
    root = jax.random.PRNGKey(seed)
    return (jax.random.fold_in(root, 0), jax.random.fold_in(root, 1),
            jax.random.fold_in(root, 2))


def step_key(seed: int, step) -> jax.Array:
    """The key of (0-based) training step ``step``: ``fold_in(data root, step)``. The loop
    (``diffplan.train.fit``) passes it to the step function; the denoiser's step splits it
    into (batch key, loss key) and draws the batch as ``batch_fn(batch_key, batch_size)``."""
    return jax.random.fold_in(root_keys(seed)[1], step)


# ------------------------------------------------------------------------------- init

def hashable(obj, what: str):
    """``obj`` if it can be a static argument of ``jit`` (hashable), else a ValueError."""
    try:
        hash(obj)
    except TypeError as e:
        raise ValueError(f"the {what} must be hashable (a flax module with a frozen config, a "
                         f"plain function): {e}") from e
    return obj


@functools.partial(jax.jit, static_argnames=("model", "x_shape", "tok_shape"))
def _init_params(key, *, model, x_shape, tok_shape):
    x = jnp.zeros(x_shape, jnp.float32)
    # (B, L) token ids, or (B, L, D) pretrained features (ones: every token real).
    tok = jnp.ones(tok_shape, jnp.float32) if len(tok_shape) == 3 else jnp.zeros(tok_shape,
                                                                                jnp.int32)
    return model.init(key, x, jnp.zeros(x_shape[:1], jnp.int32), tok)


def init_train_state(model, config: TrainConfig, init_batch,
                     key: Optional[jax.Array] = None,
                     fixed: Optional[Mapping[str, Any]] = None) -> TrainState:
    """Initial state; params from ``model.init(key, x0, t, tokens)`` (default key: the init
    key of ``root_keys(config.seed)``), then each top-level parameter named in ``fixed``
    (``frozen_*`` names only: constants of the model, see :data:`FROZEN_PREFIX`) replaced by
    the given array (same shape; ValueError otherwise).

    ``init_batch`` is a ``diffplan.losses.Batch`` (or any object with ``x0`` (B, H, W, C+G)
    and ``tokens`` (B, L)) of arrays or ``jax.ShapeDtypeStruct`` (only shapes are used; the
    model is initialised on a batch of one).
    """
    key = root_keys(config.seed)[0] if key is None else key
    # Non-partitionable threefry for the init only (scoped; init runs replicated, so
    # partitionability is irrelevant there): it compiles ~5x faster on CPU for a UNet with
    # ~150 separately initialised arrays (measured ~100 s -> ~20 s on the 2-core machine).
    with jax.threefry_partitionable(False):
        variables = _init_params(
            key, model=hashable(model, "model"), x_shape=(1,) + tuple(init_batch.x0.shape[1:]),
            tok_shape=(1,) + tuple(init_batch.tokens.shape[1:]))
    extra = sorted(set(variables) - {"params"})
    if extra:
        raise ValueError(f"model has mutable collections {extra}; only 'params' is supported")
    params = _with_fixed(variables["params"], fixed or {})
    opt_state = make_optimizer(config).init(params)
    return TrainState(params=params, ema_params=jax.tree_util.tree_map(jnp.copy, params),
                      opt_state=opt_state, step=jnp.zeros((), jnp.int32))
