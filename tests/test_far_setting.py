"""The p_mo2g_far setting (envs.gridworld.config): its generated episodes checked against a
plain-numpy oracle (Chebyshev distances, views as squares, deque BFS, compass sectors as
angles, the direction word read back from the tokens with grammar.parse), its configuration,
determinism, and that its training episodes are not its evaluation episodes.

The general invariants of every setting (expert path, instruction text, classes) are
test_gridworld_episode.check_episode's; the registry, the CLI and the training path cover the
setting in test_registry.py, test_compile_experiments.py and test_training_disjoint.py."""
from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_gridworld_bfs import oracle_bfs
from test_gridworld_episode import check_episode

import envs
from envs.gridworld import grammar, training
from envs.gridworld.config import GridConfig, make_config
from envs.gridworld.episode import fingerprints

SETTING = "p_mo2g_far"
VIEW, NEAR, FAR, MAX_OBSTACLES = 3, 4, 9, 20
"""The issue's numbers, written out (not read from the config under test)."""
COMPASS_DEGREES = {"east": 0, "northeast": 45, "north": 90, "northwest": 135, "west": 180,
                   "southwest": 225, "south": 270, "southeast": 315}
"""The oracle's own compass: each word's centre angle, counter-clockwise from east, north up;
its sector is the 45 degrees around it."""


def chebyshev(a, b) -> int:
    return max(abs(int(a[0]) - int(b[0])), abs(int(a[1]) - int(b[1])))


def in_sector(src, dst, word: str) -> bool:
    """dst lies within 22.5 degrees of the compass word's direction seen from src (row 0 north;
    an integer offset never lies on a sector's edge: tan(22.5) is irrational)."""
    degrees = math.degrees(math.atan2(-(int(dst[0]) - int(src[0])), int(dst[1]) - int(src[1])))
    off = (degrees - COMPASS_DEGREES[word] + 180.0) % 360.0 - 180.0
    return abs(off) < 22.5


@pytest.fixture(scope="module")
def parse_batch():
    """jit(vmap(grammar.parse)): tokens int (N, L) -> (matched, ref, target, dir) tokens."""
    return jax.jit(jax.vmap(grammar.parse))


def check_far_episode(ep, i: int, visible0, parsed):
    """The issue's properties of episode i (numpy arrays), by plain numpy; parsed: numpy
    (matched, ref, target, dir) tokens of the batch (grammar.parse)."""
    grid = ep.grid[i]
    agent, target, reference = (tuple(int(v) for v in a[i]) for a in
                                (ep.agent, ep.target, ep.reference))
    msg = f"episode {i}: agent {agent} reference {reference} target {target}"
    assert NEAR <= chebyshev(reference, target) <= FAR, msg
    # Visible at t=0: the reference, not the target; the target is outside the reference's view
    # too (the squares are computed here, not by env.field_of_view).
    assert 1 <= chebyshev(agent, reference) <= VIEW and visible0[i][reference], msg
    assert chebyshev(agent, target) > VIEW and not visible0[i][target], msg
    rows, cols = np.indices(grid.shape)
    ref_view = (abs(rows - reference[0]) <= VIEW) & (abs(cols - reference[1]) <= VIEW)
    assert not ref_view[target], msg
    # The instruction, read back from its tokens: the reference, the target and a direction
    # word whose sector holds the target.
    matched, ref_tok, target_tok, dir_tok = (p[i] for p in parsed)
    assert matched, msg
    assert grammar.VOCAB[ref_tok] == grammar.OBJECT_NAMES[grid[reference] - 1], msg
    assert grammar.VOCAB[target_tok] == grammar.OBJECT_NAMES[grid[target] - 1], msg
    assert in_sector(reference, target, grammar.VOCAB[dir_tok]), msg
    # Up to 20 obstacles; every object (distractors too) reachable from the agent.
    assert (grid == -1).sum() <= MAX_OBSTACLES, msg
    from_agent = oracle_bfs(grid != -1, agent)
    assert (from_agent[grid > 0] >= 0).all(), f"{msg}: an object is walled off"


def test_the_issues_configuration():
    config = make_config(SETTING)
    assert (config.size, config.view_radius, config.max_obstacles, config.max_steps) == \
        (16, VIEW, MAX_OBSTACLES, 100)
    assert config.view_radius + 1 == NEAR and config.ref_target_radius == FAR
    assert config.has_reference and config.target_beyond_reference_view
    assert config.all_objects_reachable
    assert grammar.TEMPLATES[SETTING] is grammar.TEMPLATES["p_mo2g"]  # same sentences
    assert SETTING not in dict(training.TRAINING_MIXTURE)  # training is decided later
    assert make_config(SETTING, max_steps=24).max_steps == 24
    with pytest.raises(ValueError, match="2 \\* view_radius"):
        GridConfig(setting=SETTING)  # the class defaults are p_mo2g's: view 6


@pytest.mark.parametrize("overrides, message", [
    (dict(view_radius=4), "2 \\* view_radius"),  # 8 > 8 fails: a reference could lack a target
    (dict(ref_target_radius=6), "2 \\* view_radius"),
    (dict(ref_target_radius=3), "2 \\* view_radius"),
    (dict(view_radius=None), "finite view_radius"),
    (dict(view_radius=0), "view_radius >= 1"),  # no reference could be seen at t=0
    (dict(min_objects=1), "min_objects >= 2"),
    (dict(max_steps=23), "max_steps"),  # the longest expert path: 2 * 3 + 2 * 9 = 24
])
def test_bad_far_configs_are_refused(overrides, message):
    with pytest.raises(ValueError, match=message):
        make_config(SETTING, **overrides)


@settings(max_examples=6, deadline=None, database=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_generated_episodes_have_the_issues_properties(gen_batch, grid_configs, parse_batch,
                                                       seed):
    eps, visible0 = gen_batch(SETTING, seed)
    parsed = [np.asarray(p) for p in parse_batch(eps.tokens)]
    for i in range(len(eps.agent)):
        check_episode(grid_configs[SETTING], eps, i, visible0)
        check_far_episode(eps, i, visible0, parsed)


def test_the_draws_cover_their_ranges(gen_batch):
    """Over 1024 episodes: every distance 4..9 and every direction occurs, the obstacle count
    is uniform-like over 0..20 (both ends occur, mean ~10), the reference lies 1, 2 and 3
    cells from the agent, and in some episodes a distractor lies in the target's ring and
    sector too (the class, not the place, tells the target)."""
    batches = [gen_batch(SETTING, seed)[0] for seed in range(16)]
    eps = jax.tree.map(lambda *xs: np.concatenate(xs), *batches)
    far = np.abs(eps.target - eps.reference).max(-1)
    near = np.abs(eps.agent - eps.reference).max(-1)
    obstacles = (eps.grid == -1).sum((1, 2))
    assert set(far.tolist()) == set(range(NEAR, FAR + 1))
    assert set(near.tolist()) == {1, 2, 3}
    assert set(eps.direction.tolist()) == set(range(8))
    assert obstacles.min() == 0 and obstacles.max() == MAX_OBSTACLES
    assert 8.5 < obstacles.mean() < 11.5
    rivals = 0
    for i in range(len(eps.agent)):
        word = grammar.DIRECTIONS[eps.direction[i]]
        rivals += any(NEAR <= chebyshev(eps.reference[i], cell) <= FAR
                      and in_sector(eps.reference[i], cell, word)
                      for cell in zip(*np.nonzero(eps.grid[i] > 0))
                      if cell != tuple(eps.target[i]))
    assert rivals > 0.05 * len(eps.agent)


def test_evaluation_episodes_are_the_registrys_and_deterministic():
    """Evaluation episode i of seed S is the registry's generate(fold_in(PRNGKey(S), i)) (the
    CLI's, export's and sweep's convention), the same on every call."""
    from experiments.gridworld import eval as ge

    _, generate = envs.make(f"gridworld/{SETTING}")
    first = ge.eval_episodes(make_config(SETTING), 8, 1000)
    again = ge.eval_episodes(make_config(SETTING), 8, 1000)
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(1000), i))(np.arange(8))
    direct = jax.vmap(generate)(keys)
    assert fingerprints(first) == fingerprints(again) == fingerprints(direct)
    other = ge.eval_episodes(make_config(SETTING), 8, 1001)
    assert not set(fingerprints(other)) & set(fingerprints(first))


def test_training_examples_of_the_setting():
    """The setting makes training examples as p_mo2g does (it is just not in the mixture): the
    goal channel on the target, the sub-goal on the reference until it was stood on."""
    from envs.gridworld.task import GOAL_CHANNEL, SUBGOAL_CHANNEL

    config = make_config(SETTING, language="mixed")
    batch = jax.jit(training.make_batch_fn(config, detour_prob=0.5), static_argnums=1)(
        jax.random.PRNGKey(3), 16)
    keys = training.training_episode_keys(jax.random.PRNGKey(3), 16)
    episodes = jax.vmap(lambda k: training.generate(
        jax.random.split(k, training.EXAMPLE_KEYS)[0], config))(keys)
    x0, idx = np.asarray(batch.x0), np.arange(16)
    assert x0.shape == (16, 16, 16, 8) and np.isfinite(x0).all()
    np.testing.assert_array_equal(np.asarray(batch.tokens), np.asarray(episodes.tokens))
    goal = x0[..., GOAL_CHANNEL] > 0
    assert (goal.sum((1, 2)) == 1).all()
    assert goal[idx, episodes.target[:, 0], episodes.target[:, 1]].all()
    subgoal = x0[..., SUBGOAL_CHANNEL] > 0
    at_ref = subgoal[idx, episodes.reference[:, 0], episodes.reference[:, 1]]
    at_target = subgoal[idx, episodes.target[:, 0], episodes.target[:, 1]]
    assert (at_ref ^ at_target).all() and at_ref.any()
    # The state on the reference along the expert path: reached, the target outside its view.
    ep = jax.tree.map(lambda x: x[0], episodes)
    on_ref = int(np.flatnonzero((np.asarray(ep.expert_positions) == ep.reference).all(-1))[0])
    state = training.state_along_expert(ep, config, np.int32(on_ref))
    assert bool(state.reached_reference) and tuple(state.agent) == tuple(ep.reference)
    assert chebyshev(state.agent, ep.target) > VIEW


FAR_MIXTURE = training.TRAINING_MIXTURE + ((SETTING, 36),)
"""A run that would train on the setting beside the paper's three (100 examples a batch)."""


def test_training_episodes_are_not_evaluation_episodes():
    """The episodes such a run would draw in 500 steps (18,000) share no world with the 1000
    episodes of the validation and evaluation seeds; they are far episodes (not vacuous)."""
    from experiments.gridworld import eval as ge

    train = training.training_episodes(SETTING, seed=0, steps=500, batch_size=100,
                                       mixture=FAR_MIXTURE, chunk=250)
    assert len(train.agent) == 500 * 36
    assert (np.abs(train.target - train.reference).max(-1) >= NEAR).all()
    seen = set(fingerprints(train, instruction=False))
    assert len(seen) == len(train.agent)  # not one world drawn twice
    for seed in (1000, 2001, 2002, 2003):
        episodes = ge.eval_episodes(make_config(SETTING), 1000, seed)
        assert not set(fingerprints(episodes, instruction=False)) & seen
