"""The appendix's network of BC and CQL, and what every baseline's training and acting shares.

The network sees what the planner's agent sees, the world's condition channels (B, H, W, C),
and the instruction as a goal vector (B, G) that the world computes from it (the paper gives
BC and CQL "the goal" as a one-hot vector; e.g. ``envs.gridworld.baselines.goal_vector``).
Nothing here knows a world: shapes come from the caller. The network is registered in
``diffplan.models`` (the key of checkpoints written when it lived in ``common.py`` is an alias).
"""
from __future__ import annotations

import dataclasses
from typing import Callable, Mapping

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from diffplan import models
from diffplan.train import TrainState

__all__ = ["ConvNetConfig", "GoalConvNet", "init_net", "init_state", "greedy_act",
           "GreedyAct", "action_cross_entropy", "argmax_actions", "config_dict"]


@dataclasses.dataclass(frozen=True)
class ConvNetConfig:
    """The appendix's network of BC and CQL: two 3x3 conv layers of ``channels`` (ReLU), then
    two dense layers of ``hidden`` units (ReLU) with the goal vector concatenated to the first
    one's output, i.e. before the last of the two, then a linear head of ``num_outputs`` (action
    logits for BC, Q-values for CQL)."""

    channels: int = 16
    hidden: int = 40
    num_outputs: int = 4

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d) -> "ConvNetConfig":
        return cls(**dict(d))


class GoalConvNet(nn.Module):
    """(condition float32 (B, H, W, C), goal vector float32 (B, G)) -> (B, num_outputs)."""

    config: ConvNetConfig

    @nn.compact
    def __call__(self, condition, goal):
        cfg = self.config
        x = condition.astype(jnp.float32)
        x = nn.relu(nn.Conv(cfg.channels, (3, 3), name="conv1")(x))
        x = nn.relu(nn.Conv(cfg.channels, (3, 3), name="conv2")(x))
        x = x.reshape(x.shape[0], -1)
        x = nn.relu(nn.Dense(cfg.hidden, name="dense1")(x))
        x = jnp.concatenate([x, goal.astype(jnp.float32)], axis=-1)
        x = nn.relu(nn.Dense(cfg.hidden, name="dense2")(x))
        return nn.Dense(cfg.num_outputs, name="head")(x)


def conv_net_inputs(input_shapes: Mapping[str, tuple]) -> tuple:
    """The example inputs (condition, goal) of a GoalConvNet from a checkpoint's input_shapes
    {"condition": [1, H, W, C], "goal": [1, G]} (diffplan.models). Checkpoints written before
    the goal vector left the network store the instruction's shape ("tokens") instead: they
    load through diffplan.baselines.policies.load_policy, which takes G from the world."""
    if "goal" not in input_shapes:
        raise ValueError("the checkpoint's input_shapes name no goal vector (it predates the "
                         "network's goal input): load it with diffplan.baselines.policies."
                         "load_policy(name, directory, world)")
    return tuple(jax.ShapeDtypeStruct(tuple(input_shapes[k]), jnp.float32)
                 for k in ("condition", "goal"))


models.register_model(models.class_path(GoalConvNet), GoalConvNet, ConvNetConfig,
                      inputs=conv_net_inputs)


def init_net(model, key, input_shapes: Mapping[str, tuple]):
    """The params of a (condition, goal) network: input_shapes {"condition": (1, H, W, C),
    "goal": (1, G)} (the inputs' values do not matter, only their shapes)."""
    return model.init(key, jnp.zeros(input_shapes["condition"], jnp.float32),
                      jnp.zeros(input_shapes["goal"], jnp.float32))["params"]


def init_state(model, optimizer, seed: int, input_shapes: Mapping[str, tuple]) -> TrainState:
    """The initial TrainState of a (condition, goal) network (params from PRNGKey(seed); the
    EMA slot holds a copy of the params, CQL's target network)."""
    params = init_net(model, jax.random.PRNGKey(seed), input_shapes)
    return TrainState(params=params, ema_params=params, opt_state=optimizer.init(params),
                      step=jnp.zeros((), jnp.int32))


def greedy_act(model, goal_fn: Callable, heads: int = 1, action_fn: Callable | None = None,
               decide: Callable | None = None) -> "GreedyAct":
    """act_fn(params, conditions, tokens, keys) -> argmax actions, for
    :func:`diffplan.baselines.rollout.policy_rollout`: int32 (B,), or with heads > 1 int32
    (B, heads) (the outputs split into equal heads, as ``bc.bc_loss`` trains them), then
    mapped by action_fn (default: the indices are the actions). goal_fn(tokens (B, L)) -> goal
    vectors (B, G) and action_fn are the world's (hashable: module-level functions). A world
    whose action is chosen in several greedy decisions (e.g. a cell to pick, then one to place
    on, each with what the previous ones chose in the network's goal input) gives
    decide(outputs_fn, conditions, goals) -> actions instead, outputs_fn(goal inputs (B, G'))
    -> the network's outputs (B, num_outputs) on the conditions (heads and action_fn unused).
    Hashable per (model, goal_fn, heads, action_fn, decide): one compilation serves every
    checkpoint of the same architecture."""
    return GreedyAct(model, goal_fn, heads, action_fn, decide)


@dataclasses.dataclass(frozen=True)
class GreedyAct:
    model: nn.Module
    goal_fn: Callable
    heads: int = 1
    action_fn: Callable | None = None
    decide: Callable | None = None

    def __call__(self, params, conditions, tokens, keys):
        del keys
        if self.decide is not None:
            return self.decide(lambda goals: self.model.apply({"params": params}, conditions,
                                                              goals),
                               conditions, self.goal_fn(tokens))
        out = self.model.apply({"params": params}, conditions, self.goal_fn(tokens))
        actions = argmax_actions(out, self.heads)
        return actions if self.action_fn is None else self.action_fn(actions)


def action_cross_entropy(logits, actions):
    """(mean cross-entropy, accuracy) of action logits (B, A) against expert actions int32 (B,)
    (one choice of A), or (B, K) for an action made of K choices of A / K each (the logits split
    into K equal heads, e.g. a pick cell and a place cell: their summed cross-entropy, the
    accuracy that of the whole action)."""
    logits = logits.reshape(actions.shape + (-1,))
    ce = optax.softmax_cross_entropy_with_integer_labels(logits, actions)
    right = (jnp.argmax(logits, -1) == actions).reshape(actions.shape[0], -1).all(-1)
    return ce.reshape(actions.shape[0], -1).sum(-1).mean(), jnp.mean(right)


def argmax_actions(outputs, heads: int = 1):
    """int32 (B,) the argmax of outputs (B, A), or (B, heads) that of each of ``heads`` equal
    parts (as :func:`action_cross_entropy` trains them)."""
    if heads > 1:
        outputs = outputs.reshape(outputs.shape[0], heads, -1)
    return jnp.argmax(outputs, axis=-1).astype(jnp.int32)


def config_dict(config, data: Mapping | None = None) -> dict:
    """A training config dataclass as JSON-ready metadata, with the world's description of its
    training data (e.g. the grid world's mixture of settings) merged in."""
    return {**dataclasses.asdict(config), **dict(data or {})}
