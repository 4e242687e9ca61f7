"""The exact-posterior denoiser (envs.gridworld.posterior): its candidates always hold the true
target, its draws are uniform over them, and planned like a trained denoiser it solves the
partially observed settings."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan import Planner, PlannerConfig, rollout
from envs.gridworld.config import make_config
from envs.gridworld.episode import generate_batch
from envs.gridworld.posterior import posterior_denoiser, posterior_plan, target_candidates
from envs.gridworld.task import GridTask


def _reset(setting, n, seed):
    config = make_config(setting)
    episodes = generate_batch(jax.random.PRNGKey(seed), config, n)
    task = GridTask(config)
    states = jax.vmap(task.reset)(episodes)
    return config, task, episodes, states, jax.vmap(task.condition)(states)


@pytest.mark.parametrize("setting", ["p_mo2g", "p_mo2g_far", "mo1g"])
@pytest.mark.parametrize("seed", [0, 1])
def test_the_candidates_hold_the_target(setting, seed):
    """At the start of every generated episode the target is a candidate (the support of the
    posterior is never wrong), and in P-MO2G-far it is unseen and one of several."""
    config, _, episodes, states, conditions = _reset(setting, 64, seed)
    cand = jax.vmap(lambda c, tok: target_candidates(
        config, jnp.round(c[..., 0]).astype(jnp.int32), c[..., 4] > 0.5, tok))(
            conditions, episodes.tokens)
    cand = np.asarray(cand)
    target = np.asarray(episodes.target)
    assert cand[np.arange(64), target[:, 0], target[:, 1]].all()
    if setting == "p_mo2g_far":
        assert (cand.sum((1, 2)) > 1).all()
        assert not np.asarray(states.seen)[np.arange(64), target[:, 0], target[:, 1]].any()


def test_draws_are_uniform_over_the_candidates():
    config, _, episodes, states, conditions = _reset("p_mo2g_far", 1, 3)
    condition, tokens = conditions[0], episodes.tokens[0]
    cand = np.asarray(target_candidates(config, jnp.round(condition[..., 0]).astype(jnp.int32),
                                        condition[..., 4] > 0.5, tokens))
    visited = states.visited[0].at[tuple(episodes.reference[0])].set(True)
    condition = condition.at[..., 3].set(visited.astype(jnp.float32))

    def draw(key):
        noise = jax.random.normal(key, condition.shape[:-1] + (3,))
        plan = posterior_plan(config, jnp.concatenate([condition, noise], -1), tokens)
        return plan[..., 2] > 0

    n = 4000
    picks = np.asarray(jax.jit(jax.vmap(draw))(jax.random.split(jax.random.PRNGKey(0), n)))
    assert (picks.sum((1, 2)) == 1).all() and not (picks & ~cand).any()
    counts = picks.sum(0)[cand]
    expected = n / cand.sum()
    assert counts.min() > 0.6 * expected and counts.max() < 1.4 * expected


def test_planned_with_on_refuted_it_solves_far_episodes():
    config, task, episodes, _, _ = _reset("p_mo2g_far", 16, 5)
    planner = Planner(posterior_denoiser(config),
                      PlannerConfig(num_steps=2, replan="on_refuted"))
    keys = jax.random.split(jax.random.PRNGKey(0), 16)
    out = jax.device_get(jax.jit(lambda p, k, e: rollout(task, p, k, e))(planner, keys, episodes))
    assert out.final_state.success.all() and out.final_state.reached_reference.all()
    assert (out.steps >= np.asarray(episodes.expert_length)).all()
