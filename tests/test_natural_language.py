"""The sealed natural-language test sets (envs/gridworld/natural.py, envs/kuka/natural.py):
their content is pinned by digest (a later edit shows here and must be explained), each world
has >= 60 sentences from >= 12 frames, every sentence fills only its world's slots, and none is
one of the phrasings a model trains or is developed on."""
from __future__ import annotations

import hashlib
import json
import string

import pytest

from envs.gridworld import grammar as grid_grammar
from envs.gridworld import natural as grid_natural
from envs.kuka import grammar as kuka_grammar
from envs.kuka import natural as kuka_natural

DIGESTS = {
    "gridworld via reference": "fa6b9562f7257337ff324a6da62237f2ea0d36d5662bd43d593c5989c02e5362",
    "gridworld goal only": "a968d46bfe33a90fd262c8ee9b811dca82c99798d816688895798a9fa054ef58",
    "kuka": "9d7ed9af2bbd7a8dff0fee1b00ee7fa2903f8350ae80be2632cd0de40f6b2c22",
}
"""sha256 of each set as sealed (json, sorted keys)."""


def digest(value) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()


SETS = {
    "gridworld via reference": (grid_natural.VIA_REFERENCE, {"ref", "target", "dir", "dir_h"}),
    "gridworld goal only": (grid_natural.GOAL_ONLY, {"target"}),
    "kuka": (kuka_natural.RELATIONS, {"top", "bottom"}),
}


def test_the_sets_are_as_sealed():
    assert digest(grid_natural.VIA_REFERENCE) == DIGESTS["gridworld via reference"]
    assert digest(grid_natural.GOAL_ONLY) == DIGESTS["gridworld goal only"]
    assert digest([kuka_natural.RELATIONS, list(kuka_natural.TOWERS)]) == DIGESTS["kuka"]


def test_control_an_edited_sentence_changes_the_digest():
    edited = {**grid_natural.GOAL_ONLY, "polite": ("Please go to the {target} now.",)}
    assert digest(edited) != DIGESTS["gridworld goal only"]


@pytest.mark.parametrize("name", sorted(SETS))
def test_sixty_distinct_sentences_from_twelve_frames_with_the_worlds_slots(name):
    table, slots = SETS[name]
    sentences = [s for frame in table.values() for s in frame]
    assert len(table) >= 12 and len(sentences) >= 60
    assert len(set(sentences)) == len(sentences)
    for sentence in sentences:
        used = {f for _, f, _, _ in string.Formatter().parse(sentence) if f}
        assert used <= slots, (sentence, used - slots)
        assert "top" not in slots or {"top", "bottom"} <= used
        assert "ref" not in slots or {"ref", "target"} <= used and used & {"dir", "dir_h"}
        assert "ref" in slots or "top" in slots or used == {"target"}


def test_no_natural_sentence_is_a_phrasing_models_train_or_develop_on():
    grid = set(grid_grammar.TEMPLATES["p_mo2g"]) | set(grid_grammar.TEMPLATES["mo1g"])
    kuka = set(kuka_grammar.RELATION_TEMPLATES) | set(kuka_grammar.TOWER_TEMPLATES)
    assert not set(grid_natural.sentences(True)) & grid
    assert not set(grid_natural.sentences(False)) & grid
    assert not set(kuka_natural.relation_sentences()) & kuka
    assert not set(kuka_natural.TOWERS) & kuka


def test_hyphenated_directions():
    assert [grid_natural.hyphenated(d) for d in grid_grammar.DIRECTIONS] == [
        "east", "north-east", "north", "north-west", "west", "south-west", "south",
        "south-east"]
