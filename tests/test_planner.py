"""The planner (Algorithm 1) end to end with an oracle denoiser, psi, and the metrics' inputs.

The oracle "denoiser" knows the right plan from the observation alone (the target's cell when
the target is visible, else the reference's cell) and returns the exact epsilon of that point
mass, so DDIM in-paints exactly that plan. With it the planner must solve every episode: this
checks sampler + in-painting + psi + env + rollout bookkeeping together, without training.
"""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan.planner import PlannerConfig, rollout
from diffplan.schedule import cosine_schedule
from envs.gridworld import bfs, grammar
from envs.gridworld.config import make_config
from envs.gridworld.episode import generate_batch
from envs.gridworld.task import GridTask, NUM_COND_CHANNELS, psi

SCHEDULE = cosine_schedule(100)
VISITED_CHANNEL = 3  # condition channels: cell id, obstacle, agent, visited, visible
# Token positions of the slots in the canonical templates (see grammar.TEMPLATES).
P_MO2G_REF_POS, P_MO2G_TARGET_POS, MO1G_TARGET_POS = 5, 14, 3


def _oracle_plan(cells, visited, tokens, setting):
    """(H, W, 2) plan in [-1, 1]: goal at the reference until it was visited, then at the
    target (visible by then: it lies within the view radius of the reference)."""
    if setting == "p_mo2g":
        target_tok, ref_tok = tokens[P_MO2G_TARGET_POS], tokens[P_MO2G_REF_POS]
        reference = cells == ref_tok
        goal = jnp.where(jnp.any(reference & visited), cells == target_tok, reference)
    else:
        goal = cells == tokens[MO1G_TARGET_POS]
    goal = goal.astype(jnp.float32) * 2 - 1
    path = -jnp.ones_like(goal)
    return jnp.stack([path, goal], axis=-1)


def make_oracle_apply(setting):
    alphas_cumprod = SCHEDULE.alphas_cumprod

    def apply_fn(params, x_t, t, tokens):
        del params
        cells = jnp.round(x_t[..., 0]).astype(jnp.int32)
        visited = x_t[..., VISITED_CHANNEL] > 0.5
        x0 = jax.vmap(lambda c, v, tok: _oracle_plan(c, v, tok, setting))(cells, visited, tokens)
        ab = alphas_cumprod[t][:, None, None, None]
        return (x_t[..., NUM_COND_CHANNELS:] - jnp.sqrt(ab) * x0) / jnp.sqrt(1 - ab)

    return apply_fn


@pytest.fixture(scope="module")
def p_mo2g_episodes():
    return generate_batch(jax.random.PRNGKey(7), make_config("p_mo2g"), 12)


def _run(setting, episodes, mode, **kw):
    task = GridTask(make_config(setting))
    config = PlannerConfig(mode=mode, num_steps=2, warm_start_step=1, **kw)
    keys = jax.random.split(jax.random.PRNGKey(0), episodes.tokens.shape[0])
    run = jax.jit(lambda k, e: rollout(task, make_oracle_apply(setting), None, SCHEDULE, k, e,
                                       config))
    return run(keys, episodes)


@pytest.fixture(scope="module")
def on_the_fly_result(p_mo2g_episodes):
    return _run("p_mo2g", p_mo2g_episodes, "on_the_fly")


def test_oracle_on_the_fly_solves_p_mo2g_in_order(on_the_fly_result, p_mo2g_episodes):
    r = on_the_fly_result
    assert bool(jnp.all(r.final_state.success))
    assert bool(jnp.all(r.final_state.reached_reference))
    assert int(jnp.sum(r.final_state.collisions)) == 0
    # Going via the reference with the true geometry is exactly as long as the expert path.
    np.testing.assert_array_equal(np.asarray(r.steps), np.asarray(p_mo2g_episodes.expert_length))


def test_trajectories_are_4_connected_and_inside(on_the_fly_result):
    pos = np.asarray(on_the_fly_result.positions)
    assert pos.min() >= 0 and pos.max() < 16
    jumps = np.abs(np.diff(pos, axis=1)).sum(-1)
    assert set(np.unique(jumps)) <= {0, 1}
    steps = np.asarray(on_the_fly_result.steps)
    for i, s in enumerate(steps):
        assert np.all(jumps[i, :s] == 1), "the agent moved on every step before the end"
        assert np.all(pos[i, s:] == pos[i, s]), "positions after the end repeat the final cell"


def test_denoiser_calls_counted(on_the_fly_result):
    r = on_the_fly_result
    # One full plan (2 calls) before each move.
    np.testing.assert_array_equal(np.asarray(r.denoiser_calls), 2 * np.asarray(r.steps))
    np.testing.assert_array_equal(np.asarray(r.num_plans), np.asarray(r.steps))


def test_one_shot_plans_once_and_fails_on_unseen_targets(p_mo2g_episodes):
    r = _run("p_mo2g", p_mo2g_episodes, "one_shot")
    np.testing.assert_array_equal(np.asarray(r.num_plans), 1)
    # The first plan points at the reference, so one-shot hovers there (only a target right
    # next to the reference can be stumbled upon).
    success = np.asarray(r.final_state.success)
    assert success.mean() < 0.5
    assert bool(jnp.all(r.final_state.reached_reference))
    np.testing.assert_array_equal(np.asarray(r.steps)[~success], 100)


def test_k_shot_replans_at_the_goal_estimate(p_mo2g_episodes):
    r = _run("p_mo2g", p_mo2g_episodes, "k_shot", k=2)
    assert bool(jnp.all(r.final_state.success))
    np.testing.assert_array_equal(np.asarray(r.num_plans), 2)


def test_warm_start_costs_fewer_calls(p_mo2g_episodes, on_the_fly_result):
    r = _run("p_mo2g", p_mo2g_episodes, "warm_start")
    assert bool(jnp.all(r.final_state.success))
    # First plan 2 calls, each warm re-plan 1 call.
    np.testing.assert_array_equal(np.asarray(r.denoiser_calls), 2 + (np.asarray(r.steps) - 1))


def test_warm_schedule_of_its_own(p_mo2g_episodes):
    """warm_num_steps: warm start's first plan takes warm_num_steps calls (not num_steps), its
    re-plans warm_num_steps minus warm_start_step; the oracle planner still solves every
    episode."""
    task = GridTask(make_config("p_mo2g"))
    config = PlannerConfig(mode="warm_start", num_steps=5, warm_num_steps=3, warm_start_step=1)
    keys = jax.random.split(jax.random.PRNGKey(0), 12)
    r = jax.jit(lambda k, e: rollout(task, make_oracle_apply("p_mo2g"), None, SCHEDULE, k, e,
                                     config))(keys, p_mo2g_episodes)
    assert bool(jnp.all(r.final_state.success))
    np.testing.assert_array_equal(np.asarray(r.denoiser_calls),
                                  3 + 2 * (np.asarray(r.steps) - 1))


def test_results_do_not_depend_on_batch_composition(p_mo2g_episodes, on_the_fly_result):
    half = jax.tree.map(lambda x: x[6:], p_mo2g_episodes)
    task = GridTask(make_config("p_mo2g"))
    config = PlannerConfig(mode="on_the_fly", num_steps=2, warm_start_step=1)
    keys = jax.random.split(jax.random.PRNGKey(0), 12)[6:]
    r = jax.jit(lambda k, e: rollout(task, make_oracle_apply("p_mo2g"), None, SCHEDULE, k, e,
                                     config))(keys, half)
    np.testing.assert_array_equal(np.asarray(r.positions),
                                  np.asarray(on_the_fly_result.positions)[6:])


def test_psi_never_enters_a_known_obstacle():
    """psi with adversarial plans (random path maps, goal on or behind obstacles)."""
    config = make_config("mo1g", max_obstacles=10)
    task = GridTask(config)
    eps = generate_batch(jax.random.PRNGKey(3), config, 64)
    states = jax.vmap(task.reset)(eps)
    plans = jax.random.uniform(jax.random.PRNGKey(4), (64, 16, 16, 2), minval=-1, maxval=1)
    actions = jax.jit(jax.vmap(psi))(states, plans)
    nxt = np.asarray(states.agent) + np.asarray(bfs.MOVES)[np.asarray(actions)]
    grid = np.asarray(eps.grid)
    for i in range(64):
        r, c = nxt[i]
        if 0 <= r < 16 and 0 <= c < 16:
            assert grid[i, r, c] != -1
        else:
            # Off the grid only if every in-grid neighbour is a known obstacle.
            raise AssertionError(f"psi moved off the grid in episode {i}")


def test_psi_follows_plan_path_when_costs_tie():
    """With the goal straight ahead after a detour, psi prefers the plan's marked cells."""
    config = make_config("1o1g")
    eps = generate_batch(jax.random.PRNGKey(0), config, 1)
    state = jax.vmap(GridTask(config).reset)(eps)
    state = jax.tree.map(lambda x: x[0], state)
    state = state.replace(agent=jnp.array([5, 5], jnp.int32))
    goal = jnp.full((16, 16), -1.0).at[7, 7].set(1)
    # Two equally short routes; the plan marks the one going east first.
    path_east = jnp.full((16, 16), -1.0).at[5, 6].set(1).at[5, 7].set(1).at[6, 7].set(1)
    path_south = jnp.full((16, 16), -1.0).at[6, 5].set(1).at[7, 5].set(1).at[7, 6].set(1)
    assert int(psi(state, jnp.stack([path_east, goal], -1))) == 1  # east
    assert int(psi(state, jnp.stack([path_south, goal], -1))) == 2  # south


def test_path_end_cell_follows_the_connected_unvisited_path():
    """Without a goal channel the goal is the far end of the path connected to the agent: a
    stray path cell far away is ignored, and half way along, the visited half is excluded so
    the agent heads on rather than back."""
    from envs.gridworld.task import path_end_cell

    path = jnp.full((16, 16), -1.0)
    for c in range(3, 10):  # a path along row 4 from (4, 3) to (4, 9), then down to (6, 9)
        path = path.at[4, c].set(1)
    path = path.at[5, 9].set(1).at[6, 9].set(1).at[15, 0].set(1)  # + a stray cell
    plan = jnp.stack([path, jnp.full((16, 16), -1.0)], -1)
    start = jnp.array([4, 3], jnp.int32)
    np.testing.assert_array_equal(path_end_cell(plan, start), [6, 9])
    middle = jnp.array([4, 8], jnp.int32)
    # Plain "farthest along the path" from past the middle picks the start's end ((4, 3) is 5
    # moves away, (6, 9) 3); with the visited cells excluded it is (6, 9) ...
    np.testing.assert_array_equal(path_end_cell(plan, middle), [4, 3])
    visited = jnp.zeros((16, 16), bool).at[4, 3:9].set(True)
    np.testing.assert_array_equal(path_end_cell(plan, middle, visited), [6, 9])
    # ... and an agent off the path, or at its end, gets its own cell.
    np.testing.assert_array_equal(path_end_cell(plan, jnp.array([10, 10])), [10, 10])
    visited = visited.at[4, 9].set(True).at[5:7, 9].set(True)
    np.testing.assert_array_equal(path_end_cell(plan, jnp.array([6, 9]), visited), [6, 9])
    # psi of a goal-less task walks it: from the start, east.
    config = make_config("1o1g")
    eps = generate_batch(jax.random.PRNGKey(0), config, 1)
    state = jax.tree.map(lambda x: x[0], jax.vmap(GridTask(config).reset)(eps))
    state = state.replace(agent=start, grid=jnp.zeros_like(state.grid),
                          visited=jnp.zeros((16, 16), bool).at[4, 3].set(True))
    assert int(psi(state, plan, use_goal_channel=False)) == 1


def test_planner_config_validation():
    with pytest.raises(ValueError, match="mode"):
        PlannerConfig(mode="two_shot")
    with pytest.raises(ValueError, match="warm_start_step"):
        PlannerConfig(num_steps=4, warm_start_step=4)
    with pytest.raises(ValueError, match="warm_start_step"):
        PlannerConfig(num_steps=10, warm_num_steps=2, warm_start_step=2)
    with pytest.raises(ValueError, match="warm_num_steps"):
        PlannerConfig(num_steps=10, warm_num_steps=0, warm_start_step=0)
    config = PlannerConfig(num_steps=10, warm_num_steps=2, warm_start_step=1)
    assert (config.full_plan_calls, config.warm_plan_calls) == (10, 1)
    warm = dataclasses.replace(config, mode="warm_start")
    assert (warm.full_plan_calls, warm.warm_plan_calls) == (2, 1)


def test_oracle_template_positions_match_grammar():
    ids = grammar.compile_templates("p_mo2g")[0]
    assert ids[P_MO2G_REF_POS] == grammar.SLOT_REF
    assert ids[P_MO2G_TARGET_POS] == grammar.SLOT_TARGET
    assert grammar.compile_templates("mo1g")[0][MO1G_TARGET_POS] == grammar.SLOT_TARGET


@pytest.mark.parametrize("mode, fresh_noise", [("on_the_fly", True), ("warm_start", True),
                                               ("on_the_fly", False)])
def test_stream_rollout_matches_batched_rollout(p_mo2g_episodes, mode, fresh_noise):
    """The slot-refilling rollout gives every episode exactly what the batched one gives."""
    from diffplan.planner import rollout_stream

    task = GridTask(make_config("p_mo2g"))
    config = PlannerConfig(mode=mode, num_steps=2, warm_start_step=1, fresh_noise=fresh_noise)
    keys = jax.random.split(jax.random.PRNGKey(0), 12)
    apply_fn = make_oracle_apply("p_mo2g")
    batched = jax.jit(lambda k, e: rollout(task, apply_fn, None, SCHEDULE, k, e, config))(
        keys, p_mo2g_episodes)
    stream = jax.jit(lambda k, e: rollout_stream(task, apply_fn, None, SCHEDULE, k, e, config,
                                                 num_slots=5, num_fresh=2))(keys, p_mo2g_episodes)
    for name in ("positions", "steps", "done", "denoiser_calls", "num_plans", "first_plan"):
        np.testing.assert_array_equal(np.asarray(getattr(stream, name)),
                                      np.asarray(getattr(batched, name)), err_msg=name)
    np.testing.assert_array_equal(np.asarray(stream.final_state.success),
                                  np.asarray(batched.final_state.success))
    np.testing.assert_array_equal(np.asarray(stream.final_state.collisions),
                                  np.asarray(batched.final_state.collisions))


def test_stream_in_pieces_matches_one_stream(p_mo2g_episodes):
    """StreamRollout run a few moves per call gives exactly rollout_stream's result."""
    from diffplan.planner import StreamRollout, rollout_stream

    task = GridTask(make_config("p_mo2g"))
    config = PlannerConfig(mode="warm_start", num_steps=2, warm_start_step=1)
    keys = jax.random.split(jax.random.PRNGKey(1), 12)
    apply_fn = make_oracle_apply("p_mo2g")
    whole = jax.jit(lambda k, e: rollout_stream(task, apply_fn, None, SCHEDULE, k, e, config,
                                                num_slots=4))(keys, p_mo2g_episodes)
    stream = StreamRollout(task, apply_fn, SCHEDULE, config, num_slots=4)
    advance = jax.jit(lambda k, e, c: stream.advance(None, k, e, c, max_moves=3))
    carry = jax.jit(stream.start)(None, keys, p_mo2g_episodes)
    retired, calls = [], 0
    while not bool(carry.finished):
        carry = advance(keys, p_mo2g_episodes, carry)
        retired.append(int(carry.episodes_retired))
        calls += 1
    pieces = stream.result(carry)
    assert calls > 2 and retired == sorted(retired) and retired[-1] == 12
    for a, b in zip(jax.tree.leaves(pieces), jax.tree.leaves(whole)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="on_the_fly and warm_start"):
        StreamRollout(task, apply_fn, SCHEDULE, PlannerConfig(mode="one_shot"), num_slots=4)


@pytest.mark.parametrize("fresh_noise", [True, False])
def test_fresh_noise_controls_the_replan_noise(p_mo2g_episodes, fresh_noise):
    """A denoiser predicting eps = 0 turns the initial noise into the plan: with fresh_noise the
    plans of successive moves differ, without it every re-plan repeats the episode's plan."""
    task = GridTask(make_config("p_mo2g"))
    config = PlannerConfig(mode="on_the_fly", num_steps=2, warm_start_step=1, record_plans=True,
                           fresh_noise=fresh_noise)

    def zero_eps(params, x_t, t, tokens):
        return jnp.zeros(x_t.shape[:-1] + (task.num_gen_channels,), x_t.dtype)

    keys = jax.random.split(jax.random.PRNGKey(0), 12)
    out = jax.jit(lambda k, e: rollout(task, zero_eps, None, SCHEDULE, k, e, config))(
        keys, p_mo2g_episodes)
    plans = np.asarray(out.plans)
    steps = np.asarray(out.steps)
    multi = np.where(steps >= 2)[0]
    assert len(multi) > 0
    same = [np.array_equal(plans[i, 0], plans[i, 1]) for i in multi]
    assert all(same) if not fresh_noise else not any(same)


@pytest.mark.parametrize("chunk", [1, 5, 12])
def test_plan_subset_equals_full_batch_planning(p_mo2g_episodes, chunk):
    """k-shot re-plans only the episodes that need it, in sub-batches: the same plans as a
    full-batch plan where needed, the old plan elsewhere."""
    from diffplan.planner import _plan_subset, make_planner

    task = GridTask(make_config("p_mo2g"))
    config = PlannerConfig(mode="k_shot", num_steps=2, warm_start_step=1)

    def noisy_eps(params, x_t, t, tokens):  # depends on the noise, the condition and the words
        return jnp.tanh(x_t[..., NUM_COND_CHANNELS:] * 0.5 + x_t[..., :1] * 0.01
                        + tokens[:, :1, None, None] * 0.001)

    plan_fn = make_planner(task, noisy_eps, None, SCHEDULE, config)
    states = jax.vmap(task.reset)(p_mo2g_episodes)
    tokens = p_mo2g_episodes.tokens
    keys = jax.random.split(jax.random.PRNGKey(3), 12)
    old = jnp.zeros((12, 16, 16, 2)) - 0.5
    need = jnp.array([1, 0, 0, 1, 1, 0, 1, 0, 0, 0, 1, 1], bool)
    full = plan_fn(keys, states, tokens)
    got = jax.jit(lambda n: _plan_subset(plan_fn, n, keys, states, tokens, old, chunk))(need)
    expected = jnp.where(need[:, None, None, None], full, old)
    np.testing.assert_allclose(np.asarray(got), np.asarray(expected), atol=1e-6)
    none = jax.jit(lambda n: _plan_subset(plan_fn, n, keys, states, tokens, old, chunk))(
        jnp.zeros(12, bool))
    np.testing.assert_array_equal(np.asarray(none), np.asarray(old))
