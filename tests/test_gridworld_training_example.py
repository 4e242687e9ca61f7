"""envs.gridworld.task.training_example: the supervised examples, checked against a plain-numpy
oracle (deque BFS): the path target is a shortest path from the agent's cell (through the
reference unless reached) to the target, the condition channels match the state, and examples
with detours leave the expert path."""
from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_gridworld_bfs import oracle_bfs

from envs.gridworld import grammar
from envs.gridworld.config import make_config
from envs.gridworld.episode import OBSTACLE_CELL, generate
from envs.gridworld.task import GOAL_CHANNEL, PATH_CHANNEL, SUBGOAL_CHANNEL
from envs.gridworld.training import training_example

BATCH = 24


@pytest.fixture(scope="module")
def examples_fn():
    config = make_config("p_mo2g")

    @jax.jit
    def run(keys, detour_prob):
        del detour_prob
        return jax.vmap(lambda k: (training_example(k, config, 1.0),
                                   training_example(k, config, 0.0),
                                   generate(jax.random.split(k, 5)[0], config)))(keys)

    return config, run


def _connected(mask, start, end):
    """True if the cells of mask form a 4-connected set containing start and end."""
    cells = {tuple(c) for c in np.argwhere(mask)}
    if tuple(start) not in cells or tuple(end) not in cells:
        return False
    stack, seen = [tuple(start)], {tuple(start)}
    while stack:
        r, c = stack.pop()
        for dr, dc in ((-1, 0), (0, 1), (1, 0), (0, -1)):
            n = (r + dr, c + dc)
            if n in cells and n not in seen:
                seen.add(n)
                stack.append(n)
    return seen == cells


@settings(max_examples=4, deadline=None, database=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_path_target_is_a_shortest_path_through_the_reference(examples_fn, seed):
    config, run = examples_fn
    keys = jax.random.split(jax.random.PRNGKey(seed), BATCH)
    (x_d, _, seen_d), (x_e, _, _), ep = jax.device_get(run(keys, 0))
    left_expert = 0
    for i in range(BATCH):
        grid = ep.grid[i]
        passable = grid != OBSTACLE_CELL
        target, reference = tuple(ep.target[i]), tuple(ep.reference[i])
        for x, detour in ((x_d[i], True), (x_e[i], False)):
            agent = tuple(np.argwhere(x[..., 2] > 0)[0])  # feature "agent" = channel 2
            assert passable[agent]
            path = x[..., PATH_CHANNEL] > 0
            goal = np.argwhere(x[..., GOAL_CHANNEL] > 0)
            assert goal.tolist() == [list(target)]
            visited = x[..., 3] > 0
            assert visited[agent]
            reached = visited[reference]
            # The sub-goal: the reference until the agent has stood on it, then the target.
            subgoal = np.argwhere(x[..., SUBGOAL_CHANNEL] > 0)
            assert subgoal.tolist() == [list(target if reached else reference)]
            # Shortest: number of path cells - 1 equals the oracle's distance.
            d_target = oracle_bfs(passable, target)
            if reached:
                length = d_target[agent]
            else:
                length = oracle_bfs(passable, reference)[agent] + d_target[reference]
                assert path[reference]
            assert length >= 0 and _connected(path, agent, target)
            # Every leg is shortest, so the path has length + 1 cells unless its legs overlap.
            assert path.sum() - 1 <= length
            if reached:
                assert path.sum() - 1 == length
            assert path[agent] and path[target] and not np.any(path & ~passable)
            # Condition channel 0 shows exactly the seen cells' tokens.
            cells = x[..., 0].astype(int)
            seen = x[..., 4] > 0
            assert np.all(cells[~seen] == grammar.UNSEEN_ID)
            if detour:
                assert np.array_equal(seen, seen_d[i])
                left_expert += not ep.expert_path[i][agent] or not np.array_equal(
                    visited, visited & ep.expert_path[i])
    assert left_expert > 0  # detours do leave the expert path


@settings(max_examples=30, deadline=None, database=None)
@given(row=st.integers(0, 7), col=st.integers(0, 7))
def test_near_agent_is_the_cell_and_its_four_neighbours(row, col):
    from envs.gridworld.training import near_agent

    agent = np.zeros((8, 8), np.float32)
    agent[row, col] = 1
    expected = np.zeros((8, 8), bool)
    for dr, dc in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)):
        r, c = row + dr, col + dc
        if 0 <= r < 8 and 0 <= c < 8:
            expected[r, c] = True
    np.testing.assert_array_equal(np.asarray(near_agent(agent)), expected)


def test_path_near_agent_weight_weighs_the_path_around_the_agent():
    from envs.gridworld.training import make_batch_fn, near_agent

    config = make_config("1o1g")
    key = jax.random.PRNGKey(3)
    plain = make_batch_fn(config)(key, 4)
    weighted = make_batch_fn(config, path_near_agent_weight=4.0)(key, 4)
    np.testing.assert_array_equal(np.asarray(plain.x0), np.asarray(weighted.x0))
    near = np.stack([np.asarray(near_agent(x[..., 2])) for x in np.asarray(plain.x0)])
    assert near.sum(axis=(1, 2)).min() >= 3  # the agent's cell and at least two neighbours
    np.testing.assert_array_equal(np.asarray(weighted.loss_mask[..., 0]), 1 + 4.0 * near)
    np.testing.assert_array_equal(np.asarray(plain.loss_mask[..., 0]), np.ones(near.shape))
    np.testing.assert_array_equal(np.asarray(weighted.loss_mask[..., 1:]),
                                  np.asarray(plain.loss_mask[..., 1:]))
    with pytest.raises(ValueError, match="path_near_agent_weight"):
        make_batch_fn(config, path_near_agent_weight=-1.0)


@pytest.mark.parametrize("setting", ["p_mo2g", "1o1g"])
def test_later_leg_value_marks_the_leg_after_the_reference(setting):
    """later_leg_value < 1: the same path cells, +1 on a shortest path to the reference (the
    whole path once it was reached, or without one), later_leg_value on the rest."""
    from envs.gridworld.training import make_batch_fn

    config = make_config(setting)
    key = jax.random.PRNGKey(11)
    plain = np.asarray(make_batch_fn(config, detour_prob=0.5)(key, 48).x0)
    legs = np.asarray(make_batch_fn(config, detour_prob=0.5, later_leg_value=0.5)(key, 48).x0)
    np.testing.assert_array_equal(np.delete(plain, PATH_CHANNEL, -1),
                                  np.delete(legs, PATH_CHANNEL, -1))
    np.testing.assert_array_equal(plain[..., PATH_CHANNEL] > 0, legs[..., PATH_CHANNEL] > 0)
    assert set(np.unique(legs[..., PATH_CHANNEL])) <= {-1.0, 0.5, 1.0}
    later_legs = 0
    for x in legs:
        path = x[..., PATH_CHANNEL]
        agent = tuple(np.argwhere(x[..., 2] > 0)[0])
        reference = tuple(np.argwhere(x[..., SUBGOAL_CHANNEL] > 0)[0])
        target = tuple(np.argwhere(x[..., GOAL_CHANNEL] > 0)[0])
        if reference == target:  # reached, or no reference: one leg
            assert not np.any(path == 0.5)
            continue
        later_legs += np.any(path == 0.5)
        current = path == 1.0
        passable = x[..., 0].astype(int) != OBSTACLE_CELL  # seen obstacles; the rest is free
        assert _connected(current, agent, reference)
        # The current leg is a shortest path on the true grid, so at least the seen-map distance.
        assert current.sum() - 1 >= oracle_bfs(passable, reference)[agent]
        assert _connected((path == 0.5) | (path == 1.0), agent, target)
    if setting == "p_mo2g":
        assert later_legs > 0
    with pytest.raises(ValueError, match="later_leg_value"):
        make_batch_fn(config, later_leg_value=0.0)


def test_searcher_route_examples_explore_past_the_reference():
    """search_prob = 1 in P-MO2G-far: every example's agent stood on the reference and then
    searched (some off the expert's walk); its targets are still a shortest path
    from where it stands to the target, and the target as goal and sub-goal. Settings whose
    target the reference shows are left as they are."""
    from envs.gridworld.training import make_batch_fn

    far, near = make_config("p_mo2g_far"), make_config("p_mo2g")
    keys = jax.random.split(jax.random.PRNGKey(3), BATCH)
    run = jax.jit(jax.vmap(lambda k: (training_example(k, far, 0.5, search_prob=1.0),
                                      generate(jax.random.split(k, 5)[0], far),
                                      training_example(k, near, 0.5, search_prob=1.0),
                                      training_example(k, near, 0.5))))
    (x, _, _), ep, near_search, near_plain = jax.device_get(run(keys))
    np.testing.assert_array_equal(near_search[0], near_plain[0])
    off_expert = past_reference = 0
    for i in range(BATCH):
        target, reference = tuple(ep.target[i]), tuple(ep.reference[i])
        visited, agent = x[i, ..., 3] > 0, tuple(np.argwhere(x[i, ..., 2] > 0)[0])
        assert visited[reference]
        path = x[i, ..., PATH_CHANNEL] > 0
        passable = ep.grid[i] != OBSTACLE_CELL
        assert path.sum() - 1 == oracle_bfs(passable, target)[agent]
        assert _connected(path, agent, target)
        for channel in (GOAL_CHANNEL, SUBGOAL_CHANNEL):
            assert np.argwhere(x[i, ..., channel] > 0).tolist() == [list(target)]
        off_expert += bool(np.any(visited & ~ep.expert_path[i]))
        past_reference += agent != reference
    assert past_reference > BATCH // 2 and off_expert > 0
    with pytest.raises(ValueError, match="search_prob"):
        make_batch_fn(far, search_prob=1.5)


def test_stray_examples_walk_toward_the_target_before_the_reference():
    """stray_prob = 1 in P-MO2G-far: an agent that had not stood on the reference walked along a
    shortest path toward the target (never onto it), so it is nearer the target than the same
    example's agent without the walk; its sub-goal is still the reference (where the walk did
    not cross it), and its path target a shortest route through the reference (its distinct
    cells at most that route's length: the legs may overlap). Settings without a reference
    are left as they are."""
    from envs.gridworld.training import make_batch_fn

    far, mo1g = make_config("p_mo2g_far"), make_config("mo1g")
    count = 64
    keys = jax.random.split(jax.random.PRNGKey(5), count)
    run = jax.jit(jax.vmap(lambda k: (training_example(k, far, 0.5, stray_prob=1.0),
                                      training_example(k, far, 0.5),
                                      generate(jax.random.split(k, 5)[0], far),
                                      training_example(k, mo1g, 0.5, stray_prob=1.0),
                                      training_example(k, mo1g, 0.5))))
    (x, _, _), (plain, _, _), ep, mo1g_stray, mo1g_plain = jax.device_get(run(keys))
    np.testing.assert_array_equal(mo1g_stray[0], mo1g_plain[0])
    stray_distance = plain_distance = pending = 0
    for i in range(count):
        target, reference = tuple(ep.target[i]), tuple(ep.reference[i])
        passable = ep.grid[i] != OBSTACLE_CELL
        to_target = oracle_bfs(passable, target)
        agent = tuple(np.argwhere(x[i, ..., 2] > 0)[0])
        plain_agent = tuple(np.argwhere(plain[i, ..., 2] > 0)[0])
        if (plain[i, ..., 3] > 0)[reference]:  # past the reference (or a detour crossed it)
            continue
        assert to_target[agent] >= 1
        if not (x[i, ..., 3] > 0)[reference]:  # the walk did not cross the reference
            assert np.argwhere(x[i, ..., SUBGOAL_CHANNEL] > 0).tolist() == [list(reference)]
            path = x[i, ..., PATH_CHANNEL] > 0
            assert path.sum() - 1 <= oracle_bfs(passable, reference)[agent] + to_target[reference]
            assert _connected(path, agent, reference)
        pending += 1
        stray_distance += to_target[agent]
        plain_distance += to_target[plain_agent]
    assert pending >= 5 and stray_distance < plain_distance
    with pytest.raises(ValueError, match="stray_prob"):
        make_batch_fn(far, stray_prob=-0.1)
