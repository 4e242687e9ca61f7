"""Word-level instruction language shared by the worlds: vocabulary, tokenizer, templates.

Both worlds describe their instructions with templates, plain sentences with named slots
(``"Go to the {target}."``). A world builds a :class:`Vocabulary` from its templates and its slot
fillers, compiles each template once into an int32 array of token ids in which slot ``k`` is the
negative marker ``-(k + 1)`` (:func:`compile_template`), and fills the markers inside ``jit``
with :func:`fill_slots`: instructions are produced in JAX as token ids and turned into text only
for export (:meth:`Vocabulary.decode`). :func:`concat_segments` joins several compiled sentences
into one padded instruction under ``jit`` (the Kuka world's multi-sentence instructions).

Token id 0 is padding in every vocabulary. Text is lower-cased and split into words and the
punctuation tokens '.' and ','; decoding re-attaches punctuation and capitalises sentences.
"""
from __future__ import annotations

import re
from typing import Iterable, Mapping, Sequence

import numpy as np

PAD_ID = 0

_WORD_RE = re.compile(r"\{[a-z]+\}|[a-z]+|[.,]|[^\sa-z.,]+")


def split_words(text: str) -> list[str]:
    """Lower-cases and splits text into words and punctuation tokens ('.' and ','); a slot
    ``{name}`` stays one token; any other run of characters (digits, '!', ...) becomes a word of
    its own (outside every vocabulary)."""
    return _WORD_RE.findall(text.lower())


def template_words(templates: Iterable[str], slots: Iterable[str] = ()) -> set[str]:
    """Every word of the templates except their slot tokens (``"{name}"``)."""
    slots = set(slots)
    words: set[str] = set()
    for template in templates:
        words.update(w for w in split_words(template) if w not in slots)
    return words


class Vocabulary:
    """A fixed word list: word i has token id i; ``specials`` (their ids first, id 0 the
    padding) never come out of :meth:`encode` and are dropped by :meth:`decode` where they
    are padding."""

    def __init__(self, words: Sequence[str], num_specials: int = 1):
        words = tuple(words)
        if len(set(words)) != len(words):
            raise ValueError("vocabulary words must be unique")
        self.words = words
        self.word_to_id = {w: i for i, w in enumerate(words)}
        self.specials = words[:num_specials]

    def __len__(self) -> int:
        return len(self.words)

    def encode(self, text: str, max_tokens: int) -> np.ndarray:
        """text -> int32 (max_tokens,) ids padded with 0.

        Raises ValueError naming every word outside the vocabulary, if the text is empty, or
        if it is too long.
        """
        if not isinstance(text, str):
            raise ValueError(f"an instruction must be a str, got {type(text).__name__}")
        words = split_words(text)
        if not words:
            raise ValueError("the instruction is empty")
        unknown = sorted({w for w in words if w not in self.word_to_id or w in self.specials})
        if unknown:
            raise ValueError(f"instruction has words outside the vocabulary: {unknown}")
        if len(words) > max_tokens:
            raise ValueError(f"instruction has {len(words)} tokens, more than "
                             f"max_tokens={max_tokens}")
        ids = np.zeros(max_tokens, np.int32)
        ids[: len(words)] = [self.word_to_id[w] for w in words]
        return ids

    def decode(self, ids) -> str:
        """int token ids (padding 0 dropped) -> text with punctuation re-attached and the first
        letter of each sentence capitalised."""
        words = [self.words[int(i)] for i in np.asarray(ids).ravel() if int(i) != PAD_ID]
        text = re.sub(r" ([.,])", r"\1", " ".join(words))
        return re.sub(r"(^|[.] )([a-z])", lambda m: m.group(1) + m.group(2).upper(), text)

    def compile(self, template: str, slots: Sequence[str], length: int) -> np.ndarray:
        """See :func:`compile_template`."""
        return compile_template(template, self, slots, length)


def compile_template(template: str, vocab: Vocabulary, slots: Sequence[str],
                     length: int) -> np.ndarray:
    """A template as int32 (length,) token ids, padded with 0, in which the slot token
    ``slots[k]`` (e.g. ``"{target}"``) is the marker ``-(k + 1)``."""
    markers = {s: -(k + 1) for k, s in enumerate(slots)}
    words = split_words(template)
    if len(words) > length:
        raise ValueError(f"template {template!r} has {len(words)} tokens, more than {length}")
    row = np.zeros(length, np.int32)
    row[: len(words)] = [markers[w] if w in markers else vocab.word_to_id[w] for w in words]
    return row


def fill_slots(template_ids, slot_tokens):
    """Replaces slot marker ``-(k + 1)`` by ``slot_tokens[k]``; jnp-compatible (works in jit).

    template_ids: int (L,) a compiled template; slot_tokens: int (S,) one token id per slot.
    Returns int32 (L,).
    """
    import jax.numpy as jnp

    template_ids = jnp.asarray(template_ids)
    slot_tokens = jnp.asarray(slot_tokens)
    out = template_ids
    for k in range(slot_tokens.shape[0]):
        out = jnp.where(template_ids == -(k + 1), slot_tokens[k], out)
    return out.astype(jnp.int32)


def concat_segments(segments, lengths, max_tokens: int):
    """Joins token segments into one padded sequence; jnp-compatible (works in jit).

    segments: int (K, S) token ids, segment k's first lengths[k] entries are its tokens;
    lengths: int (K,) (0 drops a segment). Returns int32 (max_tokens,): the segments back to
    back, padded with 0 (tokens past max_tokens are dropped).
    """
    import jax.numpy as jnp

    segments = jnp.asarray(segments)
    lengths = jnp.asarray(lengths)
    num, size = segments.shape
    starts = jnp.cumsum(lengths) - lengths
    cols = jnp.arange(size)
    where = jnp.where(cols[None, :] < lengths[:, None], starts[:, None] + cols[None, :],
                      max_tokens)
    out = jnp.zeros(max_tokens, jnp.int32)
    return out.at[where.ravel()].set(segments.ravel().astype(jnp.int32), mode="drop")


def lengths_of(compiled: np.ndarray) -> np.ndarray:
    """int32 (...,) number of tokens (non-padding entries) of compiled templates (..., L)."""
    return (np.asarray(compiled) != PAD_ID).sum(-1).astype(np.int32)


def render(template: str, fillers: Mapping[str, str]) -> str:
    """Plain-Python rendering of a template, slot names without braces (``{"target": ...}``)."""
    return template.format(**fillers)
