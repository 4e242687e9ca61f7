"""The Kuka world's sealed held-out phrasings (``grammar.HELDOUT``, ``grammar.HELDOUT_TOWERS``,
the language "heldout"): new frames made of the vocabulary's words, at least two words from every
other phrasing, and out of every training pool and batch. Each check runs once on a planted
defect too, to show that it can fail."""
from __future__ import annotations

import dataclasses
import json
import os

import jax
import numpy as np
import pytest

from diffplan import language
from envs.kuka import grammar, scene
from envs.kuka.config import COLUMNS, TaskSpec

SPLITS = {"relation": grammar.RELATION_SPLIT, "tower": grammar.TOWER_SPLIT}
SEALED = {("relation", k) for k in grammar.HELDOUT} | {("tower", k)
                                                      for k in grammar.HELDOUT_TOWERS}
TRAINING_LANGUAGES = ("canonical", "paraphrased") + language.TRAINING_ONLY
"""Every language a training batch may draw (the Kuka recipe's specs, the reader's batches)."""


def word_distance(a: str, b: str) -> int:
    """Plain Python: the word-level edit distance (insertions, deletions, substitutions) of two
    templates, split as the grammar splits them (a slot is one word)."""
    x, y = language.split_words(a), language.split_words(b)
    row = list(range(len(y) + 1))
    for i, u in enumerate(x, 1):
        prev, row[0] = row[:], i
        for j, v in enumerate(y, 1):
            row[j] = min(prev[j] + 1, row[j - 1] + 1, prev[j - 1] + (u != v))
    return row[-1]


def nearest_other(split, template: str) -> int:
    """The smallest word distance from template to a training, development or extra phrasing
    of its split."""
    others = split.training + split.unseen + split.extra
    return min(word_distance(template, split.templates[k]) for k in others)


def sealed_in_training_pools(split) -> set[int]:
    """The sealed phrasings that any training language's pool of split holds."""
    drawn = set(split.training)
    for lang in TRAINING_LANGUAGES:
        drawn |= set(split.pool(lang).tolist())
    return drawn & set(split.sealed)


def sealed_sentences(tokens) -> set[tuple[str, int]]:
    """The sealed phrasings among the sentences of instructions tokens int (N, L)."""
    found = {t for row in grammar.sentence_templates_batch(tokens) for t in row}
    assert None not in found  # every sentence is one of the grammar's phrasings
    return found & SEALED


def test_the_sealed_set_is_what_issue_52_asks_for():
    assert len(grammar.HELDOUT) >= 8 and len(grammar.HELDOUT_TOWERS) >= 2
    assert grammar.RELATION_SPLIT.sealed == grammar.HELDOUT
    assert grammar.TOWER_SPLIT.sealed == grammar.HELDOUT_TOWERS
    openings = {language.split_words(grammar.RELATION_TEMPLATES[k])[0] for k in grammar.HELDOUT}
    assert {"on", "under"} <= openings  # sentences that open with their preposition
    assert set(grammar.HELDOUT) & set(grammar.INVERTED)  # both orders of the two blocks
    assert set(grammar.HELDOUT) - set(grammar.INVERTED)
    assert "heldout" in grammar.LANGUAGES


@pytest.mark.parametrize("kind", sorted(SPLITS))
def test_every_sealed_phrasing_is_two_words_from_every_other(kind):
    split = SPLITS[kind]
    for k in split.sealed:
        assert nearest_other(split, split.templates[k]) >= 2, split.templates[k]
    # planted: a development phrasing with one word changed is one word away, and caught
    planted = grammar.RELATION_TEMPLATES[9].replace("below", "under")
    assert nearest_other(grammar.RELATION_SPLIT, planted) == 1


def test_sealed_phrasings_are_made_of_the_shipped_vocabulary():
    """Every rendering encodes with today's vocabulary, which is still the shipped denoiser's
    (so it can read them) and fits the fixed sentence and instruction lengths."""
    path = os.path.join(os.path.dirname(__file__), "..", "checkpoints", "kuka", "4600",
                        "metadata", "metadata")
    with open(path) as f:
        assert tuple(json.load(f)["extra"]["vocabulary"]) == grammar.VOCAB
    for k in grammar.HELDOUT:
        for top, bottom in ((0, 1), (3, 2)):
            text = grammar.render([(top, bottom)], True, [k], grammar.HELDOUT_TOWERS[0])
            assert grammar.decode(grammar.encode(text)) == text
        assert len(language.split_words(grammar.RELATION_TEMPLATES[k])) <= 13
    for k in grammar.HELDOUT_TOWERS:
        grammar.encode(grammar.TOWER_TEMPLATES[k])
    with pytest.raises(ValueError, match="beside"):  # planted: a word outside the vocabulary
        grammar.encode("Beside the red block put the blue block.")


@pytest.mark.parametrize("kind", sorted(SPLITS))
def test_no_training_language_pool_holds_a_sealed_phrasing(kind):
    split = SPLITS[kind]
    assert not sealed_in_training_pools(split)
    assert split.pool("heldout").tolist() == list(split.sealed)

    # planted: a split whose broad pool leaks a sealed phrasing is caught
    class Leaky(type(split)):
        def pool(self, lang):
            pool = super().pool(lang)
            return np.append(pool, self.sealed[0]) if lang == language.BROAD else pool

    leaky = Leaky(**{f.name: getattr(split, f.name) for f in dataclasses.fields(split)})
    assert sealed_in_training_pools(leaky) == {split.sealed[0]}


def test_training_refuses_the_sealed_language():
    from envs.kuka.training import Recipe

    for spec in (TaskSpec("stacking", False, "heldout"), ["rearrangement", True, "heldout"]):
        with pytest.raises(ValueError, match="held-out"):
            Recipe(specs=(spec,))
    from experiments.kuka.role_probe import check_extra

    with pytest.raises(ValueError, match="sealed held-out"):
        check_extra([grammar.RELATION_TEMPLATES[grammar.HELDOUT[0]]])


def test_kuka_training_batches_never_hold_a_sealed_phrasing():
    """The shipped recipe's batches, a "broad" recipe's, and the reader's (every training
    language there is) over a few steps; and, planted, episodes of the language "heldout",
    which the same check finds."""
    import kuka_fixtures as kf
    from envs.kuka import reader
    from envs.kuka.episode import generate
    from envs.kuka.training import Recipe

    assert not {s.language for s in Recipe().specs} & set(language.NEVER_TRAINED)
    for broad in (False, True):
        for step in range(2):
            assert not sealed_sentences(kf.training_tokens(broad, step))
    role_batch = jax.jit(reader.role_batch)
    for step in range(3):
        assert not sealed_sentences(np.asarray(role_batch(jax.random.PRNGKey(step))[0]))
    keys = jax.random.split(jax.random.PRNGKey(4), 16)
    planted = set()
    for spec in COLUMNS.values():
        spec = dataclasses.replace(spec, language="heldout")
        tokens = np.asarray(jax.vmap(lambda k: generate(k, spec).tokens)(keys))
        found = {t for row in grammar.sentence_templates_batch(tokens) for t in row}
        assert found <= SEALED  # a held-out episode is phrased in sealed phrasings only
        planted |= sealed_sentences(tokens)
    assert planted and {k for kind, k in planted if kind == "tower"}


def test_sealed_phrasings_state_their_relation():
    """Rendered with two blocks, each sealed phrasing's block words name the upper block first
    exactly when the grammar says so (INVERTED: the lower first)."""
    for k in grammar.HELDOUT:
        text = grammar.render([(1, 3)], False, [k])
        words = [w for w in language.split_words(text) if w in scene.BLOCK_NAMES]
        inverted = k in grammar.INVERTED
        assert words == (["yellow", "green"] if inverted else ["green", "yellow"])
