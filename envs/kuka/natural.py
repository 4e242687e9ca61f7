"""SEALED natural-language test set of the Kuka world (``--language natural``).

Written and committed before any denoiser was trained on the pretrained text encoder's
features, and never used for a choice: no training batch draws it, no recipe, checkpoint or
threshold is chosen on it; it is measured once, at the end of the work that produces a model,
and reported whatever comes out. tests/test_natural_language.py pins its digest.

One sentence per instructed relation "{top} on {bottom}", as people type them, grouped by
frame: polite forms, questions, synonyms (cube, over, beneath, rest, sit), the lower block
named first, preposition-first, lower case without punctuation, commas, first person,
casual, "so that" / result phrasing, "with" constructions and anaphora. A multi-relation
instruction is one such sentence per relation; a stacking instruction with one relation
starts with one of the tower sentences.
"""
from __future__ import annotations

RELATIONS: dict[str, tuple[str, ...]] = {
    "polite": (
        "Please put the {top} block on the {bottom} block.",
        "Could you please place the {top} cube on top of the {bottom} cube?",
        "Kindly set the {top} block onto the {bottom} one.",
        "Would you mind stacking the {top} block on the {bottom} block?",
        "If you could, put the {top} cube onto the {bottom} cube, please.",
    ),
    "question": (
        "Could you place {top} over {bottom}?",
        "Can you stack the {top} block on the {bottom} block?",
        "Will you put the {top} cube on the {bottom} one?",
        "Can the {top} block go on top of the {bottom} block?",
        "How about putting the {top} block on the {bottom} block?",
    ),
    "synonyms": (
        "Rest the {top} cube on the {bottom} cube.",
        "Lay the {top} block over the {bottom} block.",
        "Sit the {top} cube on top of the {bottom} cube.",
        "Drop the {top} block onto the {bottom} block.",
        "Position the {top} cube above the {bottom} one.",
    ),
    "bottom_first": (
        "The {bottom} block goes beneath the {top} block.",
        "I want the {bottom} cube beneath the {top} cube.",
        "Keep the {bottom} block under the {top} block.",
        "The {bottom} cube should end up below the {top} cube.",
        "Have the {bottom} block supporting the {top} block.",
    ),
    "preposition_first": (
        "On top of the {bottom} block, place the {top} block.",
        "Onto the {bottom} cube goes the {top} cube.",
        "Beneath the {top} block, put the {bottom} block.",
        "Over the {bottom} block, set the {top} block.",
        "Under the {top} cube should be the {bottom} cube.",
    ),
    "lower_case": (
        "put the {top} block on the {bottom} block",
        "stack {top} on {bottom}",
        "place the {top} cube on top of the {bottom} cube",
        "the {top} block goes on the {bottom} block",
        "{top} block onto {bottom} block",
    ),
    "commas": (
        "Take the {top} block, and put it on the {bottom} block.",
        "Pick up the {top} cube, then set it on the {bottom} cube.",
        "Grab the {top} block, lift it, and place it on the {bottom} block.",
        "The {top} block, please, on top of the {bottom} block.",
        "Move the {top} cube over, onto the {bottom} cube.",
    ),
    "first_person": (
        "I want the {top} block on the {bottom} block.",
        "I need the {top} cube sitting on the {bottom} cube.",
        "I'd like the {top} block placed on top of the {bottom} block.",
        "We need the {top} block stacked on the {bottom} block.",
        "I'd like to see the {top} block on the {bottom} one.",
    ),
    "casual": (
        "{top} on {bottom}.",
        "Stick the {top} one on the {bottom} one.",
        "Pop the {top} block on the {bottom} block.",
        "Chuck the {top} cube on top of the {bottom} cube.",
        "{top} cube goes on the {bottom} cube.",
    ),
    "result": (
        "Make it so the {top} block rests on the {bottom} block.",
        "The {top} block should end up on the {bottom} block.",
        "Arrange things so that the {top} cube sits on the {bottom} cube.",
        "Finish with the {top} block on top of the {bottom} block.",
        "Leave the {top} cube resting on the {bottom} cube.",
    ),
    "with": (
        "Cover the {bottom} block with the {top} block.",
        "Top the {bottom} cube with the {top} cube.",
        "Use the {bottom} block as a base for the {top} block.",
        "With the {bottom} block at the bottom, put the {top} block on it.",
        "Support the {top} cube with the {bottom} cube.",
    ),
    "anaphora": (
        "Take the {top} block and put it on the {bottom} block.",
        "Find the {bottom} cube and place the {top} cube on it.",
        "See the {bottom} block? Put the {top} block on top of it.",
        "The {top} block: stack it on the {bottom} block.",
        "Pick the {top} cube up and lower it onto the {bottom} cube.",
    ),
}
"""60 relation sentences, 12 frames."""

TOWERS: tuple[str, ...] = (
    "Please build a tower out of all four blocks.",
    "Could you stack all four cubes into a single tower?",
    "stack every block into one tower",
    "I want all four blocks in one tower.",
    "Make one tall tower using every cube.",
    "Put all the blocks into a single stack.",
    "Can you pile all four blocks up into one tower?",
    "All four cubes, one tower, please.",
)
"""The tower sentence of a stacking instruction with one relation."""


def relation_sentences() -> tuple[str, ...]:
    """Every relation sentence, frame by frame."""
    return tuple(s for frame in RELATIONS.values() for s in frame)
