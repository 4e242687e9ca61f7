"""The GoTo missions' language: "go to the {color} {type}" ("a" when several objects match).

minigrid's GoTo levels phrase every mission with ``GoToInstr(ObjDesc(type, color))``: "go to",
an article ("the" when one object matches the description, else "a"), a colour and an object
type (key, ball or box; the levels here never describe a door or a location). :func:`parse`
reads that grammar and refuses anything else in one line; :func:`encode` gives the default
token ids (this module's own word vocabulary; a pretrained tokenizer may replace it, see
``BabyAIConfig.tokenizer``).
"""
from __future__ import annotations

import re

import numpy as np

from diffplan.language import Vocabulary

COLORS = ("red", "green", "blue", "purple", "yellow", "grey")
"""minigrid's colours in the order of their indices (``COLOR_TO_IDX``)."""
TYPES = ("key", "ball", "box")
"""The object types a GoTo mission of these levels names."""
TYPE_INDEX = {"key": 5, "ball": 6, "box": 7}
"""minigrid's type index (``OBJECT_TO_IDX``) of each named type."""
WORDS = ("<pad>", "go", "to", "the", "a") + COLORS + TYPES
VOCAB = Vocabulary(WORDS)
VOCAB_SIZE = len(WORDS)
MAX_TOKENS = 8
"""Token ids per instruction (a GoTo mission has 5 words; 8 leaves room for a tokenizer's
start and end markers)."""

_MISSION = re.compile(r"go to (the|a) (" + "|".join(COLORS) + r") (" + "|".join(TYPES) + r")")


def parse(mission: str) -> tuple[int, int]:
    """(minigrid colour index, minigrid type index) of the object a GoTo mission names; a
    ValueError of one line for a mission outside the grammar."""
    match = _MISSION.fullmatch(mission.strip()) if isinstance(mission, str) else None
    if match is None:
        raise ValueError(f"mission {mission!r} is outside the GoTo grammar "
                         "'go to the|a <color> <key|ball|box>'")
    return COLORS.index(match.group(2)), TYPE_INDEX[match.group(3)]


def encode(mission: str, max_tokens: int = MAX_TOKENS) -> np.ndarray:
    """int32 (max_tokens,) ids of a GoTo mission's words (0 = padding)."""
    parse(mission)
    return VOCAB.encode(mission, max_tokens)


def decode(ids) -> str:
    """The words of token ids (padding dropped)."""
    return VOCAB.decode(ids).lower()
