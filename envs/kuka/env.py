"""The Kuka block world: pure reset / step over a :class:`State` pytree (mujoco_playground style).

One high-level action is one pick-and-place, given on the planner's 24 x 24 grid
(:mod:`envs.kuka.grid`): ``action = int32 (4,) (pick_row, pick_col, place_row, place_col)``.
The block picked is the highest block covering the pick cell (none: the arm moves without
grasping); it is placed on the highest other block covering the place cell, centred on it, or
on the floor at the place cell's centre where no block covers it. The primitive
(:mod:`envs.kuka.primitive`) carries it around the base along :func:`grid.arc_points`
(:func:`step_along` takes another path). Every action costs primitive.NUM_STEPS physics steps.

The episode ends when its relations hold (strictly: metrics.on_matrix; stacking also needs the
four blocks in one tower) or after ``episode.max_steps`` placements; stepping a done state
changes nothing. Nothing here depends on the task but through the Episode's arrays, so one
compiled step serves every task. Everything is jit- and vmap-able; one ``mjx.Model``
(physics.mjx_model) serves every episode.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from envs.kuka import grid, metrics, physics, primitive, scene
from envs.kuka.config import TaskSpec
from envs.kuka.episode import Episode, generate


@struct.dataclass
class State:
    """Dynamic state of one episode (leading batch axes allowed when vmapped).

    data: mjx.Data, the physics (block poses in qpos, the suction in eq_active);
    episode: the Episode (instruction, constraints, the expert's goal);
    t: int32 () placements made; done: bool ();
    frames: float32 (primitive.NUM_FRAMES, nq) the physics qpos every primitive.FRAME_EVERY
      steps of the last placement (the initial qpos at reset), for videos.
    """

    data: object
    episode: Episode
    t: jax.Array
    done: jax.Array
    frames: jax.Array


def reset(episode: Episode) -> State:
    """The state at t = 0: blocks at rest at episode.block_xy, the arm at home, nothing held;
    done already if the episode allows no placement (max_steps 0: an instruction a reader
    refused, envs.kuka.reader.read_episodes)."""
    data = physics.initial_data(episode.block_xy)
    return State(data=data, episode=episode, t=jnp.zeros((), jnp.int32),
                 done=jnp.asarray(episode.max_steps) <= 0,
                 frames=jnp.broadcast_to(data.qpos, (primitive.NUM_FRAMES,) + data.qpos.shape))


def on_matrix(state: State):
    """bool (4, 4) [i, j]: block i is on block j (strict)."""
    return metrics.on_matrix(physics.block_pos(state.data), physics.held(state.data))


def satisfied(state: State):
    """bool (3,): each instructed constraint holds (strict; padding rows False)."""
    return metrics.satisfied(on_matrix(state), state.episode.constraints)


def goal_reached_poses(pos, held, episode: Episode):
    """bool (): the episode's instructed relations hold for block centres pos float (4, 3) and
    held bool (4,) (and, for stacking, the four blocks stand in one tower)."""
    valid = episode.constraints[:, 0] >= 0
    relations = jnp.all(metrics.satisfied(metrics.on_matrix(pos, held), episode.constraints)
                        | ~valid)
    return relations & (metrics.single_tower(pos, held) | ~episode.tower)


def goal_reached(state: State):
    """bool (): :func:`goal_reached_poses` of the state's physical poses."""
    return goal_reached_poses(physics.block_pos(state.data), physics.held(state.data),
                              state.episode)


def view(state: State):
    """The planner's view (top int32 (24, 24), height int32 (24, 24)); see grid.top_down_view."""
    return grid.view_of(state.data)


def flange_cell(state: State):
    """int32 (2,): the grid cell under the arm's flange (the end effector's position on the
    planner's map)."""
    return grid.xy_to_cell(state.data.xpos[physics.flange_id(), :2])


def resolve(data, action):
    """What an action means in this physical state: :func:`resolve_poses` of its poses."""
    return resolve_poses(physics.block_pos(data), physics.block_quat(data), physics.held(data),
                         action)


def resolve_poses(pos, quat, held, action):
    """What an action int (4,) means for blocks at pos float (4, 3), quat (4, 4), held bool (4,).

    Returns (block int32 () the block to pick or -1, place float32 (3,) the top-centre target
    of the placed block, pick_xy float32 (2,), place_xy float32 (2,))."""
    action = jnp.asarray(action, jnp.int32)
    pos, quat, held = jnp.asarray(pos), jnp.asarray(quat), jnp.asarray(held, bool)
    top, _ = grid.top_down_view(pos, quat, held)
    block = top[action[0], action[1]]
    place, place_xy, _ = place_of(pos, quat, held, block, action[2:])
    pick_xy = jnp.where(block >= 0, pos[jnp.maximum(block, 0), :2],
                        grid.cell_center(action[:2]))
    return block, place, pick_xy, place_xy


def place_of(pos, quat, held, block, cell):
    """Where ``block`` (int (), -1: none) goes when put at cell int (2,): on the highest other
    block covering the cell (held ones aside), centred on it, else on the floor at the cell's
    centre. Returns (place float32 (3,) the top-centre target, place_xy float32 (2,), support
    int32 () the block it goes on, -1: the floor)."""
    cover = grid.footprints(pos, quat) & ~jnp.asarray(held, bool)[:, None, None]
    others = cover[:, cell[0], cell[1]] & (jnp.arange(scene.NUM_BLOCKS) != block)
    support = jnp.argmax(jnp.where(others, pos[:, 2], -jnp.inf))
    on_block = others.any()
    place_xy = jnp.where(on_block, pos[support, :2], grid.cell_center(cell))
    support_top = jnp.where(on_block, pos[support, 2] + scene.BLOCK_HALF_SIZE[2], 0.0)
    return (primitive.place_target(support_top, place_xy), place_xy,
            jnp.where(on_block, support, -1).astype(jnp.int32))


def _advance(state: State, data, frames) -> State:
    moved = state.replace(data=data, t=state.t + 1, frames=frames)
    moved = moved.replace(done=goal_reached(moved) | (moved.t >= state.episode.max_steps))
    # Done states are returned unchanged.
    return jax.tree.map(lambda new, old: jnp.where(state.done, old, new), moved, state)


def step_along(state: State, action, waypoints_xy) -> State:
    """One pick-and-place (action int32 (4,), see the module docstring) carried along
    waypoints_xy float (N, 2) (its ends are replaced by the pick and place points)."""
    block, place, _, _ = resolve(state.data, action)
    data, frames = primitive.pick_and_place(state.data, block, place, waypoints_xy)
    return _advance(state, data, frames)


def step(state: State, action) -> State:
    """One pick-and-place (action int32 (4,)) carried around the base (grid.arc_points)."""
    _, _, pick_xy, place_xy = resolve(state.data, action)
    waypoints = grid.arc_points(pick_xy, place_xy, primitive.NUM_WAYPOINTS)
    return step_along(state, action, waypoints)


SETTLE_SECONDS = 1.0
"""Simulated seconds the blocks settle, the arm held in its retreat pose and nothing held,
before success is read (experiments.kuka.eval)."""


def settle(state: State, seconds: float = SETTLE_SECONDS) -> State:
    """The state after ``seconds`` (float, may be traced) more of physics at rest: suction off, the
    arm's servo targets held where the last placement's retreat left them (its flange 0.1 m
    above the block it released), nothing else changed (t, done and the episode are kept)."""
    num = jnp.round(jnp.asarray(seconds, jnp.float32) / scene.TIMESTEP).astype(jnp.int32)
    data = state.data.replace(eq_active=jnp.zeros_like(state.data.eq_active))
    return state.replace(data=physics.simulate(data, num))


reset_batch = jax.jit(jax.vmap(reset))
"""jitted reset over a batch of episodes (shared by the CLIs, benchmark and tests)."""
step_batch = jax.jit(jax.vmap(step))
"""jitted step over a batch of states and actions (B, 4)."""
settle_batch = jax.jit(jax.vmap(settle, in_axes=(0, None)))
"""jitted settle over a batch of states (one compilation serves every duration)."""


@dataclasses.dataclass(frozen=True)
class KukaEnv:
    """The world for one task, mujoco_playground style: ``reset(key)``, ``step(state, action)``
    (pure; jit and vmap them). Hashable (pass as a static argument)."""

    spec: TaskSpec

    @property
    def mjx_model(self):
        return physics.mjx_model()

    @property
    def mj_model(self):
        return scene.mj_model()

    @property
    def max_steps(self) -> int:
        return self.spec.max_steps

    def generate(self, key) -> Episode:
        return generate(key, self.spec)

    def reset(self, key) -> State:
        """A fresh episode of the task from key, at t = 0."""
        return reset(self.generate(key))

    def reset_episode(self, episode: Episode) -> State:
        return reset(episode)

    def step(self, state: State, action) -> State:
        return step(state, action)

    def step_along(self, state: State, action, waypoints_xy) -> State:
        return step_along(state, action, waypoints_xy)

    def done(self, state: State):
        return state.done

    def view(self, state: State):
        return view(state)
