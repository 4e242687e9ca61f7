"""The slots of an instruction in any phrasing: which word names the reference, the target and
the compass direction (what the baselines' goal vector, the searcher and the exact-posterior
denoiser read of an instruction; the denoiser reads the words themselves)."""
from __future__ import annotations

import jax.numpy as jnp

from envs.gridworld import grammar

__all__ = ["NUM_CLASSES", "instruction_slots", "instruction_cells"]

NUM_CLASSES = len(grammar.OBJECT_NAMES)
"""Object classes an instruction can name."""


def _heuristic_slots(tokens):
    """(ref, target, dir) token ids int32 () of one instruction none of the grammar's phrasings
    matches: the target is the last object word, the reference the first when there are two,
    the direction the first direction word (0 where absent)."""
    length = tokens.shape[-1]
    cls = tokens - grammar.OBJECT_TOKEN_OFFSET
    is_object = (cls >= 0) & (cls < NUM_CLASSES)
    pos = jnp.arange(length)
    last = jnp.argmax(jnp.where(is_object, pos, -1))
    first = jnp.argmax(jnp.where(is_object, length - pos, -1))
    count = jnp.sum(is_object)
    is_dir = jnp.any(tokens[:, None] == jnp.asarray(grammar.DIRECTION_TOKEN_IDS), axis=-1)
    return (jnp.where(count >= 2, tokens[first], 0), jnp.where(count >= 1, tokens[last], 0),
            jnp.where(jnp.any(is_dir), tokens[jnp.argmax(is_dir)], 0))


def instruction_slots(tokens):
    """(ref, target, dir) token ids int32 () of one instruction int32 (L,): the words in the
    slots of whichever of the grammar's phrasings it is (``grammar.parse``), else those of
    :func:`_heuristic_slots`; 0 where the instruction has no such slot."""
    matched, *slots = grammar.parse(tokens)
    return tuple(jnp.where(matched, a, b) for a, b in zip(slots, _heuristic_slots(tokens)))


def instruction_cells(cells, tokens):
    """Where the instruction's words are on the map: (reference bool (H, W), target bool (H, W),
    direction int32 () the compass sector 0..7 its direction word names, -1 if none). cells
    int32 (H, W) the condition's cell tokens (unseen cells hold no object token, so only seen
    cells match); tokens int32 (L,) the instruction."""
    ref_token, target_token, dir_token = instruction_slots(tokens)
    reference = (cells == ref_token) & (ref_token > 0)
    target = (cells == target_token) & (target_token > 0)
    is_direction = jnp.asarray(grammar.DIRECTION_TOKEN_IDS) == dir_token
    direction = jnp.where(jnp.any(is_direction), jnp.argmax(is_direction), -1)
    return reference, target, direction
