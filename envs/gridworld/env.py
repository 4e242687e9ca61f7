"""The grid world's dynamics and observations: pure functions over a :class:`State` pytree.

``reset(episode, config) -> State``, ``step(state, action, config) -> State``,
``observe(state, config) -> Observation``. Actions 0..3 = north, east, south, west. A move into an
obstacle or off the grid leaves the agent in place and counts as a collision. The episode is done
when the agent stands on the target or after ``config.max_steps`` moves; stepping a done state
changes nothing.

The observation never carries information about cells the agent has not seen.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from envs.gridworld import bfs, grammar
from envs.gridworld.config import GridConfig
from envs.gridworld.episode import OBSTACLE_CELL, Episode

NUM_FEATURES = 4
"""Binary feature channels of an observation: obstacle seen, agent, visited, visible."""


@struct.dataclass
class State:
    """Dynamic state of one episode (leading batch axes allowed when vmapped).

    grid: int8 (H, W) the true world (see Episode.grid); agent, target, reference: int32 (2,);
    seen: bool (H, W) cells seen so far; visited: bool (H, W) cells stood on so far;
    t: int32 () moves taken; collisions: int32 (); reached_reference: bool () stood on the
    reference (False when the setting has none; since an episode ends on the target, a
    successful episode with reached_reference went to the reference first); done: bool ();
    success: bool () stands on the target.
    """

    grid: jax.Array
    agent: jax.Array
    target: jax.Array
    reference: jax.Array
    seen: jax.Array
    visited: jax.Array
    t: jax.Array
    collisions: jax.Array
    reached_reference: jax.Array
    done: jax.Array
    success: jax.Array


@struct.dataclass
class Observation:
    """What the agent knows.

    cells: int32 (H, W) token id of each cell as seen so far: grammar.UNSEEN_ID where unseen,
      EMPTY_ID, OBSTACLE_ID, or the object's name's token id (shared with the instruction words).
    features: float32 (H, W, NUM_FEATURES) 0/1 channels: obstacle seen, agent, visited, visible
      (seen so far).
    """

    cells: jax.Array
    features: jax.Array


def field_of_view(agent, size: int, radius):
    """bool (size, size): the square of Chebyshev radius around agent, clipped at the border.
    radius None = the whole grid."""
    if radius is None:
        return jnp.ones((size, size), bool)
    rows = jnp.arange(size)[:, None]
    cols = jnp.arange(size)[None, :]
    return (jnp.abs(rows - agent[0]) <= radius) & (jnp.abs(cols - agent[1]) <= radius)


def _on(pos, cell):
    return jnp.all(pos == cell)


def reset(episode: Episode, config: GridConfig) -> State:
    """The state at t=0 of an episode."""
    size = config.size
    agent = episode.agent
    on_target = _on(agent, episode.target)
    on_reference = config.has_reference & _on(agent, episode.reference)
    return State(
        grid=episode.grid, agent=agent, target=episode.target, reference=episode.reference,
        seen=field_of_view(agent, size, config.view_radius),
        visited=jnp.zeros((size, size), bool).at[agent[0], agent[1]].set(True),
        t=jnp.int32(0), collisions=jnp.int32(0),
        reached_reference=jnp.asarray(on_reference),
        done=on_target, success=on_target,
    )


def step(state: State, action, config: GridConfig) -> State:
    """One move (action int32 () in 0..3). Done states are returned unchanged."""
    size = config.size
    target_cell = state.agent + bfs.MOVES[action]
    inside = jnp.all((target_cell >= 0) & (target_cell < size))
    clipped = jnp.clip(target_cell, 0, size - 1)
    blocked = ~inside | (state.grid[clipped[0], clipped[1]] == OBSTACLE_CELL)
    agent = jnp.where(blocked, state.agent, clipped)
    on_target = _on(agent, state.target)
    on_reference = config.has_reference & _on(agent, state.reference)
    reached_reference = state.reached_reference | on_reference
    t = state.t + 1
    moved = State(
        grid=state.grid, agent=agent, target=state.target, reference=state.reference,
        seen=state.seen | field_of_view(agent, size, config.view_radius),
        visited=state.visited.at[agent[0], agent[1]].set(True),
        t=t, collisions=state.collisions + blocked.astype(jnp.int32),
        reached_reference=reached_reference,
        done=on_target | (t >= config.max_steps), success=on_target,
    )
    return jax.tree.map(lambda old, new: jnp.where(state.done, old, new), state, moved)


def cell_tokens(grid):
    """int32 (H, W) token id of every cell of a true grid (int8 (H, W))."""
    grid = grid.astype(jnp.int32)
    tokens = jnp.where(grid == OBSTACLE_CELL, grammar.OBSTACLE_ID, grammar.EMPTY_ID)
    return jnp.where(grid > 0, grammar.class_to_token(grid), tokens).astype(jnp.int32)


def observe(state: State, config: GridConfig) -> Observation:
    """The agent's observation; unseen cells carry no information about the world."""
    size = config.size
    cells = jnp.where(state.seen, cell_tokens(state.grid), grammar.UNSEEN_ID)
    obstacle = state.seen & (state.grid == OBSTACLE_CELL)
    agent = jnp.zeros((size, size), bool).at[state.agent[0], state.agent[1]].set(True)
    features = jnp.stack([obstacle, agent, state.visited, state.seen], axis=-1)
    return Observation(cells=cells.astype(jnp.int32), features=features.astype(jnp.float32))


def done(state: State):
    """bool (): the episode is over (on the target or out of moves)."""
    return state.done
