"""Behaviour cloning (the paper's BC baseline, appendix): the conv network of
:class:`diffplan.baselines.nets.GoalConvNet` learns the expert's action (cross-entropy) on
batches of (condition, goal vector, expert action) that the world draws (e.g. the states along
the grid world's expert shortest paths, ``envs.gridworld.baselines.bc_batch``); Adam, lr 1e-3
(the appendix's learning rate). It acts greedily (argmax of its logits,
:func:`diffplan.baselines.nets.greedy_act`).
"""
from __future__ import annotations

import dataclasses
from typing import Callable, Mapping

import jax
import optax

from diffplan.baselines import nets
from diffplan.train import TrainState, fit, run_metadata

__all__ = ["BCTrainConfig", "bc_loss", "make_bc_step", "train_bc"]


@dataclasses.dataclass(frozen=True)
class BCTrainConfig:
    """seed, steps, batch_size, lr (Adam), checkpoint_every / log_every. What the batches hold
    (e.g. the grid world's mixture of settings) is the world's, recorded beside these."""

    seed: int = 0
    steps: int = 10000
    batch_size: int = 128
    lr: float = 1e-3
    checkpoint_every: int = 2000
    log_every: int = 100


def bc_loss(params, model, conditions, goals, actions):
    """(mean cross-entropy of the model's action logits against the expert actions, accuracy)
    for conditions (B, H, W, C) and goal vectors (B, G). actions int32 (B,) (one choice of
    num_outputs), or (B, K) for an action made of K choices of num_outputs / K each (the
    logits split into K equal heads, e.g. a pick cell and a place cell; the loss is their
    summed cross-entropy, the accuracy that of the whole action)."""
    return nets.action_cross_entropy(model.apply({"params": params}, conditions, goals),
                                     actions)


def make_bc_step(model, optimizer, batch_fn: Callable):
    """step(state, key, data) -> (state, metrics): one optimizer step on batch_fn(key) =
    (conditions, goals, actions) (data unused)."""

    def step(state: TrainState, key, data):
        del data
        batch = batch_fn(key)
        (loss, acc), grads = jax.value_and_grad(bc_loss, has_aux=True)(state.params, model,
                                                                       *batch)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        return (TrainState(params=params, ema_params=params, opt_state=opt_state,
                           step=state.step + 1), {"loss": loss, "accuracy": acc})

    return step


def train_bc(out_dir: str, batch_fn: Callable, input_shapes: Mapping[str, tuple],
             config: BCTrainConfig = BCTrainConfig(),
             net: nets.ConvNetConfig = nets.ConvNetConfig(), *, data: Mapping | None = None,
             progress: bool = True, callback: Callable | None = None):
    """Trains BC into out_dir (resuming); returns diffplan.train.FitResult.

    batch_fn(key, batch_size) -> (conditions (B, H, W, C), goals (B, G), actions int32 (B,) or
    (B, K): see :func:`bc_loss`): the world's expert examples. input_shapes: {"condition":
    (1, H, W, C), "goal": (1, G)}.
    data: the world's description of the batches, stored in the run's train config (a run of
    other data refuses to resume). callback: ``diffplan.train.fit``'s (after every record and
    checkpoint; it may raise to stop training, e.g. at a time budget)."""
    model = nets.GoalConvNet(net)
    optimizer = optax.adam(config.lr)
    metadata = run_metadata(model, net, nets.config_dict(config, data), dict(input_shapes),
                            {"baseline": "bc"})
    step = make_bc_step(model, optimizer, lambda key: batch_fn(key, config.batch_size))
    return fit(step, lambda: nets.init_state(model, optimizer, config.seed, input_shapes),
               steps=config.steps, seed=config.seed, out_dir=out_dir, metadata=metadata,
               checkpoint_every=config.checkpoint_every, log_every=config.log_every,
               progress=progress, desc="BC", callback=callback)
