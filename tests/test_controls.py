"""The language controls (envs.gridworld.controls): the reference named as a visible
distractor, the direction reversed; only the instruction's word changes, and the metric reads
who the agent stood on first."""
from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

from envs.gridworld import controls, env, grammar
from envs.gridworld.config import make_config
from envs.gridworld.episode import generate_batch

N = 32


@pytest.fixture(scope="module")
def p_mo2g():
    config = make_config("p_mo2g")
    eps = jax.tree.map(np.asarray, generate_batch(jax.random.PRNGKey(4), config, N))
    visible0 = np.asarray(jax.vmap(lambda e: env.reset(e, config).seen)(eps))
    keys = jax.random.split(jax.random.PRNGKey(9), N)
    named, cells, valid = jax.vmap(functools.partial(controls.name_a_distractor,
                                                     setting="p_mo2g"))(keys, eps, visible0)
    return eps, visible0, jax.tree.map(np.asarray, named), np.asarray(cells), np.asarray(valid)


def test_the_named_distractor_is_seen_at_the_start_and_only_its_name_changes(p_mo2g):
    eps, visible0, named, cells, valid = p_mo2g
    assert valid.sum() >= N // 2  # most P-MO2G episodes show a distractor at t = 0
    for i in np.flatnonzero(valid):
        r, c = cells[i]
        cls = int(eps.grid[i, r, c])
        assert visible0[i, r, c] and cls > 0
        assert cls not in (int(eps.target_class[i]), int(eps.reference_class[i]))
        changed = np.flatnonzero(named.tokens[i] != eps.tokens[i])
        assert len(changed) == 1  # the reference's name, nothing else
        assert grammar.VOCAB[named.tokens[i][changed[0]]] == grammar.OBJECT_NAMES[cls - 1]
        assert grammar.VOCAB[eps.tokens[i][changed[0]]] == \
            grammar.OBJECT_NAMES[int(eps.reference_class[i]) - 1]
    for i in np.flatnonzero(~valid):
        np.testing.assert_array_equal(named.tokens[i], eps.tokens[i])
    # The world is the world: nothing but the tokens differs.
    np.testing.assert_array_equal(named.grid, eps.grid)
    np.testing.assert_array_equal(named.reference, eps.reference)


def test_reversing_the_direction_names_the_opposite_sector(p_mo2g):
    eps = p_mo2g[0]
    reversed_ = jax.tree.map(np.asarray, jax.vmap(functools.partial(
        controls.reverse_direction, setting="p_mo2g"))(eps))
    for i in range(N):
        changed = np.flatnonzero(reversed_.tokens[i] != eps.tokens[i])
        assert len(changed) == 1
        word = grammar.VOCAB[reversed_.tokens[i][changed[0]]]
        assert word == grammar.DIRECTIONS[(int(eps.direction[i]) + 4) % 8]


def test_named_first_reads_the_order_of_first_visits():
    # Three 5-move walks along row 0; the named cell (0, 2), the reference (0, 4) or (0, 1).
    positions = np.zeros((3, 6, 2), int)
    positions[:, :, 1] = np.arange(6)
    steps = np.array([5, 5, 1])
    named = np.array([[0, 2], [0, 2], [0, 2]])
    reference = np.array([[0, 4], [0, 1], [0, 4]])
    np.testing.assert_array_equal(controls.first_visit(positions, steps, named), [2, 2, 6])
    np.testing.assert_array_equal(controls.named_first(positions, steps, named, reference),
                                  [True, False, False])


def test_in_mo1g_the_goal_is_named_as_a_visible_distractor():
    """With no reference (MO1G) the names control renames the goal: one token changes, from
    the target's name to a distractor's seen at t = 0, and the rendered text (what a features
    denoiser reads, experiments.gridworld.controls.changed_slots) names the same object."""
    from envs.gridworld.sentences import episode_texts
    from experiments.gridworld.controls import changed_slots

    config = make_config("mo1g")
    eps = jax.tree.map(np.asarray, generate_batch(jax.random.PRNGKey(5), config, N))
    visible0 = np.asarray(jax.vmap(lambda e: env.reset(e, config).seen)(eps))
    keys = jax.random.split(jax.random.PRNGKey(9), N)
    named, cells, valid = jax.tree.map(np.asarray, jax.vmap(functools.partial(
        controls.name_a_distractor, setting="mo1g"))(keys, eps, visible0))
    assert valid.sum() >= N // 2
    slots = changed_slots("names", eps, valid, cells)
    np.testing.assert_array_equal(slots["reference_class"], eps.reference_class)
    texts = episode_texts(eps, "mo1g", **slots)
    for i in np.flatnonzero(valid):
        r, c = cells[i]
        cls = int(eps.grid[i, r, c])
        assert visible0[i, r, c] and cls > 0 and cls != int(eps.target_class[i])
        changed = np.flatnonzero(named.tokens[i] != eps.tokens[i])
        assert len(changed) == 1
        assert grammar.VOCAB[named.tokens[i][changed[0]]] == grammar.OBJECT_NAMES[cls - 1]
        assert grammar.OBJECT_NAMES[cls - 1] in texts[i]
        assert grammar.OBJECT_NAMES[int(eps.target_class[i]) - 1] not in texts[i]
    for i in np.flatnonzero(~valid):
        np.testing.assert_array_equal(named.tokens[i], eps.tokens[i])
