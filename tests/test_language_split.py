"""The phrasing split of both worlds (diffplan.language.TemplateSplit): canonical, training
paraphrases and held-out phrasings ("unseen" in the grid world, "development" in the Kuka world);
no held-out phrasing in any training batch; a word outside the vocabulary refused in one line
naming it; the slot matcher against a plain-Python oracle."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from diffplan import language
from envs.gridworld import grammar as grid_grammar
from envs.gridworld.config import REFERENCE_SETTINGS, SETTINGS, make_config
from envs.kuka import grammar as kuka_grammar

KUKA_SPLITS = {"relation": kuka_grammar.RELATION_SPLIT, "tower": kuka_grammar.TOWER_SPLIT}
ALL_SPLITS = {**{f"grid/{s}": grid_grammar.SPLITS[s] for s in SETTINGS},
              **{f"kuka/{k}": v for k, v in KUKA_SPLITS.items()}}


# ------------------------------------------------------------------ the split itself

@pytest.mark.parametrize("name", sorted(ALL_SPLITS))
def test_a_third_held_out_made_of_training_words(name):
    split = ALL_SPLITS[name]
    n = len(split.templates) - len(split.extra) - len(split.sealed)  # as before the sealed set
    assert len(split.unseen) == n // 3 and 0 not in split.unseen
    training_words = language.template_words([split.templates[i] for i in split.training],
                                             split.slots)
    for i in split.unseen + split.sealed:
        assert language.template_words([split.templates[i]], split.slots) <= training_words


@pytest.mark.parametrize("setting", SETTINGS)
def test_grid_settings_have_twelve_phrasings(setting):
    assert len(grid_grammar.TEMPLATES[setting]) >= 12


def test_word_order_varies_in_training_and_held_out_phrasings():
    """P-MO2G: phrasings that name the target before the reference, in both parts; Kuka:
    inverted prepositions (the lower block named first) in both parts."""
    split = grid_grammar.SPLITS["p_mo2g"]

    def target_first(i):
        t = split.templates[i]
        return t.index("{target}") < t.index("{ref}")

    assert any(target_first(i) for i in split.training)
    assert any(target_first(i) for i in split.unseen)
    inverted = set(kuka_grammar.INVERTED)
    assert inverted & set(kuka_grammar.RELATION_SPLIT.training)
    assert inverted & set(kuka_grammar.RELATION_SPLIT.unseen)
    for i in kuka_grammar.INVERTED:
        t = kuka_grammar.RELATION_TEMPLATES[i]
        assert t.index("{bottom}") < t.index("{top}")


def test_split_refuses_new_words_in_held_out_phrasings():
    with pytest.raises(ValueError, match="zebra"):
        language.TemplateSplit(("Go to the {t}.", "Walk to the {t}.", "Ride the zebra to the {t}."),
                               (2,), ("{t}",))
    with pytest.raises(ValueError, match="unseen"):
        language.TemplateSplit(("a {t}.", "b {t}."), (0,), ("{t}",))


@pytest.mark.parametrize("name", sorted(ALL_SPLITS))
def test_pools(name):
    split = ALL_SPLITS[name]
    assert split.pool("canonical").tolist() == [0]
    paraphrased = split.pool("paraphrased").tolist()
    assert 0 not in paraphrased and not set(paraphrased) & set(split.unseen)
    assert sorted(paraphrased + [0] + list(split.unseen) + list(split.extra)
                  + list(split.sealed)) == list(range(len(split.templates)))
    assert split.pool(split.unseen_name).tolist() == list(split.unseen)
    mixed = split.pool(language.TRAINING)
    assert (mixed == 0).mean() == 0.5 and not set(mixed.tolist()) & set(split.unseen)
    assert not set(mixed.tolist()) & set(split.extra)
    assert split.pool(language.BROAD).tolist() == paraphrased + list(split.extra)
    with pytest.raises(ValueError, match="klingon"):
        split.pool("klingon")


def test_draw_template_stays_in_pool_and_covers_it():
    pool = np.array([3, 5, 7], np.int32)
    draws = np.asarray(jax.vmap(lambda k: language.draw_template(k, pool))(
        jax.random.split(jax.random.PRNGKey(0), 300)))
    assert set(draws.tolist()) == {3, 5, 7}
    assert language.draw_template(jax.random.PRNGKey(1), np.array([4])).tolist() == 4


# ------------------------------------------------------------------ the slot matcher

def _oracle_match(tokens, compiled):
    """Plain Python: the first template whose fixed words equal the tokens and whose slots hold
    non-padding tokens; its slot tokens (first occurrence)."""
    for n, row in enumerate(compiled.tolist()):
        if all((t == w) if w >= 0 else (t != 0) for t, w in zip(tokens.tolist(), row)):
            slots = []
            for k in range(1, -min(min(r) for r in compiled.tolist()) + 1):
                slots.append(tokens[row.index(-k)] if -k in row else 0)
            return n, slots
    return -1, None


@settings(max_examples=60, deadline=None)
@given(setting=st.sampled_from(SETTINGS), template=st.integers(0, 11),
       ref=st.integers(1, 15), target=st.integers(1, 15), direction=st.integers(0, 7))
def test_match_template_against_oracle(setting, template, ref, target, direction):
    compiled = grid_grammar.compile_templates(setting)
    tokens = np.asarray(grid_grammar.fill_template(compiled[template], ref, target, direction))
    index, slots = language.match_template(tokens, compiled)
    want_index, want_slots = _oracle_match(tokens, compiled)
    assert int(index) == want_index == template  # the phrasings are distinct in structure
    assert np.asarray(slots).tolist() == want_slots
    ref_tok, target_tok = grid_grammar.class_to_token(ref), grid_grammar.class_to_token(target)
    assert int(slots[1]) == target_tok
    if setting in REFERENCE_SETTINGS:
        assert int(slots[0]) == ref_tok
        assert int(slots[2]) == grid_grammar.DIRECTION_TOKEN_IDS[direction]


def test_match_template_rejects_other_sentences():
    compiled = grid_grammar.compile_templates("p_mo2g")
    tokens = grid_grammar.encode("Go to the apple.")
    index, slots = language.match_template(tokens, compiled)
    assert int(index) == -1 and np.asarray(slots).tolist() == [0, 0, 0]
    assert grid_grammar.which_template(tokens) == ("1o1g", 0)
    assert grid_grammar.which_template(grid_grammar.encode("apple go the to.")) is None


# ------------------------------------------------------------------ episodes and training

@pytest.mark.parametrize("setting", SETTINGS)
def test_grid_episodes_draw_from_their_pool_same_worlds(setting):
    from envs.gridworld.episode import generate

    keys = jax.random.split(jax.random.PRNGKey(5), 64)
    eps = {lang: jax.vmap(lambda k: generate(k, make_config(setting, language=lang)))(keys)
           for lang in language.LANGUAGES}
    for lang, ep in eps.items():
        templates = np.asarray(ep.template)
        assert set(templates.tolist()) <= set(grid_grammar.template_pool(setting, lang).tolist())
        for i in range(8):
            assert grid_grammar.which_template(ep.tokens[i])[1] == templates[i]
        # The phrasing changes the words only: the same worlds in every language.
        np.testing.assert_array_equal(ep.grid, eps["canonical"].grid)
        np.testing.assert_array_equal(ep.agent, eps["canonical"].agent)
    assert make_config(setting, paraphrase=True) == make_config(setting, language="paraphrased")
    with pytest.raises(ValueError, match="language"):
        make_config(setting, language="klingon")


def test_no_held_out_phrasing_in_a_grid_training_batch():
    from envs.gridworld.training import Recipe, make_mixture_batch_fn

    batch_fn = jax.jit(Recipe().batch_fn(), static_argnums=1)
    seen = []
    for step in range(4):
        batch = batch_fn(jax.random.PRNGKey(step), 64)
        seen += [grid_grammar.which_template(t)[1] for t in np.asarray(batch.tokens)]
    assert not set(seen) & set(grid_grammar.UNSEEN_TEMPLATES)
    share = np.mean(np.asarray(seen) == 0)
    assert 0.35 < share < 0.65  # canonical and paraphrased both well represented
    assert len(set(seen)) == 8
    with pytest.raises(ValueError, match="held-out"):
        make_mixture_batch_fn(language="unseen")


def _held_out_within(template_ids, keep_ids):
    """The held-out phrasings a training template could become by dropping words that are not
    slot fillers: with padding holes kept in place, only a held-out phrasing equal to a prefix
    of the template whose remainder is all droppable words."""
    found = []
    for k in grid_grammar.UNSEEN_TEMPLATES:
        for setting in ("mo1g", "p_mo2g"):
            held = grid_grammar.compile_templates(setting)[k]
            n = int((held != 0).sum())
            rest = template_ids[n:]
            droppable = ~np.isin(rest, keep_ids) & (rest > 0)
            if np.array_equal(template_ids[:n], held[:n]) and np.all(droppable | (rest == 0)):
                found.append((setting, k))
    return found


def test_word_dropout_drops_other_words_only_and_keeps_the_episodes():
    """Recipe(word_dropout=...): the same worlds, plans and loss weights as without it; the
    tokens differ only where a word other than an object name or direction became padding,
    at about the rate asked; no dropped training phrasing can become a held-out one."""
    from envs.gridworld.training import SLOT_WORD_IDS, Recipe

    plain = jax.jit(Recipe().batch_fn(), static_argnums=1)(jax.random.PRNGKey(3), 64)
    dropped = jax.jit(Recipe(word_dropout=0.3).batch_fn(), static_argnums=1)(
        jax.random.PRNGKey(3), 64)
    for a, b in ((plain.x0, dropped.x0), (plain.loss_mask, dropped.loss_mask)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    before, after = np.asarray(plain.tokens), np.asarray(dropped.tokens)
    changed = before != after
    assert np.all(after[changed] == 0)
    assert not np.any(changed & np.isin(before, SLOT_WORD_IDS))
    droppable = (before != 0) & ~np.isin(before, SLOT_WORD_IDS)
    assert 0.2 < changed.sum() / droppable.sum() < 0.4
    assert Recipe(word_dropout=0.3).metadata()["word_dropout"] == 0.3
    assert "word_dropout" not in Recipe().metadata()  # older checkpoints still match
    for setting in ("mo1g", "p_mo2g"):
        for ids in grid_grammar.compile_templates(setting)[:8]:
            assert not _held_out_within(ids, SLOT_WORD_IDS)
    with pytest.raises(ValueError, match="word_dropout"):
        Recipe(word_dropout=1.0).batch_fn()


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.0, 0.9))
def test_drop_words_invariants(seed, rate):
    """drop_words only turns droppable words into padding; rate 0 is the identity."""
    tokens = np.asarray(jax.random.randint(jax.random.PRNGKey(seed), (4, 12), 0, 9))
    keep = np.array([2, 5], np.int32)
    out = np.asarray(language.drop_words(jax.random.PRNGKey(seed + 1), tokens, rate, keep))
    changed = out != tokens
    assert np.all(out[changed] == 0) and not np.any(changed & np.isin(tokens, keep))
    assert not np.any(changed & (tokens == 0))
    np.testing.assert_array_equal(
        np.asarray(language.drop_words(jax.random.PRNGKey(0), tokens, 0.0, keep)), tokens)


def test_no_held_out_phrasing_in_a_kuka_training_batch():
    from envs.kuka.config import TaskSpec
    from envs.kuka.training import SPECS, Recipe

    import kuka_fixtures as kf

    assert {s.language for s in SPECS} == {"canonical", "paraphrased"}
    assert {s.language for s in Recipe().specs} == {"canonical", "paraphrased"}
    found = []
    for step in range(2):
        for row in kf.training_tokens(False, step):
            sentences = kuka_grammar.sentence_templates(row)
            assert None not in sentences
            found += sentences
    unseen = ({("relation", i) for i in kuka_grammar.RELATION_SPLIT.unseen}
              | {("tower", i) for i in kuka_grammar.TOWER_SPLIT.unseen})
    assert not set(found) & unseen
    assert ("relation", 0) in found and any(k == "relation" and i > 0 for k, i in found)
    for never in ("development", "unseen"):  # "unseen": the old name, refused as well
        with pytest.raises(ValueError, match="development"):
            Recipe(specs=(TaskSpec("stacking", False, never),))
    with pytest.raises(ValueError, match="held-out"):  # a recorded spec under the old name
        Recipe(specs=[["stacking", False, "unseen"]])


def test_a_broad_kuka_training_batch_draws_the_extras_and_no_held_out_phrasing():
    """The "broad" training language adds the extra relation phrasings; evaluation rows
    (paraphrased, development) never draw them, and they leave the vocabulary as it was."""
    import dataclasses

    import kuka_fixtures as kf
    from envs.kuka.config import COLUMNS
    from envs.kuka.episode import generate

    found = [t for row in kf.training_tokens(True, 0) for t in kuka_grammar.sentence_templates(row)]
    assert None not in found
    relations = {i for kind, i in found if kind == "relation"}
    assert relations & set(kuka_grammar.EXTRA) and relations & {1, 2, 3, 4, 5, 6, 7}
    assert not relations & set(kuka_grammar.RELATION_SPLIT.unseen)
    keys = jax.random.split(jax.random.PRNGKey(2), 32)
    for spec in COLUMNS.values():
        for phrasing in ("paraphrased", "development"):
            spec = dataclasses.replace(spec, language=phrasing)
            rows = np.asarray(jax.vmap(lambda k: generate(k, spec).tokens)(keys))
            for row in rows:
                assert not {i for kind, i in kuka_grammar.sentence_templates(row)
                            if kind == "relation"} & set(kuka_grammar.EXTRA)
    extra_words = language.template_words(
        [kuka_grammar.RELATION_TEMPLATES[i] for i in kuka_grammar.EXTRA], kuka_grammar.SLOTS)
    assert extra_words <= set(kuka_grammar.VOCAB)


def test_template_split_refuses_bad_extras():
    templates = ("go to the {x} .", "walk to the {x} .", "go walk to the {x} .",
                 "to the {x} go .")
    language.TemplateSplit(templates, (2,), ("{x}",), (3,))
    with pytest.raises(ValueError, match="extra must be distinct"):
        language.TemplateSplit(templates, (2,), ("{x}",), (2,))
    with pytest.raises(ValueError, match="extra must be distinct"):
        language.TemplateSplit(templates, (2,), ("{x}",), (0,))
    with pytest.raises(ValueError, match=r"extra phrasing .* \['run'\]"):
        language.TemplateSplit(templates + ("run to the {x} .",), (2,), ("{x}",), (4,))
    split = language.TemplateSplit(templates, (2,), ("{x}",), (3,))
    assert list(split.pool("paraphrased")) == [1] and list(split.pool("broad")) == [1, 3]
    assert list(split.pool("mixed")) == [0, 1] and list(split.pool("unseen")) == [2]


def test_a_split_with_development_and_sealed_pools():
    """A world may name its held-out pool "development" and add a sealed pool ("heldout"):
    training languages never draw either, and the grid world's split is as it was."""
    templates = ("go to the {x} .", "walk to the {x} .", "go walk to the {x} .",
                 "to the {x} go .", "the {x} walk to .")
    split = language.TemplateSplit(templates, (2,), ("{x}",), sealed=(3, 4),
                                   unseen_name=language.DEVELOPMENT)
    assert split.languages == ("canonical", "paraphrased", "development", "heldout")
    assert list(split.pool("development")) == [2] and list(split.pool("heldout")) == [3, 4]
    assert split.training == (0, 1)
    for lang in language.TRAINING_ONLY + ("canonical", "paraphrased"):
        assert not set(split.pool(lang).tolist()) & {2, 3, 4}
    for lang in ("unseen", "klingon"):
        with pytest.raises(ValueError, match="unknown language"):
            split.pool(lang)
    for lang in language.NEVER_TRAINED:
        with pytest.raises(ValueError, match="held-out"):
            language.check_training_language(lang, split.languages)
    for name, split_of_grid in grid_grammar.SPLITS.items():
        assert split_of_grid.languages == language.LANGUAGES and not split_of_grid.sealed
    for bad, match in (({"sealed": (2,)}, "sealed must be distinct"),
                       ({"sealed": (0,)}, "sealed must be distinct"),
                       ({"unseen_name": "heldout"}, "unseen_name must be")):
        with pytest.raises(ValueError, match=match):
            language.TemplateSplit(templates, (2,), ("{x}",), **bad)
    with pytest.raises(ValueError, match=r"sealed phrasing .* \['run'\]"):
        language.TemplateSplit(templates + ("run to the {x} .",), (2,), ("{x}",), sealed=(5,))


def test_kuka_development_episodes_use_development_phrasings_only():
    from envs.kuka.config import COLUMNS
    import dataclasses
    from envs.kuka.episode import generate

    keys = jax.random.split(jax.random.PRNGKey(2), 16)
    for spec in COLUMNS.values():
        spec = dataclasses.replace(spec, language="development")
        tokens = np.asarray(jax.vmap(lambda k: generate(k, spec).tokens)(keys))
        for row in tokens:
            for kind, i in kuka_grammar.sentence_templates(row):
                assert i in KUKA_SPLITS[kind].unseen


# ------------------------------------------------------------------ refusal

@pytest.mark.parametrize("encode, text, word", [
    (grid_grammar.encode, "Go to the zebra first.", "zebra"),
    (grid_grammar.encode, "Walk to the apple, then hop north to the pear.", "hop"),
    (kuka_grammar.encode, "Stack the purple block on the red block.", "purple"),
])
def test_out_of_vocabulary_instruction_refused_in_one_line(encode, text, word):
    with pytest.raises(ValueError) as info:
        encode(text)
    message = str(info.value)
    assert word in message and "\n" not in message


# ------------------------------------------------------------------ the baselines' goal

@pytest.mark.parametrize("lang", language.LANGUAGES)
def test_baseline_goal_vector_reads_every_phrasing(lang):
    from envs.gridworld import baselines
    from envs.gridworld.episode import generate

    config = make_config("p_mo2g", language=lang)
    ep = jax.vmap(lambda k: generate(k, config))(jax.random.split(jax.random.PRNGKey(7), 64))
    vec = np.asarray(baselines.goal_vector(ep.tokens))
    n = baselines.NUM_CLASSES
    np.testing.assert_array_equal(vec[:, :n].argmax(1) + 1, ep.target_class)
    np.testing.assert_array_equal(vec[:, n:2 * n].argmax(1) + 1, ep.reference_class)
    np.testing.assert_array_equal(vec[:, 2 * n:].argmax(1), ep.direction)
    assert (vec.sum(1) == 3).all()
    one = baselines.goal_vector(jnp.asarray(grid_grammar.encode("apple go north pear.")))
    assert float(one.sum()) == 3  # not a phrasing: last object the target, first the reference
