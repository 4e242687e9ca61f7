"""What the grid-world baselines share: the goal vector, the appendix's conv network, expert
examples and the training mixture.

The baselines see what our agent sees: the condition channels of ``GridTask.condition`` (cell
token id as a float-valued integer, i.e. the objects' class ids in the grid; obstacle seen,
agent, visited, visible), never the hidden world, and the instruction's token ids. The
instruction reaches them as a one-hot goal vector (the paper's appendix), :func:`goal_vector`:

  [one-hot of the target's class (15) | one-hot of the reference's class (15, zeros without a
  reference) | one-hot of the compass direction (8, zeros without one)]  = GOAL_DIM floats.

The paper gives BC and CQL "the goal" as a one-hot vector; in P-MO2G the target is not visible
at first, so the reference and the direction, which the instruction names, are one-hot encoded
beside it (our planner reads the same words). The vector is read off the tokens: the target is
the last object word, the reference the first one when there are two (every template of
``envs.gridworld.grammar`` names the reference first), the direction any direction word.

Training data of every baseline comes from the training key stream
(``envs.gridworld.training.training_episode_keys``), never from the evaluation seeds, in the
planner's mixture of settings (``TRAINING_MIXTURE``: one model per baseline serves the three
settings, as one denoiser does).
"""
from __future__ import annotations

import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp

from envs.gridworld import bfs, grammar
from envs.gridworld.config import make_config
from envs.gridworld.episode import generate
from envs.gridworld.training import (TRAINING_MIXTURE, _state_along_expert,
                                     training_episode_keys)

NUM_CLASSES = len(grammar.OBJECT_NAMES)
NUM_DIRECTIONS = len(grammar.DIRECTIONS)
GOAL_DIM = 2 * NUM_CLASSES + NUM_DIRECTIONS
NUM_ACTIONS = 4


def goal_vector(tokens):
    """float32 (..., GOAL_DIM): the one-hot goal vector of instruction tokens int (..., L)
    (see the module docstring). Padding tokens (all 0) give the zero vector."""
    tokens = jnp.asarray(tokens, jnp.int32)
    length = tokens.shape[-1]
    cls = tokens - grammar.OBJECT_TOKEN_OFFSET
    is_object = (cls >= 0) & (cls < NUM_CLASSES)
    pos = jnp.arange(length)
    last = jnp.argmax(jnp.where(is_object, pos, -1), axis=-1)
    first = jnp.argmax(jnp.where(is_object, length - pos, -1), axis=-1)
    count = jnp.sum(is_object, axis=-1)
    target = jnp.take_along_axis(cls, last[..., None], axis=-1)[..., 0]
    reference = jnp.take_along_axis(cls, first[..., None], axis=-1)[..., 0]
    target_hot = jax.nn.one_hot(target, NUM_CLASSES) * (count >= 1)[..., None]
    reference_hot = jax.nn.one_hot(reference, NUM_CLASSES) * (count >= 2)[..., None]
    direction_hot = jnp.any(tokens[..., :, None] == jnp.asarray(grammar.DIRECTION_TOKEN_IDS),
                            axis=-2).astype(jnp.float32)
    return jnp.concatenate([target_hot, reference_hot, direction_hot], axis=-1)


@dataclasses.dataclass(frozen=True)
class ConvNetConfig:
    """The appendix's network of BC and CQL: two 3x3 conv layers of ``channels`` (ReLU), then
    two dense layers of ``hidden`` units (ReLU) with the goal vector concatenated to the first
    one's output, i.e. before the last of the two, then a linear head of ``num_outputs`` (action
    logits for BC, Q-values for CQL)."""

    channels: int = 16
    hidden: int = 40
    num_outputs: int = NUM_ACTIONS

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d) -> "ConvNetConfig":
        return cls(**dict(d))


class GoalConvNet(nn.Module):
    """(condition float32 (B, H, W, C), tokens int32 (B, L)) -> (B, num_outputs)."""

    config: ConvNetConfig

    @nn.compact
    def __call__(self, condition, tokens):
        cfg = self.config
        x = condition.astype(jnp.float32)
        x = nn.relu(nn.Conv(cfg.channels, (3, 3), name="conv1")(x))
        x = nn.relu(nn.Conv(cfg.channels, (3, 3), name="conv2")(x))
        x = x.reshape(x.shape[0], -1)
        x = nn.relu(nn.Dense(cfg.hidden, name="dense1")(x))
        x = jnp.concatenate([x, goal_vector(tokens)], axis=-1)
        x = nn.relu(nn.Dense(cfg.hidden, name="dense2")(x))
        return nn.Dense(cfg.num_outputs, name="head")(x)


def config_dict(config) -> dict:
    """A training config dataclass as JSON-ready metadata (its mixture as lists)."""
    d = dataclasses.asdict(config)
    if "mixture" in d:
        d["mixture"] = [list(m) for m in d["mixture"]]
    return d


def init_net(model, key, height: int = 16, width: int = 16, channels: int = 5):
    """The params of a (condition, tokens) network."""
    cond = jnp.zeros((1, height, width, channels), jnp.float32)
    tokens = jnp.zeros((1, grammar.MAX_TOKENS), jnp.int32)
    return model.init(key, cond, tokens)["params"]


def greedy_act(model):
    """act_fn(params, conditions, tokens, keys) -> argmax actions int32 (B,), for
    :func:`diffplan.baselines.rollout.policy_rollout`. Hashable per model (one compilation
    serves every checkpoint of the same architecture)."""
    return _GreedyAct(model)


@dataclasses.dataclass(frozen=True)
class _GreedyAct:
    model: nn.Module

    def __call__(self, params, conditions, tokens, keys):
        del keys
        out = self.model.apply({"params": params}, conditions, tokens)
        return jnp.argmax(out, axis=-1).astype(jnp.int32)


def move_index(src, dst):
    """int32 (): the action (0..3 = N, E, S, W) from cell src to its 4-neighbour dst (int32
    (2,) each); 0 if dst is not a neighbour."""
    return jnp.argmax(jnp.all(bfs.MOVES == (dst - src)[None, :], axis=-1)).astype(jnp.int32)


def expert_example(key, config):
    """(episode, state, index, move): an episode of ``config``, the state after ``index``
    expert moves (uniform in 0..expert_length - 1, the field of view accumulated along the
    way) and the expert's next move there."""
    k_episode, k_index = jax.random.split(key)
    episode = generate(k_episode, config)
    index = jax.random.randint(k_index, (), 0, jnp.maximum(episode.expert_length, 1))
    state = _state_along_expert(episode, config, index)
    positions = episode.expert_positions
    return episode, state, index, move_index(positions[index], positions[index + 1])


def mixture_examples(example_fn, key, batch_size: int, mixture=TRAINING_MIXTURE):
    """Examples of the settings in fixed proportions: ``example_fn(key, config)`` vmapped over
    ``count * batch_size / sum(counts)`` training-stream keys of each setting
    (``training_episode_keys(fold_in(key, setting index), n)``), concatenated in the order of
    ``mixture``. batch_size must be a multiple of sum(counts)."""
    total = sum(count for _, count in mixture)
    if batch_size % total:
        raise ValueError(f"batch size {batch_size} is not a multiple of the mixture's {total} "
                         f"examples {mixture}")
    scale = batch_size // total
    parts = []
    for i, (setting, count) in enumerate(mixture):
        keys = training_episode_keys(jax.random.fold_in(key, i), count * scale)
        fn = functools.partial(example_fn, config=make_config(setting))
        parts.append(jax.vmap(fn)(keys))
    return jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts)

