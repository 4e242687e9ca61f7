"""envs/babyai/training.py: the layout cache (training seeds only, written once, read back
equal; a planted cache of evaluation seeds is refused), the expert's cached actions succeed in
minigrid itself, and the examples: condition channels are the Task's for the replayed state,
the labels a route from the agent's cell to a stand cell beside an object the mission names,
and psi following the labelled plan completes the episode in the port."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.babyai import env as port
from envs.babyai import episode as E
from envs.babyai import seeds, training
from envs.babyai.config import make_config
from envs.babyai.task import BabyAITask, GOAL, NUM_COND_CHANNELS, PATH, SUBGOAL

COUNT = {"goto_local": 12, "goto": 6}


@pytest.fixture(scope="module")
def caches(tmp_path_factory):
    root = tmp_path_factory.mktemp("babyai_cache")
    return root, {level: training.cached_layouts(level, n, cache_dir=root)
                  for level, n in COUNT.items()}


def test_the_cache_is_written_once_and_read_back(caches):
    root, layouts = caches
    for level, n in COUNT.items():
        path = root / f"{level}_0_{n}.npz"
        assert path.exists()
        again = training.cached_layouts(level, n, cache_dir=root)
        np.testing.assert_array_equal(again.seeds, [seeds.training_seed(j) for j in range(n)])
        np.testing.assert_array_equal(again.episodes.grid, layouts[level].episodes.grid)
        np.testing.assert_array_equal(again.actions, layouts[level].actions)
        assert list(again.missions) == list(layouts[level].missions)


def test_training_layouts_never_use_an_evaluation_seed(caches):
    for layouts in caches[1].values():
        training.check_training_seeds(layouts)


def test_control_a_cache_of_evaluation_seeds_is_refused(caches):
    planted = caches[1]["goto_local"]
    planted = training.Layouts(planted.level, planted.episodes,
                               np.array([seeds.evaluation_seed(2001, i)
                                         for i in range(len(planted))]), planted.missions,
                               planted.actions, planted.lengths)
    with pytest.raises(ValueError, match="evaluation seeds"):
        training.check_training_seeds(planted)


def test_the_cached_expert_succeeds_in_minigrid(caches):
    for level, layouts in caches[1].items():
        env = E.make_env(make_config(level))
        for i in range(len(layouts)):
            E.reset_quietly(env, layouts.seeds[i])
            for t in range(layouts.lengths[i]):
                _, reward, terminated, truncated, _ = env.step(int(layouts.actions[i, t]))
            assert terminated and reward > 0, (level, i)


@pytest.mark.parametrize("level", list(COUNT))
def test_examples_are_labelled_by_the_route_to_the_named_object(caches, level):
    layouts = caches[1][level]
    task = BabyAITask(make_config(level))
    h, w = task.config.height, task.config.width
    x0, tokens, mask = jax.device_get(jax.jit(training.make_batch_fn(task, layouts),
                                              static_argnums=1)(jax.random.PRNGKey(1), 16))
    assert x0.shape == (16, task.height, task.width, NUM_COND_CHANNELS + 3)
    gen = x0[..., NUM_COND_CHANNELS:]
    assert set(np.unique(gen)) <= {-1.0, 1.0}
    assert (gen[:, h:] == -1).all() and (gen[:, :, w:] == -1).all()   # padding
    assert (mask[:, h:] == 0).all() and (mask[:, :h, :w] > 0).any()
    used = mask.reshape(16, -1).max(-1) > 0
    assert used.mean() >= 0.75
    for b in np.flatnonzero(used):
        path, goal, sub = (gen[b, :h, :w, c] > 0 for c in (PATH, GOAL, SUBGOAL))
        agent = np.argwhere(x0[b, :h, :w, 4] > 0)[0]
        assert goal.sum() == 1 and sub.sum() == 1
        assert path[tuple(agent)] and path[sub].all()
        (gr, gc), (sr, sc) = np.argwhere(goal)[0], np.argwhere(sub)[0]
        assert abs(gr - sr) + abs(gc - sc) == 1
        # the goal is an object of the mission's description (the episode's own fields)
        idx = np.flatnonzero((layouts.episodes.tokens == tokens[b]).all(-1))
        kinds = {(int(layouts.episodes.target_type[i]), int(layouts.episodes.target_color[i]))
                 for i in idx}
        cell = layouts.episodes.grid[idx[0], gr, gc]
        assert (int(cell[0]), int(cell[1])) in kinds
        # the route is connected: every path cell but the ends has a path neighbour on each side
        assert _connected(path, tuple(agent))


def _connected(mask, start):
    seen, stack = {start}, [start]
    while stack:
        r, c = stack.pop()
        for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0)):
            n = (r + dr, c + dc)
            if 0 <= n[0] < mask.shape[0] and 0 <= n[1] < mask.shape[1] and mask[n] and n not in seen:
                seen.add(n)
                stack.append(n)
    return len(seen) == mask.sum()


def test_psi_on_the_labelled_plan_completes_the_episode(caches):
    """From each layout's start, psi on the labelled plan of the current state (re-labelled
    every step, as an oracle denoiser would plan) reaches the object: the labels are a plan
    psi can follow."""
    layouts = caches[1]["goto_local"]
    task = BabyAITask(make_config("goto_local"))
    from envs.babyai import expert

    def run(episode):
        def body(s, _):
            path, goal, sub, _ = expert.expert_plan(s)
            plan = jnp.stack([jnp.where(m, 1.0, -1.0) for m in (path, goal, sub)], -1)
            return task.step(s, task.psi(s, plan)), None

        s, _ = jax.lax.scan(body, task.reset(episode), None, length=task.max_steps)
        return s.terminated, s.step_count

    done, steps = jax.device_get(jax.jit(jax.vmap(run))(layouts.episodes))
    assert done.all()
    # psi weighs turns only at the next cell, so it may take a longer turn than the expert
    assert (steps <= layouts.lengths + 4).all() and steps.sum() <= 1.5 * layouts.lengths.sum()
