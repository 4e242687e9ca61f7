"""The paper's psi (GridTask(psi_kind="follow")): the neighbour the plan marks most strongly,
a second plan where it marks none, then a greedy step; the fallback moves counted."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from diffplan import Planner, PlannerConfig, rollout
from envs.gridworld import bfs
from envs.gridworld.config import make_config
from envs.gridworld.episode import OBSTACLE_CELL, generate_batch
from envs.gridworld.task import GridTask, psi_follow, unfollowable
from test_plan_samples import numpy_branches
from test_planner import (P_MO2G_REF_POS, P_MO2G_TARGET_POS, VISITED_CHANNEL, as_denoiser,
                          oracle_planner)

MOVES = np.array([[-1, 0], [0, 1], [1, 0], [0, -1]])


def _numpy_follow(grid, seen, visited, agent, plan):
    """Plain-numpy restatement: (move, fell back)."""
    h, w = grid.shape
    known_obstacle = seen & (grid == OBSTACLE_CELL)
    heading = np.asarray(goal_estimate_np(known_obstacle, visited, plan))
    candidates, branches = numpy_branches(known_obstacle, visited, tuple(int(v) for v in agent),
                                          plan)
    arriving = [c for c in candidates if branches[c[0]] >= 0]
    pool = arriving or candidates
    if pool:
        best = max(c[2] for c in pool)
        return min(c[0] for c in pool if c[2] == best), False
    goal = np.unravel_index(np.argmax(np.where(known_obstacle, -np.inf, plan[..., 1])), (h, w))
    big, dist = np.iinfo(np.int32).max, []
    for m in MOVES:
        r, c = agent + m
        ok = 0 <= r < h and 0 <= c < w and not known_obstacle[r, c]
        if ok and (r, c) == tuple(goal) and tuple(goal) != tuple(heading):
            ok = False
        dist.append(abs(r - heading[0]) + abs(c - heading[1]) if ok else big)
    return int(np.argmin(dist)), True


def goal_estimate_np(known_obstacle, visited, plan):
    sub = np.where(known_obstacle | visited, -np.inf, plan[..., 2])
    return np.unravel_index(np.argmax(sub), sub.shape)


@functools.lru_cache(maxsize=None)
def _states():
    config = make_config("p_mo2g")
    eps = generate_batch(jax.random.PRNGKey(5), config, 16)
    return jax.device_get(jax.vmap(GridTask(config).reset)(eps))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 15), st.integers(0, 2 ** 30), st.floats(-0.9, 0.9))
def test_follow_matches_a_numpy_oracle(i, seed, shift):
    """Random plans (path values shifted so that sometimes no neighbour is marked), random
    visited cells: psi_follow and unfollowable agree with the plain-numpy restatement."""
    states = _states()
    state = jax.tree.map(lambda x: x[i], states)
    rng = np.random.default_rng(seed)
    plan = np.clip(rng.uniform(-1, 1, (16, 16, 3)) + np.array([shift, 0, 0]), -1, 1)
    plan = plan.astype(np.float32)
    visited = np.asarray(state.visited) | (rng.uniform(size=(16, 16)) < 0.3)
    state = state.replace(visited=jnp.asarray(visited))
    want, fell_back = _numpy_follow(np.asarray(state.grid), np.asarray(state.seen), visited,
                                    np.asarray(state.agent), plan)
    assert int(jax.jit(psi_follow)(state, jnp.asarray(plan))) == want
    assert bool(jax.jit(unfollowable)(state, jnp.asarray(plan))) == fell_back


def test_follow_never_enters_a_known_obstacle():
    states = _states()
    plans = jax.random.uniform(jax.random.PRNGKey(2), (16, 16, 16, 3), minval=-1, maxval=1)
    moves = np.asarray(jax.vmap(psi_follow)(states, plans))
    nxt = np.asarray(states.agent) + MOVES[moves]
    for k, (r, c) in enumerate(nxt):
        assert 0 <= r < 16 and 0 <= c < 16
        assert not (states.seen[k, r, c] and states.grid[k, r, c] == OBSTACLE_CELL)


def _path_oracle_apply(params, x_t, t, tokens):
    """An "x0 network" whose plan marks every cell on a shortest route (over the cells not known
    to be obstacles) from the agent to the sub-goal, as a well-trained path channel would; goal
    and sub-goal as test_planner's oracle."""
    del params, t

    def one(x, tok):
        cells = jnp.round(x[..., 0]).astype(jnp.int32)
        visited = x[..., VISITED_CHANNEL] > 0.5
        reference, target = cells == tok[P_MO2G_REF_POS], cells == tok[P_MO2G_TARGET_POS]
        subgoal = jnp.where(jnp.any(reference & visited), target, reference)
        goal = jnp.where(jnp.any(target), target, reference)
        passable = x[..., 1] < 0.5
        agent_flat = jnp.argmax(x[..., 2].ravel())
        agent = jnp.stack([agent_flat // 16, agent_flat % 16])
        sub_flat = jnp.argmax(subgoal.ravel())
        sub = jnp.stack([sub_flat // 16, sub_flat % 16])
        d_a = bfs.bfs_distance(passable, agent)
        d_s = bfs.bfs_distance(passable, sub)
        on = (d_a >= 0) & (d_s >= 0) & (d_a + d_s == d_a[sub[0], sub[1]])
        signed = lambda m: m.astype(jnp.float32) * 2 - 1  # noqa: E731
        return jnp.stack([signed(on), signed(goal), signed(subgoal)], -1)

    return jax.vmap(one)(x_t, tokens)


def _run(planner, task, episodes):
    keys = jax.random.split(jax.random.PRNGKey(0), episodes.tokens.shape[0])
    return jax.device_get(jax.jit(lambda p, k, e: rollout(task, p, k, e))(planner, keys,
                                                                          episodes))


@pytest.fixture(scope="module")
def episodes():
    return generate_batch(jax.random.PRNGKey(7), make_config("p_mo2g"), 12)


FOLLOW = GridTask(make_config("p_mo2g"), psi_kind="follow")


def test_a_marked_shortest_route_carries_the_agent_without_fallbacks(episodes):
    config = PlannerConfig(mode="on_the_fly", num_steps=2, warm_start_step=1)
    planner = Planner(as_denoiser(_path_oracle_apply, "x0"), config)
    r = _run(planner, FOLLOW, episodes)
    assert r.final_state.success.all() and r.final_state.reached_reference.all()
    np.testing.assert_array_equal(r.fallback_moves, 0)
    np.testing.assert_array_equal(r.num_plans, r.steps)  # no second plans were needed
    assert (r.final_state.collisions == 0).all()


def test_unmarked_plans_are_planned_again_once_then_counted_as_fallbacks(episodes):
    """test_planner's oracle marks no path: every move costs a second plan (on-the-fly) and is
    a fallback move; one-shot never plans again; the search psi reports no fallbacks."""
    config = PlannerConfig(mode="on_the_fly", num_steps=2, warm_start_step=1)
    r = _run(oracle_planner("p_mo2g", config), FOLLOW, episodes)
    np.testing.assert_array_equal(r.num_plans, 2 * r.steps)
    np.testing.assert_array_equal(r.denoiser_calls, 4 * r.steps)
    np.testing.assert_array_equal(r.fallback_moves, r.steps)
    one_shot = PlannerConfig(mode="one_shot", num_steps=2)
    r = _run(oracle_planner("p_mo2g", one_shot), FOLLOW, episodes)
    np.testing.assert_array_equal(r.num_plans, 1)
    np.testing.assert_array_equal(r.fallback_moves, r.steps)
    r = _run(oracle_planner("p_mo2g", config), GridTask(make_config("p_mo2g")), episodes)
    assert r.fallback_moves is None


def test_bad_psi_kind_is_refused():
    with pytest.raises(ValueError, match="psi_kind"):
        GridTask(make_config("p_mo2g"), psi_kind="teleport")


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 15), st.integers(0, 2 ** 30), st.sampled_from([-0.8, -0.5, 0.3]))
def test_a_lower_mark_is_the_same_psi_on_a_shifted_path_channel(i, seed, mark):
    """Reading path > mark as marked is psi_follow (and unfollowable) with mark 0 on a path
    channel lowered by mark: the threshold moves, nothing else does."""
    state = jax.tree.map(lambda x: x[i], _states())
    rng = np.random.default_rng(seed)
    plan = rng.uniform(-0.9, 0.9, (16, 16, 3)).astype(np.float32)
    visited = np.asarray(state.visited) | (rng.uniform(size=(16, 16)) < 0.3)
    state = state.replace(visited=jnp.asarray(visited))
    shifted = plan - np.array([mark, 0, 0], np.float32)
    follow = jax.jit(psi_follow, static_argnums=(2, 3))
    unfollow = jax.jit(unfollowable, static_argnums=(2, 3))
    assert int(follow(state, plan, True, mark)) == int(follow(state, shifted, True, 0.0))
    assert bool(unfollow(state, plan, True, mark)) == bool(unfollow(state, shifted, True, 0.0))


def test_faint_marks_are_followed_only_below_the_mark(episodes):
    """A shortest route marked -0.5 instead of +1: with follow_mark 0 every move falls back;
    with the default mark (-0.8) the route carries the agent without fallbacks."""
    def faint(params, x_t, t, tokens):
        out = _path_oracle_apply(params, x_t, t, tokens)
        return out.at[..., 0].set(jnp.where(out[..., 0] > 0, -0.5, -1.0))

    config = PlannerConfig(mode="on_the_fly", num_steps=2, warm_start_step=1)
    planner = Planner(as_denoiser(faint, "x0"), config)
    high = GridTask(make_config("p_mo2g"), psi_kind="follow", follow_mark=0.0)
    r = _run(planner, high, episodes)
    np.testing.assert_array_equal(r.fallback_moves, r.steps)
    assert FOLLOW.follow_mark == -0.8
    r = _run(planner, FOLLOW, episodes)
    assert r.final_state.success.all() and r.final_state.reached_reference.all()
    np.testing.assert_array_equal(r.fallback_moves, 0)


def test_a_mark_outside_the_path_range_is_refused():
    for mark in (1.0, -1.5, float("nan")):
        with pytest.raises(ValueError, match="follow_mark"):
            GridTask(make_config("p_mo2g"), psi_kind="follow", follow_mark=mark)
