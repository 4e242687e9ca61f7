"""diffplan.language (shared by both worlds) and the Kuka grammar: vocabulary, round trips, the
jnp instruction builder against plain-Python rendering, paraphrases with inverted prepositions."""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan import language
from envs.kuka import grammar, scene
from envs.kuka.config import COLUMNS
from envs.kuka.episode import episode_keys, generate


def test_fill_slots_and_concat_segments_match_python():
    vocab = language.Vocabulary(("<pad>", "a", "b", "c", "x", "y", "."))
    compiled = vocab.compile("a {p} b {q} .", ("{p}", "{q}"), 8)
    np.testing.assert_array_equal(compiled, [1, -1, 2, -2, 6, 0, 0, 0])
    filled = np.asarray(language.fill_slots(compiled, np.array([4, 5])))
    assert vocab.decode(filled) == "A x b y."
    segments = np.array([[1, 2, 0], [3, 0, 0], [4, 5, 6]])
    for lengths in ([2, 1, 3], [0, 1, 3], [2, 0, 0], [2, 1, 1]):
        out = np.asarray(jax.jit(language.concat_segments, static_argnums=2)(
            segments, np.array(lengths), 5))
        expected = [t for row, n in zip(segments, lengths) for t in row[:n]][:5]
        np.testing.assert_array_equal(out, expected + [0] * (5 - len(expected)))


def test_vocabulary_layout():
    assert grammar.VOCAB[0] == grammar.PAD and len(set(grammar.VOCAB)) == len(grammar.VOCAB)
    for i, name in enumerate(scene.BLOCK_NAMES):
        assert grammar.VOCAB[grammar.block_token(i)] == name
    lengths = language.lengths_of(grammar.RELATIONS)
    assert lengths.max() <= grammar.SENTENCE_TOKENS
    # Three relations in the longest phrasing fit the fixed instruction length.
    assert 3 * lengths.max() <= grammar.MAX_TOKENS
    assert language.lengths_of(grammar.TOWERS).max() + lengths.max() <= grammar.MAX_TOKENS


def test_every_relation_template_round_trips():
    for k, (top, bottom) in itertools.product(range(len(grammar.RELATION_TEMPLATES)),
                                              itertools.permutations(range(4), 2)):
        text = grammar.render([(top, bottom)], False, [k])
        assert grammar.decode(grammar.encode(text)) == text
        words = language.split_words(text)
        # Inverted paraphrases name the lower block first.
        first, second = scene.BLOCK_NAMES[top], scene.BLOCK_NAMES[bottom]
        if k in grammar.INVERTED:
            first, second = second, first
        assert words.index(first) < words.index(second)
    for k in range(len(grammar.TOWER_TEMPLATES)):
        text = grammar.TOWER_TEMPLATES[k]
        assert grammar.decode(grammar.encode(text)) == text


def test_paraphrases_invert_prepositions():
    inverted = [grammar.RELATION_TEMPLATES[k] for k in grammar.INVERTED]
    assert any("below" in t for t in inverted) and len(inverted) >= 2
    for t in inverted:
        assert t.index("{bottom}") < t.index("{top}")
    assert len(set(grammar.RELATION_TEMPLATES)) == len(grammar.RELATION_TEMPLATES)


def test_unknown_words_raise():
    with pytest.raises(ValueError, match="purple"):
        grammar.encode("Stack the purple block on top of the red block.")


@pytest.mark.parametrize("phrasing", grammar.LANGUAGES + (language.BROAD,))
def test_instruction_tokens_match_rendering(phrasing):
    """The jnp builder's tokens decode to the plain rendering of the same choices."""
    keys = jax.random.split(jax.random.PRNGKey(3), 64)
    cases = []
    for i in range(64):
        n = 1 + i % 3
        order = np.random.default_rng(100 + i).permutation(4)
        rows = [(int(order[j + 1]), int(order[j])) for j in range(n)]
        cases.append((rows, n == 1 and bool(i % 2)))  # as episodes: a tower, one relation
    constraints = np.array([np.concatenate([np.array(r, np.int32),
                                            -np.ones((3 - len(r), 2), np.int32)])
                            for r, _ in cases])
    towers = np.array([t for _, t in cases])
    build = jax.jit(jax.vmap(lambda k, c, t: grammar.instruction_tokens(k, c, t, phrasing)))
    tokens = np.asarray(build(keys, constraints, towers))
    for (rows, tower), ids in zip(cases, tokens):
        text = grammar.decode(ids)
        sentences = [s.strip() + "." for s in text.split(".") if s.strip()]
        assert len(sentences) == len(rows) + int(tower)
        rel_sentences = sentences[int(tower):]
        for (top, bottom), sentence in zip(rows, rel_sentences):
            matches = [k for k in range(len(grammar.RELATION_TEMPLATES))
                       if grammar.render([(top, bottom)], False, [k]) == sentence]
            assert matches, sentence
            assert matches[0] in grammar.RELATION_SPLIT.pool(phrasing)
        if tower:
            assert grammar.TOWER_TEMPLATES.index(sentences[0]) in \
                grammar.TOWER_SPLIT.pool(phrasing)


def test_episode_instructions_state_their_constraints():
    """Canonical instructions of generated episodes render from the episode's constraints."""
    for spec in COLUMNS.values():
        eps = jax.vmap(lambda k: generate(k, spec))(episode_keys(5, 8))
        for c, tok, tower in zip(np.asarray(eps.constraints), np.asarray(eps.tokens),
                                 np.asarray(eps.tower)):
            tower_sentence = bool(tower) and not spec.multi
            assert grammar.decode(tok) == grammar.render(c, tower_sentence)
            assert (c[:, 0] >= 0).sum() == spec.num_constraints
        assert jnp.asarray(eps.tokens).dtype == jnp.int32


def _roles_oracle(text, rows):
    """Plain Python: (role or None) of each token of a rendered instruction (the words of
    ``language.split_words`` with "." kept): a block name in the j-th relation sentence is
    0 if it is that relation's top, 1 if its bottom; None elsewhere."""
    out, sentence = [], 0
    relation_start = len([s for s in text.split(".") if s.strip()]) - len(rows)
    for word in language.split_words(text):
        j = sentence - relation_start
        if 0 <= j < len(rows) and word in scene.BLOCK_NAMES:
            top, bottom = rows[j]
            out.append(0 if word == scene.BLOCK_NAMES[top] else
                       1 if word == scene.BLOCK_NAMES[bottom] else None)
        else:
            out.append(None)
        sentence += word == "."
    return out


@pytest.mark.parametrize("phrasing", ("paraphrased", "development", language.BROAD))
def test_token_roles_match_a_plain_parse(phrasing):
    """Which block each block word names (the Kuka auxiliary labels), for every task column,
    against a plain-Python reading of the rendered sentence: in inverted phrasings the first
    block named is the lower one."""
    from envs.kuka.training import training_example, training_state

    seen_inverted = 0
    for spec in COLUMNS.values():
        spec = spec.__class__(spec.kind, spec.multi, phrasing)
        keys = jax.random.split(jax.random.PRNGKey(11), 16)
        eps = jax.vmap(lambda k: training_state(k, spec, 0.0)[2])(keys)
        _, tokens, roles, named = jax.vmap(lambda k: training_example(k, spec, 0.0))(keys)
        np.testing.assert_array_equal(tokens, eps.tokens)
        for c, tok, r, m in zip(np.asarray(eps.constraints), np.asarray(eps.tokens),
                                np.asarray(roles), np.asarray(named)):
            rows = [(int(t), int(b)) for t, b in c if t >= 0]
            length = int((tok != 0).sum())
            expected = _roles_oracle(grammar.decode(tok), rows)
            assert len(expected) == length
            got = [int(x) if ok else None for x, ok in zip(r[:length], m[:length])]
            assert got == expected
            assert not m[length:].any()
            assert sum(e is not None for e in expected) == 2 * len(rows)
            names = [e for e in expected if e is not None]
            seen_inverted += any(names[i] == 1 for i in range(0, len(names), 2))
    assert seen_inverted > 0
