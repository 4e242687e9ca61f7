"""The registry (contract 6): every registered world and setting runs the planner-task protocol
reset -> condition -> psi -> step under jit(vmap), and bad names and overrides are refused."""
from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

import envs
from diffplan.task import Task

BATCH = 2


@functools.lru_cache(maxsize=None)
def _protocol(task):
    """jit(vmap(episode, key -> one move of the protocol)), compiled once per distinct task
    (the two Kuka names share one KukaTask, so one compilation)."""

    def run(episode, key):
        state = task.reset(episode)
        condition = task.condition(state)
        tokens = task.tokens(episode)
        plan = jax.random.uniform(key, (task.height, task.width, task.num_gen_channels),
                                  minval=-1.0, maxval=1.0)
        after = task.step(state, task.psi(state, plan))
        return (condition, tokens, task.position(state), task.position(after),
                task.done(after), task.new_information(condition, task.condition(after)))

    return jax.jit(jax.vmap(run))


def _one_move(name):
    task, generate = envs.make(name)
    keys = jax.random.split(jax.random.PRNGKey(7), BATCH)
    episodes = jax.jit(jax.vmap(generate))(keys)
    plan_keys = jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys)
    return task, jax.device_get(_protocol(task)(episodes, plan_keys))


@pytest.mark.parametrize("name", envs.names())
def test_every_registered_world_runs_the_protocol_under_jit_vmap(name):
    task, (condition, tokens, before, after, done, new_info) = _one_move(name)
    assert isinstance(task, Task)
    assert condition.shape == (BATCH, task.height, task.width, task.num_cond_channels)
    assert condition.dtype == np.float32 and np.isfinite(condition).all()
    assert tokens.ndim == 2 and tokens.shape[0] == BATCH and tokens.dtype == np.int32
    assert (tokens > 0).any(axis=1).all()  # every episode has an instruction
    for cells in (before, after):
        assert cells.shape == (BATCH, 2)
        assert ((cells >= 0) & (cells < np.array([task.height, task.width]))).all()
    assert done.shape == (BATCH,) and done.dtype == bool
    assert new_info.shape == (BATCH,)


def test_names_cover_both_worlds():
    assert {"gridworld/1o1g", "gridworld/mo1g", "gridworld/p_mo2g", "gridworld/p_mo2g_far",
            "kuka/stacking", "kuka/rearrangement"} <= set(envs.names())


def test_overrides_reach_the_config_and_the_task():
    task, generate = envs.make("gridworld/mo1g", max_obstacles=0, path_weight=0.0)
    assert task.config.max_obstacles == 0 and task.path_weight == 0.0
    episode = jax.jit(generate)(jax.random.PRNGKey(0))
    assert not (np.asarray(episode.grid) == -1).any()
    task, generate = envs.make("kuka/rearrangement", multi=True, follow_path=False)
    assert not task.follow_path and generate.keywords["spec"].multi


@pytest.mark.parametrize("name, overrides, needle", [
    ("gridworld/nowhere", {}, "unknown world 'gridworld/nowhere'"),
    ("gridworld/p_mo2g", {"view_radious": 3}, "view_radious"),
    ("kuka/stacking", {"colour": "red"}, "colour"),
    ("gridworld/p_mo2g", {"view_radius": 20}, "view_radius"),
])
def test_bad_names_and_overrides_are_refused_by_name(name, overrides, needle):
    with pytest.raises(ValueError, match=needle):
        envs.make(name, **overrides)


def test_register_adds_a_world_and_protects_the_built_ins():
    calls = []

    def factory(**overrides):
        calls.append(overrides)
        return envs.make("gridworld/1o1g", **overrides)

    envs.register("test/copy_of_1o1g", factory)
    try:
        assert "test/copy_of_1o1g" in envs.names()
        task, _ = envs.make("test/copy_of_1o1g", max_steps=40)
        assert calls == [{"max_steps": 40}] and task.max_steps == 40
    finally:
        envs._USER.pop("test/copy_of_1o1g")
    with pytest.raises(ValueError, match="built-in"):
        envs.register("gridworld/p_mo2g", factory)
    with pytest.raises(ValueError, match="world/setting"):
        envs.register("nameless", factory)
