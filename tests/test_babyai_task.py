"""BabyAITask: the condition channels (the agent's map from its own observations, padded to the
UNet's multiple), psi on an oracle plan succeeding in minigrid itself (every action replayed
there), the re-planning predicates on hand-made plans, and bad input refused in one line."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs.babyai import episode as E
from envs.babyai import grammar, seeds
from envs.babyai import objects as O
from envs.babyai.config import make_config
from envs.babyai.task import (AGENT_CHANNEL, BLOCKED_CHANNEL, BabyAITask, GOAL, ID_CHANNEL,
                              NUM_KINDS, SEEN_CHANNEL, cell_kinds)

TASK_SEED = 11
"""Layouts: evaluation_seed(TASK_SEED, i), no seed any result is reported on."""


@pytest.fixture(scope="module")
def layouts():
    return {level: E.layouts(make_config(level),
                             [seeds.evaluation_seed(TASK_SEED, i) for i in range(n)])
            for level, n in (("goto_local", 16), ("goto", 8))}


def test_geometry_matches_minigrid(layouts):
    for level, (h, w, steps, hp) in {"goto_local": (8, 8, 64, 8), "goto_obj_maze": (22, 22, 576, 24),
                                     "goto": (22, 22, 576, 24)}.items():
        config = make_config(level)
        env = E.make_env(config)
        E.reset_quietly(env, 0)
        assert (env.height, env.width, env.max_steps) == (h, w, steps) == (
            config.height, config.width, config.max_steps)
        task = BabyAITask(config)
        assert task.height == task.width == hp and task.max_steps == steps


def test_cell_kinds_are_distinct_and_within_the_vocabulary():
    cells = [(O.UNSEEN, 0, 0), O.EMPTY_CELL, O.WALL_CELL]
    cells += [(O.DOOR, c, s) for c in range(6) for s in range(3)]
    cells += [(t, c, 0) for t in (O.KEY, O.BALL, O.BOX) for c in range(6)]
    kinds = np.asarray(cell_kinds(jnp.asarray(cells, jnp.uint8)))
    assert sorted(kinds) == list(range(NUM_KINDS))
    task = BabyAITask(make_config("goto_local"))
    assert task.vocab_size == grammar.VOCAB_SIZE + NUM_KINDS <= 64


def test_condition_is_the_agents_map_padded_with_walls(layouts):
    task = BabyAITask(make_config("goto"))
    eps = layouts["goto"]
    states = jax.vmap(task.reset)(eps)
    cond = jax.device_get(jax.vmap(task.condition)(states))
    states = jax.device_get(states)
    assert cond.shape == (8, 24, 24, 8) and cond.dtype == np.float32
    seen = states.known[..., 0] != O.UNSEEN
    np.testing.assert_array_equal(cond[:, :22, :22, SEEN_CHANNEL], seen)
    assert 0 < seen.sum(axis=(1, 2)).max() <= 49
    # unseen cells carry the unseen id whatever the true grid holds
    assert (cond[:, :22, :22, ID_CHANNEL][~seen] == task.cell_id_base).all()
    # the padding reads as known walls
    assert (cond[:, 22:, :, ID_CHANNEL] == task.cell_id_base + 2).all()
    assert (cond[:, :, 22:, BLOCKED_CHANNEL] == 1).all()
    for b in range(8):
        agent = np.argwhere(cond[b, ..., AGENT_CHANNEL] == 1)
        np.testing.assert_array_equal(agent, [states.pos[b]])


def _oracle_plan(task, state):
    """The plan an oracle denoiser would draw: the goal channel +1 on the instructed objects."""
    h, w = state.target.shape
    goal = jnp.pad(jnp.where(state.target, 1.0, -1.0),
                   ((0, task.height - h), (0, task.width - w)), constant_values=-1.0)
    return jnp.full((task.height, task.width, 3), -1.0).at[..., GOAL].set(goal)


@pytest.mark.parametrize("level", ["goto_local", "goto"])
def test_psi_on_an_oracle_plan_succeeds_in_minigrid(layouts, level):
    """psi's actions in the port, replayed in minigrid: every episode ends with minigrid's own
    reward > 0, at the step the port says."""
    task = BabyAITask(make_config(level))
    eps = layouts[level]

    def run(episode):
        def body(s, _):
            a = task.psi(s, _oracle_plan(task, s))
            return task.step(s, a), jnp.where(s.done, -1, a)

        s, actions = jax.lax.scan(body, task.reset(episode), None, length=task.max_steps)
        return s.terminated, s.step_count, actions

    done, steps, actions = jax.device_get(jax.jit(jax.vmap(run))(eps))
    assert done.all()
    env = E.make_env(make_config(level))
    for i in range(len(steps)):
        E.reset_quietly(env, seeds.evaluation_seed(TASK_SEED, i))
        for t in range(steps[i]):
            _, reward, terminated, _, _ = env.step(int(actions[i, t]))
            assert terminated == (t == steps[i] - 1)
        assert reward > 0
    if level == "goto":
        assert (actions == O.TOGGLE).any()      # doors were opened on the way


def test_refuted_and_at_goal_estimate_on_hand_made_plans(layouts):
    task = BabyAITask(make_config("goto_local"))
    episode = jax.tree.map(lambda x: x[0], layouts["goto_local"])
    state = task.reset(episode)
    known = np.asarray(state.known)
    pos = np.asarray(state.pos)

    def plan_on(cell):
        plan = -np.ones((8, 8, 3), np.float32)
        plan[cell[0], cell[1], GOAL] = 1.0
        return jnp.asarray(plan)

    empty = next(tuple(c) for c in np.argwhere(known[..., 0] == O.EMPTY) if tuple(c) != tuple(pos))
    unseen = tuple(np.argwhere(known[..., 0] == O.UNSEEN)[0])
    assert bool(task.plan_refuted(state, plan_on(empty)))         # a seen empty cell
    assert not bool(task.plan_refuted(state, plan_on(unseen)))    # may hold the object
    assert float(task.plan_cost(state, plan_on(empty))) >= 1e4
    assert float(task.plan_cost(state, plan_on(unseen))) < 1e4
    beside = tuple(pos + np.array([0, 1])) if pos[1] < 6 else tuple(pos - np.array([0, 1]))
    assert bool(task.at_goal_estimate(state, plan_on(beside))) == (
        known[beside][0] in (O.UNSEEN, O.KEY, O.BALL, O.BOX))


@pytest.mark.parametrize("call, needle", [
    (lambda: envs.make("babyai/nowhere"), "unknown world 'babyai/nowhere'"),
    (lambda: make_config("nowhere"), "unknown BabyAI level 'nowhere'"),
    (lambda: make_config("PutNext"), "not one the Task can plan"),
    (lambda: make_config("BabyAI-PutNextLocal-v0"), "not one the Task can plan"),
    (lambda: envs.make("babyai/goto", path_wieght=1.0), "path_wieght"),
    (lambda: grammar.parse("put the red ball next to the blue box"), "outside the GoTo grammar"),
    (lambda: grammar.parse("go to the red ball on your left"), "outside the GoTo grammar"),
    (lambda: make_config("goto").tokenize("go to the pink ball"), "outside the GoTo grammar"),
    (lambda: BabyAITask(make_config("goto"), num_gen_channels=2), "3 generated channels"),
])
def test_bad_input_is_refused_in_one_line(call, needle):
    with pytest.raises(ValueError, match=needle) as info:
        call()
    assert "\n" not in str(info.value)


def test_a_level_of_another_mission_is_refused_in_one_line():
    """A minigrid level whose mission is not GoTo, handed to the episode converter."""
    import gymnasium

    env = gymnasium.make("BabyAI-PutNextLocal-v0").unwrapped
    E.reset_quietly(env, 0)
    with pytest.raises(ValueError, match="not a GoTo mission") as info:
        E.from_env(env, make_config("goto_local"))
    assert "\n" not in str(info.value)


def test_a_pluggable_tokenizer_fills_the_episode_tokens():
    def ids(mission):
        out = np.zeros(10, np.int32)
        out[:len(mission.split())] = [101 + len(w) for w in mission.split()]
        return out

    task, generate = envs.make("babyai/goto_local", tokenizer=ids, max_tokens=10)
    episode = jax.jit(generate)(jax.random.PRNGKey(0))
    assert episode.tokens.shape == (10,) and int(episode.tokens[0]) == 103   # "go"
    with pytest.raises(ValueError, match="must return 8 integer ids"):
        make_config("goto_local", tokenizer=ids).tokenize("go to the red ball")


def test_the_batched_route_search_equals_the_per_map_one(layouts):
    """navigate.cost_to_go under vmap runs its relaxation with the batch laid out last (psi's
    speed on the 22 x 22 maps): the same fields, bit for bit, as one map at a time, including
    maps whose goal is unreachable and a batched start beside an unbatched enter."""
    from envs.babyai import navigate
    from envs.babyai.task import _route_field

    task = BabyAITask(make_config("goto"))
    states = jax.vmap(task.reset)(layouts["goto"])
    plans = jax.random.uniform(jax.random.PRNGKey(3), (8, 22, 22, 3), minval=-1, maxval=1)
    _, enter, _, stand, _ = jax.vmap(lambda s, p: _route_field(s, p, 1.0, 2.0))(states, plans)
    start = jnp.where(stand, 0.5, jnp.inf).at[0].set(jnp.inf)       # map 0: no goal at all
    batched = np.asarray(jax.jit(jax.vmap(navigate.cost_to_go))(enter, start))
    one = jax.jit(navigate.cost_to_go)
    for b in range(8):
        np.testing.assert_array_equal(batched[b], np.asarray(one(enter[b], start[b])))
    assert np.isinf(batched[0]).all() and np.isfinite(batched[1]).any()
    shared = np.asarray(jax.vmap(navigate.cost_to_go, in_axes=(None, 0))(enter[1], start))
    np.testing.assert_array_equal(shared[1], batched[1])


def _reachable_np(blocked, pos):
    """Plain-numpy oracle of task.reachable: breadth-first search from pos over cells not
    blocked; a blocked cell counts when a reached cell is beside it."""
    h, w = blocked.shape
    reached = np.zeros((h, w), bool)
    reached[tuple(pos)] = True
    frontier = [tuple(pos)]
    while frontier:
        r, c = frontier.pop()
        for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0)):
            rr, cc = r + dr, c + dc
            if 0 <= rr < h and 0 <= cc < w and not blocked[rr, cc] and not reached[rr, cc]:
                reached[rr, cc] = True
                frontier.append((rr, cc))
    beside = np.zeros((h, w), bool)
    for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        shifted = np.zeros((h, w), bool)
        shifted[max(dr, 0):h + min(dr, 0), max(dc, 0):w + min(dc, 0)] = \
            reached[max(-dr, 0):h + min(-dr, 0), max(-dc, 0):w + min(-dc, 0)]
        beside |= shifted
    return reached | beside


def test_reachable_equals_a_breadth_first_search_on_random_maps(layouts):
    from envs.babyai.task import known_blocked, reachable

    task_state = BabyAITask(make_config("goto")).reset(
        jax.tree.map(lambda x: x[0], layouts["goto"]))
    rng = np.random.default_rng(0)
    fn = jax.jit(reachable)
    for trial in range(12):
        kinds = rng.choice([O.UNSEEN, O.EMPTY, O.WALL, O.BALL], size=(22, 22),
                           p=[0.3, 0.3, 0.3, 0.1])
        known = np.zeros((22, 22, 3), np.uint8)
        known[..., 0] = kinds
        pos = rng.integers(0, 22, size=2)
        known[pos[0], pos[1]] = O.EMPTY_CELL
        state = task_state.replace(known=jnp.asarray(known), pos=jnp.asarray(pos, jnp.int32))
        blocked = np.asarray(known_blocked(jnp.asarray(known)))
        np.testing.assert_array_equal(np.asarray(fn(state)), _reachable_np(blocked, pos),
                                      err_msg=f"trial {trial}")


def test_psi_heads_for_the_best_cell_it_can_reach(layouts):
    """An unseen cell walled in on the agent's map can never be faced: the goal estimate skips
    it for the best reachable candidate, and falls back to it only when nothing is reachable
    (before, the agent turned on the spot until the episode ran out)."""
    from envs.babyai.task import goal_estimate

    task = BabyAITask(make_config("goto_local"))
    state = task.reset(jax.tree.map(lambda x: x[0], layouts["goto_local"]))
    known = np.zeros((8, 8, 3), np.uint8)
    known[...] = O.EMPTY_CELL
    known[0, :], known[-1, :], known[:, 0], known[:, -1] = (O.WALL_CELL,) * 4
    known[2, 2] = (O.UNSEEN, 0, 0)                       # walled in below
    known[1, 2] = known[3, 2] = known[2, 1] = known[2, 3] = O.WALL_CELL
    known[5, 5] = (O.BALL, 0, 0)
    state = state.replace(known=jnp.asarray(known), pos=jnp.asarray([6, 1], jnp.int32),
                          ruled_out=jnp.zeros((8, 8), bool))
    plan = -np.ones((8, 8, 3), np.float32)
    plan[2, 2, GOAL], plan[5, 5, GOAL] = 1.0, 0.5
    assert tuple(np.asarray(goal_estimate(state, jnp.asarray(plan)))) == (5, 5)
    walled = known.copy()
    walled[5, 5] = O.EMPTY_CELL                          # no reachable candidate left
    state = state.replace(known=jnp.asarray(walled))
    assert tuple(np.asarray(goal_estimate(state, jnp.asarray(plan)))) == (2, 2)


def test_new_information_ignores_faced_floor_but_not_a_ruled_out_object(layouts):
    task = BabyAITask(make_config("goto_local"))
    state = task.reset(jax.tree.map(lambda x: x[0], layouts["goto_local"]))
    empty = [tuple(c) for c in np.argwhere(np.asarray(state.known)[..., 0] == O.EMPTY)]
    floor, ball = empty[0], empty[1]
    state = state.replace(known=state.known.at[ball].set(jnp.asarray((O.BALL, 0, 0), jnp.uint8)))
    cond = task.condition(state)
    rule_out = lambda cell: task.condition(  # noqa: E731
        state.replace(ruled_out=state.ruled_out.at[cell].set(True)))
    assert not bool(task.new_information(cond, cond))
    assert not bool(task.new_information(cond, rule_out(floor)))
    assert bool(task.new_information(cond, rule_out(ball)))
    seen = task.condition(state.replace(known=state.known.at[floor].set(
        jnp.asarray(O.WALL_CELL, jnp.uint8))))
    assert bool(task.new_information(cond, seen))
