"""The "on_refuted" re-planning trigger: a plan is kept until what the agent has seen disproves
it (envs.gridworld.task.plan_refuted: the cell it heads for or its goal estimate seen without
an object, its path through a seen obstacle, no cell left to head for), or its sub-goal is
reached; never by which object the instruction names."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from diffplan import PlannerConfig, rollout
from envs.gridworld.config import make_config
from envs.gridworld.task import GridTask, plan_refuted
from envs.gridworld.episode import OBSTACLE_CELL
from test_planner import _open_state, _point_plan, oracle_planner, p_mo2g_episodes  # noqa: F401


TARGET_CLASS, REFERENCE_CLASS = 3, 5


def _state(agent, target, reference, seen_cells=None, reached=False):
    """A 16 x 16 grid holding only the target (object class TARGET_CLASS) and the reference
    (REFERENCE_CLASS), the agent where given; everything seen unless seen_cells lists the
    seen ones."""
    state = _open_state(agent)
    seen = jnp.ones((16, 16), bool)
    if seen_cells is not None:
        seen = jnp.zeros((16, 16), bool)
        for cell in seen_cells:
            seen = seen.at[cell].set(True)
    grid = state.grid.at[tuple(target)].set(TARGET_CLASS).at[tuple(reference)].set(
        REFERENCE_CLASS)
    return state.replace(grid=grid, target=jnp.array(target, jnp.int32),
                         reference=jnp.array(reference, jnp.int32), seen=seen,
                         reached_reference=jnp.bool_(reached))


def _numpy_refuted(state, plan):
    """Plain restatement from the seen cells and the plan alone."""
    seen, visited = np.asarray(state.seen), np.asarray(state.visited)
    grid = np.asarray(state.grid)
    known_obstacle = seen & (grid == OBSTACLE_CELL)
    no_object = seen & (grid <= 0)
    plan = np.asarray(plan)
    sub = np.where(known_obstacle | visited, -np.inf, plan[..., 2])
    heading = np.unravel_index(np.argmax(sub), sub.shape)
    goal = np.unravel_index(np.argmax(np.where(known_obstacle, -np.inf, plan[..., 1])),
                            sub.shape)
    through_wall = bool(((plan[..., 0] > 0) & known_obstacle).any())
    return bool(no_object[heading] or no_object[goal] or through_wall
                or plan[heading[0], heading[1], 2] <= 0)


def test_hand_cases():
    plan = _point_plan(goal=(9, 9), subgoal=(9, 9))
    # The guess is unseen: nothing disproves it.
    hidden = _state((0, 0), target=(12, 12), reference=(0, 1), seen_cells=[(0, 0), (0, 1)],
                    reached=True)
    assert not bool(plan_refuted(hidden, plan))
    # The guessed cell has been seen and it is empty: refuted.
    assert bool(plan_refuted(hidden.replace(seen=hidden.seen.at[9, 9].set(True)), plan))
    # The target has come into view elsewhere: that alone does not refute the plan (which
    # object the instruction names is the denoiser's to read, not the trigger's).
    assert not bool(plan_refuted(hidden.replace(seen=hidden.seen.at[12, 12].set(True)), plan))
    # The guess is seen and holds an object: kept, whichever object it is.
    right = _state((0, 0), target=(9, 9), reference=(0, 1), reached=True)
    assert not bool(plan_refuted(right, plan))
    assert not bool(plan_refuted(right.replace(reached_reference=jnp.bool_(False)), plan))
    to_reference = _point_plan(goal=(9, 9), subgoal=(0, 1))
    assert not bool(plan_refuted(right, to_reference))
    # The goal estimate seen empty refutes the plan even while its sub-goal holds an object.
    empty_goal = _point_plan(goal=(4, 4), subgoal=(0, 1))
    assert bool(plan_refuted(right, empty_goal))
    # A path drawn through a cell now seen to be an obstacle: refuted.
    walled = right.replace(grid=right.grid.at[3, 3].set(OBSTACLE_CELL))
    assert not bool(plan_refuted(walled, plan))
    assert bool(plan_refuted(walled, plan.at[3, 3, 0].set(0.5)))
    # A plan whose sub-goal channel marks no cell the agent may still head for is refuted.
    blank = plan.at[..., 2].set(-1.0)
    assert bool(plan_refuted(hidden, blank))
    assert bool(GridTask(make_config("p_mo2g_far")).plan_refuted(hidden, blank))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2 ** 30), st.booleans(), st.floats(0.0, 1.0), st.floats(0.0, 0.3))
def test_matches_a_numpy_oracle(seed, reached, seen_share, wall_share):
    rng = np.random.default_rng(seed)
    cells = rng.choice(256, size=3, replace=False)
    agent, target, reference = (tuple(map(int, divmod(int(c), 16))) for c in cells)
    seen_cells = [tuple(map(int, divmod(int(c), 16)))
                  for c in np.flatnonzero(rng.random(256) < seen_share)] + [agent]
    state = _state(agent, target, reference, seen_cells, reached)
    walls = (rng.random((16, 16)) < wall_share) & (np.asarray(state.grid) == 0)
    walls[agent] = False
    state = state.replace(grid=jnp.where(walls, OBSTACLE_CELL, state.grid).astype(jnp.int8))
    plan = jnp.asarray(rng.uniform(-1, 1, (16, 16, 3)), jnp.float32)
    want = _numpy_refuted(state, plan)
    assert bool(plan_refuted(state, plan)) == want
    # The privileged fields change nothing.
    moved = state.replace(target=jnp.array(reference, jnp.int32),
                          reference=jnp.array(target, jnp.int32),
                          reached_reference=jnp.bool_(not reached))
    assert bool(plan_refuted(moved, plan)) == want


def test_control_the_oracle_tells_a_refuted_plan_from_a_kept_one():
    """The oracle above is not constant: on hand-made states it says both."""
    right = _state((0, 0), target=(9, 9), reference=(0, 1), reached=True)
    assert not _numpy_refuted(right, _point_plan(goal=(9, 9), subgoal=(9, 9)))
    assert _numpy_refuted(right, _point_plan(goal=(9, 8), subgoal=(9, 8)))


def _run(config, episodes):
    task = GridTask(make_config("p_mo2g"))
    keys = jax.random.split(jax.random.PRNGKey(0), episodes.tokens.shape[0])
    return jax.device_get(jax.jit(lambda p, k, e: rollout(task, p, k, e))(
        oracle_planner("p_mo2g", config), keys, episodes))


def test_a_right_plan_is_kept_and_the_episode_solved(p_mo2g_episodes):
    """The oracle's plans head for the reference, then the target: re-planning only when
    refuted or at the sub-goal solves every episode in order at the expert's length with far
    fewer plans than re-planning before every move."""
    always = _run(PlannerConfig(mode="on_the_fly", num_steps=2), p_mo2g_episodes)
    kept = _run(PlannerConfig(mode="on_the_fly", num_steps=2, replan="on_refuted"),
                p_mo2g_episodes)
    assert kept.final_state.success.all() and kept.final_state.reached_reference.all()
    np.testing.assert_array_equal(kept.steps, always.steps)
    assert (kept.num_plans <= always.num_plans).all()
    assert kept.num_plans.sum() * 3 < always.num_plans.sum()


class _NoRefutation:
    """A task that does not say when a plan is refuted."""

    def __init__(self, task):
        self._task = task

    def __getattr__(self, name):
        if name == "plan_refuted":
            raise AttributeError(name)
        return getattr(self._task, name)


def test_a_task_without_plan_refuted_refuses_the_trigger(p_mo2g_episodes):
    task = _NoRefutation(GridTask(make_config("p_mo2g")))
    planner = oracle_planner("p_mo2g", PlannerConfig(mode="on_the_fly", num_steps=2,
                                                     replan="on_refuted"))
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    episodes = jax.tree.map(lambda x: x[:2], p_mo2g_episodes)
    with pytest.raises(ValueError, match="plan_refuted"):
        rollout(task, planner, keys, episodes)


def test_a_follow_plan_is_dropped_where_its_path_would_not_take_the_agent_there():
    """With psi_kind "follow" a kept plan is also refuted where psi, replaying its marks, would
    not arrive where it heads: no neighbour marked, or a gap. Where the only marked neighbour
    was visited, psi steps back onto it, and the plan stands if the marks lead on from there."""
    task = GridTask(make_config("p_mo2g"), psi_kind="follow")
    plan = _point_plan(goal=(9, 9), subgoal=(9, 9))
    state = _state((5, 5), target=(9, 9), reference=(0, 1), reached=True)
    assert not bool(GridTask(make_config("p_mo2g")).plan_refuted(state, plan))
    assert bool(task.plan_refuted(state, plan))
    ahead = plan.at[5, 6:10, 0].set(1.0).at[5:10, 9, 0].set(1.0)
    assert not bool(task.plan_refuted(state, ahead))
    assert bool(task.plan_refuted(state, ahead.at[7, 9, 0].set(-1.0)))  # a gap
    behind = state.replace(visited=state.visited.at[5, 6].set(True))
    assert not bool(task.plan_refuted(behind, ahead))
    assert bool(task.plan_refuted(behind, ahead.at[7, 9, 0].set(-1.0)))
