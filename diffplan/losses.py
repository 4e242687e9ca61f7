"""The denoiser's objective: the DDPM noise-prediction loss on the generated channels, and the
optimisation step built on it.

The planning tensor ``x0`` is (B, H, W, C + G): C condition channels (kept clean) then G
generated channels (path, goal). One training step (the paper's objective, sec. 3.3):

    t   ~ U{0, ..., T-1}                  (B,)   (or skewed to noisier t: draw_timesteps)
    eps ~ N(0, 1)                         (B, H, W, G)   generated channels only
    x_t = [x0[..., :C],  sqrt(ab_t) x0[..., C:] + sqrt(1 - ab_t) eps]
    L   = sum(loss_mask * (eps_theta(x_t, t, tokens) - eps)^2) / sum(loss_mask)

with ``ab = cosine_schedule(T).alphas_cumprod`` (target x0[..., C:] instead of eps for
``prediction="x0"``). ``loss_mask`` (B, H, W, G) lets the caller drop parts of the loss (e.g.
the goal channel outside the seen area).

Optionally a batch labels instruction tokens (``Batch.token_labels``, ``token_weights``), and the
step adds :func:`token_loss`, a weighted cross-entropy of the denoiser's token head
(``DenoiserConfig.token_classes``) on those labels: an auxiliary signal that the text features
must carry what the labels say (in the Kuka world: which named block goes on top).
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import optax

from diffplan import sharding as shd
from diffplan.schedule import cosine_schedule
from diffplan.train_state import (TrainConfig, TrainState, hashable, is_frozen,
                                  lr_schedule, make_optimizer)

__all__ = ["Batch", "check_batch", "with_token_labels", "diffusion_loss", "draw_timesteps",
           "token_loss", "make_train_step", "make_val_loss"]


class Batch(NamedTuple):
    """One training batch.

    Attributes:
      x0: float32 (B, H, W, C + G), the clean planning tensor (conditions, then generated).
      tokens: int32 (B, L), instruction token ids, 0 = padding; or float32 (B, L, D), a
        pretrained text encoder's token features, 0 = padding (a denoiser with
        ``DenoiserConfig.context_dim`` D; ``diffplan.instruction``).
      loss_mask: float32 (B, H, W, G), weight of each generated entry in the loss.
      token_labels: None, or int32 (B, L): a class in [0, K) for each token (any value where
        its weight is 0), K the denoiser's ``token_classes``.
      token_weights: None (exactly when token_labels is), or float32 (B, L): the weight of each
        token's cross-entropy in :func:`token_loss` (0 = unlabelled).
    """

    x0: jax.Array
    tokens: jax.Array
    loss_mask: jax.Array
    token_labels: Optional[jax.Array] = None
    token_weights: Optional[jax.Array] = None


def check_batch(batch: Batch, num_gen_channels: int) -> None:
    """Raises ValueError unless the batch's shapes fit (x0 (B, H, W, C+G) with 0 < G <= C+G,
    tokens (B, L), loss_mask (B, H, W, G), token labels and weights both absent or both
    (B, L)); arrays or ShapeDtypeStructs."""
    x0, tokens, mask = batch[:3]
    if len(x0.shape) != 4:
        raise ValueError(f"Batch.x0 must be (B, H, W, C+G), got shape {tuple(x0.shape)}")
    B, H, W, CG = x0.shape
    if not 0 < num_gen_channels <= CG:
        raise ValueError(f"num_gen_channels={num_gen_channels} must be in [1, {CG}] "
                         f"(x0 has {CG} channels)")
    if len(tokens.shape) not in (2, 3) or tokens.shape[0] != B:
        raise ValueError(f"Batch.tokens must be (B={B}, L) token ids or (B={B}, L, D) "
                         f"features, got shape {tuple(tokens.shape)}")
    if tuple(mask.shape) != (B, H, W, num_gen_channels):
        raise ValueError(f"Batch.loss_mask must be {(B, H, W, num_gen_channels)}, got "
                         f"{tuple(mask.shape)}")
    labels, weights = (tuple(batch[3:]) + (None, None))[:2]
    if (labels is None) != (weights is None):
        raise ValueError("Batch.token_labels and Batch.token_weights come together: give both "
                         "or neither")
    for name, value in (("token_labels", labels), ("token_weights", weights)):
        if value is not None and tuple(value.shape) != tuple(tokens.shape[:2]):
            raise ValueError(f"Batch.{name} must have the tokens' shape "
                             f"{tuple(tokens.shape[:2])}, got {tuple(value.shape)}")


def with_token_labels(batch: Batch, labels: jax.Array, labelled: jax.Array,
                      weight: float) -> Batch:
    """``batch`` with token labels (int (B, L)) weighted ``weight`` where ``labelled`` (bool
    (B, L)), 0 elsewhere; the batch unchanged when weight is 0 (no token loss: the step then
    matches a batch that never had labels)."""
    if not weight:
        return batch
    return batch._replace(token_labels=labels.astype(jnp.int32),
                          token_weights=jnp.where(labelled, jnp.float32(weight), 0.0))


def draw_timesteps(key: jax.Array, batch_size: int, num_timesteps: int,
                   power: float = 1.0) -> jax.Array:
    """int32 (batch_size,) training timesteps in [0, num_timesteps): uniform at power 1 (the
    paper's draw, exactly ``jax.random.randint``); otherwise floor(T * u ** (1 / power)), u ~
    U[0, 1), so P(t < k) = (k / T) ** power: a power > 1 draws the noisier timesteps more
    often. The loss at each t keeps its target, so only how often each t is trained changes."""
    if power == 1.0:
        return jax.random.randint(key, (batch_size,), 0, num_timesteps, dtype=jnp.int32)
    u = jax.random.uniform(key, (batch_size,), jnp.float32)
    t = jnp.floor(num_timesteps * u ** (1.0 / power)).astype(jnp.int32)
    return jnp.clip(t, 0, num_timesteps - 1)


def with_sentences(batch: Batch, sentences=None) -> Batch:
    """The batch as the network reads it: unchanged without a sentence table; with one
    (``diffplan.instruction.SentenceTable``), ``batch.tokens`` holds sentence ids int (B, S)
    (-1 = absent) and becomes their assembled features float32 (B, L, D)."""
    if sentences is None:
        return batch
    from diffplan.instruction import assemble_batch

    return batch._replace(tokens=assemble_batch(sentences, batch.tokens))


def instruction_input(tokens):
    """What the network reads of Batch.tokens: int32 token ids (B, L), or float32 features
    (B, L, D) as they are."""
    return tokens.astype(jnp.float32 if tokens.ndim == 3 else jnp.int32)


def diffusion_loss(params, apply_fn: Callable, batch: Batch, key: jax.Array,
                   alphas_cumprod: jax.Array, num_gen_channels: int, prediction: str = "eps",
                   timestep_power: float = 1.0):
    """The masked noise-prediction MSE of one batch.

    Args:
      params: model ``params`` collection.
      apply_fn: ``apply_fn({"params": params}, x_t, t, tokens) -> eps`` (B, H, W, G).
      batch: a ``Batch``.
      key: PRNG key (timesteps and noise).
      alphas_cumprod: float32 (T,).
      num_gen_channels: G.
      prediction: "eps" (target: the noise) or "x0" (target: the clean generated channels).
      timestep_power: how timesteps are drawn (:func:`draw_timesteps`; 1: uniform).

    Returns:
      (loss scalar, aux dict with ``t`` (B,) and ``mask_sum``).
    """
    check_batch(batch, num_gen_channels)
    x0, tokens, loss_mask = batch[:3]
    x0 = x0.astype(jnp.float32)
    G = num_gen_channels
    C = x0.shape[-1] - G
    B = x0.shape[0]
    T = alphas_cumprod.shape[0]
    t_key, eps_key = jax.random.split(key)
    t = draw_timesteps(t_key, B, T, timestep_power)
    eps = jax.random.normal(eps_key, x0.shape[:-1] + (G,), jnp.float32)
    ab = alphas_cumprod[t][:, None, None, None]
    x_gen = jnp.sqrt(ab) * x0[..., C:] + jnp.sqrt(1.0 - ab) * eps
    x_t = jnp.concatenate([x0[..., :C], x_gen], axis=-1)
    pred = apply_fn({"params": params}, x_t, t, instruction_input(tokens))
    if pred.shape != eps.shape:
        raise ValueError(f"model output shape {pred.shape} != generated-channel shape "
                         f"{eps.shape}")
    mask = loss_mask.astype(jnp.float32)
    msum = jnp.sum(mask)
    target = eps if prediction == "eps" else x0[..., C:]
    sq = jnp.sum(mask * jnp.square(pred.astype(jnp.float32) - target))
    loss = jnp.where(msum > 0, sq / jnp.maximum(msum, 1e-12), 0.0)
    return loss, {"t": t, "mask_sum": msum}


def token_loss(params, logits_fn: Callable, batch: Batch):
    """The weighted cross-entropy of the token head on a batch's token labels:
    sum(w * CE(logits, label)) / max(#(w > 0), 1), so a constant weight lam on the labelled
    tokens gives lam times their mean cross-entropy.

    logits_fn: ``logits_fn({"params": params}, tokens (B, L)) -> (B, L, K)``; batch: a
    ``Batch`` with token_labels and token_weights. Returns a scalar.
    """
    logits = logits_fn({"params": params}, batch.tokens.astype(jnp.int32)).astype(jnp.float32)
    weights = batch.token_weights.astype(jnp.float32)
    labels = jnp.where(weights > 0, batch.token_labels, 0).astype(jnp.int32)
    ce = optax.softmax_cross_entropy_with_integer_labels(logits, labels)
    return jnp.sum(weights * ce) / jnp.maximum(jnp.sum(weights > 0), 1)


# ------------------------------------------------------------------------------- the step

def goal_loss(params, logits_fn: Callable, batch: Batch):
    """The learned-goal baseline's loss (``TrainConfig.objective = "goal"``): for each
    generated channel after the path (g >= 1), the cross-entropy of the network's logits over
    the H x W cells against the cell where the clean plan holds its maximum (the goal, the
    sub-goal), over the examples whose loss mask weighs that channel anywhere.

    logits_fn: ``logits_fn({"params": params}, x0, t, tokens) -> (B, H, W, G)`` (the model
    reads the conditions alone, e.g. ``GoalClassifier.logits``). Returns (mean cross-entropy
    over channels and examples, accuracy: the share of those argmax cells it ranks first)."""
    x0, tokens, loss_mask = batch[:3]
    x0 = x0.astype(jnp.float32)
    g_all = loss_mask.shape[-1]
    c = x0.shape[-1] - g_all
    logits = logits_fn({"params": params}, x0, jnp.zeros(x0.shape[:1], jnp.int32),
                       instruction_input(tokens)).astype(jnp.float32)
    b = x0.shape[0]
    total, hits, count = 0.0, 0.0, 0.0
    for g in range(1, g_all):
        flat = logits[..., g].reshape(b, -1)
        target = jnp.argmax(x0[..., c + g].reshape(b, -1), axis=-1)
        weight = (loss_mask[..., g].reshape(b, -1).max(-1) > 0).astype(jnp.float32)
        ce = -jnp.take_along_axis(jax.nn.log_softmax(flat, -1), target[:, None], -1)[:, 0]
        total = total + jnp.sum(weight * ce)
        hits = hits + jnp.sum(weight * (jnp.argmax(flat, -1) == target))
        count = count + jnp.sum(weight)
    count = jnp.maximum(count, 1.0)
    return total / count, hits / count


def _alphas_cumprod(config: TrainConfig) -> jax.Array:
    return cosine_schedule(config.num_train_timesteps).alphas_cumprod


def _compute_cfg(config: TrainConfig) -> TrainConfig:
    """``config`` with the fields that do not enter the optimisation step normalised, so the
    compiled step is shared by runs that differ only in seed, logging or checkpointing (the
    seed enters through the keys, which are arguments)."""
    return dataclasses.replace(config, seed=0, checkpoint_every=1, log_every=1, val_every=0,
                               val_batches=1)


def _make_core_step(model, config: TrainConfig, alphas_cumprod):
    """The un-jitted pure step: (state, batch, key) -> (state, metrics)."""
    optimizer = make_optimizer(config)
    schedule = lr_schedule(config)
    G = config.num_gen_channels
    ab = jnp.asarray(alphas_cumprod, jnp.float32)

    def core(state: TrainState, batch: Batch, key: jax.Array):
        def loss_fn(p):
            if config.objective == "goal":
                loss, accuracy = goal_loss(p, functools.partial(model.apply, method="logits"),
                                           batch)
                return loss, {"accuracy": accuracy}
            loss, _ = diffusion_loss(p, model.apply, batch, key, ab, G, config.prediction,
                                     config.timestep_power)
            if batch.token_labels is None:
                return loss, {}
            tl = token_loss(p, functools.partial(model.apply, method="token_logits"), batch)
            return loss + tl, {"diffusion_loss": loss, "token_loss": tl}

        (loss, parts), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        grad_norm = optax.tree.norm(grads)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        n = state.step.astype(jnp.float32)
        decay = jnp.minimum(config.ema_decay, (1.0 + n) / (10.0 + n))
        ema = jax.tree_util.tree_map_with_path(
            lambda path, e, p: e if is_frozen(path) else decay * e + (1.0 - decay) * p,
            state.ema_params, params)  # a frozen constant stays exactly as written
        new_state = TrainState(params=params, ema_params=ema, opt_state=opt_state,
                               step=state.step + 1)
        metrics = {"loss": loss, "grad_norm": grad_norm, "lr": schedule(state.step), **parts}
        return new_state, metrics

    return core


@functools.partial(jax.jit, static_argnames=("model", "config", "mesh"))
def _train_step_jit(state, batch, key, alphas_cumprod, *, model, config, mesh):
    state = shd.constrain_replicated(state, mesh)
    batch = shd.constrain_batch(batch, mesh)
    new_state, metrics = _make_core_step(model, config, alphas_cumprod)(state, batch, key)
    return shd.constrain_replicated((new_state, metrics), mesh)


def make_train_step(model, config: TrainConfig, *, mesh=None, alphas_cumprod=None):
    """A jitted pure ``train_step(state, batch, key) -> (state, metrics)``: the loss's
    gradient (the diffusion loss, plus :func:`token_loss` when the batch labels tokens),
    clipped AdamW, then the EMA update (``TrainState``).

    The batch is split over the ``"data"`` axis of ``mesh`` (default: all devices); state,
    key and metrics (``loss``, ``grad_norm``, ``lr``: scalars; with token labels also
    ``diffusion_loss`` and ``token_loss``) are replicated. A thin wrapper places the inputs
    (a no-op when they already are; ``train_step.placed`` skips it) and calls a jitted
    function whose compilation is cached per (model, config without seed and logging
    fields, mesh): ``diffplan.train.train`` uses the same compiled step.
    """
    mesh = shd.data_mesh() if mesh is None else mesh
    ab = _alphas_cumprod(config) if alphas_cumprod is None else jnp.asarray(alphas_cumprod)
    ab = shd.replicate(ab, mesh)
    cfg = _compute_cfg(config)
    hashable(model, "model")

    def placed(state: TrainState, batch: Batch, key: jax.Array):
        return _train_step_jit(state, batch, key, ab, model=model, config=cfg, mesh=mesh)

    def train_step(state: TrainState, batch: Batch, key: jax.Array):
        return placed(shd.replicate(state, mesh), shd.shard_batch(Batch(*batch), mesh),
                      shd.replicate(key, mesh))

    train_step.placed = placed
    return train_step


@functools.partial(jax.jit, static_argnames=("model", "config", "batch_fn", "mesh"))
def _val_loss(params, sentences, val_root, alphas_cumprod, *, model, config, batch_fn, mesh):
    """Mean loss of ``params`` over ``config.val_batches`` batches with fixed keys (timesteps
    drawn uniformly whatever ``config.timestep_power``: the paper's objective, comparable
    across recipes); sentence ids assembled from ``sentences`` when given
    (:func:`with_sentences`)."""
    def body(total, j):
        batch_key, loss_key = jax.random.split(jax.random.fold_in(val_root, j))
        batch = with_sentences(Batch(*batch_fn(batch_key, config.batch_size)), sentences)
        batch = shd.constrain_batch(batch, mesh)
        loss, _ = diffusion_loss(params, model.apply, batch, loss_key, alphas_cumprod,
                                 config.num_gen_channels, config.prediction)
        return total + loss, None

    total, _ = jax.lax.scan(body, jnp.zeros((), jnp.float32), jnp.arange(config.val_batches))
    return shd.constrain_replicated(total / config.val_batches, mesh)


def make_val_loss(model, config: TrainConfig, batch_fn: Callable, val_root: jax.Array, *,
                  mesh) -> Callable:
    """``val_loss(params, sentences=None) -> scalar``: the mean loss over
    ``config.val_batches`` batches of ``batch_fn`` whose keys are fixed by ``val_root`` (batch
    j: ``fold_in(val_root, j)``); ``sentences``: the sentence table of a batch_fn that draws
    sentence ids (``diffplan.train.train``)."""
    cfg = dataclasses.replace(_compute_cfg(config), val_batches=config.val_batches)
    loss = functools.partial(
        _val_loss, val_root=shd.replicate(val_root, mesh),
        alphas_cumprod=shd.replicate(_alphas_cumprod(config), mesh), model=model, config=cfg,
        batch_fn=hashable(batch_fn, "val_batch_fn"), mesh=mesh)
    return lambda params, sentences=None: loss(params, sentences)
