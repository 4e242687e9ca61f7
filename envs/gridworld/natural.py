"""SEALED natural-language test set of the grid world (``--language natural``).

Written and committed before any denoiser was trained on the pretrained text encoder's
features, and never used for a choice: no training batch draws it, no setting, recipe,
checkpoint or threshold is chosen on it; it is measured once, at the end of the work that
produces a model, and reported whatever comes out. tests/test_natural_language.py pins its
digest, so a later edit shows.

Sentences as people type them, grouped by frame (a way of phrasing): polite forms, questions,
commas and "then", synonyms (locate, head, proceed, make your way), clause order reversed
(the target named first), preposition-first, lower case without punctuation, hyphenated
directions ("north-east"), first person, casual, "before"/"after" constructions and
anaphora. Slots: ``{ref}``, ``{target}``, ``{dir}`` (a compass direction, e.g. "northeast")
and ``{dir_h}`` (the same direction hyphenated, e.g. "north-east"; "north" stays "north").
"""
from __future__ import annotations

VIA_REFERENCE: dict[str, tuple[str, ...]] = {
    "polite": (
        "Please go to the {ref} first, and then find the {target} to the {dir} of it.",
        "Could you please visit the {ref} first? After that, the {target} is {dir} of it.",
        "Would you mind heading to the {ref} first and then looking {dir} of it for the "
        "{target}?",
        "Kindly walk over to the {ref}, then search {dir} of it until you find the {target}.",
        "If you could, stop by the {ref} first; the {target} should be somewhere {dir} of it.",
    ),
    "question": (
        "Can you go to the {ref} and then find the {target}, which is {dir} of it?",
        "Could you locate the {ref} first and then look {dir} from there for the {target}?",
        "Will you visit the {ref} before finding the {target} to its {dir}?",
        "Can you find the {target}? It is {dir} of the {ref}, so go to the {ref} first.",
        "Why not start at the {ref} and then go {dir} to the {target}?",
    ),
    "commas_then": (
        "Go to the {ref}, then go {dir}, then find the {target}.",
        "First the {ref}, then the {target}, which lies {dir} of it.",
        "Walk to the {ref}, turn {dir}, and keep going until you reach the {target}.",
        "Reach the {ref}, then, from there, head {dir} to the {target}.",
        "Start with the {ref}, then continue {dir} to get to the {target}.",
    ),
    "synonyms": (
        "Locate the {ref}, then proceed {dir} to locate the {target}.",
        "Make your way to the {ref} and then proceed {dir} toward the {target}.",
        "Head for the {ref}; afterwards, travel {dir} to reach the {target}.",
        "Seek out the {ref} first, then move {dir} and track down the {target}.",
        "Approach the {ref}, then advance {dir} until you arrive at the {target}.",
    ),
    "target_first": (
        "The {target} you want is {dir} of the {ref}; visit the {ref} first.",
        "Find the {target}, which sits {dir} of the {ref}, but stop at the {ref} first.",
        "Your destination is the {target}, located {dir} of the {ref}, so go to the {ref} "
        "before anything else.",
        "To reach the {target}, first go to the {ref}; the {target} is {dir} from there.",
        "The {target} is hidden somewhere {dir} of the {ref}. Begin at the {ref}.",
    ),
    "preposition_first": (
        "{dir_h} of the {ref} is the {target}; go to the {ref} first.",
        "To the {dir} of the {ref} you will find the {target}, but visit the {ref} first.",
        "From the {ref}, head {dir} to find the {target}; start by going to the {ref}.",
        "After the {ref}, go {dir} and you will come to the {target}.",
        "Beyond the {ref}, to the {dir}, lies the {target}. Go to the {ref} first.",
    ),
    "lower_case": (
        "go to the {ref} then go {dir} to the {target}",
        "first find the {ref} and then the {target} which is {dir} of it",
        "visit the {ref} then look {dir} for the {target}",
        "head to the {ref} first then {dir} to the {target}",
        "go to the {ref} and after that go {dir} to find the {target}",
    ),
    "hyphenated": (
        "Go to the {ref} first; the {target} is {dir_h} of it.",
        "Visit the {ref}, then head {dir_h} to find the {target}.",
        "The {target} lies {dir_h} of the {ref}. Go to the {ref} first.",
        "Start at the {ref} and walk {dir_h} until you see the {target}.",
        "From the {ref}, go {dir_h}; that is where the {target} is. Go to the {ref} first.",
    ),
    "first_person": (
        "I want you to go to the {ref} first and then find the {target} {dir} of it.",
        "I need the {target}, which is {dir} of the {ref}; please go to the {ref} first.",
        "I'd like you to visit the {ref}, then go {dir} to the {target}.",
        "We should go to the {ref} first, then look {dir} for the {target}.",
        "I think the {target} is {dir} of the {ref}, so go there after the {ref}.",
    ),
    "casual": (
        "Hit the {ref} first, then the {target} over to the {dir}.",
        "Swing by the {ref}, then grab the {target} {dir} of it.",
        "{ref} first, then {target}, it's {dir} of the {ref}.",
        "Ok, go to the {ref}, and the {target} is a bit {dir} of there.",
        "Check out the {ref}, then go get the {target} to the {dir}.",
    ),
    "before_after": (
        "Before you look for the {target}, go to the {ref}; the {target} is {dir} of it.",
        "After visiting the {ref}, go {dir} to find the {target}.",
        "Once you are at the {ref}, the {target} is to the {dir}.",
        "Only after reaching the {ref} should you go {dir} to the {target}.",
        "Do not go to the {target} until you have been to the {ref}; it lies {dir} of the "
        "{ref}.",
    ),
    "anaphora": (
        "There is a {ref} nearby. Go to it, then go {dir} of it to find the {target}.",
        "Go to the {ref}. From it, the {target} is to the {dir}.",
        "Find the {ref}. Once there, look {dir}: that is where the {target} is.",
        "See the {ref}? Go there first. The {target} is {dir} of it.",
        "The {ref} is your first stop. Past it, to the {dir}, is the {target}.",
    ),
}
"""Go to the reference first; the target lies in a direction from it (P-MO2G, P-MO2G-far):
60 sentences, 12 frames."""

GOAL_ONLY: dict[str, tuple[str, ...]] = {
    "polite": (
        "Please go to the {target}.",
        "Could you please walk to the {target}?",
        "Kindly make your way to the {target}.",
        "Would you mind going over to the {target}?",
        "If you could, head to the {target}, please.",
    ),
    "question": (
        "Can you go to the {target}?",
        "Could you locate the {target} for me?",
        "Will you find the {target}?",
        "Can you get to where the {target} is?",
        "Why not go to the {target}?",
    ),
    "commas_then": (
        "Look around, then go to the {target}.",
        "Find the {target}, then stop there.",
        "Go to the {target}, and stay there.",
        "Walk, carefully, to the {target}.",
        "Find the {target}, then stand on it.",
    ),
    "synonyms": (
        "Locate the {target}.",
        "Proceed to the {target}.",
        "Head for the {target}.",
        "Make your way to the {target}.",
        "Seek out the {target}.",
    ),
    "target_first": (
        "The {target} is your destination.",
        "The {target} is where I want you.",
        "The {target}: go there.",
        "The {target} is the thing to reach.",
        "The {target}, that is where you need to be.",
    ),
    "preposition_first": (
        "To the {target}, please.",
        "Over to the {target} you go.",
        "Towards the {target}, go.",
        "At the {target} is where you should end up.",
        "Next to nothing else but the {target}: go there.",
    ),
    "lower_case": (
        "go to the {target}",
        "find the {target}",
        "walk to the {target}",
        "head to the {target}",
        "get to the {target}",
    ),
    "first_person": (
        "I want you to go to the {target}.",
        "I need you at the {target}.",
        "I'd like you to find the {target}.",
        "We should go to the {target}.",
        "I think you should walk to the {target}.",
    ),
    "casual": (
        "Hit the {target}.",
        "Grab the {target}.",
        "Ok, go get the {target}.",
        "Swing by the {target}.",
        "Check out the {target}.",
    ),
    "goal_words": (
        "Your target is the {target}.",
        "The goal: the {target}.",
        "Your task is to reach the {target}.",
        "Get yourself to the {target}.",
        "Aim for the {target}.",
    ),
    "before_after": (
        "Before doing anything else, go to the {target}.",
        "After looking around, walk to the {target}.",
        "Once you see the {target}, go to it.",
        "Go to the {target} and then you are done.",
        "Don't stop until you reach the {target}.",
    ),
    "anaphora": (
        "There is a {target} here. Go to it.",
        "See the {target}? Go there.",
        "Find the {target} and stand on it.",
        "The {target} is somewhere around. Get to it.",
        "Look for the {target}. Once you see it, walk to it.",
    ),
}
"""Go to the target (1O1G, MO1G): 60 sentences, 12 frames."""


def sentences(has_reference: bool) -> tuple[str, ...]:
    """Every sentence of the set for settings with a reference or without, frame by frame."""
    table = VIA_REFERENCE if has_reference else GOAL_ONLY
    return tuple(s for frame in table.values() for s in frame)


def hyphenated(direction: str) -> str:
    """'northeast' -> 'north-east' (the {dir_h} slot); 'north' stays 'north'."""
    for half in ("north", "south"):
        if direction.startswith(half) and direction != half:
            return f"{half}-{direction[len(half):]}"
    return direction
