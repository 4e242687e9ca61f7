"""The "on_refuted" re-planning trigger: a plan is kept until what the agent sees disproves
where it heads (envs.gridworld.task.plan_refuted), or its sub-goal is reached."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from diffplan import PlannerConfig, rollout
from envs.gridworld.config import make_config
from envs.gridworld.task import GridTask, goal_estimate, plan_refuted, sought_cell
from envs.gridworld.episode import OBSTACLE_CELL
from test_planner import _open_state, _point_plan, oracle_planner, p_mo2g_episodes  # noqa: F401


def _state(agent, target, reference, seen_cells=None, reached=False):
    """An empty 16 x 16 grid, the agent, target and reference where given; everything seen
    unless seen_cells lists the seen ones."""
    state = _open_state(agent)
    seen = jnp.ones((16, 16), bool)
    if seen_cells is not None:
        seen = jnp.zeros((16, 16), bool)
        for cell in seen_cells:
            seen = seen.at[cell].set(True)
    return state.replace(target=jnp.array(target, jnp.int32),
                         reference=jnp.array(reference, jnp.int32), seen=seen,
                         reached_reference=jnp.bool_(reached))


def _numpy_refuted(state, plan, has_reference):
    """Plain restatement: the heading cell and the sought cell by hand."""
    seen, visited = np.asarray(state.seen), np.asarray(state.visited)
    known_obstacle = seen & (np.asarray(state.grid) == OBSTACLE_CELL)
    sub = np.where(known_obstacle | visited, -np.inf, np.asarray(plan[..., 2]))
    heading = np.unravel_index(np.argmax(sub), sub.shape)
    sought = tuple(np.asarray(state.target if not has_reference or bool(state.reached_reference)
                              else state.reference))
    wrong = heading != sought and (seen[heading] or seen[sought])
    return bool(wrong or plan[heading[0], heading[1], 2] <= 0)


def test_sought_cell_is_the_reference_until_reached():
    s = _state((0, 0), target=(9, 9), reference=(3, 3))
    np.testing.assert_array_equal(sought_cell(s, True), [3, 3])
    np.testing.assert_array_equal(sought_cell(s.replace(reached_reference=jnp.bool_(True)),
                                              True), [9, 9])
    np.testing.assert_array_equal(sought_cell(s, False), [9, 9])


def test_hand_cases():
    plan = _point_plan(goal=(9, 9), subgoal=(9, 9))
    # The guess is unseen and the target too: nothing disproves it.
    hidden = _state((0, 0), target=(12, 12), reference=(0, 1), seen_cells=[(0, 0), (0, 1)],
                    reached=True)
    assert not bool(plan_refuted(hidden, plan, True))
    # The guessed cell has been seen and it is empty: refuted.
    assert bool(plan_refuted(hidden.replace(seen=hidden.seen.at[9, 9].set(True)), plan, True))
    # The target has come into view elsewhere: refuted.
    assert bool(plan_refuted(hidden.replace(seen=hidden.seen.at[12, 12].set(True)), plan, True))
    # The guess is right and seen: kept.
    right = _state((0, 0), target=(9, 9), reference=(0, 1), reached=True)
    assert not bool(plan_refuted(right, plan, True))
    # Before the reference is reached, the plan must head for the reference.
    assert bool(plan_refuted(right.replace(reached_reference=jnp.bool_(False)), plan, True))
    # A plan whose sub-goal channel marks no cell the agent may still head for is refuted.
    blank = plan.at[..., 2].set(-1.0)
    assert bool(plan_refuted(hidden, blank, True))
    assert bool(GridTask(make_config("p_mo2g_far")).plan_refuted(hidden, blank))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2 ** 30), st.booleans(), st.booleans(), st.floats(0.0, 1.0))
def test_matches_a_numpy_oracle(seed, has_reference, reached, seen_share):
    rng = np.random.default_rng(seed)
    cells = rng.choice(256, size=3, replace=False)
    agent, target, reference = (tuple(map(int, divmod(int(c), 16))) for c in cells)
    seen_cells = [tuple(map(int, divmod(int(c), 16)))
                  for c in np.flatnonzero(rng.random(256) < seen_share)] + [agent]
    state = _state(agent, target, reference, seen_cells, reached)
    plan = jnp.asarray(rng.uniform(-1, 1, (16, 16, 3)), jnp.float32)
    want = _numpy_refuted(state, plan, has_reference)
    assert bool(plan_refuted(state, plan, has_reference)) == want
    heading = goal_estimate(state, plan)
    assert plan_refuted(state, plan, has_reference) | jnp.all(heading == sought_cell(
        state, has_reference)) | ~state.seen[tuple(heading)]


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
