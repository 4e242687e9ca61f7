"""envs.gridworld.env: dynamics and observations against a plain numpy re-implementation.

Rollouts (conftest.rollout) run jitted reset + step + observe under vmap for episodes of a seed
with mixed actions (half the batch follows the expert path, half acts at random)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from envs.gridworld import grammar
from envs.gridworld.config import REFERENCE_SETTINGS, SETTINGS

SEEDS = st.integers(0, 2**32 - 1)
MOVES = np.array([[-1, 0], [0, 1], [1, 0], [0, -1]])  # N, E, S, W; row 0 is north


def fov_square(agent, size: int, radius) -> np.ndarray:
    """bool (B, size, size): Chebyshev square of radius around each agent (B, 2), clipped."""
    if radius is None:
        return np.ones((len(agent), size, size), bool)
    rows = np.arange(size)[None, :, None]
    cols = np.arange(size)[None, None, :]
    return ((np.abs(rows - agent[:, 0, None, None]) <= radius)
            & (np.abs(cols - agent[:, 1, None, None]) <= radius))


def true_tokens(grid) -> np.ndarray:
    """int (..., H, W) token id of every cell of true grids."""
    grid = grid.astype(np.int64)
    tokens = np.where(grid == -1, grammar.OBSTACLE_ID, grammar.EMPTY_ID)
    return np.where(grid > 0, grid - 1 + grammar.OBJECT_TOKEN_OFFSET, tokens)


def expected_observation(grid, agent, seen, visited):
    """(cells int (B, H, W), features bool (B, H, W, 4)) computed from scratch."""
    b, h, w = grid.shape
    cells = np.where(seen, true_tokens(grid), grammar.UNSEEN_ID)
    agent_map = np.zeros((b, h, w), bool)
    agent_map[np.arange(b), agent[:, 0], agent[:, 1]] = True
    features = np.stack([seen & (grid == -1), agent_map, visited, seen], -1)
    return cells, features


def check_observation(obs_cells, obs_features, grid, agent, seen, visited, where=""):
    cells, features = expected_observation(grid, agent, seen, visited)
    assert obs_cells.dtype == np.int8 and obs_features.dtype == np.bool_
    np.testing.assert_array_equal(obs_cells, cells, err_msg=where)
    np.testing.assert_array_equal(obs_features, features, err_msg=where)


@settings(max_examples=4, deadline=None, database=None)
@given(seed=SEEDS)
@pytest.mark.parametrize("setting", SETTINGS)
def test_rollout_matches_numpy_dynamics(rollout, grid_configs, setting, seed):
    """Step by step: positions, collisions (exactly when a move is blocked), accumulated field of
    view, visited cells, t, done (on the target or at max_steps, then frozen), success iff on
    the target, and the observation, all equal a from-scratch numpy simulation."""
    config = grid_configs[setting]
    r = rollout(setting, seed)
    eps, s0, states, obs = r["episodes"], r["states0"], r["states"], r["obs"]
    b, size = eps.agent.shape[0], config.size
    idx = np.arange(b)
    grid = eps.grid
    agent = eps.agent.copy()
    seen = fov_square(agent, size, config.view_radius)
    visited = np.zeros((b, size, size), bool)
    visited[idx, agent[:, 0], agent[:, 1]] = True
    t = np.zeros(b, int)
    collisions = np.zeros(b, int)
    success = (agent == eps.target).all(-1)
    done = success.copy()
    reached_ref = config.has_reference & (agent == eps.reference).all(-1)

    def compare(state, where):
        np.testing.assert_array_equal(state.agent, agent, err_msg=where)
        np.testing.assert_array_equal(state.seen, seen, err_msg=where)
        np.testing.assert_array_equal(state.visited, visited, err_msg=where)
        np.testing.assert_array_equal(state.t, t, err_msg=where)
        np.testing.assert_array_equal(state.collisions, collisions, err_msg=where)
        np.testing.assert_array_equal(state.done, done, err_msg=where)
        np.testing.assert_array_equal(state.success, success, err_msg=where)
        np.testing.assert_array_equal(state.reached_reference, reached_ref, err_msg=where)
        np.testing.assert_array_equal(state.grid, grid, err_msg=where)

    compare(s0, "t=0")
    check_observation(r["obs0"].cells, r["obs0"].features, grid, agent, seen, visited, "t=0")
    assert not done.any()
    for step in range(r["actions"].shape[1]):
        live = ~done
        nxt = agent + MOVES[r["actions"][:, step]]
        inside = ((nxt >= 0) & (nxt < size)).all(-1)
        clipped = np.clip(nxt, 0, size - 1)
        blocked = ~inside | (grid[idx, clipped[:, 0], clipped[:, 1]] == -1)
        new_agent = np.where(blocked[:, None], agent, nxt)
        agent = np.where(live[:, None], new_agent, agent)
        collisions = collisions + (live & blocked)
        t = t + live
        seen = seen | (live[:, None, None] & fov_square(agent, size, config.view_radius))
        visited[idx[live], agent[live, 0], agent[live, 1]] = True
        on_target = (agent == eps.target).all(-1)
        if config.has_reference:
            reached_ref = reached_ref | (live & (agent == eps.reference).all(-1))
        success = np.where(live, on_target, success)
        done = done | (live & (on_target | (t >= config.max_steps)))
        state = type(s0)(*[leaf[:, step] for leaf in _leaves(states)])
        where = f"{setting} seed {seed} step {step}"
        compare(state, where)
        check_observation(obs.cells[:, step], obs.features[:, step], grid, agent, seen, visited,
                          where)
        # Invariants, stated directly.
        assert ((agent >= 0) & (agent < size)).all()
        assert (grid[idx, agent[:, 0], agent[:, 1]] != -1).all(), "agent in an obstacle"
        np.testing.assert_array_equal(state.success, (state.agent == eps.target).all(-1))

    # Every episode ends inside the rollout: on the target or after exactly max_steps moves.
    assert done.all()
    np.testing.assert_array_equal(t[~success], config.max_steps)
    assert (t[success] <= config.max_steps).all()
    # Expert-following episodes (even indices) succeed within their expert length.
    even = idx % 2 == 0
    assert success[even].all()
    assert (t[even] <= eps.expert_length[even]).all()
    # The random walkers collide: the check of collision counting is not vacuous.
    assert collisions[~even].sum() > 0


def _leaves(state):
    import dataclasses

    return [getattr(state, f.name) for f in dataclasses.fields(state)]


@pytest.mark.parametrize("setting", SETTINGS)
def test_done_states_are_frozen(rollout, setting):
    r = rollout(setting, 0)
    states = r["states"]
    done = states.done  # (B, T)
    for leaf in _leaves(states):
        same = (leaf[:, 1:] == leaf[:, :-1]).reshape(done.shape[0], done.shape[1] - 1, -1).all(-1)
        assert same[done[:, :-1]].all()
    assert done[:, :-1].any()  # some state was done before the end
    # done is absorbing.
    assert (done[:, 1:] >= done[:, :-1]).all()


@pytest.mark.parametrize("setting", SETTINGS)
def test_field_of_view(rollout, grid_configs, setting):
    """seen is monotone, starts as the clipped Chebyshev square around the agent (visible0) and
    always contains the current square; fully observable settings see everything."""
    config = grid_configs[setting]
    r = rollout(setting, 1)
    s0, states, eps = r["states0"], r["states"], r["episodes"]
    square0 = fov_square(eps.agent, config.size, config.view_radius)
    np.testing.assert_array_equal(s0.seen, square0)
    np.testing.assert_array_equal(r["visible0"], square0)
    seen = np.concatenate([s0.seen[:, None], states.seen], axis=1)
    assert (seen[:, 1:] >= seen[:, :-1]).all()
    b, t = states.agent.shape[:2]
    current = fov_square(states.agent.reshape(b * t, 2), config.size, config.view_radius)
    assert (states.seen.reshape(b * t, config.size, config.size) >= current).all()
    if config.view_radius is None:
        assert seen.all()
    else:
        side = 2 * config.view_radius + 1
        assert (s0.seen.sum((1, 2)) <= side * side).all()
        assert (s0.seen.sum((1, 2)) < config.size ** 2).all()
        assert (seen[:, -1].sum((1, 2)) > seen[:, 0].sum((1, 2))).any()  # the view grows


@pytest.mark.parametrize("setting", REFERENCE_SETTINGS)
def test_target_hidden_reference_visible_at_t0(rollout, setting):
    r = rollout(setting, 2)
    eps, cells = r["episodes"], r["obs0"].cells
    idx = np.arange(len(eps.agent))
    target_cells = cells[idx, eps.target[:, 0], eps.target[:, 1]]
    ref_cells = cells[idx, eps.reference[:, 0], eps.reference[:, 1]]
    assert (target_cells == grammar.UNSEEN_ID).all()
    np.testing.assert_array_equal(
        ref_cells, eps.reference_class - 1 + grammar.OBJECT_TOKEN_OFFSET)
    # The target class word does not appear anywhere in the t=0 observation.
    target_tokens = eps.target_class - 1 + grammar.OBJECT_TOKEN_OFFSET
    assert not (cells == target_tokens[:, None, None]).any((1, 2)).any()


@settings(max_examples=4, deadline=None, database=None)
@given(seed=SEEDS)
def test_observe_never_leaks_unseen_cells(rollout, observe_fn, grid_configs, seed):
    """Rewriting the world in unseen cells (and moving the hidden target/reference fields) does
    not change the observation."""
    setting = "p_mo2g"
    config = grid_configs[setting]
    r = rollout(setting, seed % 3)
    rng = np.random.default_rng(seed)
    b = r["episodes"].agent.shape[0]
    step = int(rng.integers(0, r["actions"].shape[1]))
    for state, cells, features in [
        (r["states0"], r["obs0"].cells, r["obs0"].features),
        (type(r["states0"])(*[leaf[:, step] for leaf in _leaves(r["states"])]),
         r["obs"].cells[:, step], r["obs"].features[:, step]),
    ]:
        noise = rng.integers(-1, config.num_classes + 1, size=state.grid.shape).astype(np.int8)
        grid = np.where(state.seen, state.grid, noise)
        assert (grid != state.grid).any()  # the perturbation changes the world
        moved = state.replace(grid=grid, target=rng.integers(0, 16, (b, 2)).astype(np.int32),
                              reference=rng.integers(0, 16, (b, 2)).astype(np.int32))
        obs = observe_fn(setting)(moved)
        np.testing.assert_array_equal(np.asarray(obs.cells), cells)
        np.testing.assert_array_equal(np.asarray(obs.features), features)
        assert (cells[~state.seen] == grammar.UNSEEN_ID).all()
