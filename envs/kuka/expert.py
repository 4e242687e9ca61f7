"""The scripted expert: the next pick-and-place and the end effector's path on the grid.

The expert builds the episode's goal relations (Episode.goal, bottom up) in order: it moves the
top block of the first relation that does not hold (strictly) onto its bottom block. Its action
picks the cell of the block's centre and places on the cell of the support's centre; the end
effector carries the block around the base along grid.arc_points, and the path drawn on the
grid is the cells it passes over (both ends included). These are the diffusion model's training
targets: the path channel and the goal estimate (the place cell).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from envs.kuka import env, grid, physics, scene, metrics
from envs.kuka.config import MAX_STEPS


@struct.dataclass
class ExpertStep:
    """The expert's decision in one state.

    action: int32 (4,) (pick_row, pick_col, place_row, place_col) for env.step;
    block, support: int32 () the block moved and the block it goes on;
    path: bool (24, 24) the cells under the end effector's carry path;
    goal: int32 (2,) the place cell (the goal estimate's target);
    relation: int32 () the goal relation worked on (3 when every relation holds: the action
      then repeats the last relation, and the episode is done anyway).
    """

    action: jax.Array
    block: jax.Array
    support: jax.Array
    path: jax.Array
    goal: jax.Array
    relation: jax.Array


def decide(pos, held, episode) -> ExpertStep:
    """The expert's next pick-and-place for block poses pos float (4, 3), held bool (4,) and the
    episode's goal (pure; vmap over episodes)."""
    goal = episode.goal
    valid = goal[:, 0] >= 0
    on = metrics.on_matrix(pos, held)
    holds = on[jnp.maximum(goal[:, 0], 0), jnp.maximum(goal[:, 1], 0)] | ~valid
    first = jnp.argmin(holds)  # the first relation that does not hold
    relation = jnp.where(holds.all(), goal.shape[0], first)
    last = jnp.maximum(valid.sum() - 1, 0)
    top, bottom = goal[jnp.where(holds.all(), last, first)]
    cells = grid.block_cells(pos)
    pick, place = cells[top], cells[bottom]
    return ExpertStep(action=jnp.concatenate([pick, place]).astype(jnp.int32), block=top,
                      support=bottom, path=grid.path_map(pos[top, :2], pos[bottom, :2]),
                      goal=place.astype(jnp.int32), relation=relation.astype(jnp.int32))


def next_step(state: env.State) -> ExpertStep:
    """The expert's next pick-and-place in a state (pure; vmap over episodes)."""
    return decide(physics.block_pos(state.data), physics.held(state.data), state.episode)


def planned_poses(episode, num_built):
    """float32 (4, 3) block centres after the first num_built (int ()) goal relations are built
    exactly (each top block centred one block height above its support), the rest flat where
    they started: the states along the expert's plan without physics (e.g. for training data;
    :func:`decide` works on them with nothing held)."""
    half = scene.BLOCK_HALF_SIZE[2]
    pos = jnp.concatenate([jnp.asarray(episode.block_xy, jnp.float32),
                           jnp.full((scene.NUM_BLOCKS, 1), half, jnp.float32)], axis=1)
    for k in range(episode.goal.shape[0]):  # build order: every support is in place already
        top, bottom = episode.goal[k]
        moved = pos.at[jnp.maximum(top, 0)].set(pos[jnp.maximum(bottom, 0)]
                                                + jnp.array([0.0, 0.0, 2 * half]))
        pos = jnp.where((k < num_built) & (top >= 0), moved, pos)
    return pos


def act(state: env.State):
    """int32 (4,): the expert's next action."""
    return next_step(state).action


def rollout(states):
    """Runs the expert on a batch of states (leading axis B, e.g. env.reset_batch(episodes))
    until every episode is done (each after at most its max_steps placements).

    Returns (final env.State, frames float32 (B, MAX_STEPS, NUM_FRAMES, nq): placement
    k's recorded qpos (env.State.frames) in frames[:, k] for k < final t; the rest is
    unspecified). One compilation serves every task."""
    b = states.t.shape[0]
    frames = jnp.broadcast_to(states.frames[:, None],
                              (b, MAX_STEPS) + states.frames.shape[1:])

    def body(carry):
        states, frames = carry
        index = jnp.minimum(states.t, MAX_STEPS - 1)
        states = jax.vmap(env.step)(states, jax.vmap(act)(states))
        frames = frames.at[jnp.arange(b), index].set(states.frames)
        return states, frames

    return jax.lax.while_loop(lambda c: jnp.any(~c[0].done), body, (states, frames))


run_expert = jax.jit(rollout)
"""jitted rollout (shared by the CLIs and tests; one compilation per batch size)."""
