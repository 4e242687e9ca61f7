"""The grid world as a planner task: condition channels, psi, and training examples.

Planning tensor of the grid world (H x W x (C + G), C = 5, G = 2):
  channel 0  cell token id (float-valued integer; see env.Observation.cells),
  channels 1-4  obstacle seen, agent, visited, visible (0/1),
  channel 5  path: +1 on the cells of the plan, -1 elsewhere,
  channel 6  goal estimate: +1 on the believed target cell, -1 elsewhere.

psi (the inverse dynamics, Sec. 3.3 of the paper): from the agent's cell, the first move of the
cheapest path to the goal estimate (argmax of channel 6) over the cells not known to be obstacles
(unseen cells are assumed free), where entering a cell costs ``1 + path_weight * (1 - p)`` with
p in [0, 1] the plan's path value of that cell. Cells the plan marks as path are therefore
preferred, and the agent follows the plan's route (through the reference in P-MO2G) rather than
the straight line to the goal. A Dijkstra-style field computed by Bellman-Ford relaxation in JAX.
psi never moves into a known obstacle or off the grid; as the field of view is at least one cell
around the agent, it never collides.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from envs.gridworld import bfs, env
from envs.gridworld.config import GridConfig
from envs.gridworld.episode import OBSTACLE_CELL, Episode, expert_path_positions, generate

NUM_COND_CHANNELS = 1 + env.NUM_FEATURES
NUM_GEN_CHANNELS = 2
PATH_CHANNEL, GOAL_CHANNEL = NUM_COND_CHANNELS, NUM_COND_CHANNELS + 1


def condition_from_observation(obs: env.Observation):
    """float32 (H, W, C) condition channels from an observation."""
    return jnp.concatenate([obs.cells[..., None].astype(jnp.float32),
                            obs.features.astype(jnp.float32)], axis=-1)


def goal_cell(plan, excluded=None):
    """int32 (2,): the argmax cell of the plan's goal channel (plan float32 (H, W, G)), among
    cells not in ``excluded`` (bool (H, W), e.g. known obstacles)."""
    goal = plan[..., 1]
    if excluded is not None:
        goal = jnp.where(excluded, -jnp.inf, goal)
    flat = jnp.argmax(goal.ravel())
    return jnp.stack([flat // goal.shape[1], flat % goal.shape[1]]).astype(jnp.int32)


def path_end_cell(plan, agent, excluded=None):
    """int32 (2,): where the plan's path leads from the agent: among the path cells (value > 0,
    not in ``excluded``) connected to the agent's cell through such cells (4-neighbours), the
    one farthest along them (BFS distance); the agent's cell if none. The goal of a model
    trained without a goal channel (the paper's ablations without g). Stray path cells not
    connected to the agent are ignored; psi excludes the visited cells too, so that an agent
    half way along its path heads on, not back to where it came from."""
    size = plan.shape[1]
    on_path = plan[..., 0] > 0
    if excluded is not None:
        on_path = on_path & ~excluded
    at_agent = env._cell_mask(agent, size)
    along = bfs.bfs_distance(on_path | at_agent, agent)  # -1 where not connected
    score = jnp.where(on_path, along, -1).ravel()
    flat = jnp.argmax(score)
    cell = jnp.stack([flat // size, flat % size]).astype(jnp.int32)
    return jnp.where(score[flat] >= 0, cell, agent.astype(jnp.int32))


def goal_estimate(state: env.State, plan, use_goal_channel: bool = True):
    """int32 (2,): the cell psi heads for: the goal channel's argmax off known obstacles, or
    (use_goal_channel=False) the end of the unvisited path connected to the agent."""
    known_obstacle = state.seen & (state.grid == OBSTACLE_CELL)
    if use_goal_channel:
        return goal_cell(plan, known_obstacle)
    return path_end_cell(plan, state.agent, known_obstacle | state.visited)


def psi(state: env.State, plan, path_weight: float = 2.0, use_goal_channel: bool = True):
    """The next move (int32 () in 0..3) following the plan; see the module docstring.

    plan: float32 (H, W, G) in [-1, 1] (path, goal estimate). use_goal_channel=False heads for
    the far end of the plan's path instead (for models trained without a goal estimate).
    """
    known_obstacle = state.seen & (state.grid == OBSTACLE_CELL)
    passable = ~known_obstacle
    path01 = (jnp.clip(plan[..., 0], -1.0, 1.0) + 1.0) / 2.0
    enter_cost = 1.0 + path_weight * (1.0 - path01)
    goal = goal_estimate(state, plan, use_goal_channel)
    field = bfs.cost_to_go(passable, goal, enter_cost)
    return bfs.best_move(field, passable, state.agent, enter_cost)


@dataclasses.dataclass(frozen=True)
class GridTask:
    """diffplan.task.Task for a grid-world setting (hashable; pass as a static argument)."""

    config: GridConfig
    path_weight: float = 2.0
    use_goal_channel: bool = True

    @property
    def height(self) -> int:
        return self.config.size

    @property
    def width(self) -> int:
        return self.config.size

    num_cond_channels: int = NUM_COND_CHANNELS
    num_gen_channels: int = NUM_GEN_CHANNELS

    @property
    def max_steps(self) -> int:
        return self.config.max_steps

    def reset(self, episode: Episode) -> env.State:
        return env.reset(episode, self.config)

    def condition(self, state: env.State):
        return condition_from_observation(env.observe(state, self.config))

    def tokens(self, episode: Episode):
        return episode.tokens

    def psi(self, state: env.State, plan):
        return psi(state, plan, self.path_weight, self.use_goal_channel)

    def step(self, state: env.State, action):
        return env.step(state, action, self.config)

    def done(self, state: env.State):
        return env.done(state)

    def position(self, state: env.State):
        return state.agent

    def at_goal_estimate(self, state: env.State, plan):
        return jnp.all(state.agent == goal_estimate(state, plan, self.use_goal_channel))


def _state_along_expert(episode: Episode, config: GridConfig, index):
    """The state after following the expert path for ``index`` moves (int32 ())."""
    positions = episode.expert_positions  # (P, 2)
    steps = jnp.arange(positions.shape[0])
    taken = steps <= index
    size = config.size
    fovs = jax.vmap(lambda p: env.field_of_view(p, size, config.view_radius))(positions)
    seen = jnp.any(fovs & taken[:, None, None], axis=0)
    visited = bfs.positions_to_mask(positions, size, taken)
    agent = positions[index]
    if config.has_reference:
        on_ref = jnp.all(positions == episode.reference, axis=-1)
        reached_reference = jnp.any(on_ref & taken)
    else:
        reached_reference = jnp.array(False)
    on_target = jnp.all(agent == episode.target)
    return env.State(
        grid=episode.grid, agent=agent, target=episode.target, reference=episode.reference,
        seen=seen, visited=visited, t=index.astype(jnp.int32), collisions=jnp.int32(0),
        reached_reference=reached_reference, done=on_target, success=on_target,
    )


def _random_detour(key, state: env.State, config: GridConfig, num_moves, max_moves: int):
    """The state after ``num_moves`` (int32 () <= max_moves, static) uniformly random moves
    from ``state`` (moves into obstacles or off the grid stay in place, as in the world)."""
    actions = jax.random.randint(key, (max_moves,), 0, 4)

    def move(s, inputs):
        i, action = inputs
        moved = env.step(s, action, config)
        return jax.tree.map(lambda new, old: jnp.where(i < num_moves, new, old), moved, s), None

    state, _ = jax.lax.scan(move, state, (jnp.arange(max_moves), actions))
    return state


def _expert_from(state: env.State, episode: Episode, config: GridConfig):
    """bool (H, W): the cells of a shortest path from the agent's cell through the reference
    (unless already reached) to the target, ends included."""
    passable = episode.grid != OBSTACLE_CELL
    reference = (jnp.where(state.reached_reference, state.agent, episode.reference)
                 if config.has_reference else episode.reference)
    positions, length, _ = expert_path_positions(config, passable, state.agent, episode.target,
                                                 reference)
    valid = jnp.arange(positions.shape[0]) <= length
    return bfs.positions_to_mask(positions, config.size, valid)


def training_example(key, config: GridConfig, detour_prob: float = 0.0, max_detour: int = 8):
    """One supervised example: a state along an expert path and the plan from there.

    The agent is placed after a uniformly drawn number of expert moves (0..expert_length - 1)
    with the field of view accumulated along the way. With probability ``detour_prob`` it then
    takes 1..max_detour uniformly random moves (so the model also sees the states an imperfect
    on-the-fly agent reaches). The path target is a shortest path from there (through the
    reference unless it was reached) to the target, ends included (without a detour: the rest
    of the expert path); the goal target is the target cell, whether or not it has been seen
    (the model must infer it from the instruction and the reference).

    Returns (x0 float32 (H, W, C + G), tokens int32 (L,), seen bool (H, W)).
    """
    k_episode, k_index, k_detour, k_moves, k_walk = jax.random.split(key, 5)
    episode = generate(k_episode, config)
    length = jnp.maximum(episode.expert_length, 1)
    index = jax.random.randint(k_index, (), 0, length)
    state = _state_along_expert(episode, config, index)
    if detour_prob > 0:
        detour = jax.random.bernoulli(k_detour, detour_prob) & ~state.done
        num_moves = jnp.where(detour, jax.random.randint(k_moves, (), 1, max_detour + 1), 0)
        state = _random_detour(k_walk, state, config, num_moves, max_detour)
        path = _expert_from(state, episode, config)
    else:
        steps = jnp.arange(episode.expert_positions.shape[0])
        remaining = (steps >= index) & (steps <= episode.expert_length)
        path = bfs.positions_to_mask(episode.expert_positions, config.size, remaining)
    obs = env.observe(state, config)
    goal = jnp.zeros_like(path).at[episode.target[0], episode.target[1]].set(True)
    x0 = jnp.concatenate([
        condition_from_observation(obs),
        (path.astype(jnp.float32) * 2 - 1)[..., None],
        (goal.astype(jnp.float32) * 2 - 1)[..., None],
    ], axis=-1)
    return x0, episode.tokens, state.seen
