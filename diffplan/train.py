"""Training the in-painting denoiser: the DDPM noise-prediction loss on the generated channels.

The planning tensor ``x0`` is (B, H, W, C + G): C condition channels (kept clean) then G
generated channels (path, goal). One training step (the paper's objective, sec. 3.3):

    t   ~ U{0, ..., T-1}                  (B,)
    eps ~ N(0, 1)                         (B, H, W, G)   generated channels only
    x_t = [x0[..., :C],  sqrt(ab_t) x0[..., C:] + sqrt(1 - ab_t) eps]
    L   = sum(loss_mask * (eps_theta(x_t, t, tokens) - eps)^2) / sum(loss_mask)

with ``ab = cosine_schedule(T).alphas_cumprod``. ``loss_mask`` (B, H, W, G) lets the caller
drop parts of the loss (e.g. the goal channel outside the seen area).

Optimisation (paper appendix A): AdamW, learning rate 0 -> ``lr`` linearly over
``warmup_steps`` then cosine decay to 0 at ``steps`` (``optax.warmup_cosine_decay_schedule``),
gradient clipping by global norm, and an exponential moving average of the params (used for
evaluation).

``train`` runs the loop: the batch of step i is ``batch_fn(key_i, batch_size)`` with
``key_i`` a function of (seed, i) only, so a resumed run sees exactly the data (and noise) an
uninterrupted one would; checkpoints (``diffplan.checkpoint``) every ``checkpoint_every``
steps and at the end; resume from the newest one in ``out_dir``; metrics to
``out_dir/metrics.jsonl`` (and TensorBoard when tensorboardX is importable); data parallel over
all devices (``diffplan.sharding``).
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import time
import warnings
from typing import Any, Callable, Mapping, NamedTuple, Optional

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from diffplan import checkpoint as ckpt
from diffplan import sharding as shd

__all__ = [
    "Batch",
    "TrainConfig",
    "TrainState",
    "TrainResult",
    "NonFiniteLossError",
    "OutputWriteError",
    "ConfigMismatchError",
    "lr_schedule",
    "make_optimizer",
    "diffusion_loss",
    "init_train_state",
    "make_train_step",
    "step_key",
    "checkpoint_metadata",
    "train",
]

_SYNC_EVERY = 16  # the host checks for non-finite losses (and bounds queued steps) this often


class Batch(NamedTuple):
    """One training batch.

    Attributes:
      x0: float32 (B, H, W, C + G), the clean planning tensor (conditions, then generated).
      tokens: int32 (B, L), instruction token ids, 0 = padding.
      loss_mask: float32 (B, H, W, G), weight of each generated entry in the loss.
    """

    x0: jax.Array
    tokens: jax.Array
    loss_mask: jax.Array


class NonFiniteLossError(RuntimeError):
    """Training produced a non-finite loss or gradient norm; nothing after the last good
    checkpoint was saved. Attributes: ``step`` (1-based count of the failing step, or the
    window it fell in), ``last_checkpoint_step`` (None if none)."""

    def __init__(self, message: str, step: int, last_checkpoint_step: Optional[int]):
        super().__init__(message)
        self.step = step
        self.last_checkpoint_step = last_checkpoint_step


class OutputWriteError(OSError):
    """Training could not write its metrics log (e.g. the disk is full); the checkpoints saved
    before are intact."""


class ConfigMismatchError(ValueError):
    """``out_dir`` holds a checkpoint written with different configs than the requested ones."""


# ------------------------------------------------------------------------------- configs

# Fields that do not change the computation: they may differ when resuming.
PREDICTIONS = ("eps", "x0")
"""What the network predicts for the generated channels: the noise (the paper's objective) or
the clean plan x0 (whose loss weighs every noise level alike, so the model must infer the
goal from the conditions even when the noisy channels carry no information)."""

_RESUMABLE_FIELDS = ("checkpoint_every", "log_every", "val_every", "val_batches")


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
      num_gen_channels: G, the number of trailing generated channels of x0 (2: path, goal).
      prediction: "eps" (the paper) or "x0": the network's target (see PREDICTIONS).
      checkpoint_every: save a checkpoint every this many steps (and at the end).
      log_every: append metrics every this many steps (and at the end).
      val_every: evaluate the EMA params' loss on fixed validation batches every this many
        steps (0: never).
      val_batches: number of validation batches.
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
    num_gen_channels: int = 2
    prediction: str = "eps"
    checkpoint_every: int = 1000
    log_every: int = 50
    val_every: int = 0
    val_batches: int = 4

    def __post_init__(self):
        ints = {f.name for f in dataclasses.fields(self) if f.type in ("int", int)}
        if self.prediction not in PREDICTIONS:
            raise ValueError(f"TrainConfig.prediction must be one of {PREDICTIONS}, "
                             f"got {self.prediction!r}")
        for f in dataclasses.fields(self):
            if f.name == "prediction":
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
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"TrainConfig.ema_decay must be in [0, 1), got {self.ema_decay}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "TrainConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown TrainConfig fields: {unknown}")
        return cls(**dict(d))


@flax.struct.dataclass
class TrainState:
    """The whole optimisation state (a pytree).

    Attributes:
      params: the model's ``params`` collection.
      ema_params: the exponential moving average of ``params`` (for evaluation).
      opt_state: optax state of ``make_optimizer(config)``.
      step: int32 scalar, the number of completed optimisation steps.
    """

    params: Any
    ema_params: Any
    opt_state: Any
    step: jax.Array


class TrainResult(NamedTuple):
    """What ``train`` returns: the final state, the last logged training loss (mean over the
    last logging window; None if no step ran in this call), and the last metrics record."""

    state: TrainState
    final_loss: Optional[float]
    last_metrics: Optional[dict]

    @property
    def ema_params(self):
        return self.state.ema_params


# ------------------------------------------------------------------------------- optimiser

def lr_schedule(config: TrainConfig) -> optax.Schedule:
    """0 -> ``lr`` linearly over ``warmup_steps``, then cosine decay to 0 at ``steps``."""
    return optax.warmup_cosine_decay_schedule(
        init_value=0.0, peak_value=config.lr, warmup_steps=config.warmup_steps,
        decay_steps=config.steps, end_value=0.0)


def _decay_mask(params):
    return jax.tree_util.tree_map(lambda p: jnp.ndim(p) > 1, params)


def make_optimizer(config: TrainConfig) -> optax.GradientTransformation:
    """Global-norm clipping then AdamW on ``lr_schedule(config)``."""
    adamw = optax.adamw(lr_schedule(config), b1=0.9, b2=0.999, eps=1e-8,
                        weight_decay=config.weight_decay, mask=_decay_mask)
    if config.grad_clip > 0:
        return optax.chain(optax.clip_by_global_norm(config.grad_clip), adamw)
    return adamw


# ------------------------------------------------------------------------------- loss

def _check_batch(batch: Batch, num_gen_channels: int) -> None:
    x0, tokens, mask = batch
    if len(x0.shape) != 4:
        raise ValueError(f"Batch.x0 must be (B, H, W, C+G), got shape {tuple(x0.shape)}")
    B, H, W, CG = x0.shape
    if not 0 < num_gen_channels <= CG:
        raise ValueError(f"num_gen_channels={num_gen_channels} must be in [1, {CG}] "
                         f"(x0 has {CG} channels)")
    if len(tokens.shape) != 2 or tokens.shape[0] != B:
        raise ValueError(f"Batch.tokens must be (B={B}, L), got shape {tuple(tokens.shape)}")
    if tuple(mask.shape) != (B, H, W, num_gen_channels):
        raise ValueError(f"Batch.loss_mask must be {(B, H, W, num_gen_channels)}, got "
                         f"{tuple(mask.shape)}")


def diffusion_loss(params, apply_fn: Callable, batch: Batch, key: jax.Array,
                   alphas_cumprod: jax.Array, num_gen_channels: int, prediction: str = "eps"):
    """The masked noise-prediction MSE of one batch.

    Args:
      params: model ``params`` collection.
      apply_fn: ``apply_fn({"params": params}, x_t, t, tokens) -> eps`` (B, H, W, G).
      batch: a ``Batch``.
      key: PRNG key (timesteps and noise).
      alphas_cumprod: float32 (T,).
      num_gen_channels: G.

    Returns:
      (loss scalar, aux dict with ``t`` (B,) and ``mask_sum``).
    """
    _check_batch(batch, num_gen_channels)
    x0, tokens, loss_mask = batch
    x0 = x0.astype(jnp.float32)
    G = num_gen_channels
    C = x0.shape[-1] - G
    B = x0.shape[0]
    T = alphas_cumprod.shape[0]
    t_key, eps_key = jax.random.split(key)
    t = jax.random.randint(t_key, (B,), 0, T, dtype=jnp.int32)
    eps = jax.random.normal(eps_key, x0.shape[:-1] + (G,), jnp.float32)
    ab = alphas_cumprod[t][:, None, None, None]
    x_gen = jnp.sqrt(ab) * x0[..., C:] + jnp.sqrt(1.0 - ab) * eps
    x_t = jnp.concatenate([x0[..., :C], x_gen], axis=-1)
    pred = apply_fn({"params": params}, x_t, t, tokens.astype(jnp.int32))
    if pred.shape != eps.shape:
        raise ValueError(f"model output shape {pred.shape} != generated-channel shape "
                         f"{eps.shape}")
    mask = loss_mask.astype(jnp.float32)
    msum = jnp.sum(mask)
    target = eps if prediction == "eps" else x0[..., C:]
    sq = jnp.sum(mask * jnp.square(pred.astype(jnp.float32) - target))
    loss = jnp.where(msum > 0, sq / jnp.maximum(msum, 1e-12), 0.0)
    return loss, {"t": t, "mask_sum": msum}


# ------------------------------------------------------------------------------- state / step

def _alphas_cumprod(config: TrainConfig) -> jax.Array:
    from diffplan.schedule import cosine_schedule
    return cosine_schedule(config.num_train_timesteps).alphas_cumprod


def _root_keys(seed):
    """(init key, data root, validation root), all functions of ``seed`` only."""
    root = jax.random.PRNGKey(seed)
    return (jax.random.fold_in(root, 0), jax.random.fold_in(root, 1),
            jax.random.fold_in(root, 2))


def step_key(seed: int, step) -> jax.Array:
    """The key of (0-based) training step ``step``; ``train`` splits it into
    (batch key, loss key) and draws the batch as ``batch_fn(batch_key, batch_size)``."""
    return jax.random.fold_in(_root_keys(seed)[1], step)


def _compute_cfg(config: TrainConfig) -> TrainConfig:
    """``config`` with the fields that do not enter the optimisation step normalised, so the
    compiled step is shared by runs that differ only in seed, logging or checkpointing (the
    seed enters through the keys, which are arguments)."""
    return dataclasses.replace(config, seed=0, checkpoint_every=1, log_every=1, val_every=0,
                               val_batches=1)


def _static(obj, what: str):
    try:
        hash(obj)
    except TypeError as e:
        raise ValueError(f"the {what} must be hashable (a flax module with a frozen config, a "
                         f"plain function): {e}") from e
    return obj


@functools.partial(jax.jit, static_argnames=("model", "x_shape", "tok_shape"))
def _init_params(key, *, model, x_shape, tok_shape):
    x = jnp.zeros(x_shape, jnp.float32)
    tok = jnp.zeros(tok_shape, jnp.int32)
    return model.init(key, x, jnp.zeros(x_shape[:1], jnp.int32), tok)


def init_train_state(model, config: TrainConfig, init_batch: Batch,
                     key: Optional[jax.Array] = None) -> TrainState:
    """Initial state; params from ``model.init(key, x0, t, tokens)`` (default key from seed).

    ``init_batch`` may hold arrays or ``jax.ShapeDtypeStruct`` (only shapes are used; the
    model is initialised on a batch of one).
    """
    key = _root_keys(config.seed)[0] if key is None else key
    # Non-partitionable threefry for the init only (scoped; init runs replicated, so
    # partitionability is irrelevant there): it compiles ~5x faster on CPU for a UNet with
    # ~150 separately initialised arrays (measured ~100 s -> ~20 s on the 2-core machine).
    with jax.threefry_partitionable(False):
        variables = _init_params(
            key, model=_static(model, "model"), x_shape=(1,) + tuple(init_batch.x0.shape[1:]),
            tok_shape=(1,) + tuple(init_batch.tokens.shape[1:]))
    extra = sorted(set(variables) - {"params"})
    if extra:
        raise ValueError(f"model has mutable collections {extra}; only 'params' is supported")
    params = variables["params"]
    opt_state = make_optimizer(config).init(params)
    return TrainState(params=params, ema_params=jax.tree_util.tree_map(jnp.copy, params),
                      opt_state=opt_state, step=jnp.zeros((), jnp.int32))


def _make_core_step(model, config: TrainConfig, alphas_cumprod):
    """The un-jitted pure step: (state, batch, key) -> (state, metrics)."""
    optimizer = make_optimizer(config)
    schedule = lr_schedule(config)
    G = config.num_gen_channels
    ab = jnp.asarray(alphas_cumprod, jnp.float32)

    def core(state: TrainState, batch: Batch, key: jax.Array):
        def loss_fn(p):
            return diffusion_loss(p, model.apply, batch, key, ab, G, config.prediction)

        (loss, _), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        grad_norm = optax.tree.norm(grads)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        n = state.step.astype(jnp.float32)
        decay = jnp.minimum(config.ema_decay, (1.0 + n) / (10.0 + n))
        ema = jax.tree_util.tree_map(lambda e, p: decay * e + (1.0 - decay) * p,
                                     state.ema_params, params)
        new_state = TrainState(params=params, ema_params=ema, opt_state=opt_state,
                               step=state.step + 1)
        metrics = {"loss": loss, "grad_norm": grad_norm, "lr": schedule(state.step)}
        return new_state, metrics

    return core


@functools.partial(jax.jit, static_argnames=("model", "config", "mesh"))
def _train_step_jit(state, batch, key, alphas_cumprod, *, model, config, mesh):
    state = shd.constrain_replicated(state, mesh)
    batch = shd.constrain_batch(batch, mesh)
    new_state, metrics = _make_core_step(model, config, alphas_cumprod)(state, batch, key)
    return shd.constrain_replicated((new_state, metrics), mesh)


def make_train_step(model, config: TrainConfig, *, mesh=None, alphas_cumprod=None):
    """A jitted pure ``train_step(state, batch, key) -> (state, metrics)``.

    The batch is split over the ``"data"`` axis of ``mesh`` (default: all devices); state,
    key and metrics (``loss``, ``grad_norm``, ``lr``: scalars) are replicated. A thin wrapper
    places the inputs (a no-op when they already are; ``train_step.placed`` skips it) and
    calls a jitted function whose compilation is cached per (model, config without seed and
    logging fields, mesh): ``train`` uses the same compiled step.
    """
    mesh = shd.data_mesh() if mesh is None else mesh
    ab = _alphas_cumprod(config) if alphas_cumprod is None else jnp.asarray(alphas_cumprod)
    ab = shd.replicate(ab, mesh)
    cfg = _compute_cfg(config)
    _static(model, "model")

    def placed(state: TrainState, batch: Batch, key: jax.Array):
        return _train_step_jit(state, batch, key, ab, model=model, config=cfg, mesh=mesh)

    def train_step(state: TrainState, batch: Batch, key: jax.Array):
        return placed(shd.replicate(state, mesh), shd.shard_batch(Batch(*batch), mesh),
                      shd.replicate(key, mesh))

    train_step.placed = placed
    return train_step


# ------------------------------------------------------------------------------- the loop

@functools.partial(jax.jit, static_argnames=("batch_fn", "batch_size", "mesh"))
def _draw_batch(data_root, step, *, batch_fn, batch_size, mesh):
    """(batch of step ``step``, loss key of step ``step``) from ``fold_in(data_root, step)``.

    ``step`` is traced, so one compilation serves every step (and every seed)."""
    batch_key, loss_key = jax.random.split(jax.random.fold_in(data_root, step))
    batch = shd.constrain_batch(Batch(*batch_fn(batch_key, batch_size)), mesh)
    return batch, shd.constrain_replicated(loss_key, mesh)


@functools.partial(jax.jit, static_argnames=("model", "config", "batch_fn", "mesh"))
def _val_loss(params, val_root, alphas_cumprod, *, model, config, batch_fn, mesh):
    """Mean loss of ``params`` over ``config.val_batches`` batches with fixed keys."""

    def body(total, j):
        batch_key, loss_key = jax.random.split(jax.random.fold_in(val_root, j))
        batch = shd.constrain_batch(Batch(*batch_fn(batch_key, config.batch_size)), mesh)
        loss, _ = diffusion_loss(params, model.apply, batch, loss_key, alphas_cumprod,
                                 config.num_gen_channels, config.prediction)
        return total + loss, None

    total, _ = jax.lax.scan(body, jnp.zeros((), jnp.float32), jnp.arange(config.val_batches))
    return shd.constrain_replicated(total / config.val_batches, mesh)


class _Window:
    """Per-step metrics (device scalars) since the last log; fetched to the host only at
    check points, so the loop does not wait for the device every step."""

    def __init__(self):
        self.pending = []  # (step, metrics on device)
        self.host = []  # (step, loss, grad_norm, lr)

    def add(self, step, metrics):
        self.pending.append((step, metrics))

    def fetch(self):
        if self.pending:
            vals = jax.device_get([m for _, m in self.pending])
            self.host += [(s, float(v["loss"]), float(v["grad_norm"]), float(v["lr"]))
                          for (s, _), v in zip(self.pending, vals)]
            self.pending = []
        for s, loss, gn, _ in self.host:
            if not (math.isfinite(loss) and math.isfinite(gn)):
                return s  # the first non-finite step (1-based count)
        return None

    def summary(self):
        """Mean loss, last grad norm and lr of the window; then clears it."""
        out = {"loss": float(np.mean([h[1] for h in self.host])),
               "grad_norm": self.host[-1][2], "lr": self.host[-1][3]}
        self.host = []
        return out


def _truncate_metrics(path: str, after_step: int) -> None:
    """Drops records with step > after_step (logged before a crash, replayed on resume)."""
    if not os.path.exists(path):
        return
    keep = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue  # a torn last line from a crash
            if int(rec.get("step", 0)) <= after_step:
                keep.append(line)
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write("".join(k + "\n" for k in keep))
    os.replace(tmp, path)


def _model_config_dict(model, model_config) -> tuple[dict, Optional[str]]:
    if model_config is None:
        model_config = getattr(model, "config", None)
    if model_config is None:
        return {}, None
    cls = None if isinstance(model_config, Mapping) else ckpt.class_path(model_config)
    return ckpt.config_to_dict(model_config), cls


def checkpoint_metadata(model, model_config, train_config: TrainConfig, init_batch: Batch,
                        extra_metadata: Optional[Mapping[str, Any]] = None) -> dict:
    """The JSON metadata ``train`` stores with every checkpoint.

    ``{"model_config": dict, "model_config_class": "module:Class" (None for a dict config),
    "model_class": "module:Class", "train_config": dict, "extra": dict,
    "input_shapes": {"x": [1, H, W, C+G], "tokens": [1, L]}}`` -- enough for
    ``diffplan.checkpoint.load_params_for_eval`` to rebuild the model and check shapes.
    """
    mc_dict, mc_class = _model_config_dict(model, model_config)
    G = train_config.num_gen_channels
    if mc_dict.get("num_gen_channels", G) != G:
        raise ValueError(f"model config num_gen_channels={mc_dict['num_gen_channels']} != "
                         f"train config num_gen_channels={G}")
    metadata = {
        "model_config": mc_dict,
        "model_config_class": mc_class,
        "model_class": ckpt.class_path(model),
        "train_config": train_config.to_dict(),
        "extra": dict(extra_metadata or {}),
        "input_shapes": {"x": [1, *map(int, init_batch.x0.shape[1:])],
                         "tokens": [1, *map(int, init_batch.tokens.shape[1:])]},
    }
    try:
        return ckpt.config_to_dict(metadata)
    except TypeError as e:
        raise ValueError(f"configs / extra_metadata must be JSON-serialisable: {e}") from e


def _check_resume(meta: dict, requested: dict, out_dir: str) -> None:
    problems = []
    problems += ckpt.diff_dicts(meta.get("model_config", {}), requested["model_config"],
                                "model_config")
    stored_tc = {k: v for k, v in meta.get("train_config", {}).items()
                 if k not in _RESUMABLE_FIELDS}
    req_tc = {k: v for k, v in requested["train_config"].items() if k not in _RESUMABLE_FIELDS}
    problems += ckpt.diff_dicts(stored_tc, req_tc, "train_config")
    problems += ckpt.diff_dicts(meta.get("extra", {}), requested["extra"], "extra")
    problems += ckpt.diff_dicts(meta.get("input_shapes", {}), requested["input_shapes"],
                                "input_shapes")
    problems += ckpt.diff_dicts(meta.get("model_class"), requested["model_class"], "model_class")
    if problems:
        raise ConfigMismatchError(
            f"{out_dir!r} holds a checkpoint (step {meta.get('step')}) written with different "
            "settings than requested, so it cannot be resumed: " + "; ".join(problems)
            + ". Use a new out_dir or the stored settings.")


def _resume(out_dir: str, init_fn, metadata: dict, repl):
    """(step, state, stored metadata) of the newest readable checkpoint in out_dir, or
    (None, None, None) if there is none. A corrupted newer checkpoint is reported, moved aside
    (renamed ``corrupt-<step>-<time>``) and the previous one is used."""
    steps = ckpt.all_steps(out_dir)
    damaged = []
    for step in reversed(steps):
        try:
            stored = ckpt.read_metadata(out_dir, step)
            _check_resume(stored, ckpt.config_to_dict(metadata), out_dir)
            abstract = jax.eval_shape(init_fn)
            abstract = jax.tree_util.tree_map(
                lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=repl), abstract)
            state, _ = ckpt.load_checkpoint(out_dir, step, target=abstract)
        except ckpt.CorruptCheckpointError as e:
            damaged.append((step, e))
            continue
        if int(state.step) != step:
            raise ValueError(f"checkpoint {step} in {out_dir!r} holds step {int(state.step)}")
        for bad, error in damaged:
            aside = os.path.join(out_dir, f"corrupt-{bad}-{int(time.time())}")
            os.replace(os.path.join(out_dir, str(bad)), aside)
            warnings.warn(f"{error}; moved it to {aside} and resumed from step {step}",
                          stacklevel=3)
        return step, state, stored
    if damaged:
        raise ckpt.CorruptCheckpointError(
            f"no readable checkpoint in {out_dir!r} (" + "; ".join(str(e) for _, e in damaged)
            + "): delete the directory to start over")
    return None, None, None


def train(model, model_config, train_config: TrainConfig, batch_fn: Callable, out_dir: str, *,
          init_batch: Optional[Batch] = None, progress: bool = True,
          extra_metadata: Optional[Mapping[str, Any]] = None,
          val_batch_fn: Optional[Callable] = None, mesh=None, tensorboard: bool = True,
          callback: Optional[Callable[[int, dict], None]] = None) -> TrainResult:
    """Trains ``model`` (resuming from ``out_dir`` if it holds a checkpoint).

    Args:
      model: flax linen module, ``model.apply({"params": p}, x_t (B,H,W,C+G), t (B,),
        tokens (B,L)) -> eps (B,H,W,G)``.
      model_config: its config (object with ``to_dict()``/``from_dict()``, or a dict); stored
        in the checkpoints together with the classes of model and config.
      train_config: a ``TrainConfig``.
      batch_fn: pure, jit-able ``batch_fn(key, batch_size) -> Batch``; called inside ``jit``
        with the key of the step (a function of (seed, step) only).
      out_dir: where checkpoints, ``config.json``, ``metrics.jsonl`` and ``tb/`` go.
      init_batch: a Batch (arrays or ShapeDtypeStructs) giving the input shapes; default
        ``batch_fn(key, 1)`` evaluated abstractly (``jax.eval_shape``).
      progress: show a tqdm bar (loss, steps/s).
      extra_metadata: JSON-serialisable dict stored with the checkpoints (e.g. data settings);
        must match when resuming.
      val_batch_fn: like ``batch_fn`` for validation (default ``batch_fn`` with fixed
        validation keys); used when ``train_config.val_every > 0``.
      mesh: a ``diffplan.sharding.data_mesh`` (default: all devices).
      tensorboard: also log to ``out_dir/tb`` if tensorboardX is importable.
      callback: called as ``callback(step, record)`` after every metrics record and every
        checkpoint (record: the latest metrics record, or None), once that step's checkpoint
        (if any) is written; it may raise to stop training (a checkpoint of this very step is
        kept, nothing later is saved).

    Returns:
      ``TrainResult(state, final_loss, last_metrics)``.

    Raises:
      ConfigMismatchError (a ValueError): ``out_dir`` holds a checkpoint of other settings.
      NonFiniteLossError: the loss became NaN/inf (the last good checkpoint stays intact).
      ValueError: batch size not divisible by the number of devices, bad batch shapes.
    """
    cfg = train_config
    if not isinstance(cfg, TrainConfig):
        raise ValueError(f"train_config must be a TrainConfig, got {type(cfg).__name__}")
    mesh = shd.data_mesh() if mesh is None else mesh
    shd.check_divisible(cfg.batch_size, mesh)
    os.makedirs(out_dir, exist_ok=True)
    repl = shd.replicated_sharding(mesh)

    init_key, _, _ = _root_keys(cfg.seed)
    if init_batch is None:
        init_batch = jax.eval_shape(lambda k: batch_fn(k, 1), init_key)
    init_batch = Batch(*init_batch)
    _check_batch(jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype),
                                        init_batch), cfg.num_gen_channels)
    metadata = checkpoint_metadata(model, model_config, cfg, init_batch, extra_metadata)

    # ---- state: fresh or resumed
    _static(model, "model")
    _static(batch_fn, "batch_fn")
    init_fn = lambda: init_train_state(model, cfg, init_batch)  # noqa: E731
    last_ckpt, state, stored = _resume(out_dir, init_fn, metadata, repl)
    wall_before = 0.0
    if state is not None:
        wall_before = float(stored.get("wall_time", 0.0))
    else:
        state = shd.replicate(init_fn(), mesh)
    start = int(state.step)
    with open(os.path.join(out_dir, "config.json"), "w") as f:
        json.dump(metadata, f, indent=2, sort_keys=True)
    metrics_path = os.path.join(out_dir, "metrics.jsonl")
    _truncate_metrics(metrics_path, start)
    if start >= cfg.steps:
        return TrainResult(state, None, None)

    _, data_root, val_root = shd.replicate(_root_keys(cfg.seed), mesh)
    train_step = make_train_step(model, cfg, mesh=mesh)
    val_fn = None
    if cfg.val_every > 0:
        val_cfg = dataclasses.replace(_compute_cfg(cfg), val_batches=cfg.val_batches)
        val_fn = functools.partial(
            _val_loss, val_root=val_root,
            alphas_cumprod=shd.replicate(_alphas_cumprod(cfg), mesh), model=model,
            config=val_cfg, batch_fn=_static(val_batch_fn or batch_fn, "val_batch_fn"),
            mesh=mesh)

    writer = None
    if tensorboard:
        try:
            from tensorboardX import SummaryWriter
            writer = SummaryWriter(os.path.join(out_dir, "tb"))
        except ImportError:
            writer = None
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=cfg.steps, initial=start, desc="train", dynamic_ncols=True)

    t0 = time.perf_counter()
    t_last, step_last = t0, start
    window = _Window()
    final_loss, last_record = None, None

    def check_finite(step):
        bad = window.fetch()
        if bad is None:
            return
        where = (f"the last good checkpoint is step {last_ckpt} in {out_dir!r} (left intact)"
                 if last_ckpt is not None else "no checkpoint had been saved yet")
        raise NonFiniteLossError(
            f"training stopped: non-finite loss or gradient norm at step {bad} (detected at "
            f"step {step} of {cfg.steps}); {where}. Check the data (batch_fn) and the "
            "learning rate.", bad, last_ckpt)

    try:
        for i in range(start, cfg.steps):
            batch, loss_key = _draw_batch(data_root, i, batch_fn=batch_fn,
                                          batch_size=cfg.batch_size, mesh=mesh)
            state, metrics = train_step.placed(state, batch, loss_key)
            done = i + 1
            window.add(done, metrics)
            is_last = done == cfg.steps
            do_log = done % cfg.log_every == 0 or is_last
            do_ckpt = done % cfg.checkpoint_every == 0 or is_last
            do_val = val_fn is not None and (done % cfg.val_every == 0 or is_last)
            if bar is not None:
                bar.update(1)
            if not (do_log or do_ckpt or do_val) and (done - start) % _SYNC_EVERY:
                continue
            check_finite(done)
            if do_log or do_val:
                now = time.perf_counter()
                record = {"step": done, **window.summary(),
                          "steps_per_sec": (done - step_last) / max(now - t_last, 1e-9),
                          "wall_time": wall_before + now - t0}
                if do_val:
                    record["val_loss"] = float(val_fn(state.ema_params))
                final_loss = record["loss"]
                last_record = record
                t_last, step_last = time.perf_counter(), done
                try:
                    with open(metrics_path, "a") as f:
                        f.write(json.dumps(record) + "\n")
                except OSError as e:
                    raise OutputWriteError(
                        f"could not append to {metrics_path} ({e.strerror or e}); "
                        + (f"the last good checkpoint is step {last_ckpt}" if last_ckpt
                           is not None else "no checkpoint had been saved yet")) from e
                if writer is not None:
                    for k, v in record.items():
                        if k != "step":
                            writer.add_scalar(f"train/{k}", v, done)
                if bar is not None:
                    bar.set_postfix(loss=f"{record['loss']:.4f}",
                                    steps_s=f"{record['steps_per_sec']:.2f}")
            if do_ckpt:
                meta = dict(metadata, wall_time=wall_before + time.perf_counter() - t0)
                if final_loss is not None:
                    meta["last_loss"] = final_loss
                t_save = time.perf_counter()
                ckpt.save_checkpoint(out_dir, done, state, meta)
                last_ckpt = done
                t_last += time.perf_counter() - t_save  # steps/s measures training only
            if callback is not None and (do_log or do_val or do_ckpt):
                callback(done, last_record)
    finally:
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.close()
    return TrainResult(state, final_loss, last_record)
