"""Instructions to subword ids with a pretrained tokenizer's ``tokenizer.json``, read by the
``tokenizers`` library (the maintained Rust tokenizer: no hand-written WordPiece here).

Any text is accepted: a word the vocabulary lacks is split into known pieces, or becomes the
unknown token. Only an empty instruction and one longer than the fixed length are refused,
each with one line.
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
import tokenizers

DEFAULT_LENGTH = 64
"""Tokens per instruction, ``[CLS]`` and ``[SEP]`` included. The project's longest instruction
(three Kuka relations in the longest phrasing) is 41 tokens; 64 leaves room for a person's
own wording of three relations, and stays cheap for the encoder and a cross-attention."""


@dataclasses.dataclass(frozen=True, eq=False)
class Subwords:
    """A tokenizer read from ``tokenizer.json`` text, its own padding and truncation off.

    tokenizer: the ``tokenizers.Tokenizer``; pad_id: the id written after an instruction's
    last token (masked out, so any id in the vocabulary would do); max_length: the most
    tokens the encoder behind it has positions for."""
    tokenizer: tokenizers.Tokenizer
    pad_id: int
    max_length: int

    def tokenize(self, texts: str | Sequence[str], length: int = DEFAULT_LENGTH):
        """Instructions -> (ids int32, mask bool), each (B, length); a single string gives
        shape (length,). Each row is ``[CLS] tokens [SEP]`` then ``pad_id``; mask is true at
        real tokens (the special ones included).

        Raises ValueError (one line) for an empty instruction (no token but the special ones),
        one longer than ``length`` tokens (naming the limit), an empty batch, or a length
        outside 2..max_length.
        """
        if not 2 <= length <= self.max_length:
            raise ValueError(f"length {length} is outside 2..{self.max_length} (the "
                             f"encoder's positions)")
        single = isinstance(texts, str)
        batch = [texts] if single else list(texts)
        if not batch:
            raise ValueError("no instruction to tokenize (an empty batch)")
        for i, text in enumerate(batch):
            if not isinstance(text, str):
                raise ValueError(f"instruction {i} is a {type(text).__name__}, not a string")
        encodings = self.tokenizer.encode_batch(batch, add_special_tokens=True)
        ids = np.full((len(batch), length), self.pad_id, np.int32)
        mask = np.zeros((len(batch), length), bool)
        for i, encoding in enumerate(encodings):
            n = len(encoding.ids)
            if all(encoding.special_tokens_mask):
                raise ValueError(f"instruction {i} is empty: {batch[i]!r} has no word")
            if n > length:
                raise ValueError(f"instruction {i} is {n} tokens long, over the limit of "
                                 f"{length} ([CLS] and [SEP] included): {_clip(batch[i])}")
            ids[i, :n] = encoding.ids
            mask[i, :n] = True
        return (ids[0], mask[0]) if single else (ids, mask)


def _clip(text: str, chars: int = 60) -> str:
    """text's repr, cut after ``chars`` characters."""
    return repr(text) if len(text) <= chars else repr(text[:chars]) + "..."


def read_subwords(text: str, vocab_size: int, max_length: int,
                  pad_id: int | None = None) -> Subwords:
    """A :class:`Subwords` from the text of a ``tokenizer.json``.

    vocab_size: the encoder's embedding rows (a tokenizer with more ids is refused: they would
    index past the table); max_length: the encoder's positions; pad_id: the config's
    ``pad_token_id`` if it has one, else the tokenizer's padding id, else 0.
    Raises ValueError (one line) if the text is not a tokenizer the library reads.
    """
    try:
        tokenizer = tokenizers.Tokenizer.from_str(text)
    except Exception as e:  # the library raises a bare Exception on malformed JSON
        raise ValueError(f"tokenizer.json is not a tokenizer the tokenizers library reads: "
                         f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    if tokenizer.get_vocab_size(with_added_tokens=True) > vocab_size:
        raise ValueError(f"tokenizer.json has {tokenizer.get_vocab_size(True)} tokens, more "
                         f"than the encoder's {vocab_size} embeddings")
    if pad_id is None:
        padding = tokenizer.padding
        pad_id = padding["pad_id"] if padding else 0
    tokenizer.no_padding()
    tokenizer.no_truncation()
    return Subwords(tokenizer, int(pad_id), max_length)
