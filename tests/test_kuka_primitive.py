"""The pick-and-place primitive under physics: a block put on another stays after settling; an
empty pick moves nothing; a place on empty floor lands at the cell."""
from __future__ import annotations

import jax
import numpy as np
import pytest

import kuka_fixtures as kf
from envs.kuka import env, expert, grid, physics, primitive, scene

pytestmark = pytest.mark.filterwarnings(kf.MJX_CAST_WARNING)


def _free_cell(pos):
    """A cell on the 0.6 m circle whose centre is at least 0.3 m (Chebyshev) from every block."""
    centres = grid.cell_centers()
    radius = np.linalg.norm(centres, axis=-1)
    far = np.abs(centres[:, :, None, :] - pos[None, None, :, :2]).max(-1).min(-1)
    ok = (np.abs(radius - 0.6) < 0.05) & (far > 0.3)
    rows, cols = np.nonzero(ok)
    return np.array([rows[0], cols[0]], np.int32)


@pytest.fixture(scope="module")
def placed():
    episodes = kf.episodes("rearrangement_single", 2)
    states = env.reset_batch(episodes)
    pos0 = np.asarray(jax.vmap(physics.block_pos)(states.data))
    actions = np.asarray(jax.vmap(expert.act)(states)).copy()
    actions[2, :2] = (12, 12)  # the base: no block there
    actions[3, 2:] = _free_cell(pos0[3])  # a place on empty floor
    after = env.step_batch(states, actions)
    settled = physics.simulate_batch(after.data, 200)  # 1 s more
    get = jax.vmap(physics.block_pos)
    yaw = jax.vmap(physics.block_yaw)
    return dict(episodes=episodes, actions=actions, pos0=pos0, after=after,
                yaw0=np.asarray(yaw(states.data)), yaw2=np.asarray(yaw(settled)),
                pos1=np.asarray(get(after.data)), pos2=np.asarray(get(settled)),
                held=np.asarray(jax.vmap(physics.held)(settled)))


def test_block_put_on_another_stays(placed):
    for i in (0, 1):
        top, bottom = placed["episodes"].constraints[i, 0]
        pos = placed["pos2"][i]
        assert kf.numpy_on(pos, placed["held"][i], top, bottom)
        assert np.hypot(*(pos[top, :2] - pos[bottom, :2])) < 0.01
        assert abs(pos[top, 2] - pos[bottom, 2] - 2 * scene.BLOCK_HALF_SIZE[2]) < 0.003
        # Carried as it lay: the suction does not twist the block.
        assert np.degrees(np.abs(placed["yaw2"][i] - placed["yaw0"][i])).max() < 2.0
        others = [b for b in range(4) if b != top]
        assert np.abs(pos[others] - placed["pos0"][i][others]).max() < 0.005
        # Settling one more second changes nothing.
        assert np.abs(placed["pos2"][i] - placed["pos1"][i]).max() < 0.002
    assert bool(placed["after"].done[0]) and int(placed["after"].t[0]) == 1
    assert not placed["held"].any()


def test_empty_pick_moves_nothing(placed):
    assert np.abs(placed["pos2"][2] - placed["pos0"][2]).max() < 0.002
    assert int(placed["after"].t[2]) == 1 and not bool(placed["after"].done[2])


def test_place_on_empty_floor_lands_on_the_cell(placed):
    block = placed["actions"][3, :2]
    moved = int(np.argmin(np.abs(grid.block_cells(placed["pos0"][3]) - block).sum(-1)))
    target = np.asarray(grid.cell_center(placed["actions"][3, 2:]))
    pos = placed["pos2"][3][moved]
    assert np.hypot(*(pos[:2] - target)) < 0.01
    assert abs(pos[2] - scene.BLOCK_HALF_SIZE[2]) < 0.002


def test_plan_is_reachable_and_fixed_length():
    assert primitive.NUM_STEPS == sum(m + h for _, m, h, _ in primitive.PHASES)
    states = env.reset_batch(kf.episodes("rearrangement_single", 2))
    s0 = jax.tree.map(lambda x: x[0], states)
    block, place, pick_xy, place_xy = env.resolve(s0.data, expert.act(s0))
    way = grid.arc_points(pick_xy, place_xy, primitive.NUM_WAYPOINTS)
    ctrl, weld, err = jax.jit(primitive.plan)(s0.data, block, place, way)
    assert ctrl.shape == (primitive.NUM_STEPS, 7) and weld.shape == (primitive.NUM_STEPS,)
    assert float(err) < 1e-3
    assert (np.abs(np.asarray(ctrl)) <= scene.JOINT_LIMITS + 1e-6).all()
