"""The grid world's instructions as sentences, for a denoiser on a frozen pretrained text
encoder's features (``diffplan.instruction``; ``DenoiserConfig.context_dim`` > 0).

- The text path: :func:`episode_texts` renders each episode's instruction from its phrasing
  (``Episode.template``, any language, the natural set's included) and its slots; 
  :func:`with_features` fills ``Episode.features`` with the encoded text on the host, before
  a rollout (``GridTask(text="features")`` hands them to the planner).
- The table path (training): :func:`sentence_index` lists every distinct sentence of the
  given phrasings filled in every way (a table's rows) and maps an episode's (template,
  reference, target, direction) to its sentences' rows, in order, inside ``jit``
  (:meth:`SentenceIndex.ids`). :func:`training_index` is the index of the training phrasings
  only (canonical and training paraphrases of both meanings): training draws its sentence ids
  from it, so no held-out or natural-language sentence list can reach a training batch
  (:func:`check_training_templates`).
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Mapping, Sequence

import jax.numpy as jnp
import numpy as np

from diffplan.instruction import cell_names, fitting_table, shared_encoder, split_sentences
from envs.gridworld import grammar

FEATURE_TOKENS = 48
"""L of the grid world's instruction features: wordpieces per instruction, each sentence's
[CLS] and [SEP] counted. The longest instruction of any phrasing set (the training and
held-out phrasings and the natural set, every filling) is 32 (tests/test_instruction.py
measures it); 48 leaves room for a person's own wording."""
KINDS = (True, False)
"""The two meanings of the grid world's instructions: with a reference (P-MO2G, P-MO2G-far)
and without (1O1G, MO1G)."""


def episode_texts(episodes, setting: str, reference_class=None, direction=None,
                  target_class=None) -> list[str]:
    """Each episode's instruction as text (numpy or jax Episode batch, leading axis N), rendered
    from its phrasing (:func:`grammar.render`). reference_class / direction / target_class
    int (N,): slots to write instead of the episode's own (the language controls)."""
    template = np.asarray(episodes.template).reshape(-1)
    ref = np.asarray(episodes.reference_class if reference_class is None
                     else reference_class).reshape(-1)
    dirs = np.asarray(episodes.direction if direction is None else direction).reshape(-1)
    target = np.asarray(episodes.target_class if target_class is None
                        else target_class).reshape(-1)
    return [grammar.render(setting, int(t), int(r), int(g), int(d))
            for t, r, g, d in zip(template, ref, target, dirs)]


def with_features(episodes, setting: str, encoder, reference_class=None, direction=None,
                  target_class=None):
    """The episodes with ``features`` float32 (N, L, D): their instructions
    (:func:`episode_texts`) encoded by ``encoder`` (a ``diffplan.instruction.
    InstructionEncoder``), each distinct sentence once (and read from the disk cache when the
    same sentences were encoded before)."""
    texts = episode_texts(episodes, setting, reference_class, direction, target_class)
    distinct = dict.fromkeys(s for text in texts for s in split_sentences(text))
    encoder.table(list(distinct))  # encodes what is new, through the disk cache
    return episodes.replace(features=encoder.encode(texts))


@dataclasses.dataclass(frozen=True, eq=False)
class SentenceIndex:
    """Rows of a sentence table and the map from an episode's instruction to them.

    sentences: the table's rows, distinct. lookup: {has_reference: int32 (NUM_TEMPLATES,
    C + 1, C + 1, 8, S)}, indexed by template, reference class (0 without one), target class
    and direction (0 without one): the rows of the instruction's sentences in order, -1 after
    its last and for every template the index does not hold. templates: {has_reference: the
    template indices it holds}."""

    sentences: tuple[str, ...]
    lookup: Mapping[bool, np.ndarray]
    templates: Mapping[bool, tuple[int, ...]]

    def ids(self, has_reference: bool, template, ref_class, target_class, direction):
        """int32 (S,) the rows of an episode's instruction's sentences (jit-able; -1 = absent,
        all -1 for a template the index does not hold)."""
        table = jnp.asarray(self.lookup[has_reference])
        rows = table[jnp.clip(template, 0, grammar.NUM_TEMPLATES - 1), ref_class, target_class,
                     jnp.maximum(direction, 0)]
        return jnp.where(template < grammar.NUM_TEMPLATES, rows, -1).astype(jnp.int32)


def fillings(has_reference: bool, classes: Sequence[int] | None = None):
    """Every (reference class, target class, direction) an instruction of the meaning can
    have (classes 1-based, default all; 0 and -1 where it has no reference)."""
    classes = range(1, len(grammar.OBJECT_NAMES) + 1) if classes is None else classes
    if not has_reference:
        return [(0, t, -1) for t in classes]
    return [(r, t, d) for r in classes for t in classes if r != t
            for d in range(len(grammar.DIRECTIONS))]


def sentence_index(templates: Mapping[bool, Sequence[int]],
                   classes: Sequence[int] | None = None) -> SentenceIndex:
    """The :class:`SentenceIndex` of the given phrasings ({has_reference: template indices of
    :data:`grammar.TEMPLATES`}) in every filling (with the object classes given, default all;
    others map to no sentence); sentences listed in order of first occurrence (meaning,
    template, then filling)."""
    rows: dict[str, int] = {}
    split = {}
    for kind in KINDS:
        setting = "p_mo2g" if kind else "mo1g"
        for t in templates.get(kind, ()):
            if not 0 <= t < grammar.NUM_TEMPLATES:
                raise ValueError(f"template {t} is not one of the grammar's phrasings")
            for r, g, d in fillings(kind, classes):
                parts = split_sentences(grammar.render(setting, t, r, g, d))
                split[kind, t, r, g, d] = [rows.setdefault(s, len(rows)) for s in parts]
    size = max([len(v) for v in split.values()], default=1)
    classes = len(grammar.OBJECT_NAMES) + 1
    lookup = {kind: np.full((grammar.NUM_TEMPLATES, classes, classes, len(grammar.DIRECTIONS),
                             size), -1, np.int32) for kind in KINDS}
    for (kind, t, r, g, d), ids in split.items():
        lookup[kind][t, r, g, max(d, 0), :len(ids)] = ids
    return SentenceIndex(tuple(rows), lookup,
                         {kind: tuple(templates.get(kind, ())) for kind in KINDS})


def training_templates() -> dict[bool, tuple[int, ...]]:
    """{has_reference: the phrasings training draws} (``TemplateSplit.training``: canonical
    and the training paraphrases; never a held-out, extra or natural-language one)."""
    return {kind: tuple(grammar.SPLITS["p_mo2g" if kind else "mo1g"].training) for kind in KINDS}


def check_training_templates(templates: Mapping[bool, Sequence[int]]) -> None:
    """ValueError (one line) unless every template is a training phrasing of its meaning (so
    no held-out and no natural-language sentence can enter a training table)."""
    allowed = training_templates()
    for kind, indices in templates.items():
        bad = sorted(set(map(int, indices)) - set(allowed[kind]))
        if bad:
            raise ValueError(f"templates {bad} are not training phrasings (training draws "
                             f"{list(allowed[kind])}): no training table may hold them")


@functools.lru_cache(maxsize=None)
def training_index() -> SentenceIndex:
    """The index of the training phrasings (:func:`training_templates`): the rows of the
    training sentence table."""
    templates = training_templates()
    check_training_templates(templates)
    return sentence_index(templates)


def longest_instruction(index: SentenceIndex, lengths) -> int:
    """The most wordpieces an instruction of the index has (lengths int (N,): each sentence's,
    ``SentenceTable.length``; an absent sentence, row -1, counts 0)."""
    lengths = np.append(np.asarray(lengths), 0)
    return max(int(lengths[table].sum(-1).max()) for table in index.lookup.values())


def instruction_encoder(directory: str | None = None, max_tokens: int = FEATURE_TOKENS):
    """The grid world's ``diffplan.instruction.InstructionEncoder``: the shipped pretrained
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
                         "the grid world's")



def cell_features(encoder=None) -> np.ndarray:
    """float32 (len(CELL_TOKENS), D): the encoder's features of each cell token's name
    (``diffplan.instruction.cell_names``: "<unseen>" -> "unseen", padding -> zeros), what a
    denoiser with ``DenoiserConfig.cell_context`` embeds a cell by."""
    return (instruction_encoder() if encoder is None else encoder).name_features(
        cell_names(grammar.CELL_TOKENS))
