"""The expert: shortest routes on the true grid to the objects the mission names (privileged:
training labels and reference rows only, never the planner's agent).

The expert's route runs over the true grid (walls, objects and locked doors block; a closed
door costs a toggle more) to a cell beside one of the verifier's positions (``State.target``),
then it faces that object: the same search and action rule as psi
(:mod:`envs.babyai.navigate`), handed the truth instead of a plan.
"""
from __future__ import annotations

import jax.numpy as jnp

from envs.babyai import env, navigate
from envs.babyai import objects as O


def true_enter(grid):
    """float32 (H, W): the actions to enter each cell of the true grid (inf where blocked)."""
    kind = grid[..., 0]
    blocked = (kind == O.WALL) | O.pickable(grid) | ((kind == O.DOOR) & (grid[..., 2] == O.LOCKED))
    closed = (kind == O.DOOR) & (grid[..., 2] == O.CLOSED)
    return jnp.where(blocked, jnp.inf, 1.0 + closed)


def expert_field(state: env.State):
    """(field, enter, goal, stand, start) of the expert's search from the true state."""
    enter = true_enter(state.grid)
    goal = state.target
    stand = navigate.adjacent(goal) & jnp.isfinite(enter) & ~goal
    start = jnp.where(stand, 0.0, jnp.inf)
    return navigate.cost_to_go(enter, start), enter, goal, stand, start


def expert_action(state: env.State):
    """int32 (): the expert's next action."""
    field, enter, goal, stand, _ = expert_field(state)
    closed = (state.grid[..., 0] == O.DOOR) & (state.grid[..., 2] == O.CLOSED)
    return navigate.act(field, enter, goal, stand, closed, state.pos, state.direction)


def expert_plan(state: env.State):
    """(path bool (H, W) the cells of the expert's route from the agent's cell to its stand
    cell, ends included; goal bool (H, W) the object it will face there; subgoal bool (H, W)
    the stand cell; length float32 () the route's cost (inf when unreachable))."""
    field, enter, goal, _, start = expert_field(state)
    h, w = field.shape
    path, end = navigate.route(field, enter, start, state.pos, h * w)
    subgoal = jnp.zeros((h, w), bool).at[end[0], end[1]].set(True)
    # the object faced from the stand cell: the first goal neighbour in direction order
    cells = end[None, :] + O.DIR_DELTA
    r, c = jnp.clip(cells[:, 0], 0, h - 1), jnp.clip(cells[:, 1], 0, w - 1)
    inside = (cells[:, 0] >= 0) & (cells[:, 0] < h) & (cells[:, 1] >= 0) & (cells[:, 1] < w)
    d = jnp.argmax(inside & goal[r, c])
    faced = jnp.zeros((h, w), bool).at[r[d], c[d]].set(True)
    return path, faced, subgoal, field[state.pos[0], state.pos[1]]
