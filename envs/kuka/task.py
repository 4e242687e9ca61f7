"""The Kuka block world as a planner task (``diffplan.task.Task``): condition channels and psi.

Planning tensor of the Kuka world (24 x 24 x (C + G), C = 2, G = 3), on the top-down grid of
:mod:`envs.kuka.grid` (row 0 north):
  channel 0  the token id of the colour word of the cell's top block (red 1, green 2, blue 3,
             yellow 4: the instruction's own ids, so that ``grid_repr="embed"`` looks cells and
             instruction words up in one embedding table, as the grid world's cells are), 0 (the
             padding id) where no block covers the cell;
  channel 1  the stack height there (blocks covering the cell) / 4;
  channel 2  path: +1 on the cells the end effector passes over carrying the block (the
             in-painted trajectory, both ends included), -1 elsewhere;
  channel 3  goal estimate: +1 on the visible top of the block the picked one goes on (where the
             instruction's next relation puts it), -1 elsewhere;
  channel 4  pick: +1 on the visible top of the block to move, -1 elsewhere (the path's start
             made explicit, as the grid world's sub-goal channel makes its next cell explicit;
             the paper's two output channels are the path and the goal estimate).

psi (the inverse dynamics) turns a plan into one pick-and-place (:class:`Action`):
  * the block to pick is the clear block (its own centre cell shows it on top) whose visible top
    cells have the highest summed pick value; the block to place it on is the other visible block
    whose top cells have the highest summed goal value (the sum is the correlation of the plan's
    channel with the +1 / -1 map the training target would draw for that block, up to a
    constant: the best-matching target; a mean let a sliver of a covered block that the goal
    blob spilled onto beat the block itself: 95.7% -> 98.0% right decisions on 256 examples of
    the training recipe, 88% -> 100% in multi-constraint stacking); the action's cells are
    the blocks' centre cells (``env.resolve`` maps a cell to the block on top of it; for a
    support that is not clear, the highest-valued cell of its visible top);
  * the carry path is the in-painted path: the path cells connected to the pick cell (8
    neighbours) ordered by their distance along the path (:func:`path_waypoints`), resampled to
    ``primitive.NUM_WAYPOINTS`` points; where the path does not connect the pick to the place
    cell, the expert's arc around the base (``grid.arc_points``) is used.
It is executed by the primitive under physics (``env.step_along``); the world is observed again
after every placement and the planner re-plans (on-the-fly: one plan per placement).

The training targets of the generated channels (what the denoiser learns) live in
``envs.kuka.training``.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from diffplan.instruction import instruction_of
from envs.kuka import env, grammar, grid, physics, primitive, scene
from envs.kuka.config import MAX_STEPS
from envs.kuka.episode import Episode

NUM_COND_CHANNELS = 2
NUM_GEN_CHANNELS = 3
TOKEN_CHANNEL, HEIGHT_CHANNEL = 0, 1
PATH, GOAL, PICK = 0, 1, 2
"""Indices of the generated channels within a plan (H, W, G)."""
EMPTY_TOKEN = 0
"""Channel 0 of a cell no block covers (the padding id)."""
TEXT_INPUTS = ("tokens", "features")
"""What a KukaTask hands the planner of an episode's instruction (``KukaTask.text``)."""
PATH_ITERATIONS = 48
"""Relaxation sweeps of the distance along the path (a carry arc spans at most ~30 cells)."""


def condition_from_view(top, height):
    """float32 (24, 24, 2) condition channels of a top-down view (top int (24, 24) block index
    or -1, height int (24, 24))."""
    top = jnp.asarray(top)
    token = jnp.where(top >= 0, grammar.block_token(top), EMPTY_TOKEN)
    return jnp.stack([token.astype(jnp.float32),
                      jnp.asarray(height, jnp.float32) / scene.NUM_BLOCKS], axis=-1)


def view_of_condition(condition):
    """(top int32 (24, 24), height int32 (24, 24)): the view a condition was made from."""
    token = jnp.round(condition[..., TOKEN_CHANNEL]).astype(jnp.int32)
    height = jnp.round(condition[..., HEIGHT_CHANNEL] * scene.NUM_BLOCKS).astype(jnp.int32)
    return jnp.where(token > 0, token - 1, grid.NO_BLOCK), height


@struct.dataclass
class Action:
    """One pick-and-place: cells int32 (4,) (pick_row, pick_col, place_row, place_col), the
    action of ``env.step``; waypoints float32 (N, 2) the carry path's xy (m)."""

    cells: jax.Array
    waypoints: jax.Array


def block_scores(top, values):
    """float32 (4,): the sum of values (24, 24) over each block's visible top cells (-inf for
    blocks not visible)."""
    mine = jnp.asarray(top)[None] == jnp.arange(scene.NUM_BLOCKS)[:, None, None]
    count = mine.sum((1, 2))
    total = jnp.where(mine, values[None], 0.0).sum((1, 2))
    return jnp.where(count > 0, total, -jnp.inf)


def block_cell(top, block_pos, block, values):
    """int32 (2,): the cell of ``block``'s centre if the block shows there (it is clear), else
    the cell with the highest value among those showing it on top."""
    top = jnp.asarray(top)
    centre = grid.block_cells(block_pos)[block]
    flat = jnp.argmax(jnp.where(top == block, values, -jnp.inf).ravel())
    best = grid.cell_of(flat)
    return jnp.where(top[centre[0], centre[1]] == block, centre, best).astype(jnp.int32)


def clear_blocks(top, block_pos):
    """bool (4,): the block shows on top at its own centre cell (nothing rests on it)."""
    cells = grid.block_cells(block_pos)
    return jnp.asarray(top)[cells[:, 0], cells[:, 1]] == jnp.arange(scene.NUM_BLOCKS)


def decide(top, block_pos, plan):
    """(pick block int32 (), place block int32 (), cells int32 (4,)) that a plan asks for in
    the view ``top`` with blocks at block_pos float (4, 3); see the module docstring."""
    pick_scores = block_scores(top, plan[..., PICK])
    pick = jnp.argmax(jnp.where(clear_blocks(top, block_pos), pick_scores, -jnp.inf))
    goal_scores = block_scores(top, plan[..., GOAL])
    place = jnp.argmax(jnp.where(jnp.arange(scene.NUM_BLOCKS) == pick, -jnp.inf, goal_scores))
    cells = jnp.concatenate([block_cell(top, block_pos, pick, plan[..., PICK]),
                             block_cell(top, block_pos, place, plan[..., GOAL])])
    return pick.astype(jnp.int32), place.astype(jnp.int32), cells


def _cell_mask(cell):
    return jnp.zeros((grid.GRID_SIZE, grid.GRID_SIZE), bool).at[cell[0], cell[1]].set(True)


def distance_along(cells, start):
    """float32 (24, 24): the length (in cell widths, diagonal steps sqrt 2) of the shortest
    8-connected route from cell ``start`` int (2,) to each cell through ``cells`` bool (24, 24)
    (inf where none)."""
    size = grid.GRID_SIZE
    steps = [(dr, dc, float(np.hypot(dr, dc))) for dr in (-1, 0, 1) for dc in (-1, 0, 1)
             if dr or dc]
    passable = cells | _cell_mask(start)

    def sweep(_, d):
        padded = jnp.pad(d, 1, constant_values=jnp.inf)
        best = d
        for dr, dc, cost in steps:
            best = jnp.minimum(best, padded[1 + dr:1 + dr + size, 1 + dc:1 + dc + size] + cost)
        return jnp.where(passable, best, jnp.inf)

    d0 = jnp.where(_cell_mask(start), 0.0, jnp.inf).astype(jnp.float32)
    return jax.lax.fori_loop(0, PATH_ITERATIONS, sweep, d0)


def path_waypoints(path, pick_cell, place_cell, num: int):
    """The carry path of an in-painted path channel (float (24, 24), > 0 on the path).

    Waypoint k is the centroid of the path cells at fraction k / (num - 1) of the distance
    along the path from the pick cell to the place cell (a softmax over the cells' fractions,
    so the nearest cells dominate where the path is sparse); the ends are the two cells'
    centres (the primitive replaces them by the block's and the place's xy). Returns (float32 (num, 2) xy
    waypoints, ok bool (): the path connects the two cells)."""
    place_cell = jnp.asarray(place_cell)
    d = distance_along(path > 0, pick_cell)
    place = _cell_mask(place_cell)
    total = d[place_cell[0], place_cell[1]]
    ok = jnp.isfinite(total) & (total > 0)
    frac = jnp.where(jnp.isfinite(d), d / jnp.where(ok, total, 1.0), jnp.inf).ravel()
    frac = jnp.where(place.ravel(), 1.0, frac)
    s = jnp.linspace(0.0, 1.0, num)
    sigma = 0.5 / max(num - 1, 1)
    logits = -0.5 * ((frac[None] - s[:, None]) / sigma) ** 2  # (num, 576); -inf off the path
    weights = jax.nn.softmax(jnp.where(jnp.isfinite(frac)[None], logits, -jnp.inf), axis=-1)
    waypoints = weights @ jnp.asarray(grid.cell_centers()).reshape(-1, 2)
    ends = jnp.stack([grid.cell_center(pick_cell), grid.cell_center(place_cell)])
    return waypoints.at[jnp.array([0, num - 1])].set(ends), ok


def psi(state: env.State, plan, follow_path: bool = True, num_waypoints: int | None = None):
    """The pick-and-place (:class:`Action`) a plan float32 (24, 24, 3) asks for in a state."""
    num = primitive.NUM_WAYPOINTS if num_waypoints is None else num_waypoints
    top, _ = env.view(state)
    _, _, cells = decide(top, physics.block_pos(state.data), plan)
    _, _, pick_xy, place_xy = env.resolve(state.data, cells)
    arc = grid.arc_points(pick_xy, place_xy, num)
    if not follow_path:
        return Action(cells=cells, waypoints=arc)
    waypoints, ok = path_waypoints(plan[..., PATH], cells[:2], cells[2:], num)
    return Action(cells=cells, waypoints=jnp.where(ok, waypoints, arc).astype(jnp.float32))


@dataclasses.dataclass(frozen=True)
class KukaTask:
    """diffplan.task.Task for the Kuka block world (hashable; pass as a static argument).

    One task serves every Table 2 column: what differs (relations, tower, max placements,
    instruction) is data in the Episode. max_steps is the largest episode length
    (MAX_STEPS); each episode ends after its own ``episode.max_steps`` placements.
    follow_path: carry blocks along the in-painted path (False: along the expert's arc).
    text: what ``tokens(episode)`` hands the planner: "tokens" (the instruction's token ids)
    or "features" (its pretrained text features, ``Episode.features``, filled on the host by
    ``envs.kuka.sentences.with_features``: a denoiser with ``DenoiserConfig.context_dim`` > 0).
    """

    follow_path: bool = True
    height: int = grid.GRID_SIZE
    width: int = grid.GRID_SIZE
    num_cond_channels: int = NUM_COND_CHANNELS
    num_gen_channels: int = NUM_GEN_CHANNELS
    max_steps: int = MAX_STEPS
    text: str = "tokens"

    def __post_init__(self):
        if self.text not in TEXT_INPUTS:
            raise ValueError(f"text must be one of {TEXT_INPUTS}, got {self.text!r}")
        expected = (grid.GRID_SIZE, grid.GRID_SIZE, NUM_COND_CHANNELS, NUM_GEN_CHANNELS)
        got = (self.height, self.width, self.num_cond_channels, self.num_gen_channels)
        if got != expected:
            raise ValueError(f"the Kuka world plans (H, W, C, G) = {expected}, got {got}")
        if self.max_steps < MAX_STEPS:
            raise ValueError(f"max_steps must be >= {MAX_STEPS} (the longest episode), "
                             f"got {self.max_steps}")

    def reset(self, episode: Episode) -> env.State:
        """The state at t = 0 (``env.reset``); the episode's features, which the planner read
        once in ``tokens``, are not carried through the physics."""
        return env.reset(episode.replace(features=None))

    def condition(self, state: env.State):
        return condition_from_view(*env.view(state))

    def tokens(self, episode: Episode):
        """int32 (L,) token ids, or with text "features" float32 (L, D) features."""
        return instruction_of(episode, self.text)

    def psi(self, state: env.State, plan):
        return psi(state, plan, self.follow_path)

    def step(self, state: env.State, action: Action):
        return env.step_along(state, action.cells, action.waypoints)

    def done(self, state: env.State):
        return state.done

    def position(self, state: env.State):
        """The cell under the flange (after a placement: above the block just placed)."""
        return env.flange_cell(state)

    def at_goal_estimate(self, state: env.State, plan):
        """bool (): the flange is over the plan's goal estimate (the plan's placement is
        done: the arm retreats straight up from the block it placed)."""
        cell = env.flange_cell(state)
        return plan[cell[0], cell[1], GOAL] > 0

    def new_information(self, old_condition, condition):
        """bool (): the view changed (a block moved)."""
        return jnp.any(old_condition != condition)
