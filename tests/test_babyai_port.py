"""envs/babyai's jax.numpy port against minigrid itself, step for step.

The slice here: sequences 0..PER_LEVEL-1 of each level of ``envs.babyai.check_port`` (random
actions of every kind, a quarter with a step limit inside the sequence), 1,002 sequences and
~30,000 steps in all, played once in minigrid (a module fixture) and compared with the port
under jit(vmap) on the observation image, reward, terminated and truncated at every step. The
full 10,000 sequences (~300,000 steps) run in ``python -m envs.babyai.check_port`` (minutes of
minigrid stepping; docs/DESIGN.md has its last counts). A control plants a defect in the port's
occlusion and in its reward and shows the comparison catches each. The BabyAI bot's episodes,
replayed action for action in the port, succeed there at the step and with the reward minigrid
gave. A hypothesis property: the agent's map equals the true grid on every cell it has seen.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from envs.babyai import check_port, view
from envs.babyai import env as port
from envs.babyai import episode as E
from envs.babyai import objects as O
from envs.babyai.config import LEVELS, make_config

PER_LEVEL = 334
BOT_EPISODES = {"goto_local": 40, "goto_obj_maze": 20, "goto": 20}


@pytest.fixture(scope="module")
def recorded():
    return {level: check_port.record(level, PER_LEVEL) for level in LEVELS}


@pytest.mark.parametrize("level", list(LEVELS))
def test_port_matches_minigrid_step_for_step(recorded, level):
    counts = check_port.compare(recorded[level])
    assert counts["sequences"] == PER_LEVEL and counts["steps"] >= PER_LEVEL * check_port.MIN_LEN
    assert counts["resets"] == counts["sequences"]
    for field in ("image", "reward", "terminated", "truncated", "all"):
        assert counts[field] == counts["steps"], (field, counts)
    # what the sequences exercised: successes, truncations, objects picked up, doors toggled
    assert counts["successes"] > 0 and counts["truncations"] > 0 and counts["pickup"] > 0
    assert counts["toggle"] > 0
    if level == "goto_local":
        assert counts["drop"] > 0


def test_control_a_planted_defect_is_caught(recorded, monkeypatch):
    """The comparison fails on a port that sees through walls, and on one whose reward is off
    by one step."""
    rec = recorded["goto_obj_maze"]
    n = 60
    small = check_port.Recorded(jax.tree.map(lambda x: x[:n], rec.episodes), rec.actions[:n],
                                rec.images[:n], rec.rewards[:n], rec.terminated[:n],
                                rec.truncated[:n], rec.length[:n])
    assert check_port.compare(small)["all"] == check_port.compare(small)["steps"]

    monkeypatch.setattr(view, "visibility", lambda contents: jnp.ones(contents.shape[:2], bool))
    check_port.play.clear_cache()
    counts = check_port.compare(small)
    assert counts["image"] < counts["steps"]
    monkeypatch.undo()

    true_step = port.step

    def late_reward(state, action):
        out = true_step(state, action)
        return out.replace(reward=jnp.where(out.terminated, out.reward + 0.9 / out.max_steps,
                                            out.reward))

    monkeypatch.setattr(port, "step", late_reward)
    check_port.play.clear_cache()
    counts = check_port.compare(small)
    assert counts["reward"] < counts["steps"] and counts["image"] == counts["steps"]
    monkeypatch.undo()
    check_port.play.clear_cache()


def _bot_episodes(level: str, n: int):
    """(episodes, actions int32 (n, T) padded with 'done', steps int32 (n,), rewards (n,)) of the
    BabyAI bot in minigrid, from the check's layouts."""
    from minigrid.utils.baby_ai_bot import BabyAIBot

    config = make_config(level)
    env = E.make_env(config)
    episodes, runs = [], []
    for i in range(n):
        episode, _ = E.layout(env, config, check_port.seeds.evaluation_seed(
            check_port.CHECK_SEED + 1, i))
        bot, actions = BabyAIBot(env), []
        terminated = truncated = False
        while not (terminated or truncated):
            action = bot.replan()
            _, reward, terminated, truncated, _ = env.step(action)
            actions.append(int(action))
        assert terminated and reward > 0, f"the bot failed {level} episode {i} in minigrid"
        episodes.append(episode)
        runs.append((actions, reward))
    length = max(len(a) for a, _ in runs)
    actions = np.full((n, length), O.DONE, np.int32)
    for i, (a, _) in enumerate(runs):
        actions[i, :len(a)] = a
    return (jax.tree.map(lambda *xs: np.stack(xs), *episodes), actions,
            np.array([len(a) for a, _ in runs]), np.array([r for _, r in runs]))


@functools.partial(jax.jit)
def _replay(episodes, actions):
    """(first step at which the port terminates, its reward) per episode (N,)."""

    def one(episode, acts):
        def body(s, a):
            s = port.step(s, a)
            return s, (s.terminated, s.reward)

        _, (term, reward) = jax.lax.scan(body, port.reset(episode), acts)
        first = jnp.argmax(term)
        return jnp.where(term.any(), first + 1, -1), reward[first]

    return jax.vmap(one)(episodes, actions)


@pytest.mark.parametrize("level", list(LEVELS))
def test_bot_episodes_succeed_in_the_port(level):
    episodes, actions, steps, rewards = _bot_episodes(level, BOT_EPISODES[level])
    port_steps, port_rewards = jax.device_get(_replay(episodes, actions))
    np.testing.assert_array_equal(port_steps, steps)
    np.testing.assert_allclose(port_rewards, rewards, atol=1e-6)


@pytest.fixture(scope="module")
def local_layouts():
    config = make_config("goto_local")
    return E.layouts(config, [check_port.seeds.evaluation_seed(check_port.CHECK_SEED + 2, i)
                              for i in range(16)])


@jax.jit
def _walk(episode, actions):
    def body(s, a):
        s = port.step(s, a)
        return s, None

    state, _ = jax.lax.scan(body, port.reset(episode), actions)
    return state


@settings(max_examples=25, deadline=None, database=None)
@given(index=st.integers(0, 15), actions=st.lists(st.integers(0, O.NUM_ACTIONS - 1),
                                                  min_size=30, max_size=30))
def test_the_agents_map_equals_the_grid_on_every_seen_cell(local_layouts, index, actions):
    """The agent's map is written from observations only, yet it is never stale: the only
    cells that change are the one in front of the agent (always in view after the action)."""
    episode = jax.tree.map(lambda x: x[index], local_layouts)
    state = jax.device_get(_walk(episode, jnp.asarray(actions, jnp.int32)))
    seen = state.known[..., 0] != O.UNSEEN
    assert seen[tuple(state.pos)] and seen.sum() >= 7
    np.testing.assert_array_equal(state.known[seen], state.grid[seen])
