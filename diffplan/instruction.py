"""An instruction as the token features of a frozen pretrained text encoder, sentence by
sentence: what a denoiser with ``DenoiserConfig.context_dim > 0`` cross-attends to. No world
here: a world renders its phrasings into text and, for training, lists its sentences.

The text path (any English text, at evaluation and for a user's own sentence)::

    enc = InstructionEncoder(load_text_encoder(), max_tokens=48)
    feats = enc.encode("First go to the apple. Then find the pear north of it.")  # (48, 384)

The text is split into sentences (:func:`split_sentences`: after ``.``, ``?`` or ``!``
followed by a space or the end; a text without one is one sentence), each sentence is encoded
on its own (``[CLS] wordpieces [SEP]``, as the encoder's tokenizer makes them), and the
sentences' token features are concatenated in order into float32 (L, D), zeros after the last
real token. Only an empty instruction, or one of more than L wordpieces in all (each
sentence's ``[CLS]`` and ``[SEP]`` counted), is refused (one line naming the limit).

The table path (training): :meth:`InstructionEncoder.table` computes every listed sentence's
features once (cached on disk under ``~/.cache/diffplan/text-features``, keyed by the encoder's
file hashes and the sentences), and :func:`assemble` (pure, jit-able) concatenates the listed
sentences' features exactly as the text path does: ``assemble(table, ids) ==
encode(text of those sentences)``, bit for bit (tests/test_instruction.py). Pass the table to
jitted code as an argument (``diffplan.train.train(..., sentences=table)``), never as a
constant.

Exactness: a sentence's features depend on that sentence only. Each is computed by one
compiled program per width (its wordpieces rounded up to a multiple of :data:`COLUMNS`), in
chunks of :data:`CHUNK` rows, and the encoder's rows are independent; the features are then
rounded to float16 (the table's storage; at most 0.004 from float32 at |x| <= 8, beside the
encoder's own float16 weights, which move them by up to 0.0031) and used as float32.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import re
from typing import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from diffplan import bert

__all__ = ["split_sentences", "SentenceTable", "assemble", "assemble_batch",
           "InstructionEncoder", "encoder_record", "load_instruction_encoder", "CACHE_DIR",
           "TEXTS", "check_text", "encode_cached", "instruction_lengths", "shared_encoder",
           "instruction_of", "fitting_table", "text_metadata", "check_phrasings"]

CACHE_DIR = "~/.cache/diffplan/text-features"
"""Where sentence tables are cached (``$DIFFPLAN_TEXT_CACHE`` overrides it)."""
CHUNK = 16
"""Sentences per call of the encoder (the last chunk of a width is padded to it). Measured on
this CPU: 3.4 ms of CPU per sentence of 16 columns at 16 rows, 2.9 at 64, but one sentence
alone 54 ms against 185: a user's instruction is encoded at once."""
COLUMNS = 16
"""A sentence is encoded at its wordpieces rounded up to a multiple of this."""
FORMAT = 1
"""Version of the cached tables' layout (part of their key)."""
_SENTENCE_END = re.compile(r"(?<=[.?!])\s+")
_encode = jax.jit(bert.features, static_argnames="config")
"""The encoder's forward, one compiled program per width, shared by every InstructionEncoder."""


def split_sentences(text: str) -> list[str]:
    """The sentences of a text: split after ``.``, ``?`` or ``!`` followed by whitespace (the
    punctuation stays with its sentence), stripped, empty ones dropped. A text without such
    punctuation is one sentence; ``"3.5"`` or ``"e.g.the"`` do not split."""
    if not isinstance(text, str):
        raise ValueError(f"an instruction must be a str, got {type(text).__name__}")
    return [s for s in (part.strip() for part in _SENTENCE_END.split(text.strip())) if s]


class SentenceTable(struct.PyTreeNode):
    """The token features of N sentences, back to back (a pytree: pass it to jitted functions
    as an argument).

    features: float16 (T, D), sentence n's real tokens at rows start[n] .. start[n] +
      length[n] - 1 (``[CLS]`` and ``[SEP]`` included). start, length: int32 (N,).
    max_tokens: L, the length :func:`assemble` writes (static).
    """

    features: jax.Array
    start: jax.Array
    length: jax.Array
    max_tokens: int = struct.field(pytree_node=False)

    @property
    def num_sentences(self) -> int:
        return int(self.start.shape[0])

    @property
    def dim(self) -> int:
        return int(self.features.shape[-1])


def assemble(table: SentenceTable, sentence_ids) -> jax.Array:
    """The features of an instruction made of the listed sentences, in order: float32 (L, D),
    zeros after the last real token. sentence_ids int (S,): rows of the table, -1 = absent
    (skipped wherever it stands). Tokens past L are dropped (the caller checks its
    instructions fit). Pure and jit-able; vmap for a batch (:func:`assemble_batch`)."""
    ids = jnp.asarray(sentence_ids, jnp.int32)
    present = ids >= 0
    safe = jnp.maximum(ids, 0)
    lengths = jnp.where(present, table.length[safe], 0)
    ends = jnp.cumsum(lengths)
    starts = ends - lengths
    column = jnp.arange(table.max_tokens, dtype=jnp.int32)
    slot = jnp.sum(column[:, None] >= ends[None, :], axis=1)  # the sentence of each column
    real = slot < ids.shape[0]
    slot = jnp.minimum(slot, ids.shape[0] - 1)
    row = table.start[safe[slot]] + column - starts[slot]
    row = jnp.clip(row, 0, table.features.shape[0] - 1)
    out = jnp.take(table.features, row, axis=0).astype(jnp.float32)
    return jnp.where(real[:, None], out, 0.0)


def assemble_batch(table: SentenceTable, sentence_ids) -> jax.Array:
    """:func:`assemble` over leading axes: sentence_ids int (..., S) -> float32 (..., L, D)."""
    ids = jnp.asarray(sentence_ids)
    flat = ids.reshape((-1, ids.shape[-1]))
    out = jax.vmap(assemble, in_axes=(None, 0))(table, flat)
    return out.reshape(ids.shape[:-1] + out.shape[-2:])


def _clip(text: str, chars: int = 60) -> str:
    return repr(text) if len(text) <= chars else repr(text[:chars]) + "..."


class InstructionEncoder:
    """Instructions -> token features with a frozen :class:`PretrainedTextEncoder`, at a fixed
    length ``max_tokens`` (L). Keeps every sentence it encoded in memory (float16), so a
    sentence shared by many instructions is encoded once."""

    def __init__(self, encoder, max_tokens: int, cache_dir: str | None = None):
        if not 2 <= max_tokens <= encoder.config.max_position_embeddings:
            raise ValueError(f"max_tokens {max_tokens} is outside 2.."
                             f"{encoder.config.max_position_embeddings} (the encoder's positions)")
        self.encoder = encoder
        self.max_tokens = int(max_tokens)
        self.cache_dir = os.path.expanduser(
            cache_dir or os.environ.get("DIFFPLAN_TEXT_CACHE", CACHE_DIR))
        self._pieces: dict[str, np.ndarray] = {}
        self._features: dict[str, np.ndarray] = {}

    @property
    def dim(self) -> int:
        """D, the width of a token's features."""
        return int(self.encoder.config.hidden_size)

    # --------------------------------------------------------------- sentences

    def pieces(self, sentences: Sequence[str]) -> list[np.ndarray]:
        """Each sentence's wordpiece ids (int32, ``[CLS]`` ... ``[SEP]``), or an empty array
        for a sentence with no wordpiece but the special ones."""
        todo = [s for s in dict.fromkeys(sentences) if s not in self._pieces]
        if todo:
            tokenizer = self.encoder.subwords.tokenizer
            for s, e in zip(todo, tokenizer.encode_batch(todo, add_special_tokens=True)):
                real = not all(e.special_tokens_mask)
                self._pieces[s] = np.asarray(e.ids if real else [], np.int32)
        return [self._pieces[s] for s in sentences]

    def sentence_features(self, sentences: Sequence[str]) -> list[np.ndarray]:
        """Each sentence's token features, float16 (n, D) with n its wordpieces: computed in
        fixed-shape chunks per width (so a sentence's features do not depend on the others),
        or taken from memory. ValueError (one line) for a sentence over L wordpieces."""
        todo = [s for s in dict.fromkeys(sentences) if s not in self._features]
        by_width: dict[int, list[str]] = {}
        for s, ids in zip(todo, self.pieces(todo)):
            if len(ids) > self.max_tokens:
                raise ValueError(f"a sentence is {len(ids)} wordpieces long, over the limit of "
                                 f"{self.max_tokens}: {_clip(s)}")
            width = min(-(-max(len(ids), 1) // COLUMNS) * COLUMNS,
                        self.encoder.config.max_position_embeddings)
            by_width.setdefault(width, []).append(s)
        for width, group in sorted(by_width.items()):
            for lo in range(0, len(group), CHUNK):
                chunk = group[lo:lo + CHUNK]
                ids = np.zeros((CHUNK, width), np.int32)
                mask = np.zeros((CHUNK, width), bool)
                for i, s in enumerate(chunk + [chunk[0]] * (CHUNK - len(chunk))):
                    n = len(self._pieces[s])
                    ids[i, :n], mask[i, :n] = self._pieces[s], True
                out = np.asarray(_encode(self.encoder.params, ids, mask,
                                         config=self.encoder.config))
                for i, s in enumerate(chunk):
                    n = len(self._pieces[s])
                    self._features[s] = out[i, :n].astype(np.float16)
        return [self._features[s] for s in sentences]

    def name_features(self, names: Sequence[str]) -> np.ndarray:
        """float32 (N, D): each name's features, the mean over its wordpieces (without
        ``[CLS]`` / ``[SEP]``) of the encoder's output on the name alone; zeros for a name with
        no wordpiece (e.g. ""). What a denoiser with ``cell_context`` embeds a cell by."""
        out = np.zeros((len(names), self.dim), np.float32)
        real = [i for i, ids in enumerate(self.pieces(list(names))) if len(ids)]
        for i, feats in zip(real, self.sentence_features([names[i] for i in real])):
            out[i] = feats[1:-1].astype(np.float32).mean(axis=0)
        return out

    # --------------------------------------------------------------- the text path

    def sentences_of(self, text: str) -> list[str]:
        """The sentences of an instruction that hold a wordpiece (:func:`split_sentences`);
        ValueError (one line) if it is empty or longer than L wordpieces."""
        split = split_sentences(text)
        sentences = [s for s, ids in zip(split, self.pieces(split)) if len(ids)]
        if not sentences:
            raise ValueError(f"the instruction is empty: {_clip(text)} has no word")
        n = sum(len(ids) for ids in self.pieces(sentences))
        if n > self.max_tokens:
            raise ValueError(f"the instruction is {n} wordpieces long, over the limit of "
                             f"{self.max_tokens} ([CLS] and [SEP] of each sentence counted): "
                             f"{_clip(text)}")
        return sentences

    def length(self, text: str) -> int:
        """An instruction's wordpieces, each sentence's [CLS] and [SEP] counted (no limit)."""
        return int(sum(len(ids) for ids in self.pieces(split_sentences(text))))

    def encode(self, texts: str | Sequence[str]) -> np.ndarray:
        """float32 (B, L, D) features of instructions ((L, D) for one string): each one's
        sentences encoded on their own and concatenated, zeros after its last real token.
        ValueError (one line) for an empty instruction or one over L wordpieces."""
        single = isinstance(texts, str)
        batch = [texts] if single else list(texts)
        split = [self.sentences_of(t) for t in batch]
        self.sentence_features([s for sentences in split for s in sentences])
        out = np.zeros((len(batch), self.max_tokens, self.dim), np.float32)
        for i, sentences in enumerate(split):
            feats = np.concatenate([self._features[s] for s in sentences])
            out[i, :len(feats)] = feats
        return out[0] if single else out

    # --------------------------------------------------------------- the table path

    def cache_key(self, sentences: Sequence[str]) -> str:
        """The disk cache's key of a table: the encoder's file hashes, the format and the
        sentences."""
        h = hashlib.sha256(json.dumps({"format": FORMAT, "columns": COLUMNS, "chunk": CHUNK,
                                       "encoder": dict(sorted(self.encoder.sha256.items()))},
                                      sort_keys=True).encode())
        for s in sentences:
            h.update(s.encode("utf-8") + b"\0")
        return h.hexdigest()

    def table(self, sentences: Sequence[str], cache: bool = True) -> SentenceTable:
        """A :class:`SentenceTable` of the sentences (distinct), row n = sentences[n]. Read from
        the disk cache when it holds this list (``cache``), else computed and written there
        (a cache that cannot be written is skipped)."""
        sentences = list(sentences)
        if len(set(sentences)) != len(sentences):
            raise ValueError("the sentences of a table must be distinct")
        path = os.path.join(self.cache_dir, self.cache_key(sentences)[:40] + ".npz")
        features = lengths = None
        if cache and os.path.isfile(path):
            try:
                with np.load(path) as data:
                    features, lengths = data["features"], data["lengths"]
            except (OSError, ValueError, KeyError):
                features = None
            if features is not None and (len(lengths) != len(sentences) or features.shape != (
                    int(lengths.sum()), self.dim)):
                features = None
        if features is None:
            feats = self.sentence_features(sentences)
            lengths = np.array([len(f) for f in feats], np.int32)
            features = (np.concatenate(feats) if feats else
                        np.zeros((0, self.dim), np.float16))
            if cache:
                _write_atomic(path, features=features, lengths=lengths)
        else:
            self._features.update({s: features[a:a + n] for s, a, n in zip(
                sentences, np.cumsum(lengths) - lengths, lengths)})
        lengths = np.asarray(lengths, np.int32)
        return SentenceTable(features=jnp.asarray(features, jnp.float16),
                             start=jnp.asarray(np.cumsum(lengths) - lengths, jnp.int32),
                             length=jnp.asarray(lengths), max_tokens=self.max_tokens)


def _write_atomic(path: str, **arrays) -> None:
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path}.{os.getpid()}.tmp.npz"
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
    except OSError:
        pass


# ------------------------------------------------------------------ checkpoints

def encoder_record(encoder, max_tokens: int) -> dict:
    """What a checkpoint trained on these features records of them: the encoder's directory
    (``None`` for the shipped one), its files' sha256 and L."""
    from diffplan.pretrained_text import SHIPPED

    shipped = os.path.realpath(encoder.directory) == os.path.realpath(SHIPPED)
    return {"directory": None if shipped else str(encoder.directory),
            "sha256": dict(sorted(encoder.sha256.items())), "max_tokens": int(max_tokens)}


def load_instruction_encoder(record: Mapping) -> InstructionEncoder:
    """The :class:`InstructionEncoder` a checkpoint's :func:`encoder_record` names, its files
    checked against the recorded hashes (ValueError, one line, if they differ)."""
    from diffplan.pretrained_text import load_text_encoder

    try:
        directory, hashes, length = record["directory"], record["sha256"], record["max_tokens"]
    except (KeyError, TypeError):
        raise ValueError(f"not a text encoder record: {record!r}") from None
    encoder = load_text_encoder(directory, expected_sha256=hashes)
    return InstructionEncoder(encoder, int(length))


# ------------------------------------------------------------------ what a world shares

TEXTS = ("tokens", "pretrained")
"""How a world's training recipe gives the denoiser its instructions (``Recipe.text``): token
ids of the world's vocabulary, or the frozen pretrained text encoder's features of each
sentence (the batches carry sentence ids, assembled inside the step)."""


def check_text(text: str, **word_options) -> None:
    """ValueError (one line) for an instruction input other than :data:`TEXTS`, or, with
    "pretrained", for any option given a non-zero value in word_options (e.g.
    ``role_loss_weight=0.5``): such options label or drop word tokens of the world's
    vocabulary, and pretrained features have none."""
    if text not in TEXTS:
        raise ValueError(f"text must be one of {TEXTS}, got {text!r}")
    used = [name for name, value in word_options.items() if value]
    if text == "pretrained" and used:
        raise ValueError(f"{used[0]} works on the world's word tokens, which pretrained text "
                         f"features do not have (use {used[0]}=0 with text='pretrained')")


def instruction_of(episode, text: str):
    """What a task hands the planner of an episode's instruction (a world's
    ``Task.tokens``): ``episode.tokens`` (text "tokens") or ``episode.features`` float32 (L, D)
    (text "features", filled on the host before the rollout; ValueError, one line, where they
    were not)."""
    if text == "tokens":
        return episode.tokens
    if text != "features" or episode.features is None:
        raise ValueError(f"text {text!r}: a task hands the planner 'tokens' or 'features', and "
                         "features only of episodes filled with them before the rollout (the "
                         "world's sentences.with_features)")
    return episode.features


def encode_cached(encoder: InstructionEncoder, texts: Sequence[str]) -> np.ndarray:
    """float32 (N, L, D): :meth:`InstructionEncoder.encode` of the texts, each distinct sentence
    encoded once and kept in the disk cache as a table of its own (a later run with the same
    sentences reads them back). On the host: a world fills ``Episode.features`` with it before
    the rollout, once per episode."""
    texts = list(texts)
    distinct = dict.fromkeys(s for text in texts for s in split_sentences(text))
    encoder.table(list(distinct))  # encodes what is new, through the disk cache
    return encoder.encode(texts)


def instruction_lengths(lengths, sentence_ids) -> np.ndarray:
    """int (...,) wordpieces of the instructions made of table rows sentence_ids int (..., S)
    (-1 = absent, counted 0), from a table's per-sentence lengths int (N,)
    (``SentenceTable.length``). Plain numpy: what a world's check that its instructions fit in
    L counts."""
    lengths = np.append(np.asarray(lengths), 0)  # row -1 (absent) counts 0
    return lengths[np.asarray(sentence_ids)].sum(-1)


def check_phrasings(phrasings: Mapping, allowed: Mapping) -> None:
    """ValueError (one line) unless every phrasing of ``phrasings`` ({kind: indices}) is one of
    ``allowed[kind]`` (a world's training phrasings): what a world checks before it builds a
    training sentence table, so that no held-out, development or natural-language sentence can
    enter one."""
    for kind, indices in phrasings.items():
        bad = sorted(set(map(int, indices)) - set(allowed[kind]))
        if bad:
            raise ValueError(f"{kind} phrasings {bad} are not training phrasings (training "
                             f"draws {list(allowed[kind])}): no training table may hold them")


def fitting_table(encoder: InstructionEncoder, sentences: Sequence[str], longest,
                  world: str = "the world's") -> SentenceTable:
    """``encoder.table(sentences)`` (a world's training sentences), refused (ValueError, one
    line naming L) if ``longest(lengths)``, the most wordpieces an instruction made of its rows
    can have (lengths int (N,): each row's, ``SentenceTable.length``), is over L."""
    table = encoder.table(sentences)
    count = int(longest(np.asarray(table.length)))
    if count > encoder.max_tokens:
        raise ValueError(f"an instruction is {count} wordpieces long, over {world} L = "
                         f"{encoder.max_tokens}")
    return table


def text_metadata(text: str, vocabulary: Sequence[str], cell_tokens: Sequence[str],
                  encoder) -> dict:
    """What a checkpoint records of its instruction input (a world's ``Recipe.metadata``):
    text "tokens", the vocabulary its token ids index; "pretrained", the text encoder
    (:func:`encoder_record` of ``encoder()``, called only then) and the cell tokens its grid
    embedding indexes."""
    if text == "tokens":
        return {"vocabulary": list(vocabulary)}
    instruction_encoder = encoder()
    return {"text": text, "cell_tokens": list(cell_tokens),
            "text_encoder": encoder_record(instruction_encoder.encoder,
                                           instruction_encoder.max_tokens)}


PAD_TOKEN = "<pad>"


def cell_names(cell_tokens: Sequence[str]) -> tuple[str, ...]:
    """The name of each cell token a denoiser with ``DenoiserConfig.cell_context`` embeds the
    cell by: a word as is ("apple", "red"), a marker without its brackets ("<unseen>" ->
    "unseen"), the padding token as "" (zero features)."""
    return tuple("" if t == PAD_TOKEN else t.strip("<>") for t in cell_tokens)


def feature_statistics(table: SentenceTable) -> tuple[np.ndarray, np.ndarray]:
    """(mean, scale), float32 (D,) each: the per-dimension mean and standard deviation (floored
    at 1e-3) of every token row of a sentence table, the constants a denoiser with
    ``DenoiserConfig.standardize`` standardises its features with."""
    rows = np.asarray(table.features, np.float32)
    return rows.mean(axis=0), np.maximum(rows.std(axis=0), 1e-3)


def fixed_text_params(model_config, cell_tokens: Sequence[str], encoder, table) -> dict | None:
    """A world recipe's ``fixed_params(model_config)``: the constants a features denoiser
    reads, written before training; None if it reads none. With ``cell_context``:
    ``frozen_cell_features`` (len(cell_tokens), D), the features of :func:`cell_names` by
    ``encoder()``; with ``standardize``: ``frozen_feature_mean`` and ``frozen_feature_scale``
    (D,), :func:`feature_statistics` of ``table()``, the training sentence table (each
    callable is called only when needed)."""
    fixed = {}
    if getattr(model_config, "cell_context", False):
        fixed["frozen_cell_features"] = encoder().name_features(cell_names(cell_tokens))
    if getattr(model_config, "standardize", False):
        fixed["frozen_feature_mean"], fixed["frozen_feature_scale"] = \
            feature_statistics(table())
    return fixed or None


@functools.lru_cache(maxsize=None)
def shared_encoder(directory: str | None, max_tokens: int) -> InstructionEncoder:
    """The :class:`InstructionEncoder` of the shipped pretrained text encoder (directory None)
    or of a Hugging Face-format one at L = max_tokens, loaded once per process and shared (its
    sentences kept in memory)."""
    from diffplan.pretrained_text import load_text_encoder

    return InstructionEncoder(load_text_encoder(directory), max_tokens)
