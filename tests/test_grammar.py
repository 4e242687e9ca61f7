"""envs.gridworld.grammar: vocabulary, encode/decode, templates and the jnp template filler."""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.gridworld import grammar
from envs.gridworld.config import REFERENCE_SETTINGS, SETTINGS


def all_fillings(setting):
    """Every (template, ref_class, target_class, direction) of a setting (classes 1-based,
    ref_class 0 and direction -1 where the setting has no slot)."""
    templates = range(len(grammar.TEMPLATES[setting]))
    classes = range(1, len(grammar.OBJECT_NAMES) + 1)
    if setting in REFERENCE_SETTINGS:
        return [(t, r, g, d) for t, r, g, d in itertools.product(
            templates, classes, classes, range(len(grammar.DIRECTIONS))) if r != g]
    return [(t, 0, g, -1) for t, g in itertools.product(templates, classes)]


def test_vocabulary_layout():
    assert grammar.VOCAB[:4] == grammar.SPECIAL_TOKENS
    special_ids = (grammar.PAD_ID, grammar.UNSEEN_ID, grammar.EMPTY_ID, grammar.OBSTACLE_ID)
    assert special_ids == (0, 1, 2, 3)
    assert len(set(grammar.VOCAB)) == len(grammar.VOCAB)
    for k, name in enumerate(grammar.OBJECT_NAMES, start=1):
        assert grammar.VOCAB[grammar.class_to_token(k)] == name
    assert [grammar.VOCAB[i] for i in grammar.DIRECTION_TOKEN_IDS] == list(grammar.DIRECTIONS)
    assert len(set(grammar.OBJECT_NAMES)) == len(grammar.OBJECT_NAMES)


@pytest.mark.parametrize("setting", SETTINGS)
def test_round_trip_every_template_object_direction(setting):
    count = 0
    for t, r, g, d in all_fillings(setting):
        text = grammar.render(setting, t, r, g, d)
        ids = grammar.encode(text)
        assert ids.dtype == np.int32 and ids.shape == (grammar.MAX_TOKENS,)
        assert grammar.decode(ids) == text
        words = grammar.split_words(text)
        assert grammar.OBJECT_NAMES[g - 1] in words
        if setting in REFERENCE_SETTINGS:
            assert grammar.OBJECT_NAMES[r - 1] in words and grammar.DIRECTIONS[d] in words
        count += 1
    assert count == len(all_fillings(setting)) > 0


@pytest.mark.parametrize("setting", SETTINGS)
def test_paraphrases_exist(setting):
    templates = grammar.TEMPLATES[setting]
    assert len(templates) >= 12
    assert len(set(templates)) == len(templates)
    # Every template has the setting's slots (an object may be named twice; one direction).
    for template in templates:
        assert template.count("{target}") >= 1
        if setting in REFERENCE_SETTINGS:
            assert template.count("{ref}") >= 1 and template.count("{dir}") == 1
        else:
            assert "{ref}" not in template and "{dir}" not in template
    # Paraphrases of one meaning render to different texts.
    filling = all_fillings(setting)[0][1:]
    texts = {grammar.render(setting, t, *filling) for t in range(len(templates))}
    assert len(texts) == len(templates)


def test_unknown_words_raise_naming_them():
    with pytest.raises(ValueError, match="zebra") as info:
        grammar.encode("Go to the zebra, then the xylophone.")
    assert "xylophone" in str(info.value)
    assert "'the'" not in str(info.value)  # only the unknown words are listed
    with pytest.raises(ValueError, match="pad"):
        grammar.encode("go to the <pad>")
    with pytest.raises(ValueError, match="max_tokens"):
        grammar.encode("go to the apple. " * 10)


def test_encode_is_case_insensitive_and_pads():
    ids = grammar.encode("GO TO THE Apple.")
    assert list(ids[:5]) == [grammar.WORD_TO_ID[w] for w in ("go", "to", "the", "apple", ".")]
    assert (ids[5:] == grammar.PAD_ID).all()
    assert grammar.decode(ids) == "Go to the apple."


@pytest.mark.parametrize("setting", SETTINGS)
def test_compiled_templates(setting):
    compiled = grammar.compile_templates(setting)
    assert compiled.dtype == np.int32
    assert compiled.shape == (len(grammar.TEMPLATES[setting]), grammar.MAX_TOKENS)
    for row, template in zip(compiled, grammar.TEMPLATES[setting]):
        assert (row == grammar.SLOT_TARGET).sum() == template.count("{target}") >= 1
        assert (row == grammar.SLOT_REF).sum() == template.count("{ref}")
        assert ((row == grammar.SLOT_REF).sum() >= 1) == (setting in REFERENCE_SETTINGS)
        n = len(grammar.split_words(template))
        assert (row[n:] == 0).all() and (row[:n] != 0).all()
    with pytest.raises(ValueError, match="unknown setting"):
        grammar.compile_templates("mo2g")


@pytest.fixture(scope="module")
def fill_batch():
    """jit(vmap(fill_template)) over (templates (N, L), ref, target, direction): compiled once."""
    return jax.jit(jax.vmap(grammar.fill_template))


@pytest.mark.parametrize("setting", SETTINGS)
def test_fill_template_matches_render(fill_batch, setting):
    fillings = np.array(all_fillings(setting), np.int32)
    compiled = grammar.compile_templates(setting)
    # Pad to a fixed batch size so that one compilation serves every setting.
    size = 15 * 14 * 8 * len(compiled)
    assert len(fillings) <= size
    padded = np.concatenate([fillings, np.tile(fillings[:1], (size - len(fillings), 1))])
    t, r, g, d = padded.T
    tokens = np.asarray(fill_batch(jnp.asarray(compiled[t]), r, g, np.maximum(d, 0)))
    assert tokens.dtype == np.int32
    for row, (ti, ri, gi, di) in zip(tokens[: len(fillings)], fillings):
        expected = grammar.render(setting, int(ti), int(ri), int(gi), int(di))
        np.testing.assert_array_equal(row, grammar.encode(expected))


def test_phrasings_are_the_settings_templates():
    assert grammar.phrasings(True) == grammar.TEMPLATES["p_mo2g"] == grammar.TEMPLATES["p_mo2g_far"]
    assert grammar.phrasings(False) == grammar.TEMPLATES["mo1g"] == grammar.TEMPLATES["1o1g"]


@pytest.mark.parametrize("setting", ["mo1g", "p_mo2g"])
def test_slot_roles_name_the_slot_each_word_fills(setting):
    """diffplan.language.slot_roles on rendered instructions of every phrasing, against a
    plain-Python reading of the template text: the k-th slot's words get role k (the grid
    recipe's auxiliary labels: reference, target, direction), every other word none."""
    from diffplan.language import slot_roles
    from envs.gridworld.training import ROLES

    compiled = grammar.compile_templates(setting)
    rng = np.random.default_rng(0)
    fillings = all_fillings(setting)
    cases = [fillings[i] for i in rng.choice(len(fillings), 60, replace=False)]
    cases += [f for f in fillings if f[0] in grammar.UNSEEN_TEMPLATES][:8]
    texts = [grammar.render(setting, *case) for case in cases]
    tokens = np.stack([grammar.encode(t) for t in texts])
    roles, named = jax.jit(jax.vmap(lambda t: slot_roles(t, compiled)))(tokens)
    slot_role = {"{ref}": ROLES.index("reference"), "{target}": ROLES.index("target"),
                 "{dir}": ROLES.index("direction")}
    for (template, *_), ids, r, m in zip(cases, tokens, np.asarray(roles), np.asarray(named)):
        words = grammar.TEMPLATES[setting][template].replace("{", " {").replace("}", "} ")
        expected = [slot_role.get(w) for w in grammar.split_words(words)]
        n = int((ids != 0).sum())
        assert len(expected) == n
        assert [int(x) if ok else None for x, ok in zip(r[:n], m[:n])] == expected
        assert not m[n:].any()
    unknown = grammar.encode("Go to the apple and the pear.")
    assert not np.asarray(slot_roles(unknown, compiled)[1]).any()
