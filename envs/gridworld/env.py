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
    """What the agent knows, in compact form (2 bytes per cell plus the agent's cell; leading
    batch axes allowed).

    cells: int8 (H, W) token id of each cell as seen so far: grammar.UNSEEN_ID where unseen,
      EMPTY_ID, OBSTACLE_ID, or the object's name's token id (shared with the instruction words;
      the vocabulary has fewer than 128 words).
    visited: bool (H, W) cells stood on so far.
    agent: int32 (2,) the agent's cell.

    ``features`` expands it into the binary channels the planner sees (obstacle seen, agent,
    visited, visible): obstacles and visibility are functions of ``cells``, so observe does not
    materialise them (task.condition_from_observation casts everything to float32).
    """

    cells: jax.Array
    visited: jax.Array
    agent: jax.Array

    @property
    def visible(self) -> jax.Array:
        """bool (..., H, W) cells seen so far."""
        return self.cells != grammar.UNSEEN_ID

    @property
    def obstacle_seen(self) -> jax.Array:
        """bool (..., H, W) obstacles seen so far."""
        return self.cells == grammar.OBSTACLE_ID

    @property
    def agent_mask(self) -> jax.Array:
        """bool (..., H, W) True at the agent's cell."""
        h, w = self.cells.shape[-2:]
        agent = jnp.asarray(self.agent)
        return ((jnp.arange(h)[:, None] == agent[..., 0, None, None])
                & (jnp.arange(w)[None, :] == agent[..., 1, None, None]))

    @property
    def features(self) -> jax.Array:
        """bool (..., H, W, NUM_FEATURES): obstacle seen, agent, visited, visible."""
        return jnp.stack([self.obstacle_seen, self.agent_mask, jnp.asarray(self.visited),
                          self.visible], axis=-1)


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


def _cell_mask(pos, size: int):
    """bool (size, size): True at pos (int32 (2,)) only; all False if pos is off the grid.
    A comparison with coordinates, which vectorises under vmap (a scatter does not)."""
    rows = jnp.arange(size)[:, None]
    cols = jnp.arange(size)[None, :]
    return (rows == pos[0]) & (cols == pos[1])


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
    """One move (action int32 () in 0..3). Done states are returned unchanged.

    Written without scatter/gather on the grid (one-hot cell masks instead) and masking each
    update by ``~state.done`` rather than selecting between whole states, so that it vectorises
    under vmap; the constant fields (grid, target, reference) are passed through."""
    size = config.size
    frozen = state.done
    target_cell = state.agent + bfs.MOVES[action]
    inside = jnp.all((target_cell >= 0) & (target_cell < size))
    # Off the grid the mask is empty: blocked by ~inside alone.
    blocked = ~inside | jnp.any(_cell_mask(target_cell, size) & (state.grid == OBSTACLE_CELL))
    agent = jnp.where(blocked | frozen, state.agent, target_cell)
    on_target = _on(agent, state.target)
    on_reference = config.has_reference & _on(agent, state.reference)
    moving = ~frozen
    t = state.t + moving.astype(jnp.int32)
    return state.replace(
        agent=agent,
        seen=state.seen | (field_of_view(agent, size, config.view_radius) & moving),
        visited=state.visited | (_cell_mask(agent, size) & moving),
        t=t, collisions=state.collisions + (blocked & moving).astype(jnp.int32),
        reached_reference=state.reached_reference | (on_reference & moving),
        done=frozen | on_target | (t >= config.max_steps),
        success=jnp.where(frozen, state.success, on_target),
    )


def cell_tokens(grid):
    """int8 (H, W) token id of every cell of a true grid (int8 (H, W))."""
    grid = grid.astype(jnp.int8)
    tokens = jnp.where(grid == OBSTACLE_CELL, grammar.OBSTACLE_ID, grammar.EMPTY_ID)
    return jnp.where(grid > 0, grammar.class_to_token(grid), tokens).astype(jnp.int8)


def observe(state: State, config: GridConfig) -> Observation:
    """The agent's observation; unseen cells carry no information about the world."""
    cells = jnp.where(state.seen, cell_tokens(state.grid), grammar.UNSEEN_ID)
    return Observation(cells=cells.astype(jnp.int8), visited=state.visited, agent=state.agent)


def done(state: State):
    """bool (): the episode is over (on the target or out of moves)."""
    return state.done
