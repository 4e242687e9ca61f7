"""Several plans drawn per re-plan (PlannerConfig.samples), the cheapest kept: the planner's
choice, its cost accounting, the rollout's ranking by task.plan_cost, and the grid world's
plan_cost."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from diffplan import Planner, PlannerConfig, rollout
from diffplan.planner import SAMPLE_STREAM
from envs.gridworld.config import make_config
from envs.gridworld.episode import OBSTACLE_CELL
from envs.gridworld.task import FOLLOW_MARK, REFUTED_PLAN_COST, GridTask, plan_cost
from test_planner import (_open_state, _point_plan, as_denoiser, oracle_planner,  # noqa: F401
                          p_mo2g_episodes)
from test_replan_refuted import _NoRefutation, _state

C = 5  # the grid world's condition channels


def _echo(params, x_t, t, tokens):
    """An "x0 network" whose prediction is its noisy input: plans differ with the noise."""
    del params, t, tokens
    return jnp.clip(x_t[..., C:], -1.0, 1.0)


def _planner(samples, mode="on_the_fly"):
    return Planner(as_denoiser(_echo, "x0"),
                   PlannerConfig(mode=mode, num_steps=2, warm_num_steps=None, samples=samples))


def _path_mass(plans):
    return plans[..., 0].sum(axis=(-2, -1))


@pytest.mark.parametrize("bad", [0, -1, True, 2.0])
def test_bad_samples_are_refused(bad):
    with pytest.raises(ValueError, match="samples"):
        PlannerConfig(samples=bad)


def test_calls_scale_with_samples():
    one, four = PlannerConfig(), PlannerConfig(samples=4)
    assert four.full_plan_calls == 4 * one.full_plan_calls
    assert four.warm_plan_calls == 4 * one.warm_plan_calls


def test_the_cheapest_of_the_draws_is_kept():
    """plan() with K draws returns the draw of lowest rank among the plans a one-sample
    planner makes from the draws' keys; the first draw is the one-sample plan."""
    k = 4
    state = _planner(1).init(jax.random.PRNGKey(3), jnp.zeros((8,), jnp.int32))
    condition = jnp.zeros((16, 16, C))
    got, after = _planner(k).plan(state, condition, rank=_path_mass)
    base_key = jax.random.fold_in(state.key, 0)
    keys = [base_key] + [jax.random.fold_in(base_key, SAMPLE_STREAM + j) for j in range(1, k)]
    single = _planner(1)
    draws = [single._sample(key, condition, state.tokens, None) for key in keys]
    np.testing.assert_allclose(draws[0], single.plan(state, condition)[0])
    masses = [float(_path_mass(d)) for d in draws]
    assert len(set(masses)) == k  # the draws differ
    np.testing.assert_allclose(got, draws[int(np.argmin(masses))])
    assert int(after.calls) == k * 2 and int(after.num_plans) == 1


def test_plan_batch_ranks_each_row_as_plan_does():
    k, b = 3, 5
    planner = _planner(k)
    states = jax.vmap(planner.init)(jax.random.split(jax.random.PRNGKey(1), b),
                                    jnp.zeros((b, 8), jnp.int32))
    conditions = jax.random.uniform(jax.random.PRNGKey(2), (b, 16, 16, C))
    weights = jnp.arange(b, dtype=jnp.float32) - 2.0  # row i prefers more or less path mass

    def rank(i, plans):
        return weights[i] * _path_mass(plans)

    plans, _ = planner.plan_batch(states, conditions, rank=rank, chunk=2)
    for i in range(b):
        state_i = jax.tree.map(lambda x: x[i], states)
        want, _ = planner.plan(state_i, conditions[i], rank=lambda p: rank(i, p))
        np.testing.assert_allclose(plans[i], want, atol=1e-6)


def test_several_draws_without_a_ranking_are_refused():
    planner = _planner(2)
    state = planner.init(jax.random.PRNGKey(0), jnp.zeros((8,), jnp.int32))
    with pytest.raises(ValueError, match="rank"):
        planner.plan(state, jnp.zeros((16, 16, C)))
    states = jax.tree.map(lambda x: x[None], state)
    with pytest.raises(ValueError, match="rank"):
        planner.plan_batch(states, jnp.zeros((1, 16, 16, C)))


class _NoCost(_NoRefutation):
    def __getattr__(self, name):
        if name == "plan_cost":
            raise AttributeError(name)
        return getattr(self._task, name)


def _rollout(config, episodes, task=None):
    task = task or GridTask(make_config("p_mo2g"))
    keys = jax.random.split(jax.random.PRNGKey(0), episodes.tokens.shape[0])
    return jax.device_get(jax.jit(lambda p, k, e: rollout(task, p, k, e))(
        oracle_planner("p_mo2g", config), keys, episodes))


def test_rollout_with_draws_of_one_plan_changes_nothing_but_the_cost(p_mo2g_episodes):
    """The oracle's draws are all the same plan: ranking them keeps it, so the episodes go
    exactly as with one draw, at twice the denoiser calls."""
    one = _rollout(PlannerConfig(num_steps=2, replan="on_refuted"), p_mo2g_episodes)
    two = _rollout(PlannerConfig(num_steps=2, replan="on_refuted", samples=2), p_mo2g_episodes)
    assert one.final_state.success.all()
    np.testing.assert_array_equal(two.positions, one.positions)
    np.testing.assert_array_equal(two.num_plans, one.num_plans)
    np.testing.assert_array_equal(two.denoiser_calls, 2 * one.denoiser_calls)


def test_a_task_without_plan_cost_refuses_several_draws(p_mo2g_episodes):
    episodes = jax.tree.map(lambda x: x[:2], p_mo2g_episodes)
    task = _NoCost(GridTask(make_config("p_mo2g")))
    planner = oracle_planner("p_mo2g", PlannerConfig(num_steps=2, samples=2))
    with pytest.raises(ValueError, match="plan_cost"):
        rollout(task, planner, jax.random.split(jax.random.PRNGKey(0), 2), episodes)


def test_grid_plan_cost_is_the_walk_to_the_heading_cell():
    """Moves around known obstacles (unseen cells count as free) to the sub-goal's cell; a plan
    whose guessed cell was seen to hold no object costs REFUTED_PLAN_COST more."""
    state = _state((5, 5), target=(9, 9), reference=(0, 1), reached=True)
    plan = _point_plan(goal=(9, 9), subgoal=(9, 9))
    assert float(plan_cost(state, plan)) == 8.0
    wall = state.grid.at[6, 3:8].set(OBSTACLE_CELL).at[4:7, 7].set(OBSTACLE_CELL)
    walled = state.replace(grid=wall.at[9, 5].set(3))
    south = _point_plan(goal=(9, 5), subgoal=(9, 5))
    assert float(plan_cost(walled, south)) == 4 + 2 * 3  # around the wall's west end
    unseen = walled.replace(seen=walled.seen.at[6, 3:8].set(False))
    assert float(plan_cost(unseen, south)) == 4.0  # not known to be a wall
    wrong = _point_plan(goal=(9, 8), subgoal=(9, 8))
    assert float(plan_cost(state, wrong)) == 7.0 + REFUTED_PLAN_COST
    assert float(GridTask(make_config("p_mo2g")).plan_cost(state, wrong)) == \
        7.0 + REFUTED_PLAN_COST


def test_a_follow_task_ranks_a_path_psi_would_follow_there_first():
    """With the follow psi a plan along whose marks psi would not arrive where the plan heads
    costs REFUTED_PLAN_COST more: a broken path, no path, or a fork whose other leg psi takes."""
    from envs.gridworld.task import follow_moves, psi_follow

    follow = GridTask(make_config("p_mo2g"), psi_kind="follow")
    state = _state((5, 5), target=(5, 9), reference=(0, 1), reached=True)
    bare = _point_plan(goal=(5, 9), subgoal=(5, 9))
    led = bare.at[5, 5:10, 0].set(1.0)
    broken = led.at[5, 7, 0].set(-1.0)
    assert int(follow_moves(state, led)) == 4
    assert int(follow_moves(state, broken)) == -1
    assert int(follow_moves(state, bare)) == -1
    assert float(follow.plan_cost(state, led)) == 4.0
    assert float(follow.plan_cost(state, broken)) == 4.0 + REFUTED_PLAN_COST
    assert float(GridTask(make_config("p_mo2g")).plan_cost(state, broken)) == 4.0
    # A fork at (5, 7), two moves on: the replay past the first move follows the stronger
    # mark, so psi is sent off along the leg north.
    fork = led.at[1:5, 7, 0].set(1.0).at[4, 7, 0].set(1.0).at[5, 8, 0].set(0.9)
    assert int(follow_moves(state, fork)) == -1
    assert int(follow_moves(state, fork.at[4, 7, 0].set(0.8))) == 4
    # A fork at the agent's own cell: the first move takes the branch that arrives, however
    # strongly the other is marked.
    beside = led.at[1:5, 5, 0].set(1.0).at[5, 6, 0].set(0.6)
    assert int(follow_moves(state, beside)) == 4
    assert int(psi_follow(state, beside)) == 1  # east, not the stronger mark north
    assert int(psi_follow(state, beside.at[5, 7, 0].set(-1.0))) == 0  # none arrives: strongest


def numpy_replay(known_obstacle, visited, agent, plan, heading, goal, mark=FOLLOW_MARK):
    """Plain replay of psi_follow's rule from agent (a cell): moves onto the unvisited
    neighbour marked most strongly (path value above mark) until heading; -1 if it stops or
    takes 2 (H + W) moves."""
    visited = visited.copy()
    size = known_obstacle.shape[0]
    visited[agent] = True
    for moves in range(2 * 2 * size + 1):
        if agent == heading:
            return moves
        if moves == 2 * 2 * size:
            return -1
        best, best_value = None, -np.inf
        for dr, dc in ((-1, 0), (0, 1), (1, 0), (0, -1)):  # N, E, S, W
            r, c = agent[0] + dr, agent[1] + dc
            if not (0 <= r < size and 0 <= c < size) or known_obstacle[r, c] or visited[r, c]:
                continue
            if (r, c) == goal and goal != heading:
                continue
            if plan[r, c, 0] > mark and plan[r, c, 0] > best_value:
                best, best_value = (r, c), plan[r, c, 0]
        if best is None:
            return -1
        agent = best
        visited[best] = True
    return -1


def numpy_branches(known_obstacle, visited, agent, plan, mark=FOLLOW_MARK):
    """Plain restatement of psi_follow's first step: (candidates [(move, cell, path value)]:
    the marked unvisited legal neighbours, or the marked visited ones when there are none;
    branch moves {move: 1 + numpy_replay from there, -1 not arriving})."""
    size = known_obstacle.shape[0]
    sub = np.where(known_obstacle | visited, -np.inf, plan[..., 2])
    heading = tuple(int(v) for v in np.unravel_index(np.argmax(sub), sub.shape))
    goal = tuple(int(v) for v in np.unravel_index(
        np.argmax(np.where(known_obstacle, -np.inf, plan[..., 1])), sub.shape))
    marked = []
    for move, (dr, dc) in enumerate(((-1, 0), (0, 1), (1, 0), (0, -1))):
        r, c = agent[0] + dr, agent[1] + dc
        if not (0 <= r < size and 0 <= c < size) or known_obstacle[r, c]:
            continue
        if (r, c) == goal and goal != heading:
            continue
        if plan[r, c, 0] > mark:
            marked.append((move, (r, c), plan[r, c, 0]))
    fresh = [m for m in marked if not visited[m[1]]]
    candidates = fresh or marked
    branches = {}
    for move, cell, _ in candidates:
        moves = numpy_replay(known_obstacle, visited, cell, plan, heading, goal, mark)
        branches[move] = moves + 1 if moves >= 0 else -1
    return candidates, branches


def _numpy_follow_moves(state, plan):
    """Plain restatement of follow_moves: the soonest arriving branch of psi_follow's first
    step, then psi_follow's rule replayed cell by cell."""
    known_obstacle = np.asarray(state.seen) & (np.asarray(state.grid) == OBSTACLE_CELL)
    agent = tuple(int(v) for v in np.asarray(state.agent))
    _, branches = numpy_branches(known_obstacle, np.asarray(state.visited), agent,
                                 np.asarray(plan))
    arriving = [m for m in branches.values() if m >= 0]
    return min(arriving) if arriving else -1


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), density=st.floats(0.2, 0.8))
def test_follow_moves_matches_a_numpy_replay(seed, density):
    from envs.gridworld.task import follow_moves

    rng = np.random.default_rng(seed)
    state = _state(tuple(rng.integers(0, 16, 2)), target=(5, 9), reference=(0, 1))
    grid = np.where(rng.random((16, 16)) < 0.15, OBSTACLE_CELL, 0).astype(np.int8)
    grid[tuple(np.asarray(state.agent))] = 0
    state = state.replace(grid=jnp.asarray(grid), seen=jnp.asarray(rng.random((16, 16)) < 0.7),
                          visited=state.visited | jnp.asarray(rng.random((16, 16)) < 0.05))
    plan = rng.uniform(-1, 1, (16, 16, 3)).astype(np.float32)
    plan[..., 0] = np.where(rng.random((16, 16)) < density, np.abs(plan[..., 0]), -1.0)
    assert int(jax.jit(follow_moves)(state, jnp.asarray(plan))) == \
        _numpy_follow_moves(state, plan)
