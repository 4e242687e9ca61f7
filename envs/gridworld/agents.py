"""The grid world's reference agents: nothing learned, they bound what a planner can do. They
act through the loop every baseline acts through (``diffplan.baselines.rollout.policy_rollout``)
and are measured by the same metrics, on the same episodes (:data:`REFERENCE_POLICIES`).

- **oracle** knows the whole map: it is handed the task's state, hidden world included
  (:func:`privileged`, policy_rollout's ``observe``), and takes the first move of a shortest
  path on the true grid to the cell the instruction asks for next (the reference until stood
  on, then the target). ``bfs.best_move`` breaks ties as ``bfs.descend``, which draws the expert
  path, so it walks the expert's path move for move: SR (SR_ordered) 100 and SPL 1 by
  construction, which the tests check on episodes. While the reference is due it never enters
  the target's cell, which would end the episode out of order.
- **searcher** is honest: it sees what every policy sees, the condition channels (cells seen,
  obstacles seen, the agent, the cells visited) and the instruction's slots
  (``slots.instruction_slots``: reference, target and compass direction in any phrasing).
  Each move it picks goal cells and takes the first move of a shortest path to the nearest of
  them over the cells not known to be obstacles (unseen cells assumed free, re-planned as they
  are seen):

  1. the reference, until it has stood on it (when the instruction names one), without
     entering the target's cell meanwhile;
  2. the target, as soon as it is seen;
  3. otherwise the unseen cells, those in the instructed compass sector of the reference first
     (:func:`sector_mask`: the instruction says the target lies there); among the nearest,
     those nearest the reference (the target is more likely close to it).

  It keeps no memory: the visited channel says whether it stood on the reference. It assumes
  a field of view that covers the four neighbours (view radius >= 1, as in every setting), so
  it never collides. In the paper's settings step 3 never runs (1O1G and MO1G are fully
  observed; in P-MO2G the target lies within the view radius of the reference, so standing on
  the reference shows it): what separates the searcher from the oracle there is only the
  obstacles it had not seen when it chose its route. Exploration is for worlds where the
  target can stay hidden, tested on hand-made episodes.

Both are pure jax.numpy functions of one episode, vmapped over a batch by their act functions
(``act_fn(params, observations, tokens, keys) -> moves int32 (B,)``, policy_rollout's
signature; params and keys unused).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from diffplan.baselines.policies import LoadedPolicy
from envs.gridworld import bfs, env
from envs.gridworld.slots import instruction_cells, instruction_slots
from envs.gridworld.episode import OBSTACLE_CELL, compass_sector
from envs.gridworld.task import AGENT_CHANNEL, _argmax_cell

__all__ = ["REFERENCE_AGENTS", "REFERENCE_POLICIES", "sector_mask", "oracle_move",
           "searcher_move", "oracle_act", "searcher_act", "privileged"]

REFERENCE_AGENTS = ("oracle", "searcher")
NEAR_REFERENCE = 0.01
"""Weight of the Euclidean distance to the reference that breaks ties between goal cells
equally near the agent (under 1 over any two cells of a 16 x 16 grid: distance to the agent
comes first)."""


def sector_mask(reference, direction, size: int):
    """bool (size, size): the cells whose compass sector seen from reference (int32 (2,)) is
    direction (int32 () in 0..7, ``episode.compass_sector``, the sector the instruction's
    direction word names); the reference itself excluded; all False if direction < 0."""
    rows, cols = jnp.meshgrid(jnp.arange(size), jnp.arange(size), indexing="ij")
    sector = compass_sector(reference, jnp.stack([rows, cols]))
    at_reference = (rows == reference[0]) & (cols == reference[1])
    return (sector == direction) & ~at_reference & (direction >= 0)


def _first_cell(mask):
    """int32 (2,): the first cell (row-major) of mask bool (H, W); (0, 0) if it is empty."""
    return _argmax_cell(mask.astype(jnp.float32), jnp.zeros(mask.shape, bool))


def _move_to_nearest(passable, agent, goals, tie_break):
    """int32 (): the first move of a shortest path over passable cells (bool (H, W)) from
    agent (int32 (2,)) to the goal cell (goals bool (H, W)) nearest to it in moves, ties to
    the least tie_break (float32 (H, W), each value in [0, 1)); the first cell of goals when
    none is reachable."""
    distance = bfs.cost_to_go(passable, agent)  # moves from the agent (unit costs: symmetric)
    goal = _argmax_cell(-(distance + tie_break), ~goals)
    return bfs.best_move(bfs.cost_to_go(passable, goal), passable, agent)


def privileged(state):
    """policy_rollout's ``observe`` of the oracle: the whole state, hidden world included."""
    return state


def oracle_move(state: env.State):
    """int32 (): the oracle's move in one episode's state (see the module docstring)."""
    size = state.grid.shape[0]
    reference_due = jnp.all(state.reference >= 0) & ~state.reached_reference
    goal = jnp.where(reference_due, state.reference, state.target)
    passable = (state.grid != OBSTACLE_CELL) & ~(env._cell_mask(state.target, size)
                                                 & reference_due)
    return bfs.best_move(bfs.cost_to_go(passable, goal), passable, state.agent)


def searcher_move(condition, tokens):
    """int32 (): the searcher's move from one episode's condition channels (float32 (H, W, C),
    ``GridTask.condition``) and instruction tokens (int32 (L,)); see the module docstring."""
    size = condition.shape[0]
    cells = jnp.round(condition[..., 0]).astype(jnp.int32)
    known_obstacle = condition[..., 1] > 0.5
    agent = _first_cell(condition[..., AGENT_CHANNEL] > 0.5)
    visited = condition[..., 3] > 0.5
    unseen = condition[..., 4] < 0.5
    reference, target, direction = instruction_cells(cells, tokens)
    reference_due = (instruction_slots(tokens)[0] > 0) & ~jnp.any(reference & visited)
    ref_cell = _first_cell(reference)
    in_sector = unseen & sector_mask(ref_cell, direction, size) & jnp.any(reference)
    explore = jnp.where(jnp.any(in_sector), in_sector, unseen)
    goals = jnp.where(reference_due & jnp.any(reference), reference,
                      jnp.where(~reference_due & jnp.any(target), target, explore))
    passable = ~known_obstacle & ~(target & reference_due)
    rows, cols = jnp.meshgrid(jnp.arange(size), jnp.arange(size), indexing="ij")
    to_reference = jnp.sqrt((rows - ref_cell[0]) ** 2 + (cols - ref_cell[1]) ** 2)
    tie_break = NEAR_REFERENCE * to_reference * jnp.any(reference)
    return _move_to_nearest(passable, agent, goals, tie_break)


def oracle_act(params, states, tokens, keys):
    """moves int32 (B,) of the oracle in states (env.State with a leading axis B)."""
    del params, tokens, keys
    return jax.vmap(oracle_move)(states)


def searcher_act(params, conditions, tokens, keys):
    """moves int32 (B,) of the searcher: conditions float32 (B, H, W, C), tokens int32 (B, L)."""
    del params, keys
    return jax.vmap(searcher_move)(conditions, tokens)


REFERENCE_POLICIES = {
    "oracle": LoadedPolicy("oracle", oracle_act, None, observe=privileged),
    "searcher": LoadedPolicy("searcher", searcher_act, None),
}
"""The reference agents as policies for policy_rollout (experiments.gridworld.baselines'
``reference_rows``), in the order of REFERENCE_AGENTS."""
