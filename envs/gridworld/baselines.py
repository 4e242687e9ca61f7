"""What the baselines (BC, CQL, DD-style) need of the grid world; the algorithms themselves are
``diffplan.baselines``' and know no world.

The baselines see what our agent sees: the condition channels of ``GridTask.condition`` (cell
token id as a float-valued integer, i.e. the objects' class ids in the grid; obstacle seen,
agent, visited, visible), never the hidden world, and the instruction. The instruction reaches
them as a one-hot goal vector (the paper's appendix), :func:`goal_vector`:

  [one-hot of the target's class (15) | one-hot of the reference's class (15, zeros without a
  reference) | one-hot of the compass direction (8, zeros without one)]  = GOAL_DIM floats.

The paper gives BC and CQL "the goal" as a one-hot vector; in P-MO2G the target is not visible
at first, so the reference and the direction, which the instruction names, are one-hot encoded
beside it (our planner reads the same words). The vector is read off the tokens: the words in
the slots of whichever of the grammar's phrasings the instruction is (held-out ones included:
the baselines get the goal, not the sentence, as in the paper); for a sentence that is none of
them, the target is the last object word and the reference the first of two.

Training data of every baseline comes from the training key stream
(``envs.gridworld.training.training_episode_keys``), never from the evaluation seeds, in the
planner's mixture of settings (``TRAINING_MIXTURE``: one model per baseline serves the three
settings, as one denoiser does): BC and the DD-style planner learn from the states along
expert shortest paths (:func:`expert_example`), CQL from the epsilon-greedy transitions of
:class:`GridCollector`. ``train_bc``, ``train_cql``, ``train_dd`` and
``train_inverse_dynamics`` bind these to the algorithms; :data:`POLICY_WORLD` is what the
trained policies need to act here.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from diffplan.baselines import bc, cql, dd, nets
from diffplan.baselines.policies import PolicyWorld
from envs.gridworld import bfs, env, grammar
from envs.gridworld.config import GridConfig, make_config
from envs.gridworld.episode import OBSTACLE_CELL, generate
from envs.gridworld.task import AGENT_CHANNEL, NUM_COND_CHANNELS, condition_from_observation
from envs.gridworld.slots import NUM_CLASSES, instruction_slots
from envs.gridworld.training import (TRAINING_MIXTURE, state_along_expert,
                                     training_episode_keys)

NUM_DIRECTIONS = len(grammar.DIRECTIONS)
GOAL_DIM = 2 * NUM_CLASSES + NUM_DIRECTIONS
NUM_ACTIONS = 4
AGENT_VALUE = 1.0
MAX_CELL_ID = grammar.OBJECT_TOKEN_OFFSET + NUM_CLASSES - 1
PLAN_THRESHOLD = 0.5


def _goal_vector_one(tokens):
    ref, target, direction = instruction_slots(tokens)

    def hot(token, ids):
        return jnp.where(token > 0, (jnp.asarray(ids) == token).astype(jnp.float32), 0.0)

    classes = jnp.arange(NUM_CLASSES) + grammar.OBJECT_TOKEN_OFFSET
    return jnp.concatenate([hot(target, classes), hot(ref, classes),
                            hot(direction, grammar.DIRECTION_TOKEN_IDS)])


def goal_vector(tokens):
    """float32 (..., GOAL_DIM): the one-hot goal vector of instruction tokens int (..., L)
    (see the module docstring): the objects and the direction in the slots of whichever of
    the grammar's phrasings the instruction is (``grammar.parse``; any word order); for any
    other sentence, the last object word as the target, the first of two as the reference.
    Padding tokens (all 0) give the zero vector."""
    tokens = jnp.asarray(tokens, jnp.int32)
    flat = tokens.reshape((-1, tokens.shape[-1]))
    return jax.vmap(_goal_vector_one)(flat).reshape(tokens.shape[:-1] + (GOAL_DIM,))


def input_shapes(size: int = 16) -> dict:
    """The (condition, goal) network's input shapes, as its checkpoints record them."""
    return {"condition": [1, size, size, NUM_COND_CHANNELS], "goal": [1, GOAL_DIM]}


def mixture_data(mixture) -> dict:
    """The training data's description recorded in a run's metadata: {"mixture": lists}."""
    return {"mixture": [list(m) for m in mixture]}


# ------------------------------------------------------------------- expert examples

def move_index(src, dst):
    """int32 (): the action (0..3 = N, E, S, W) from cell src to its 4-neighbour dst (int32
    (2,) each); 0 if dst is not a neighbour."""
    return jnp.argmax(jnp.all(bfs.MOVES == (dst - src)[None, :], axis=-1)).astype(jnp.int32)


def expert_example(key, config: GridConfig):
    """(episode, state, index, move): an episode of ``config``, the state after ``index``
    expert moves (uniform in 0..expert_length - 1, the field of view accumulated along the
    way) and the expert's next move there."""
    k_episode, k_index = jax.random.split(key)
    episode = generate(k_episode, config)
    index = jax.random.randint(k_index, (), 0, jnp.maximum(episode.expert_length, 1))
    state = state_along_expert(episode, config, index)
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


# ------------------------------------------------------------------------------- BC

def _bc_example(key, config):
    episode, state, _, move = expert_example(key, config)
    condition = condition_from_observation(env.observe(state, config))
    return condition, goal_vector(episode.tokens), move


def bc_batch(key, batch_size: int, mixture=TRAINING_MIXTURE):
    """(conditions float32 (B, 16, 16, 5), goal vectors float32 (B, GOAL_DIM), expert moves
    int32 (B,)): states along expert paths in the mixture."""
    return mixture_examples(_bc_example, key, batch_size, mixture)


def train_bc(out_dir: str, config: bc.BCTrainConfig = bc.BCTrainConfig(),
             net: nets.ConvNetConfig = nets.ConvNetConfig(), mixture=TRAINING_MIXTURE,
             progress: bool = True):
    """diffplan.baselines.bc.train_bc on :func:`bc_batch` (config.batch_size a multiple of the
    mixture's sum)."""
    return bc.train_bc(out_dir, functools.partial(bc_batch, mixture=mixture), input_shapes(),
                       config, net, data=mixture_data(mixture), progress=progress)


# ------------------------------------------------------------------------------ CQL

def sub_goal(state: env.State, config: GridConfig):
    """The cell the instruction asks for next: the reference until stood on, then the
    target."""
    if not config.has_reference:
        return state.target
    return jnp.where(state.reached_reference, state.target, state.reference)


def expert_move(state: env.State, config: GridConfig):
    """int32 (): the first move of a shortest path on the true grid to the sub-goal."""
    passable = state.grid != OBSTACLE_CELL
    field = bfs.cost_to_go(passable, sub_goal(state, config))
    return bfs.best_move(field, passable, state.agent)


def route_reward(state: env.State, config: GridConfig):
    """float32 (): minus the Euclidean length (cells / size) of the instructed route still to
    go: agent to target, or in P-MO2G, while the reference has not been stood on, agent to
    reference plus reference to target (so stepping on the reference is not punished by a
    jump of the distance; the appendix's "the distance from the agent to the goal")."""
    def dist(a, b):
        return jnp.sqrt(jnp.sum(jnp.square((a - b).astype(jnp.float32))))

    remaining = dist(state.agent, state.target)
    if config.has_reference:
        via = dist(state.agent, state.reference) + dist(state.reference, state.target)
        remaining = jnp.where(state.reached_reference, remaining, via)
    return -remaining / config.size


def compact(obs: env.Observation):
    """The observation stored in the buffer: cells int8, visited bool, agent int8."""
    return {"cells": obs.cells, "visited": obs.visited, "agent": obs.agent.astype(jnp.int8)}


def expand(stored) -> jax.Array:
    """float32 (..., H, W, C) condition channels of stored (compact) observations."""
    obs = env.Observation(cells=stored["cells"], visited=stored["visited"],
                          agent=stored["agent"].astype(jnp.int32))
    return condition_from_observation(obs)


def q_inputs(stored, instruction):
    """The Q-network's (conditions, goal vectors) of stored observations and tokens int8."""
    return expand(stored), goal_vector(instruction)


@dataclasses.dataclass(frozen=True)
class GridCollector:
    """diffplan.baselines.cql.Collector of one setting: the expert's move is the first move of
    a shortest path on the true grid through the reference (while due) to the target; the
    reward :func:`route_reward`; an episode terminates on the target (no bootstrap), running
    out of moves is a truncation; instructions are stored as tokens int8 (L,)."""

    config: GridConfig
    num_actions: int = NUM_ACTIONS

    def episodes(self, key, n: int):
        return jax.vmap(lambda k: generate(k, self.config))(training_episode_keys(key, n))

    def reset(self, episode):
        return env.reset(episode, self.config)

    def instruction(self, episode):
        return episode.tokens.astype(jnp.int8)

    def step(self, state, action):
        return env.step(state, action, self.config)

    def observe(self, state):
        return compact(env.observe(state, self.config))

    def expert_action(self, state):
        return expert_move(state, self.config)

    def reward(self, state):
        return route_reward(state, self.config)

    def terminal(self, state):
        return state.success

    def done(self, state):
        return state.done


def collectors(mixture=TRAINING_MIXTURE) -> tuple:
    """((GridCollector, count), ...) of the mixture's settings, for cql.collect_buffer."""
    return tuple((GridCollector(make_config(setting)), count) for setting, count in mixture)


def train_cql(out_dir: str, config: cql.CQLTrainConfig = cql.CQLTrainConfig(),
              net: nets.ConvNetConfig = nets.ConvNetConfig(), mixture=TRAINING_MIXTURE,
              progress: bool = True, buffer=None):
    """diffplan.baselines.cql.train_cql with the mixture's collectors."""
    return cql.train_cql(out_dir, collectors(mixture), q_inputs, input_shapes(), config, net,
                         data=mixture_data(mixture), progress=progress, buffer=buffer)


# ------------------------------------------------------------------------ DD-style

def _cell_values(ids):
    return -1.0 + 1.5 * (ids.astype(jnp.float32) - grammar.UNSEEN_ID) / (
        MAX_CELL_ID - grammar.UNSEEN_ID)


def _frame(ids, agent_mask):
    return jnp.where(agent_mask, AGENT_VALUE, _cell_values(ids)).reshape(-1)


def frame(condition):
    """float32 (H * W,): the DD-style planner's state of condition channels (H, W, C): each
    cell's token id as seen so far (unseen, empty, obstacle, object class) mapped linearly to
    [-1, 0.5], and AGENT_VALUE on the agent's cell."""
    return _frame(condition[..., 0], condition[..., AGENT_CHANNEL] > 0.5)


def agent_plan(trajectory, condition):
    """float32 (H, W, 1): +1 on the cells where a trajectory's (cells, horizon) agent marker
    is above PLAN_THRESHOLD in any frame, -1 elsewhere (the plan of the paper's metrics)."""
    on_path = jnp.any(trajectory > PLAN_THRESHOLD, axis=-1).reshape(condition.shape[:2])
    return jnp.where(on_path, 1.0, -1.0)[..., None]


def trajectory_example(key, config: GridConfig, horizon: int):
    """(trajectory float32 (cells, horizon), tokens int32 (L,), expert move int32 ()): the
    state after a uniform number of expert moves and the expert path from there (frames of
    the map seen now with the agent moved along the path; the end repeated)."""
    episode, state, index, move = expert_example(key, config)
    obs = env.observe(state, config)
    size = config.size
    last = episode.expert_positions.shape[0] - 1
    cells = jnp.arange(size * size)

    def frame_at(j):
        pos = episode.expert_positions[jnp.minimum(index + j, last)]
        return _frame(obs.cells, (cells == pos[0] * size + pos[1]).reshape(size, size))

    frames = jax.vmap(frame_at)(jnp.arange(horizon))  # (horizon, cells)
    return frames.T, episode.tokens, move


def _trajectories(key, batch_size: int, horizon: int, mixture):
    return mixture_examples(lambda k, config: trajectory_example(k, config, horizon), key,
                            batch_size, mixture)


@dataclasses.dataclass(frozen=True)
class GridTrajectories:
    """The DD-style planner's data (dd.DDBatchFn's trajectories): (key, batch_size) ->
    (expert trajectories float32 (B, 256, horizon), goal vectors (B, GOAL_DIM)) in the
    mixture."""

    horizon: int = 16
    mixture: tuple = TRAINING_MIXTURE

    def __call__(self, key, batch_size: int):
        traj, tokens, _ = _trajectories(key, batch_size, self.horizon, self.mixture)
        return traj, goal_vector(tokens)


def id_batch(key, batch_size: int, mixture=TRAINING_MIXTURE):
    """(frames (B, 256), next frames (B, 256), expert moves (B,)) along expert paths."""
    traj, _, moves = _trajectories(key, batch_size, 2, mixture)
    return traj[..., 0], traj[..., 1], moves


def train_dd(out_dir: str, config: dd.DDTrainConfig = dd.DDTrainConfig(),
             model_config: dd.DDConfig = dd.DDConfig(), mixture=TRAINING_MIXTURE,
             progress: bool = True):
    """diffplan.baselines.dd.train_dd on :class:`GridTrajectories`."""
    return dd.train_dd(out_dir, GridTrajectories(model_config.horizon, tuple(mixture)),
                       GOAL_DIM, config, model_config, data=mixture_data(mixture),
                       progress=progress)


def train_inverse_dynamics(out_dir: str, config: dd.DDTrainConfig = dd.DDTrainConfig(),
                           id_config: dd.IDConfig = dd.IDConfig(), mixture=TRAINING_MIXTURE,
                           progress: bool = True):
    """diffplan.baselines.dd.train_inverse_dynamics on :func:`id_batch`."""
    return dd.train_inverse_dynamics(out_dir, functools.partial(id_batch, mixture=mixture),
                                     config, id_config, cells=256, data=mixture_data(mixture),
                                     progress=progress)


POLICY_WORLD = PolicyWorld(goal_fn=goal_vector, goal_dim=GOAL_DIM, frame_fn=frame,
                           plan_fn=agent_plan, plan_channels=1)
"""What the trained baselines need to act in the grid world (policies.load_policy)."""
