"""Static configuration of the BabyAI levels (hashable: usable as a jit static argument).

A level here is one of minigrid's BabyAI GoTo levels (:data:`LEVELS`); its geometry (rooms of
``room_size`` cells in a ``num_rows`` x ``num_cols`` grid of rooms, sharing walls) and its step
limit are minigrid's (``RoomGrid``: side ``(room_size - 1) * rooms + 1``; ``RoomGridLevel``:
``max_steps = room_size ** 2 * num_rows * num_cols`` for a mission of one navigation).
"""
from __future__ import annotations

import dataclasses
import re
from typing import Callable, Optional

import numpy as np

from envs.babyai import grammar


@dataclasses.dataclass(frozen=True)
class Level:
    """A BabyAI level the Task plans: minigrid's id and the geometry its generator uses."""

    env_id: str
    num_rows: int
    num_cols: int
    room_size: int = 8


LEVELS = {
    "goto_local": Level("BabyAI-GoToLocal-v0", 1, 1),
    "goto_obj_maze": Level("BabyAI-GoToObjMaze-v0", 3, 3),
    "goto": Level("BabyAI-GoTo-v0", 3, 3),
}
"""The registered levels: GoToLocal (one 8 x 8 room, 8 distractors), GoToObjMaze (3 x 3
rooms behind closed doors, one object besides the target), GoTo (3 x 3 rooms, 18 objects)."""


def level_name(name: str) -> str:
    """A level's name here from its own name or its minigrid id (``BabyAI-GoTo-v0`` ->
    ``goto``); a ValueError of one line for another BabyAI level (a minigrid id, or the start
    of one in any case and spelling: ``PutNext``, ``put_next_local``; the Task plans the GoTo
    levels of :data:`LEVELS` only) or an unknown name."""
    if name in LEVELS:
        return name
    for key, level in LEVELS.items():
        if name == level.env_id:
            return key
    plannable = ", ".join(LEVELS)
    squashed = _squash(name) if isinstance(name, str) else ""
    if len(squashed) >= 4 and any(level.startswith(squashed) for level in _babyai_levels()):
        raise ValueError(f"the BabyAI level {name!r} is not one the Task can plan (it plans the "
                         f"GoTo navigation levels {plannable})")
    raise ValueError(f"unknown BabyAI level {name!r}; plannable levels: {plannable}")


def _squash(name: str) -> str:
    """A level's name without case, underscores, dashes, the 'babyai' prefix or a '-v0'."""
    name = re.sub(r"-v\d+$", "", name.lower())
    return re.sub(r"^babyai", "", re.sub(r"[-_ ]", "", name))


def _babyai_levels() -> set[str]:
    """Every BabyAI level minigrid registers, squashed (:func:`_squash`): 'putnextlocal', ..."""
    import gymnasium
    import minigrid  # noqa: F401  (registers the levels)

    return {_squash(env_id) for env_id in gymnasium.registry if env_id.startswith("BabyAI-")}


@dataclasses.dataclass(frozen=True)
class BabyAIConfig:
    """One BabyAI level as the Task sees it.

    Attributes:
      level: a key of :data:`LEVELS` (or its minigrid id, normalised to the key).
      pad_multiple: the planning map is the level's grid padded (bottom and right, with wall
        cells) to a multiple of this: a denoiser's ``DenoiserConfig.min_size_multiple`` (4 for
        three UNet levels: GoToLocal 8 -> 8, GoTo 22 -> 24).
      max_tokens: L, the length of an episode's instruction token array.
      tokenizer: mission string -> int32 (max_tokens,) token ids (0 = padding); None is the
        GoTo grammar's own word vocabulary (:func:`envs.babyai.grammar.encode`). A pretrained
        tokenizer (e.g. a BERT word-piece one) plugs in here; the ids only reach the denoiser's
        text encoder.
    """

    level: str = "goto_local"
    pad_multiple: int = 4
    max_tokens: int = grammar.MAX_TOKENS
    tokenizer: Optional[Callable[[str], np.ndarray]] = None

    def __post_init__(self):
        object.__setattr__(self, "level", level_name(self.level))
        if not isinstance(self.pad_multiple, int) or self.pad_multiple < 1:
            raise ValueError(f"pad_multiple must be an int >= 1, got {self.pad_multiple!r}")
        if not isinstance(self.max_tokens, int) or self.max_tokens < 1:
            raise ValueError(f"max_tokens must be an int >= 1, got {self.max_tokens!r}")
        if self.tokenizer is not None and not callable(self.tokenizer):
            raise ValueError(f"tokenizer must be callable or None, got {self.tokenizer!r}")

    @property
    def spec(self) -> Level:
        return LEVELS[self.level]

    @property
    def env_id(self) -> str:
        return self.spec.env_id

    @property
    def height(self) -> int:
        """Rows of the level's grid (minigrid's ``height``)."""
        return (self.spec.room_size - 1) * self.spec.num_rows + 1

    @property
    def width(self) -> int:
        """Columns of the level's grid (minigrid's ``width``)."""
        return (self.spec.room_size - 1) * self.spec.num_cols + 1

    @property
    def map_height(self) -> int:
        """Rows of the planning map: height padded up to a multiple of pad_multiple."""
        return -(-self.height // self.pad_multiple) * self.pad_multiple

    @property
    def map_width(self) -> int:
        return -(-self.width // self.pad_multiple) * self.pad_multiple

    @property
    def max_steps(self) -> int:
        """minigrid's step limit of a one-navigation mission on this level."""
        s = self.spec
        return s.room_size ** 2 * s.num_rows * s.num_cols

    def tokenize(self, mission: str) -> np.ndarray:
        """int32 (max_tokens,) token ids of a mission; a ValueError of one line for a mission
        outside the GoTo grammar (checked whatever the tokenizer)."""
        grammar.parse(mission)
        if self.tokenizer is None:
            return grammar.encode(mission, self.max_tokens)
        ids = np.asarray(self.tokenizer(mission))
        if ids.shape != (self.max_tokens,) or not np.issubdtype(ids.dtype, np.integer):
            raise ValueError(f"the tokenizer must return {self.max_tokens} integer ids, got "
                             f"shape {ids.shape} of {ids.dtype}")
        return ids.astype(np.int32)


def make_config(level: str, **overrides) -> BabyAIConfig:
    """The configuration of a level (its name or minigrid id); overrides are BabyAIConfig
    fields."""
    return BabyAIConfig(level=level, **overrides)
