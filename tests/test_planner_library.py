"""The planner as a library (DESIGN.md contract 5): load_denoiser, Planner.init / plan /
plan_batch under jit, vmap and a user's own lax.scan, whatever the network predicts, and the
README's example."""
import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffplan
from diffplan import LoadedDenoiser, Planner, PlannerConfig
from envs.gridworld.config import make_config
from envs.gridworld.episode import generate
from envs.gridworld.task import NUM_COND_CHANNELS, GridTask
from test_planner import SCHEDULE, as_denoiser, oracle_apply, oracle_planner

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHIPPED = os.path.join(ROOT, "checkpoints", "compile_gridworld")


def _user_loop(task, planner, n, seed):
    """What a user writes: generate episodes, then a hand-written lax.scan over moves with
    Planner.plan under jax.vmap (in k_shot mode with the world's re-plan trigger). Returns
    (episodes, planner keys, positions (n, T+1, 2), success (n,), moves (n,), plans (n,))."""
    k_shot = planner.config.mode == "k_shot"

    def run_episode(key):
        episode = generate(jax.random.fold_in(key, 0), task.config)
        state = task.reset(episode)
        ps = planner.init(jax.random.fold_in(key, 1), task.tokens(episode))

        def step(carry, _):
            state, ps = carry
            running = ~task.done(state)
            replan = (task.at_goal_estimate(state, ps.plan) & running) if k_shot else running
            plan, ps = planner.plan(ps, task.condition(state), replan=replan)
            state = task.step(state, task.psi(state, plan))
            return (state, ps), state.agent

        (state, ps), path = jax.lax.scan(step, (state, ps), None, length=task.max_steps)
        return (episode, jnp.concatenate([episode.agent[None], path]), state.success, state.t,
                ps.num_plans)

    keys = jax.random.split(jax.random.PRNGKey(seed), n)
    out = jax.jit(jax.vmap(run_episode))(keys)
    planner_keys = jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys)
    return (out[0], planner_keys) + tuple(out[1:])


@pytest.mark.parametrize("mode", ["on_the_fly", "warm_start", "k_shot"])
def test_hand_written_scan_gives_the_rollout_trajectories(mode):
    """A user's own vmapped lax.scan over Planner.plan gives exactly diffplan.rollout's
    trajectories (oracle network: every plan is exact, so the test is about bookkeeping)."""
    task = GridTask(make_config("p_mo2g"))
    planner = oracle_planner("p_mo2g", PlannerConfig(mode=mode, num_steps=2, warm_start_step=1))
    episodes, pkeys, positions, success, moves, num_plans = _user_loop(task, planner, 6, seed=5)
    ref = jax.jit(lambda p, k, e: diffplan.rollout(task, p, k, e))(planner, pkeys, episodes)
    np.testing.assert_array_equal(np.asarray(positions), np.asarray(ref.positions))
    np.testing.assert_array_equal(np.asarray(success), np.asarray(ref.final_state.success))
    np.testing.assert_array_equal(np.asarray(moves), np.asarray(ref.steps))
    np.testing.assert_array_equal(np.asarray(num_plans), np.asarray(ref.num_plans))
    assert bool(np.all(np.asarray(success)))
    if mode == "k_shot":
        np.testing.assert_array_equal(np.asarray(num_plans), 2)


def test_hand_written_scan_with_the_shipped_checkpoint():
    """The same equality with the shipped network (real floating-point plans)."""
    den = diffplan.load_denoiser(SHIPPED)
    task = GridTask(make_config("p_mo2g"), num_gen_channels=den.num_gen_channels)
    planner = Planner(den, PlannerConfig(mode="warm_start", warm_num_steps=3,
                                         warm_start_step=1))
    episodes, pkeys, positions, success, moves, _ = _user_loop(task, planner, 4, seed=11)
    ref = jax.jit(lambda p, k, e: diffplan.rollout(task, p, k, e))(planner, pkeys, episodes)
    np.testing.assert_array_equal(np.asarray(positions), np.asarray(ref.positions))
    np.testing.assert_array_equal(np.asarray(moves), np.asarray(ref.steps))


def test_plan_is_pure_and_counts_calls():
    """init / plan under jit: the same inputs give the same plan; calls and moves counted as
    the mode says (warm start: 3 calls first, then 2; one_shot: plans once)."""
    task = GridTask(make_config("mo1g"))
    episode = generate(jax.random.PRNGKey(1), task.config)
    condition = task.condition(task.reset(episode))
    for mode, expected_calls in (("warm_start", [3, 5, 7]), ("one_shot", [10, 10, 10]),
                                 ("on_the_fly", [10, 20, 30])):
        config = PlannerConfig(mode=mode, num_steps=10, warm_num_steps=3, warm_start_step=1)
        planner = oracle_planner("mo1g", config)
        plan = jax.jit(planner.plan)
        ps = planner.init(jax.random.PRNGKey(0), episode.tokens)
        calls = []
        for _ in range(3):
            out, nxt = plan(ps, condition)
            again, nxt_again = plan(ps, condition)  # pure: same inputs, same outputs
            np.testing.assert_array_equal(np.asarray(out), np.asarray(again))
            assert int(nxt.calls) == int(nxt_again.calls)
            ps = nxt
            calls.append(int(ps.calls))
        assert calls == expected_calls, (mode, calls)
        assert int(ps.move) == 3
        # The oracle's plan: the goal and sub-goal at the target.
        target = tuple(np.asarray(episode.target))
        assert np.unravel_index(np.argmax(np.asarray(out[..., 1])), (16, 16)) == target


def test_x0_and_eps_networks_plan_alike():
    """The same clean-plan predictor as an x0 network, or wrapped into the noise it implies
    (an eps network), gives the same plans: the sampler gets noise either way."""
    x0_net = oracle_apply("mo1g")

    def eps_net(params, x_t, t, tokens):
        x0 = x0_net(params, x_t, t, tokens)
        ab = SCHEDULE.alphas_cumprod[t][:, None, None, None]
        return (x_t[..., NUM_COND_CHANNELS:] - jnp.sqrt(ab) * x0) / jnp.sqrt(1 - ab)

    task = GridTask(make_config("mo1g"))
    episode = generate(jax.random.PRNGKey(2), task.config)
    condition = task.condition(task.reset(episode))
    config = PlannerConfig(num_steps=4)
    plans = []
    for den in (as_denoiser(x0_net, "x0"), as_denoiser(eps_net, "eps")):
        planner = Planner(den, config)
        plan, _ = jax.jit(planner.plan)(planner.init(jax.random.PRNGKey(0), episode.tokens),
                                        condition)
        plans.append(np.asarray(plan))
    np.testing.assert_allclose(plans[0], plans[1], atol=1e-4)
    # And the x0 network's plan is the oracle's (its eps is exact, so DDIM returns it).
    expected = np.asarray(x0_net(None, jnp.zeros((1, 16, 16, 8)).at[..., :5].set(condition[None]),
                                 jnp.zeros((1,), jnp.int32), episode.tokens[None]))[0]
    np.testing.assert_allclose(plans[0], expected, atol=1e-4)


def test_bad_inputs_are_refused():
    planner = oracle_planner("mo1g", PlannerConfig())
    with pytest.raises(ValueError, match="one episode"):
        planner.init(jax.random.PRNGKey(0), jnp.zeros((2, 24), jnp.int32))
    ps = planner.init(jax.random.PRNGKey(0), jnp.zeros((24,), jnp.int32))
    with pytest.raises(ValueError, match="condition must be"):
        planner.plan(ps, jnp.zeros((16, 16, 4)))
    with pytest.raises(ValueError, match="exceeds the denoiser's schedule"):
        Planner(planner.denoiser, PlannerConfig(num_steps=500))
    with pytest.raises(ValueError, match="PlannerConfig"):
        Planner(planner.denoiser, {"mode": "on_the_fly"})
    with pytest.raises(ValueError, match="prediction"):
        LoadedDenoiser(params=None, schedule=SCHEDULE, apply_fn=oracle_apply("mo1g"),
                       prediction="v")
    with pytest.raises(FileNotFoundError):
        diffplan.load_denoiser(os.path.join(ROOT, "no-such-checkpoint"))


def test_load_denoiser_reads_schedule_target_and_shape():
    den = diffplan.load_denoiser(SHIPPED)
    assert den.prediction == "x0"
    assert den.schedule.num_train_steps == 100
    assert den.plan_shape[:2] == (16, 16) and den.num_gen_channels in (2, 3)
    assert den.num_cond_channels == NUM_COND_CHANNELS
    # A pytree: its parameters are leaves (so one compilation serves every checkpoint).
    assert len(jax.tree.leaves(den)) > 10


def _readme_example() -> str:
    text = open(os.path.join(ROOT, "README.md")).read()
    section = text.split("## Use the planner in your own JAX code", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_readme_example_runs_anywhere_as_the_clis_warm_start_row(monkeypatch, capsys,
                                                                   tmp_path):
    """The README's example runs as written from a directory other than the repository's (the
    shipped checkpoint found by name beside the package), its agents succeed, and it plans as
    the CLIs' warm-start row: the same PlannerConfig (experiments.gridworld.spec), hence the
    same denoiser calls per episode as diffplan.rollout with that config on its episodes and
    keys (the row's re-planning trigger written out by hand)."""
    from diffplan.rollouts import rollout
    from experiments.gridworld.spec import SPECS

    monkeypatch.chdir(tmp_path)
    namespace = {}
    exec(compile(_readme_example(), "README example", "exec"), namespace)
    out = capsys.readouterr().out
    assert "success" in out
    assert float(np.mean(np.asarray(namespace["success"]))) >= 0.75
    config = SPECS["p_mo2g"].planner_config("warm_start")
    assert namespace["planner"].config == config
    task, generate, keys = namespace["task"], namespace["generate"], namespace["keys"]
    episodes = jax.vmap(lambda k: generate(jax.random.fold_in(k, 0)))(keys)
    planner_keys = jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys)
    cli_row = jax.jit(lambda p, k, e: rollout(task, p, k, e))(
        Planner(namespace["den"], config), planner_keys, episodes)
    np.testing.assert_array_equal(np.asarray(namespace["calls"]),
                                  np.asarray(cli_row.denoiser_calls))
    assert float(np.mean(np.asarray(namespace["calls"]))) < 20  # not PlannerConfig()'s ~32


def test_shipped_checkpoints_are_found_by_name_from_anywhere(monkeypatch, tmp_path):
    """load_denoiser resolves a shipped checkpoint's name, or checkpoints/<name>, beside the
    package from any working directory; a missing one is one line naming where it looked."""
    from diffplan.checkpoint import SHIPPED_ROOT, resolve_checkpoint

    monkeypatch.chdir(tmp_path)
    for name in ("compile_gridworld", "checkpoints/compile_gridworld"):
        assert resolve_checkpoint(name) == os.path.join(SHIPPED_ROOT, "compile_gridworld")
    assert resolve_checkpoint(SHIPPED) == SHIPPED
    with pytest.raises(FileNotFoundError) as e:
        diffplan.load_denoiser("checkpoints/no_such_model")
    message = str(e.value)
    assert len(message.splitlines()) == 1
    assert str(tmp_path / "checkpoints" / "no_such_model") in message
    assert os.path.join(SHIPPED_ROOT, "no_such_model") in message
