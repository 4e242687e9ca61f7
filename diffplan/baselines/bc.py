"""Behaviour cloning (the paper's BC baseline, appendix): the conv network of
:class:`diffplan.baselines.common.GoalConvNet` learns the expert's move (cross-entropy) in the
states along expert shortest paths (the A* paths of the paper: ``Episode.expert_positions``,
the field of view accumulated along the way), in the planner's mixture of settings; Adam, lr
1e-3 (the appendix's learning rate). It acts greedily (argmax of its logits).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax

from diffplan.baselines import common
from diffplan.baselines.loop import fit, run_metadata
from diffplan.train import TrainState
from envs.gridworld import grammar
from envs.gridworld.task import NUM_COND_CHANNELS, condition_from_observation
from envs.gridworld import env

__all__ = ["BCTrainConfig", "bc_batch", "bc_loss", "make_bc_step", "train_bc", "act_fn"]


@dataclasses.dataclass(frozen=True)
class BCTrainConfig:
    """seed, steps, batch_size (a multiple of the mixture's sum), lr (Adam), the mixture of
    settings ((setting, count) per sum(counts) examples), checkpoint_every / log_every."""

    seed: int = 0
    steps: int = 10000
    batch_size: int = 128
    lr: float = 1e-3
    mixture: tuple = common.TRAINING_MIXTURE
    checkpoint_every: int = 2000
    log_every: int = 100


def _example(key, config):
    episode, state, _, move = common.expert_example(key, config)
    condition = condition_from_observation(env.observe(state, config))
    return condition, episode.tokens, move


def bc_batch(key, batch_size: int, mixture=common.TRAINING_MIXTURE):
    """(conditions float32 (B, 16, 16, 5), tokens int32 (B, L), expert moves int32 (B,))."""
    return common.mixture_examples(_example, key, batch_size, mixture)


def bc_loss(params, model, conditions, tokens, moves):
    """Mean cross-entropy of the model's move logits against the expert moves, and accuracy."""
    logits = model.apply({"params": params}, conditions, tokens)
    loss = optax.softmax_cross_entropy_with_integer_labels(logits, moves).mean()
    return loss, jnp.mean(jnp.argmax(logits, -1) == moves)


def make_bc_step(model, optimizer, batch_fn):
    """step(state, key, data) -> (state, metrics): one Adam step on batch_fn(key) =
    (conditions, tokens, moves) (data unused)."""

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


def init_state(model, optimizer, seed: int) -> TrainState:
    params = common.init_net(model, jax.random.PRNGKey(seed))
    return TrainState(params=params, ema_params=params, opt_state=optimizer.init(params),
                      step=jnp.zeros((), jnp.int32))


def input_shapes(size: int = 16) -> dict:
    return {"condition": [1, size, size, NUM_COND_CHANNELS], "tokens": [1, grammar.MAX_TOKENS]}


def train_bc(out_dir: str, config: BCTrainConfig = BCTrainConfig(),
             net: common.ConvNetConfig = common.ConvNetConfig(), progress: bool = True):
    """Trains BC into out_dir (resuming); returns diffplan.baselines.loop.FitResult."""
    model = common.GoalConvNet(net)
    optimizer = optax.adam(config.lr)
    metadata = run_metadata(model, net, common.config_dict(config), input_shapes(),
                            {"baseline": "bc"})
    step = make_bc_step(model, optimizer,
                        lambda key: bc_batch(key, config.batch_size, config.mixture))
    return fit(step, lambda: init_state(model, optimizer, config.seed), steps=config.steps,
               seed=config.seed, out_dir=out_dir, metadata=metadata,
               checkpoint_every=config.checkpoint_every, log_every=config.log_every,
               progress=progress, desc="BC")


def act_fn(net: common.ConvNetConfig = common.ConvNetConfig()):
    """The greedy policy of a BC network (for policy_rollout)."""
    return common.greedy_act(common.GoalConvNet(net))
