"""The Kuka world's instructions as sentences, for a denoiser on a frozen pretrained text
encoder's features (``diffplan.instruction``; ``DenoiserConfig.context_dim`` > 0).

- The text path: :func:`episode_texts` renders each episode's instruction from its phrasings
  (``Episode.phrasing``: the tower sentence's, then each relation's; any language, the sealed
  natural set's included) and its constraints; :func:`with_features` fills
  ``Episode.features`` with the encoded text on the host, before a rollout
  (``KukaTask(text="features")`` hands them to the planner).
- The table path (training): :func:`sentence_index` lists every distinct sentence of the given
  phrasings in every filling (a table's rows) and maps an episode's (phrasings, constraints,
  tower sentence) to its sentences' rows, in order, inside ``jit`` (:meth:`SentenceIndex.ids`).
  :func:`training_index` is the index of the training phrasings only (canonical, the training
  paraphrases and the training-only extras, ``grammar.EXTRA``): training draws its sentence ids
  from it, and it refuses every development, sealed held-out and natural-language phrasing
  (:func:`check_training_templates`) and sentence (:func:`check_training_sentences`).
"""
from __future__ import annotations

import dataclasses
import functools
import itertools
from typing import Mapping, Sequence

import jax.numpy as jnp
import numpy as np

from diffplan import language
from diffplan.instruction import (check_phrasings, encode_cached, fitting_table,
                                  instruction_lengths, shared_encoder, split_sentences)
from envs.kuka import grammar, scene

FEATURE_TOKENS = 80
"""L of the Kuka world's instruction features: wordpieces per instruction, each sentence's
[CLS] and [SEP] counted. The longest instruction of any phrasing set (training, development,
sealed held-out and the natural set, every filling) is 54: three natural relation sentences of
18 (the grammar's longest is 45; tests/test_kuka_features.py measures both); 80 leaves room for a
person's own wording."""
KINDS = ("tower", "relation")
"""The Kuka world's sentence kinds: the tower sentence (single-constraint stacking opens with
it) and a relation sentence ("top on bottom", one per instructed relation)."""
PAIRS = tuple(itertools.permutations(range(scene.NUM_BLOCKS), 2))
"""Every (top, bottom) a relation sentence can name: the 12 ordered pairs of distinct blocks."""


SENTENCE_ENDS = (".", "?", "!")
"""How a phrasing a sentence table holds must end (every training phrasing ends with "."): a
phrasing without it (some natural ones, "stack {top} on {bottom}") runs into the next sentence
in the text path (``diffplan.instruction.split_sentences``), so only the text path reads it."""


def _phrasings(kind: str) -> tuple[str, ...]:
    return grammar.tower_phrasings() if kind == "tower" else grammar.relation_phrasings()


def _texts(kind: str, k: int, pairs=PAIRS) -> dict[tuple[int, int], str]:
    """{(top, bottom): the text of phrasing k of the kind in that filling} ((0, 0) alone for
    the tower sentence, which names no block)."""
    if kind == "tower":
        return {(0, 0): _phrasings(kind)[k]}
    return {(a, b): grammar.render([(a, b)], False, [k]) for a, b in pairs}


def tower_sentences(episodes) -> np.ndarray:
    """bool (N,): each episode's instruction opens with the tower sentence (single-constraint
    stacking, as ``episode.generate`` writes it)."""
    constraints = np.asarray(episodes.constraints).reshape(-1, grammar.MAX_RELATIONS, 2)
    return np.asarray(episodes.tower).reshape(-1) & ((constraints[..., 0] >= 0).sum(-1) == 1)


def episode_texts(episodes) -> list[str]:
    """Each episode's instruction as text (a numpy or jax Episode batch, leading axis N),
    rendered from its phrasings (``Episode.phrasing``, :func:`grammar.render`) and its
    constraints."""
    if episodes.phrasing is None:
        raise ValueError("these episodes carry no phrasings (Episode.phrasing): generate them "
                         "with envs.kuka.episode.generate")
    phrasing = np.asarray(episodes.phrasing).reshape(-1, 1 + grammar.MAX_RELATIONS)
    constraints = np.asarray(episodes.constraints).reshape(-1, grammar.MAX_RELATIONS, 2)
    return [grammar.render(c, bool(tower), [int(k) for k, row in zip(p[1:], c) if row[0] >= 0],
                           int(p[0]))
            for p, c, tower in zip(phrasing, constraints, tower_sentences(episodes))]


def with_features(episodes, encoder):
    """The episodes with ``features`` float32 (N, L, D): their instructions
    (:func:`episode_texts`) encoded by ``encoder`` (a ``diffplan.instruction.
    InstructionEncoder``), each distinct sentence once (``diffplan.instruction.
    encode_cached``). On the host, before the rollout: once per episode."""
    return episodes.replace(features=encode_cached(encoder, episode_texts(episodes)))


@dataclasses.dataclass(frozen=True, eq=False)
class SentenceIndex:
    """Rows of a sentence table and the map from an episode's instruction to them.

    sentences: the table's rows, distinct. towers: int32 (T, P) the rows of tower phrasing k's
    sentences in order; relations: int32 (R, 4, 4, P) those of relation phrasing k naming top
    block a and bottom block b; -1 after a phrasing's last sentence and for every phrasing the
    index does not hold. T and R count every phrasing, the grammar's and the natural set's
    (``grammar.tower_phrasings``, ``grammar.relation_phrasings``); P is the most sentences one
    phrasing renders to. templates: {kind: the phrasings it holds} (:data:`KINDS`)."""

    sentences: tuple[str, ...]
    towers: np.ndarray
    relations: np.ndarray
    templates: Mapping[str, tuple[int, ...]]

    @property
    def size(self) -> int:
        """S, the sentence ids of one instruction: P for the tower sentence, then P per
        relation."""
        return (1 + grammar.MAX_RELATIONS) * self.towers.shape[-1]

    def ids(self, phrasing, constraints, tower_sentence):
        """int32 (S,) the rows of an episode's instruction's sentences, in order (jit-able; -1 =
        absent, and for a phrasing the index does not hold). phrasing int (1 + MAX_RELATIONS,)
        (``Episode.phrasing``); constraints int (MAX_RELATIONS, 2) (top, bottom), -1 rows
        absent; tower_sentence bool ()."""
        towers, relations = jnp.asarray(self.towers), jnp.asarray(self.relations)
        phrasing, constraints = jnp.asarray(phrasing), jnp.asarray(constraints)
        tower = towers[jnp.clip(phrasing[0], 0, towers.shape[0] - 1)]
        tower = jnp.where(tower_sentence & (phrasing[0] < towers.shape[0]), tower, -1)
        which = phrasing[1:]
        pair = jnp.maximum(constraints, 0)
        rows = relations[jnp.clip(which, 0, relations.shape[0] - 1), pair[:, 0], pair[:, 1]]
        present = (constraints[:, 0] >= 0) & (which < relations.shape[0])
        rows = jnp.where(present[:, None], rows, -1)
        return jnp.concatenate([tower, rows.reshape(-1)]).astype(jnp.int32)


def sentence_index(templates: Mapping[str, Sequence[int]],
                   pairs: Sequence[tuple[int, int]] = PAIRS) -> SentenceIndex:
    """The :class:`SentenceIndex` of the given phrasings ({kind: indices of
    ``grammar.tower_phrasings`` / ``grammar.relation_phrasings``}), relation phrasings filled
    with every pair given (default all :data:`PAIRS`; others map to no sentence); sentences
    listed in order of first occurrence (kind, phrasing, then pair)."""
    rows: dict[str, int] = {}
    split: dict[tuple, list[int]] = {}
    for kind in KINDS:
        count = len(_phrasings(kind))
        for k in templates.get(kind, ()):
            if not 0 <= k < count:
                raise ValueError(f"{kind} phrasing {k} is not one of the {count} phrasings")
            for (top, bottom), text in _texts(kind, k, pairs).items():
                if not text.endswith(SENTENCE_ENDS):
                    raise ValueError(f"{kind} phrasing {k} ({_phrasings(kind)[k]!r}) does not "
                                     "end its sentence: the text path reads it together with "
                                     "the next one, so a table cannot hold it on its own")
                split[kind, k, top, bottom] = [rows.setdefault(s, len(rows))
                                               for s in split_sentences(text)]
    size = max([len(v) for v in split.values()], default=1)
    blocks = scene.NUM_BLOCKS
    lookup = {"tower": np.full((len(_phrasings("tower")), size), -1, np.int32),
              "relation": np.full((len(_phrasings("relation")), blocks, blocks, size), -1,
                                  np.int32)}
    for (kind, k, top, bottom), ids in split.items():
        where = (k,) if kind == "tower" else (k, top, bottom)
        lookup[kind][where + (slice(0, len(ids)),)] = ids
    return SentenceIndex(tuple(rows), lookup["tower"], lookup["relation"],
                         {kind: tuple(templates.get(kind, ())) for kind in KINDS})


def training_templates() -> dict[str, tuple[int, ...]]:
    """{kind: the phrasings training draws}: canonical, the training paraphrases and the
    training-only extras (``TemplateSplit.training`` + ``extra``, the pools of every training
    language); never a development, sealed held-out or natural-language one."""
    splits = {"tower": grammar.TOWER_SPLIT, "relation": grammar.RELATION_SPLIT}
    return {kind: tuple(sorted(split.training + split.extra)) for kind, split in splits.items()}


def check_training_templates(templates: Mapping[str, Sequence[int]]) -> None:
    """ValueError (one line) unless every phrasing is one training draws
    (:func:`training_templates`), so that no development, held-out or natural-language
    sentence can enter a training table."""
    check_phrasings(templates, training_templates())


def never_trained_sentences() -> dict[str, str]:
    """{sentence: its language}: every sentence the development, sealed held-out and natural
    phrasings render to in every filling (what no training table may hold)."""
    out: dict[str, str] = {}
    for name in (language.DEVELOPMENT, language.HELDOUT, language.NATURAL):
        for kind, pool in zip(KINDS, grammar.phrasing_pools(name)):
            for k in pool.tolist():
                for text in _texts(kind, k).values():
                    out.update({s: name for s in split_sentences(text) if s not in out})
    return out


def check_training_sentences(sentences: Sequence[str]) -> None:
    """ValueError (one line) if a sentence is one a development, sealed held-out or
    natural-language phrasing renders (:func:`never_trained_sentences`)."""
    forbidden = never_trained_sentences()
    for s in sentences:
        if s in forbidden:
            raise ValueError(f"the sentence {s!r} is a {forbidden[s]} phrasing's: no training "
                             "table may hold it")


@functools.lru_cache(maxsize=None)
def training_index() -> SentenceIndex:
    """The index of the training phrasings (:func:`training_templates`): the rows of the
    training sentence table, checked to hold no sentence of another language."""
    templates = training_templates()
    check_training_templates(templates)
    index = sentence_index(templates)
    check_training_sentences(index.sentences)
    return index


def longest_instruction(index: SentenceIndex, lengths) -> int:
    """The most wordpieces an instruction of the index can have (lengths int (N,): each
    sentence's, from its table): the tower sentence and one relation, or MAX_RELATIONS
    relations, each the longest."""
    tower = int(instruction_lengths(lengths, index.towers).max())
    relation = int(instruction_lengths(lengths, index.relations).max())
    return max(tower + relation, grammar.MAX_RELATIONS * relation)


def instruction_encoder(directory: str | None = None, max_tokens: int = FEATURE_TOKENS):
    """The Kuka world's ``diffplan.instruction.InstructionEncoder``: the shipped pretrained
    text encoder (or the Hugging Face-format one in directory) at L = max_tokens; loaded once
    per process (``diffplan.instruction.shared_encoder``)."""
    return shared_encoder(directory, max_tokens)


def training_table(encoder=None):
    """The ``diffplan.instruction.SentenceTable`` of the training sentences
    (:func:`training_index`, its rows in that order), refused (one line) unless every
    instruction fits in the encoder's L (:func:`longest_instruction`)."""
    index = training_index()
    return fitting_table(instruction_encoder() if encoder is None else encoder,
                         index.sentences, functools.partial(longest_instruction, index),
                         "the Kuka world's")
