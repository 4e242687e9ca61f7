"""The brax environment stepped with brax's own wrappers (vmap, episode, auto-reset)."""
from __future__ import annotations

import brax.envs
import jax
import numpy as np
import pytest
from brax.envs.wrappers import training

import kuka_fixtures as kf
import envs.kuka.brax_env as kuka_brax
from envs.kuka import expert, physics

pytestmark = pytest.mark.filterwarnings(kf.MJX_CAST_WARNING)


def _actions(state, idle):
    """Continuous actions: the expert's, except episodes `idle` pick at the base (no block)."""
    cells = np.array(jax.vmap(expert.act)(state.pipeline_state))
    cells[idle, :2] = 12
    actions = jax.vmap(kuka_brax.cells_to_action)(cells)
    np.testing.assert_array_equal(np.asarray(jax.vmap(kuka_brax.action_to_cells)(actions)), cells)
    return actions


def test_registered_and_steps_with_brax_wrappers():
    """Two-relation rearrangement (4 placements allowed) wrapped with an episode length of 2:
    episodes 0-1 follow the expert and end solved after 2 steps; 2-3 do nothing and are
    truncated by the EpisodeWrapper; AutoResetWrapper then restores every first state."""
    base = brax.envs.get_environment(kuka_brax.NAME, kind="rearrangement", multi=True)
    assert isinstance(base, kuka_brax.KukaBlocks) and base.action_size == 4
    env = training.wrap(base, episode_length=2)
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    state = reset(jax.random.split(jax.random.PRNGKey(0), kf.BATCH))
    assert state.obs.shape == (kf.BATCH, base.observation_size)
    assert np.asarray(state.metrics["success"]).max() == 0.0
    first_pos = np.asarray(jax.vmap(physics.block_pos)(state.pipeline_state.data))

    state = step(state, _actions(state, [2, 3]))
    np.testing.assert_allclose(np.asarray(state.reward), [0.5, 0.5, 0, 0])
    np.testing.assert_array_equal(np.asarray(state.done), 0)
    np.testing.assert_array_equal(np.asarray(state.pipeline_state.t), 1)

    state = step(state, _actions(state, [2, 3]))
    np.testing.assert_allclose(np.asarray(state.reward), [0.5, 0.5, 0, 0])
    np.testing.assert_array_equal(np.asarray(state.done), 1)
    np.testing.assert_array_equal(np.asarray(state.info["truncation"]), [0, 0, 1, 1])
    np.testing.assert_allclose(np.asarray(state.info["episode_metrics"]["sum_reward"]),
                               [1, 1, 0, 0])
    # Auto-reset: every episode is back at its first state.
    np.testing.assert_array_equal(np.asarray(state.pipeline_state.t), 0)
    pos = np.asarray(jax.vmap(physics.block_pos)(state.pipeline_state.data))
    np.testing.assert_allclose(pos, first_pos)
    assert np.isfinite(np.asarray(state.obs)).all()
