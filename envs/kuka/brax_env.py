"""The Kuka block world as a brax environment, registered as ``"kuka_blocks"``.

    import brax.envs
    import envs.kuka.brax_env  # registers "kuka_blocks"
    env = brax.envs.get_environment("kuka_blocks", kind="stacking", multi=True)
    env = brax.envs.training.wrap(env, episode_length=6)  # vmap, episode, auto-reset
    state = jax.jit(env.reset)(jax.random.split(key, 64))
    state = jax.jit(env.step)(state, actions)               # actions float32 (64, 4)

One brax step is one pick-and-place (primitive.NUM_STEPS physics steps). The action is
continuous, float (4,) in [-1, 1]: (pick x, pick y, place x, place y) in units of the grid's
half extent (0.8 m), mapped to the grid cells of env.step. Observation float32 (53,): block
centres (12), orientations (16), the instructed constraints one-hot (3 rows of top (4) and
bottom (4), zero rows for padding) and the share of placements used. Reward: the change of the
share of instructed constraints holding (strict), so an episode's rewards sum to its success;
``metrics["success"]`` is that share. ``pipeline_state`` is the env.State (the mjx.Data in
``pipeline_state.data``).
"""
from __future__ import annotations

import brax.envs
import jax
import jax.numpy as jnp
from brax.envs.base import Env
from brax.envs.base import State as BraxState

from envs.kuka import env, grid, physics, scene
from envs.kuka.config import MAX_RELATIONS, TaskSpec
from envs.kuka.episode import generate

NAME = "kuka_blocks"
OBSERVATION_SIZE = 4 * 3 + 4 * 4 + MAX_RELATIONS * 2 * scene.NUM_BLOCKS + 1


def action_to_cells(action) -> jax.Array:
    """int32 (4,) (pick_row, pick_col, place_row, place_col) of a continuous action (4,)."""
    xy = jnp.clip(jnp.asarray(action, jnp.float32), -1, 1).reshape(2, 2) * grid.HALF_EXTENT
    return grid.xy_to_cell(xy).reshape(4)


def cells_to_action(cells) -> jax.Array:
    """float32 (4,): the continuous action whose cells are cells int (4,) (the cell centres)."""
    cells = jnp.asarray(cells).reshape(2, 2)
    return (jax.vmap(grid.cell_center)(cells) / grid.HALF_EXTENT).reshape(4)


class KukaBlocks(Env):
    """brax Env over env.State; kind "stacking"/"rearrangement", multi, language as TaskSpec."""

    def __init__(self, kind: str = "stacking", multi: bool = True,
                 language: str = "canonical", **kwargs):
        del kwargs  # brax passes backend etc.; this env always runs MJX
        self._spec = TaskSpec(kind, multi, language)

    def _observe(self, state: env.State) -> jax.Array:
        constraints = state.episode.constraints
        onehot = jax.nn.one_hot(constraints, scene.NUM_BLOCKS) * (constraints[..., None] >= 0)
        used = state.t / state.episode.max_steps
        return jnp.concatenate([physics.block_pos(state.data).ravel(),
                                physics.block_quat(state.data).ravel(), onehot.ravel(),
                                jnp.reshape(used, (1,))]).astype(jnp.float32)

    @staticmethod
    def _success(state: env.State) -> jax.Array:
        return env.satisfied(state).sum() / state.episode.num_constraints

    def reset(self, rng: jax.Array) -> BraxState:
        state = env.reset(generate(rng, self._spec))
        success = self._success(state)
        return BraxState(pipeline_state=state, obs=self._observe(state),
                         reward=jnp.zeros(()), done=jnp.zeros(()),
                         metrics={"success": success}, info={})

    def step(self, state: BraxState, action: jax.Array) -> BraxState:
        before = state.metrics["success"]
        nxt = env.step(state.pipeline_state, action_to_cells(action))
        success = self._success(nxt)
        return state.replace(pipeline_state=nxt, obs=self._observe(nxt), reward=success - before,
                             done=nxt.done.astype(jnp.float32),
                             metrics={**state.metrics, "success": success})

    @property
    def observation_size(self) -> int:
        return OBSERVATION_SIZE

    @property
    def action_size(self) -> int:
        return 4

    @property
    def backend(self) -> str:
        return "mjx"


brax.envs.register_environment(NAME, KukaBlocks)
