"""The planner (Algorithm 1) end to end with an oracle denoiser, psi, and the metrics' inputs.

The oracle "denoiser" knows the right plan from the observation alone (the target's cell when
the target is visible, else the reference's cell) and returns the exact epsilon of that point
mass, so DDIM in-paints exactly that plan. With it the planner must solve every episode: this
checks sampler + in-painting + psi + env + rollout bookkeeping together, without training.
"""
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan import LoadedDenoiser, Planner, PlannerConfig, rollout
from diffplan.schedule import cosine_schedule
from envs.gridworld import bfs, grammar
from envs.gridworld.config import make_config
from envs.gridworld.episode import generate_batch
from envs.gridworld.task import GridTask, NUM_COND_CHANNELS, psi

SCHEDULE = cosine_schedule(100)
VISITED_CHANNEL = 3  # condition channels: cell id, obstacle, agent, visited, visible
# Token positions of the slots in the canonical templates (see grammar.TEMPLATES).
P_MO2G_REF_POS, P_MO2G_TARGET_POS, MO1G_TARGET_POS = 5, 14, 3


def _oracle_plan(cells, visited, tokens, setting, num_gen_channels=3):
    """(H, W, G) plan in [-1, 1]: the sub-goal at the reference until it was visited, then at
    the target (visible by then: it lies within the view radius of the reference); the goal
    at the target once visible (before: at the reference). G = 2: the goal alone, at the
    sub-goal's cell."""
    if setting == "p_mo2g":
        target_tok, ref_tok = tokens[P_MO2G_TARGET_POS], tokens[P_MO2G_REF_POS]
        reference, target = cells == ref_tok, cells == target_tok
        subgoal = jnp.where(jnp.any(reference & visited), target, reference)
        goal = jnp.where(jnp.any(target), target, reference)
    else:
        subgoal = goal = cells == tokens[MO1G_TARGET_POS]
    signed = lambda m: m.astype(jnp.float32) * 2 - 1  # noqa: E731
    path = -jnp.ones(cells.shape, jnp.float32)
    if num_gen_channels == 2:
        return jnp.stack([path, signed(subgoal)], axis=-1)
    return jnp.stack([path, signed(goal), signed(subgoal)], axis=-1)


@functools.lru_cache(maxsize=None)
def oracle_apply(setting, num_gen_channels=3):
    """An "x0 network" that knows the right plan from the observation alone."""

    def apply_fn(params, x_t, t, tokens):
        del params, t
        cells = jnp.round(x_t[..., 0]).astype(jnp.int32)
        visited = x_t[..., VISITED_CHANNEL] > 0.5
        return jax.vmap(lambda c, v, tok: _oracle_plan(c, v, tok, setting, num_gen_channels))(
            cells, visited, tokens)

    return apply_fn


def as_denoiser(apply_fn, prediction="eps", num_gen_channels=3):
    """A LoadedDenoiser around a parameter-free network (params None)."""
    return LoadedDenoiser(params=None, schedule=SCHEDULE, apply_fn=apply_fn,
                          prediction=prediction, plan_shape=(16, 16, num_gen_channels),
                          num_cond_channels=NUM_COND_CHANNELS)


def oracle_planner(setting, config, num_gen_channels=3):
    return Planner(as_denoiser(oracle_apply(setting, num_gen_channels), "x0",
                               num_gen_channels), config)


@pytest.fixture(scope="module")
def p_mo2g_episodes():
    return generate_batch(jax.random.PRNGKey(7), make_config("p_mo2g"), 12)


def _run(setting, episodes, mode, **kw):
    task = GridTask(make_config(setting))
    config = PlannerConfig(mode=mode, num_steps=2, warm_start_step=1, warm_num_steps=None, **kw)
    keys = jax.random.split(jax.random.PRNGKey(0), episodes.tokens.shape[0])
    run = jax.jit(lambda p, k, e: rollout(task, p, k, e))
    return run(oracle_planner(setting, config), keys, episodes)


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
    r = jax.jit(lambda p, k, e: rollout(task, p, k, e))(oracle_planner("p_mo2g", config), keys,
                                                         p_mo2g_episodes)
    assert bool(jnp.all(r.final_state.success))
    np.testing.assert_array_equal(np.asarray(r.denoiser_calls),
                                  3 + 2 * (np.asarray(r.steps) - 1))


def test_results_do_not_depend_on_batch_composition(p_mo2g_episodes, on_the_fly_result):
    half = jax.tree.map(lambda x: x[6:], p_mo2g_episodes)
    task = GridTask(make_config("p_mo2g"))
    config = PlannerConfig(mode="on_the_fly", num_steps=2, warm_start_step=1)
    keys = jax.random.split(jax.random.PRNGKey(0), 12)[6:]
    r = jax.jit(lambda p, k, e: rollout(task, p, k, e))(oracle_planner("p_mo2g", config), keys,
                                                         half)
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
    from diffplan import rollout_stream

    task = GridTask(make_config("p_mo2g"))
    config = PlannerConfig(mode=mode, num_steps=2, warm_start_step=1, fresh_noise=fresh_noise)
    planner = oracle_planner("p_mo2g", config)
    keys = jax.random.split(jax.random.PRNGKey(0), 12)
    batched = jax.jit(lambda p, k, e: rollout(task, p, k, e))(planner, keys, p_mo2g_episodes)
    stream = jax.jit(lambda p, k, e: rollout_stream(task, p, k, e, num_slots=5, num_fresh=2))(
        planner, keys, p_mo2g_episodes)
    for name in ("positions", "steps", "done", "denoiser_calls", "num_plans", "first_plan"):
        np.testing.assert_array_equal(np.asarray(getattr(stream, name)),
                                      np.asarray(getattr(batched, name)), err_msg=name)
    np.testing.assert_array_equal(np.asarray(stream.final_state.success),
                                  np.asarray(batched.final_state.success))
    np.testing.assert_array_equal(np.asarray(stream.final_state.collisions),
                                  np.asarray(batched.final_state.collisions))


def test_stream_in_pieces_matches_one_stream(p_mo2g_episodes):
    """StreamRollout run a few moves per call gives exactly rollout_stream's result."""
    from diffplan import StreamRollout, rollout_stream

    task = GridTask(make_config("p_mo2g"))
    config = PlannerConfig(mode="warm_start", num_steps=2, warm_start_step=1)
    planner = oracle_planner("p_mo2g", config)
    keys = jax.random.split(jax.random.PRNGKey(1), 12)
    whole = jax.jit(lambda p, k, e: rollout_stream(task, p, k, e, num_slots=4))(
        planner, keys, p_mo2g_episodes)
    stream = StreamRollout(task, config, num_slots=4)
    advance = jax.jit(lambda p, k, e, c: stream.advance(p, k, e, c, max_moves=3))
    carry = jax.jit(stream.start)(planner, keys, p_mo2g_episodes)
    retired, calls = [], 0
    while not bool(carry.finished):
        carry = advance(planner, keys, p_mo2g_episodes, carry)
        retired.append(int(carry.episodes_retired))
        calls += 1
    pieces = stream.result(carry)
    assert calls > 2 and retired == sorted(retired) and retired[-1] == 12
    for a, b in zip(jax.tree.leaves(pieces), jax.tree.leaves(whole)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="on_the_fly and warm_start"):
        StreamRollout(task, PlannerConfig(mode="one_shot"), num_slots=4)


def _zero_eps(params, x_t, t, tokens):
    """An eps network predicting zero noise: the initial noise becomes the plan."""
    return jnp.zeros(x_t.shape[:-1] + (3,), x_t.dtype)


@pytest.mark.parametrize("fresh_noise", [True, False])
def test_fresh_noise_controls_the_replan_noise(p_mo2g_episodes, fresh_noise):
    """A denoiser predicting eps = 0 turns the initial noise into the plan: with fresh_noise the
    plans of successive moves differ, without it every re-plan repeats the episode's plan."""
    task = GridTask(make_config("p_mo2g"))
    config = PlannerConfig(mode="on_the_fly", num_steps=2, warm_start_step=1, record_plans=True,
                           fresh_noise=fresh_noise)
    keys = jax.random.split(jax.random.PRNGKey(0), 12)
    out = jax.jit(lambda p, k, e: rollout(task, p, k, e))(
        Planner(as_denoiser(_zero_eps), config), keys, p_mo2g_episodes)
    plans = np.asarray(out.plans)
    steps = np.asarray(out.steps)
    multi = np.where(steps >= 2)[0]
    assert len(multi) > 0
    same = [np.array_equal(plans[i, 0], plans[i, 1]) for i in multi]
    assert all(same) if not fresh_noise else not any(same)


def _noisy_eps(params, x_t, t, tokens):
    """Depends on the noise, the condition and the words (and not on other batch rows)."""
    return jnp.tanh(x_t[..., NUM_COND_CHANNELS:] * 0.5 + x_t[..., :1] * 0.01
                    + tokens[:, :1, None, None] * 0.001)


@pytest.mark.parametrize("mode", ["k_shot", "warm_start"])
@pytest.mark.parametrize("chunk", [1, 5, 12])
def test_plan_batch_equals_vmapped_plan(p_mo2g_episodes, mode, chunk):
    """plan_batch plans only the episodes that need it, in sub-batches: exactly the plans and
    states of jax.vmap(plan), and inactive episodes are left untouched."""
    task = GridTask(make_config("p_mo2g"))
    planner = Planner(as_denoiser(_noisy_eps),
                      PlannerConfig(mode=mode, num_steps=2, warm_start_step=1))
    conditions = jax.vmap(task.condition)(jax.vmap(task.reset)(p_mo2g_episodes))
    keys = jax.random.split(jax.random.PRNGKey(3), 12)
    ps = jax.vmap(planner.init)(keys, p_mo2g_episodes.tokens)
    # A first plan for half of them, so that the second call mixes first plans and re-plans.
    half = jnp.arange(12) % 2 == 0
    _, ps = planner.plan_batch(ps, conditions, active=half)
    replan = jnp.array([1, 0, 0, 1, 1, 0, 1, 0, 0, 0, 1, 1], bool)
    active = jnp.arange(12) != 5
    got_plans, got = jax.jit(lambda s, c, a, r: planner.plan_batch(s, c, a, r, chunk=chunk))(
        ps, conditions, active, replan)
    want_plans, want = jax.jit(jax.vmap(planner.plan))(ps, conditions, replan)
    want_plans = jnp.where(active[:, None, None, None], want_plans, ps.plan)
    want = jax.tree.map(lambda w, o: jnp.where(active.reshape((-1,) + (1,) * (w.ndim - 1)), w,
                                               o), want, ps)
    np.testing.assert_allclose(np.asarray(got_plans), np.asarray(want_plans), atol=1e-6)
    for name in ("move", "calls", "num_plans"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)),
                                      np.asarray(getattr(want, name)), err_msg=name)
    assert int(got.move[5]) == int(ps.move[5])  # inactive: no move counted


def _open_state(agent, visited_cells=()):
    """A 1O1G state on an empty grid with the agent at `agent`, seeing everything."""
    config = make_config("1o1g")
    eps = generate_batch(jax.random.PRNGKey(0), config, 1)
    state = jax.tree.map(lambda x: x[0], jax.vmap(GridTask(config).reset)(eps))
    visited = jnp.zeros((16, 16), bool).at[tuple(agent)].set(True)
    for cell in visited_cells:
        visited = visited.at[cell].set(True)
    return state.replace(agent=jnp.array(agent, jnp.int32), grid=jnp.zeros_like(state.grid),
                         seen=jnp.ones((16, 16), bool), visited=visited)


def _point_plan(goal, subgoal, second=None):
    """(16, 16, 3) plan: no path, goal and sub-goal at the given cells; `second` a weaker
    sub-goal candidate."""
    g = jnp.full((16, 16), -1.0).at[goal].set(1.0)
    s = jnp.full((16, 16), -1.0).at[subgoal].set(1.0)
    if second is not None:
        s = s.at[second].set(0.5)
    return jnp.stack([jnp.full((16, 16), -1.0), g, s], -1)


def _walk(plan, start, moves):
    """Cells visited by following psi for `moves` moves on an empty grid from `start`."""
    cells, visited = [tuple(start)], []
    for _ in range(moves):
        state = _open_state(cells[-1], visited)
        visited.append(cells[-1])
        step = np.asarray(bfs.MOVES)[int(psi(state, plan))]
        cells.append(tuple(np.asarray(cells[-1]) + step))
    return cells


def test_psi_heads_for_the_subgoal_and_steps_around_the_goal():
    """Hand-computed: on an empty grid from (5, 5) the agent heads for the sub-goal (5, 9); with
    the goal estimate at (5, 7) on the straight line, it walks a shortest detour around it
    (6 moves) instead of ending the episode there; with the sub-goal on the goal estimate it
    walks straight there (2 moves)."""
    from envs.gridworld.task import goal_estimate

    plan = _point_plan(goal=(5, 7), subgoal=(5, 9))
    np.testing.assert_array_equal(goal_estimate(_open_state((5, 5)), plan), [5, 9])
    cells = _walk(plan, (5, 5), 6)
    assert cells[-1] == (5, 9) and (5, 7) not in cells
    assert _walk(_point_plan(goal=(5, 7), subgoal=(5, 7)), (5, 5), 2) == [(5, 5), (5, 6), (5, 7)]


def test_subgoal_skips_visited_cells_and_reaching_it_triggers_a_replan():
    """The sub-goal psi heads for is the channel's argmax among unvisited cells: standing on
    the reference, the agent heads for the next candidate (the target), and k-shot's trigger
    (at_goal_estimate) fires there."""
    from envs.gridworld.task import goal_estimate

    task = GridTask(make_config("1o1g"))
    plan = _point_plan(goal=(9, 9), subgoal=(5, 5), second=(9, 9))
    on_ref = _open_state((5, 5), [(4, 5)])
    np.testing.assert_array_equal(goal_estimate(on_ref, plan), [9, 9])
    assert bool(task.at_goal_estimate(on_ref, plan))
    assert not bool(task.at_goal_estimate(_open_state((4, 5)), plan))
    # A model with 2 generated channels (no sub-goal) heads for its goal channel.
    two = jnp.stack([plan[..., 0], plan[..., 1]], -1)
    np.testing.assert_array_equal(goal_estimate(_open_state((5, 5)), two), [9, 9])


def test_a_pool_without_progress_has_no_host_callback_and_the_same_results(p_mo2g_episodes):
    """harness.rollout_fn(progress=False): the slot pool's program calls nothing on the host (so
    JAX's persistent compilation cache can keep it) and gives the progress program's rollout
    bit for bit; the progress program's callback reaches the relay's bar."""
    from experiments.harness.core import rollout_fn
    from experiments.harness.progress import PARTS, RELAY

    task = GridTask(make_config("p_mo2g"))
    config = PlannerConfig(mode="warm_start", num_steps=2, warm_start_step=1)
    planner = oracle_planner("p_mo2g", config)
    keys = jax.random.split(jax.random.PRNGKey(2), 12)

    class Bar:
        n = 0

        def update(self, k):
            self.n += k

    outs, texts, bar = [], [], Bar()
    for progress in (True, False):
        run = rollout_fn(task, 4, progress=progress)
        args = (planner, keys, p_mo2g_episodes)
        texts.append(run.lower(*args, jnp.int32(0)).as_text())
        token = RELAY.attach(bar)
        try:
            outs.append(jax.block_until_ready(run(*args, jnp.int32(token * PARTS))))
        finally:
            RELAY.detach(token)
    assert "callback" in texts[0] and "callback" not in texts[1]
    assert bar.n == 12  # only the progress program reported (12 episodes retired)
    for a, b in zip(jax.tree.leaves(outs[0]), jax.tree.leaves(outs[1])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
