"""What behaviour cloning (``diffplan.baselines.bc``) needs of the BabyAI levels; the algorithm
and its network are ``diffplan.baselines``' and know no world.

BC sees what our agent sees: the condition channels of ``BabyAITask.condition`` (the agent's
own map, padded with walls), never the true grid, and the mission as a goal vector, the
paper's one-hot goal (:func:`goal_vector`: the colour and the type the mission names, read from
its words, a hand-written parse as every baseline's goal vector). It learns the expert's
action (minigrid's seven, :data:`NUM_ACTIONS` logits) in the states along the expert's
demonstrations of the training layouts (:func:`bc_batch_fn`): the same demonstrations the
denoiser trains on (``envs.babyai.training``: the cached layouts 0..N-1 and their expert
actions), without the denoiser's detours. :data:`POLICY_WORLD` is what a trained BC needs to
act here (``diffplan.baselines.policies.load_policy("bc", directory, POLICY_WORLD)``).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from diffplan.baselines import bc, nets
from diffplan.baselines.policies import PolicyWorld
from envs.babyai import grammar
from envs.babyai import objects as O
from envs.babyai.task import NUM_COND_CHANNELS, BabyAITask
from envs.babyai.training import Layouts, layout_sampler, play

COLOR_IDS = tuple(grammar.WORDS.index(c) for c in grammar.COLORS)
TYPE_IDS = tuple(grammar.WORDS.index(t) for t in grammar.TYPES)
GOAL_DIM = len(COLOR_IDS) + len(TYPE_IDS)
NUM_ACTIONS = O.NUM_ACTIONS


def goal_vector(tokens):
    """float32 (..., GOAL_DIM): one-hot of the colour word, then of the type word, of GoTo
    missions' token ids int (..., L) (the grammar's own vocabulary); zeros where none."""
    tokens = jnp.asarray(tokens, jnp.int32)[..., None, :]
    hot = lambda ids: jnp.any(tokens == jnp.asarray(ids)[:, None], axis=-1)
    return jnp.concatenate([hot(COLOR_IDS), hot(TYPE_IDS)], axis=-1).astype(jnp.float32)


def input_shapes(task: BabyAITask) -> dict:
    """The (condition, goal) network's input shapes, as its checkpoints record them."""
    return {"condition": [1, task.height, task.width, NUM_COND_CHANNELS], "goal": [1, GOAL_DIM]}


def demonstration_example(task: BabyAITask, episode, actions, length, key):
    """(condition float32 (H, W, C), goal float32 (GOAL_DIM,), action int32 ()): the state
    after k of the expert's actions (k uniform in 0..length - 1) and its action k."""
    k = jax.random.randint(key, (), 0, jnp.maximum(length, 1))
    state = play(task, episode, actions, k)
    return (task.condition(state), goal_vector(episode.tokens),
            actions[jnp.clip(k, 0, actions.shape[0] - 1)].astype(jnp.int32))


def bc_batch_fn(task: BabyAITask, layouts: Layouts):
    """batch_fn(key, batch_size) -> (conditions, goals, actions) of demonstration states of
    layouts drawn uniformly (``training.layout_sampler``: these layouts only)."""
    sample = layout_sampler(layouts)

    def batch_fn(key, batch_size):
        pick_key, state_key = jax.random.split(key)
        episodes, actions, lengths = sample(pick_key, batch_size)
        keys = jax.random.split(state_key, batch_size)
        return jax.vmap(lambda e, a, l, k: demonstration_example(task, e, a, l, k))(
            episodes, actions, lengths, keys)

    return batch_fn


NET = nets.ConvNetConfig(num_outputs=NUM_ACTIONS)
"""The appendix's network (two 3x3 convolutions of 16, dense 40, the goal vector concatenated
before the second dense layer), a logit per minigrid action."""

POLICY_WORLD = PolicyWorld(goal_fn=goal_vector, goal_dim=GOAL_DIM)
"""BC acts greedily: the argmax of its logits is the minigrid action."""


def train_bc(out_dir: str, task: BabyAITask, layouts: Layouts,
             config: bc.BCTrainConfig = bc.BCTrainConfig(), *, progress: bool = True,
             callback=None):
    """Trains BC on the layouts' demonstrations into out_dir (resuming); the run records the
    level, its layouts' first and last minigrid seeds and their number. callback: as
    ``diffplan.train.fit``'s (it may raise to stop). Returns diffplan.train.FitResult."""
    data = {"level": layouts.level, "num_layouts": len(layouts),
            "first_seed": int(layouts.seeds[0]), "last_seed": int(layouts.seeds[-1])}
    return bc.train_bc(out_dir, bc_batch_fn(task, layouts), input_shapes(task), config, NET,
                       data=data, progress=progress, callback=callback)
