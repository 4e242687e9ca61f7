"""The scripted expert in physics on each Table 2 column, and its training targets."""
from __future__ import annotations

import jax
import numpy as np
import pytest

import kuka_fixtures as kf
from envs.kuka import env, expert, grid, physics
from envs.kuka.config import COLUMNS, MAX_RELATIONS, MAX_STEPS

pytestmark = pytest.mark.filterwarnings(kf.MJX_CAST_WARNING)


@pytest.mark.parametrize("column", list(COLUMNS))
def test_expert_satisfies_every_instructed_constraint(column):
    """Checked with the plain-numpy contract-4 check on the final physical poses."""
    spec = COLUMNS[column]
    episodes = kf.episodes(column, 11)
    final, frames = kf.expert_run(column, 11)
    pos = np.asarray(jax.vmap(physics.block_pos)(final.data))
    held = np.asarray(jax.vmap(physics.held)(final.data))
    for i in range(kf.BATCH):
        for top, bottom in episodes.constraints[i]:
            if top >= 0:
                assert kf.numpy_on(pos[i], held[i], top, bottom), (column, i, top, bottom)
        if spec.kind == "stacking":  # one tower of four, bottom block on the floor
            assert sorted(np.round((pos[i, :, 2] - 0.03) / 0.06).astype(int)) == [0, 1, 2, 3]
    needed = 3 if spec.kind == "stacking" else spec.num_constraints
    np.testing.assert_array_equal(final.t, needed)
    assert final.done.all() and not held.any()
    assert frames.shape[:2] == (kf.BATCH, MAX_STEPS)


def test_planned_poses_are_where_physics_puts_the_blocks():
    """The expert's plan without physics: at every stage it decides as on the physical state,
    and its final poses match the physical ones within 1 cm."""
    episodes = kf.episodes("stacking_multi", 11)
    final, _ = kf.expert_run("stacking_multi", 11)
    pos = np.asarray(jax.vmap(physics.block_pos)(final.data))
    for i in range(kf.BATCH):
        episode = jax.tree.map(lambda x: x[i], episodes)
        for k in range(4):
            planned = np.asarray(expert.planned_poses(episode, k))
            step = expert.decide(planned, np.zeros(4, bool), episode)
            assert int(step.relation) == k
        np.testing.assert_allclose(planned, pos[i], atol=0.01)
    states = env.reset_batch(episodes)
    start = jax.vmap(expert.planned_poses)(episodes, np.zeros(kf.BATCH, np.int32))
    np.testing.assert_allclose(np.asarray(start), np.asarray(jax.vmap(physics.block_pos)(
        states.data)), atol=1e-6)
    cells = np.asarray(jax.vmap(env.flange_cell)(states))
    assert (cells >= 0).all() and (cells < grid.GRID_SIZE).all()


def test_expert_targets_on_the_grid():
    """The first step of each episode: the path runs from the moved block's cell to the place
    cell (the support's), around the base; the action picks and places those cells."""
    episodes = kf.episodes("rearrangement_multi", 12)
    states = env.reset_batch(episodes)
    steps = jax.device_get(jax.vmap(expert.next_step)(states))
    pos = np.asarray(jax.vmap(physics.block_pos)(states.data))
    centres = grid.cell_centers()
    for i in range(kf.BATCH):
        block, support = int(steps.block[i]), int(steps.support[i])
        assert (block, support) == tuple(episodes.goal[i, 0])
        pick = np.asarray(grid.xy_to_cell(pos[i, block, :2]))
        place = np.asarray(grid.xy_to_cell(pos[i, support, :2]))
        np.testing.assert_array_equal(steps.action[i], np.concatenate([pick, place]))
        np.testing.assert_array_equal(steps.goal[i], place)
        path = steps.path[i]
        assert path.dtype == bool and path[tuple(pick)] and path[tuple(place)]
        assert np.linalg.norm(centres[path], axis=-1).min() > 0.45  # never over the base
        assert int(steps.relation[i]) == 0


def test_expert_after_the_end_reports_every_relation_done():
    final, _ = kf.expert_run("rearrangement_single", 11)
    steps = jax.vmap(expert.next_step)(final)
    np.testing.assert_array_equal(np.asarray(steps.relation), MAX_RELATIONS)
    # A done state does not change when stepped.
    again = env.step_batch(final, steps.action)
    np.testing.assert_array_equal(np.asarray(again.data.qpos), np.asarray(final.data.qpos))
    np.testing.assert_array_equal(np.asarray(again.t), np.asarray(final.t))


def test_settling_keeps_the_experts_towers_and_lets_a_lifted_block_fall():
    """env.settle: 1 s at rest, suction off. The expert's towers stand (every block moves
    < 5 mm, t and done kept); a block lifted 5 cm before settling lands on the floor."""
    final, _ = kf.expert_run("stacking_multi", 11)
    pos = np.asarray(jax.vmap(physics.block_pos)(final.data))
    settled = jax.device_get(env.settle_batch(final, np.float32(1.0)))
    after = np.asarray(jax.vmap(physics.block_pos)(settled.data))
    assert np.abs(after - pos).max() < 0.005
    np.testing.assert_array_equal(settled.t, final.t)
    np.testing.assert_array_equal(settled.done, final.done)
    states = env.reset_batch(kf.episodes("rearrangement_single", 11))
    start = np.asarray(jax.vmap(physics.block_pos)(states.data))
    lifted = start.copy()
    lifted[:, 0, 2] += 0.05
    quat = jax.vmap(physics.block_quat)(states.data)
    states = states.replace(data=jax.vmap(physics.set_blocks)(states.data, lifted, quat))
    fallen = np.asarray(jax.vmap(physics.block_pos)(env.settle_batch(states,
                                                                     np.float32(1.0)).data))
    np.testing.assert_allclose(fallen[:, :, 2], start[:, :, 2], atol=0.003)
