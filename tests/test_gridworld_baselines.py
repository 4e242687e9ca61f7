"""The baselines in the grid world (envs.gridworld.baselines): goal vectors, the shared policy
evaluation (an oracle and a hand-written loop), BC on a one-step problem, CQL's route reward and
buffer, the DD-style frames, and every baseline trained a few steps through
``experiments.train_baselines``, shipped, loaded and evaluated through
``experiments.baselines_eval.baseline_rows``. The algorithms on a toy world:
tests/test_baselines.py."""
from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from diffplan.baselines import bc, cql, dd, nets
from diffplan.baselines.rollout import policy_rollout
from envs.gridworld import baselines as gb
from envs.gridworld import bfs, env, grammar
from envs.gridworld.config import make_config
from envs.gridworld.task import GridTask
from experiments.gridworld.eval import eval_episodes, metrics_row


# ---------------------------------------------------------------------------- goal vector

def _check_goal_vector(config, episodes):
    goal = np.asarray(gb.goal_vector(episodes.tokens))
    n = gb.NUM_CLASSES
    assert goal.shape == (len(episodes.tokens), gb.GOAL_DIM)
    np.testing.assert_array_equal(goal[:, :n].argmax(-1), episodes.target_class - 1)
    np.testing.assert_array_equal(goal[:, :n].sum(-1), 1)
    if config.has_reference:
        np.testing.assert_array_equal(goal[:, n:2 * n].argmax(-1), episodes.reference_class - 1)
        np.testing.assert_array_equal(goal[:, 2 * n:].argmax(-1), episodes.direction)
        np.testing.assert_array_equal(goal[:, n:].sum(-1), 2)
    else:
        assert not goal[:, n:].any()


@pytest.mark.parametrize("setting", ["1o1g", "mo1g", "p_mo2g"])
def test_goal_vector_reads_the_instruction(setting, grid_configs, gen_batch):
    _check_goal_vector(grid_configs[setting], gen_batch(setting, 31)[0])


@pytest.mark.parametrize("language", ["paraphrased", "unseen"])
def test_goal_vector_reads_every_p_mo2g_phrasing(language):
    config = make_config("p_mo2g", language=language)
    episodes = eval_episodes(config, 48, seed=31)
    assert set(np.asarray(episodes.template).tolist()) == set(config.template_pool.tolist())
    _check_goal_vector(config, episodes)


def test_goal_vector_of_padding_is_zero():
    assert not np.asarray(gb.goal_vector(jnp.zeros((3, grammar.MAX_TOKENS), int))).any()


# ------------------------------------------------------------------ the shared evaluation

def _bfs_policy(params, conditions, tokens, keys):
    """An oracle of the observation: the first move of a shortest path over cells not seen
    as obstacles to the seen cell holding the instruction's target (fully observed worlds)."""
    del params, keys

    def one(cond, toks):
        target_token = jnp.argmax(gb.goal_vector(toks)[:gb.NUM_CLASSES]) + \
            grammar.OBJECT_TOKEN_OFFSET
        flat = jnp.argmax((cond[..., 0] == target_token).ravel())
        size = cond.shape[0]
        target = jnp.stack([flat // size, flat % size])
        agent_flat = jnp.argmax(cond[..., 2].ravel())
        agent = jnp.stack([agent_flat // size, agent_flat % size])
        passable = cond[..., 1] < 0.5
        return bfs.best_move(bfs.cost_to_go(passable, target), passable, agent)

    return jax.vmap(one)(conditions, tokens)


def _north_policy(params, conditions, tokens, keys):
    del params, tokens, keys
    return jnp.zeros(conditions.shape[0], jnp.int32)


@pytest.fixture(scope="module")
def mo1g_episodes():
    return eval_episodes(make_config("mo1g"), 32, seed=77)


def test_policy_rollout_of_an_oracle_succeeds_without_collisions(mo1g_episodes):
    task = GridTask(make_config("mo1g"))
    keys = jax.random.split(jax.random.PRNGKey(0), 32)
    out = jax.device_get(jax.jit(lambda k, e: policy_rollout(task, _bfs_policy, None, k, e))(
        keys, mo1g_episodes))
    row = metrics_row("oracle", out, mo1g_episodes, 0.0, False)
    assert row["SR"] == 100.0 and row["collisions_per_episode"] == 0.0
    np.testing.assert_array_equal(out.steps, mo1g_episodes.expert_length)  # shortest paths
    assert row["path_recall"] > 80.0


def test_policy_rollout_matches_a_hand_written_loop(mo1g_episodes):
    """Always north: the executed positions, steps and collisions equal env.step's, one
    episode at a time in Python."""
    config = make_config("mo1g")
    task = GridTask(config)
    keys = jax.random.split(jax.random.PRNGKey(1), 32)
    out = jax.device_get(jax.jit(lambda k, e: policy_rollout(task, _north_policy, None, k,
                                                             e))(keys, mo1g_episodes))
    step = jax.jit(lambda s: env.step(s, jnp.int32(0), config))
    for i in range(0, 32, 4):
        episode = jax.tree.map(lambda x: x[i], mo1g_episodes)
        state = env.reset(episode, config)
        cells = [np.asarray(state.agent)]
        while not bool(state.done):
            state = step(state)
            cells.append(np.asarray(state.agent))
        assert out.steps[i] == int(state.t) == len(cells) - 1
        np.testing.assert_array_equal(out.positions[i, :len(cells)], np.stack(cells))
        rest = out.positions[i, len(cells):]
        np.testing.assert_array_equal(rest, np.broadcast_to(cells[-1], rest.shape))
        assert out.final_state.collisions[i] == int(state.collisions)
        assert bool(out.final_state.success[i]) == bool(state.success)
    assert out.final_state.collisions.sum() > 0


# ----------------------------------------------------------------------- BC, one step

def _one_step_problems():
    """One object beside the agent, north, east, south or west of it (a different class each
    time), the instruction names it: the expert move is one step onto it."""
    size, centre = 16, 8
    conditions, tokens, moves = [], [], []
    for move, (d_row, d_col) in enumerate(np.asarray(bfs.MOVES)):
        for k in (1 + move, 5 + move):
            ids = np.full((size, size), grammar.EMPTY_ID, np.float32)
            ids[centre + d_row, centre + d_col] = grammar.class_to_token(k)
            agent = np.zeros((size, size), np.float32)
            agent[centre, centre] = 1
            conditions.append(np.stack([ids, np.zeros_like(ids), agent, agent,
                                        np.ones_like(ids)], -1))
            tokens.append(grammar.encode(f"Go to the {grammar.OBJECT_NAMES[k - 1]}."))
            moves.append(move)
    return jnp.asarray(np.stack(conditions)), jnp.asarray(np.stack(tokens)), \
        jnp.asarray(moves, jnp.int32)


def test_bc_learns_the_expert_move_of_a_one_step_problem():
    batch = _one_step_problems()
    conditions, tokens, moves = batch
    model = nets.GoalConvNet(nets.ConvNetConfig())
    optimizer = optax.adam(1e-3)
    state = nets.init_state(model, optimizer, 0, gb.input_shapes())
    goals = gb.goal_vector(tokens)
    step = jax.jit(bc.make_bc_step(model, optimizer, lambda key: (conditions, goals, moves)))
    first = None
    for i in range(60):
        state, metrics = step(state, jax.random.PRNGKey(i), None)
        first = float(metrics["loss"]) if first is None else first
    act = nets.greedy_act(model, gb.goal_vector)
    np.testing.assert_array_equal(act(state.params, conditions, tokens, None), moves)
    assert float(metrics["loss"]) < 0.05 * first


# ------------------------------------------------------------------ CQL in the grid

def test_route_reward_is_continuous_when_the_reference_is_reached():
    config = make_config("p_mo2g")
    episode = jax.tree.map(lambda x: x[0], eval_episodes(config, 1, seed=5))
    state = env.reset(episode, config)
    at_ref = state.replace(agent=episode.reference)
    before = gb.route_reward(at_ref, config)
    after = gb.route_reward(at_ref.replace(reached_reference=jnp.array(True)), config)
    assert float(before) == pytest.approx(float(after), abs=1e-6)
    assert float(gb.route_reward(state.replace(agent=episode.target), config)) < 0  # ref due


def test_cql_buffer_follows_the_behaviour_and_rewards():
    cfg = cql.CQLTrainConfig(buffer_size=2000, collectors=16, epsilon_frames=1000)
    buffer = jax.device_get(cql.collect_buffer(jax.random.PRNGKey(3),
                                               gb.collectors((("mo1g", 1),)), cfg))
    assert buffer["action"].shape == (2000,) and buffer["instruction"].dtype == np.int8
    # Late transitions follow the expert (epsilon 0.01): the agent moves unless it stands
    # on... never into a wall; their rewards are minus the distance left after the move.
    agent, nxt = buffer["obs"]["agent"].astype(int), buffer["next_obs"]["agent"].astype(int)
    moved = np.any(agent != nxt, -1)
    late = np.arange(2000) >= 1200
    assert moved[late].mean() > 0.97
    assert moved[:160].mean() < 0.95  # early frames are mostly random (epsilon near 1)
    assert np.all(buffer["reward"] <= 0)
    assert buffer["terminal"].any() and np.all(buffer["reward"][buffer["terminal"]] == 0)
    # What the Q-network reads of a stored transition is what the agent sees.
    conditions, goals = gb.q_inputs(jax.tree.map(lambda x: x[:3], buffer["obs"]),
                                    buffer["instruction"][:3])
    assert conditions.shape == (3, 16, 16, 5) and goals.shape == (3, gb.GOAL_DIM)
    np.testing.assert_array_equal(np.argwhere(np.asarray(conditions)[..., 2] > 0.5)[:, 1:],
                                  agent[:3])


# ------------------------------------------------------------------------ DD-style frames

def test_dd_training_frames_are_the_frames_the_policy_acts_on():
    """Frame 0 of a training trajectory is frame() of the condition the agent sees in that
    state; later frames move the agent marker along the expert path; agent_plan marks the
    cells the marker visits."""
    config = make_config("p_mo2g")
    key = jax.random.PRNGKey(4)
    traj, tokens, move = jax.jit(gb.trajectory_example, static_argnums=(1, 2))(key, config, 6)
    episode, state, index, move_again = jax.jit(gb.expert_example, static_argnums=1)(key,
                                                                                    config)
    condition = jax.jit(GridTask(config).condition)(state)
    np.testing.assert_array_equal(traj[:, 0], jax.jit(gb.frame)(condition))
    assert int(move) == int(move_again)
    np.testing.assert_array_equal(tokens, episode.tokens)
    path = np.asarray(episode.expert_positions)[
        np.minimum(int(index) + np.arange(6), int(episode.expert_length))]
    for j, (r, c) in enumerate(path):
        assert np.asarray(traj)[r * 16 + c, j] == gb.AGENT_VALUE
        assert (np.asarray(traj)[:, j] == gb.AGENT_VALUE).sum() == 1
    plan = np.asarray(gb.agent_plan(traj, condition))[..., 0] > 0
    on_path = np.zeros((16, 16), bool)
    on_path[tuple(path.T)] = True
    assert plan[on_path].all()
    # Off the path only cells whose value sits at the threshold (the last object class: 0.5,
    # above it by a rounding under jit) are marked.
    np.testing.assert_allclose(np.asarray(traj)[:, 0].reshape(16, 16)[plan & ~on_path], 0.5,
                               atol=1e-6)


# ----------------------------------------------------- every baseline, end to end (tiny)

TINY_MIXTURE = (("1o1g", 1), ("p_mo2g", 1))
TINY_DD = dd.DDConfig(horizon=8, widths=(8, 16), embed_dim=16, groups=4)


@pytest.fixture(scope="module")
def tiny_ship(tmp_path_factory):
    """Each baseline trained a few steps with tiny settings, through train_baselines, and
    shipped; returns (run_dir, ship_dir)."""
    from experiments.shipping import train_baselines as tb

    root = tmp_path_factory.mktemp("baselines")
    run_dir, ship_dir = str(root / "runs"), str(root / "ship")
    bc_cfg = bc.BCTrainConfig(steps=4, batch_size=4, checkpoint_every=2, log_every=2)
    cql_cfg = cql.CQLTrainConfig(steps=4, batch_size=8, buffer_size=256, collectors=8,
                                 checkpoint_every=2, log_every=2)
    dd_cfg = dd.DDTrainConfig(steps=4, batch_size=2, checkpoint_every=2, log_every=2,
                              id_steps=4, id_batch_size=4)
    tb.train_all(tb.NAMES, run_dir, bc_cfg, cql_cfg, dd_cfg, progress=False,
                 mixture=TINY_MIXTURE, dd_model=TINY_DD)
    tb.ship(tb.NAMES, run_dir, ship_dir, results=[], command="pytest", remarks=["tiny"])
    return run_dir, ship_dir, bc_cfg


def test_tiny_baselines_evaluate_through_baseline_rows(tiny_ship):
    from experiments.gridworld.baselines import baseline_rows

    _, ship_dir, _ = tiny_ship
    rows = baseline_rows("p_mo2g", (7, 8), 4, 4, False, checkpoint_root=ship_dir,
                         dd_num_steps=2)
    assert [r["method"] for r in rows] == ["BC", "CQL", "DD-style"]
    for row in rows:
        assert "SR_ordered" in row and "SR_ci95" in row
        assert set(row["per_seed"]) == {"7", "8"}
        per_seed = [row["per_seed"][seed]["SR"] for seed in ("7", "8")]
        assert all(v in (0.0, 25.0, 50.0, 75.0, 100.0) for v in per_seed)  # 4 episodes each
        assert row["SR"] == pytest.approx(sum(per_seed) / 2)  # pooled over equal seeds
    assert "plan_f1" not in rows[0] and "plan_f1" in rows[2]
    assert rows[0]["denoiser_calls_per_episode"] == 0.0
    assert rows[2]["denoiser_calls_per_episode"] == pytest.approx(2 * rows[2]["mean_steps"])
    for name in ("bc", "cql", "dd"):
        assert "tiny" in open(os.path.join(ship_dir, name, "NOTE.md")).read()


def test_per_setting_models_are_trained_shipped_and_picked_per_setting(tmp_path):
    """--per-setting: one BC per setting of the mixture, each on its setting's examples only,
    shipped under bc/<setting>/ (replacing the one model shipped before) and picked by the
    setting's rows; a setting without a model of its own is refused by name."""
    from diffplan.checkpoint import read_metadata
    from experiments.gridworld import baselines as be
    from experiments.shipping import train_baselines as tb

    run_dir, ship_dir = str(tmp_path / "runs"), str(tmp_path / "ship")
    cfg = bc.BCTrainConfig(steps=2, batch_size=4, checkpoint_every=2, log_every=1)
    tb.train_all(("bc",), run_dir, cfg, None, None, progress=False, mixture=TINY_MIXTURE)
    tb.ship(("bc",), run_dir, ship_dir, results=[], command="pytest")
    assert be.policy_directory(ship_dir, "bc", "mo1g") == os.path.join(ship_dir, "bc")
    per_run = str(tmp_path / "per")
    tb.train_all(("bc",), per_run, cfg, None, None, progress=False, mixture=TINY_MIXTURE,
                 per_setting=True)
    for setting, _ in TINY_MIXTURE:
        meta = read_metadata(os.path.join(per_run, "bc", setting))
        assert meta["train_config"]["mixture"] == [[setting, 1]]
    tb.ship(("bc",), per_run, ship_dir, results=[], command="pytest")
    note = open(os.path.join(ship_dir, "bc", "NOTE.md")).read()
    assert "one model per setting" in note and "1o1g:" in note and "p_mo2g:" in note
    for setting in ("1o1g", "p_mo2g"):
        assert be.policy_directory(ship_dir, "bc", setting) == \
            os.path.join(ship_dir, "bc", setting)
    with pytest.raises(FileNotFoundError, match="bc checkpoint for mo1g"):
        be.policy_directory(ship_dir, "bc", "mo1g")  # the one model was replaced
    rows = be.baseline_rows("1o1g", (7,), 4, 4, False, checkpoint_root=ship_dir,
                            methods=("bc",))
    assert [r["method"] for r in rows] == ["BC"]
    with pytest.raises(SystemExit):
        be.main(["--settings", "mo1g", "--methods", "bc", "--checkpoint-root", ship_dir,
                 "--episodes", "2", "--no-progress"])


def test_baseline_rows_with_one_seed_and_the_executed_success(tiny_ship):
    from diffplan.baselines.policies import load_policy
    from experiments.gridworld.policy_eval import evaluate_policy

    _, ship_dir, _ = tiny_ship
    policy = load_policy("bc", os.path.join(ship_dir, "bc"), gb.POLICY_WORLD)
    task = GridTask(make_config("1o1g"))
    episodes = eval_episodes(task.config, 6, seed=9)
    out, _ = evaluate_policy(policy, task, episodes, 9, batch_size=4, progress=False)
    final = out.positions[np.arange(6), out.steps]
    np.testing.assert_array_equal(np.all(final == episodes.target, -1), out.final_state.success)
    again, _ = evaluate_policy(policy, task, episodes, 9, batch_size=6, progress=False)
    np.testing.assert_array_equal(out.positions, again.positions)  # batching changes nothing


def test_a_killed_run_resumes_to_the_same_params(tiny_ship, tmp_path):
    """The run of the fixture wrote steps 2 and 4; delete step 4, resume, compare."""
    import shutil

    run_dir, _, bc_cfg = tiny_ship
    copy = str(tmp_path / "bc")
    shutil.copytree(os.path.join(run_dir, "bc"), copy)
    shutil.rmtree(os.path.join(copy, "4"))
    resumed = gb.train_bc(copy, bc_cfg, mixture=TINY_MIXTURE, progress=False)
    assert int(resumed.state.step) == 4
    from diffplan.checkpoint import load_checkpoint
    original, _ = load_checkpoint(os.path.join(run_dir, "bc"))
    jax.tree.map(np.testing.assert_array_equal, original["train_state"]["params"],
                 jax.device_get(resumed.state.params))


def test_resume_with_other_settings_is_refused(tiny_ship):
    import dataclasses

    from diffplan.train import ConfigMismatchError

    run_dir, _, bc_cfg = tiny_ship
    with pytest.raises(ConfigMismatchError):
        gb.train_bc(os.path.join(run_dir, "bc"), dataclasses.replace(bc_cfg, lr=0.5),
                    mixture=TINY_MIXTURE, progress=False)
    with pytest.raises(ConfigMismatchError, match="mixture"):  # other training data
        gb.train_bc(os.path.join(run_dir, "bc"), bc_cfg, mixture=(("1o1g", 2),),
                    progress=False)


def test_train_baselines_cli_refuses_bad_arguments(capsys):
    from experiments.shipping import train_baselines as tb

    for argv in (["--baselines", "bc,xyz"], ["--bc-steps", "0"], ["--remark", "hi"],
                 ["--ship", "--results", "missing.json"], ["--seed", "-1"],
                 ["--ship-dir", "elsewhere"], ["--no-train"], ["--dd-change-weight", "-1"],
                 ["--world", "kuka", "--per-setting"]):
        with pytest.raises(SystemExit) as e:
            tb.main(argv)
        assert e.value.code == 2
    err = capsys.readouterr().err
    assert "only make sense with --ship" in err and "cannot be read" in err
    assert "--seed must be >= 0" in err and "does nothing" in err
    assert "--dd-change-weight must be >= 0" in err and "--per-setting is the grid" in err


def test_train_baselines_dd_change_weight_defaults_to_the_worlds():
    from envs.kuka.baselines import DD_CHANGE_WEIGHT
    from experiments.shipping import train_baselines as tb

    def weight(argv):
        return tb.configs(tb.build_parser().parse_args(argv))[2].change_weight

    assert weight([]) == 50.0 and weight(["--world", "kuka"]) == DD_CHANGE_WEIGHT == 0.0
    assert weight(["--world", "kuka", "--dd-change-weight", "3"]) == 3.0
