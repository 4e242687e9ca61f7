"""The Kuka world's instruction language, built on the shared ``diffplan.language``.

An instruction is up to four sentences: an optional tower sentence (stacking with one
instructed relation: "Build a tower of all four blocks.") and one sentence per instructed
relation "X on Y" ("Stack the green block on top of the red block."). Each sentence kind has a
canonical phrasing (template 0, the paper's Table 2 instructions) and paraphrases (the paper's
Table 5 "complex" instructions), some of which invert the preposition and name the lower block
first ("Put the red block below the green block" means green on red). Templates have the slots
``{top}`` and ``{bottom}``; token ids are filled in JAX (:func:`instruction_tokens`).

Besides the training phrasings, each kind has **development** phrasings (relation 8-11, tower
4-5; the language ``development``): no training batch contains them, but they were looked at
to choose things (the training-only extras were picked by scoring taggers on them, the reader's
sentence-local encoder after reading the evaluation seeds' per-phrasing breakdown), so what is
measured on them is a development number, not a held-out one.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffplan import language
from envs.kuka.scene import BLOCK_NAMES

PAD = "<pad>"
SLOTS = ("{top}", "{bottom}")

RELATION_TEMPLATES: tuple[str, ...] = (
    "Stack the {top} block on top of the {bottom} block.",
    "Place the {top} block on the {bottom} block.",
    "Put the {bottom} block below the {top} block.",
    "Set the {top} block onto the {bottom} block.",
    "The {bottom} block goes under the {top} block.",
    "Put the {top} block above the {bottom} block.",
    "Move the {top} block so that it rests on the {bottom} block.",
    "The {bottom} block should be beneath the {top} block.",
    # development phrasings (8-11): never trained on, but chosen on (see the module
    # docstring); made of the training phrasings' words; 9 and 11 inverted
    "Put the {top} block on top of the {bottom} block.",
    "The {bottom} block should be below the {top} block.",
    "Move the {top} block onto the {bottom} block.",
    "Set the {bottom} block under the {top} block.",
    # training-only extras (12-18, drawn by the "broad" training language only): every opening
    # frame in both orders, every preposition in two frames, so that no verb fixes the order
    "Stack the {bottom} block below the {top} block.",
    "Place the {bottom} block beneath the {top} block.",
    "Set the {bottom} block below the {top} block.",
    "The {top} block goes on top of the {bottom} block.",
    "Move the {bottom} block under the {top} block.",
    "The {top} block should be above the {bottom} block.",
    "Place the {top} block onto the {bottom} block.",
    # SEALED HELD-OUT PHRASINGS (19-28, the language "heldout"; issue 52). Written, with new
    # frames and word orders (four open with their preposition), from the training phrasings'
    # words only, each at least two words from every training, development and extra phrasing,
    # and committed before any model was evaluated on them. No training batch may draw them
    # (no training language's pool holds them) and nothing is ever chosen on them: a model is
    # measured on them once, at the end of the work that produced it, and the result reported
    # as it comes out. Do not edit, reorder or tune them.
    "On the {bottom} block put the {top} block.",
    "Under the {top} block put the {bottom} block.",
    "Onto the {bottom} block move the {top} block.",
    "Above the {bottom} block should be the {top} block.",
    "Place onto the {bottom} block the {top} block.",
    "Put under the {top} block the {bottom} block.",
    "The {top} block should be put on the {bottom} block.",
    "The {bottom} block should be set under the {top} block.",
    "Set it so that the {top} block rests on the {bottom} block.",
    "Place it so that the {bottom} block goes under the {top} block.",
)
"""One relation "top on bottom"; 0 is canonical, 1-7 the training paraphrases, 8-11 the
development phrasings, 12-18 training-only extras (:data:`EXTRA`), 19-28 the sealed held-out
phrasings (:data:`HELDOUT`)."""
INVERTED = tuple(k for k, t in enumerate(RELATION_TEMPLATES) if t.index("{bottom}") < t.index(
    "{top}"))
"""The relation phrasings that name the lower block first (2, 4, 7, 9, 11, 12, 13, 14, 16 of
the first 19: the preposition inverted, "Put the {bottom} block below the {top} block.")."""
EXTRA = tuple(range(12, 19))
HELDOUT = tuple(range(19, 29))
"""The sealed held-out relation phrasings (drawn only by the language ``heldout``): never
trained on, never chosen on (see the comment above them)."""
"""Relation phrasings only the ``broad`` training language draws (``diffplan.language.BROAD``):
the ``paraphrased`` and ``development`` evaluation rows never contain them, and they add no word, so
the vocabulary (and every checkpoint's) is the same with or without them."""

TOWER_TEMPLATES: tuple[str, ...] = (
    "Build a tower of all four blocks.",
    "Stack all four blocks into one tower.",
    "Make a single tower with the four blocks.",
    "Pile the four blocks up into one tower.",
    # development phrasings (4-5): never trained on, but chosen on
    "Build one tower with all four blocks.",
    "Make a tower of the four blocks.",
    # SEALED HELD-OUT PHRASINGS (6-8, the language "heldout"): as the sealed relation
    # phrasings above, never trained on, nothing ever chosen on them; do not edit them.
    "Into one tower stack all four blocks.",
    "With all four blocks build a single tower.",
    "Pile up all four blocks into a single tower.",
)
"""The tower sentence of single-constraint stacking; 0 is canonical, 1-3 the training
paraphrases, 4-5 the development phrasings, 6-8 the sealed held-out phrasings
(:data:`HELDOUT_TOWERS`)."""
HELDOUT_TOWERS = (6, 7, 8)

RELATION_SPLIT = language.TemplateSplit(RELATION_TEMPLATES, (8, 9, 10, 11), SLOTS, EXTRA,
                                        sealed=HELDOUT, unseen_name=language.DEVELOPMENT)
TOWER_SPLIT = language.TemplateSplit(TOWER_TEMPLATES, (4, 5), SLOTS, sealed=HELDOUT_TOWERS,
                                     unseen_name=language.DEVELOPMENT)
"""Of each sentence kind: development phrasings (kept out of training, chosen on) and sealed
held-out phrasings (kept out of training, never chosen on); every word of them occurs in a
training phrasing, so the vocabulary is that of the training phrasings."""
LANGUAGES = RELATION_SPLIT.languages
"""canonical: every sentence in its template 0; paraphrased: every sentence in a uniformly drawn
training paraphrase (never template 0); development: every sentence in a uniformly drawn
development phrasing; heldout: every sentence in a uniformly drawn sealed held-out phrasing
(:data:`RELATION_SPLIT`, :data:`TOWER_SPLIT`)."""
RENAMED = {language.UNSEEN: language.DEVELOPMENT}
"""Kuka language names recorded before they were renamed (older metadata, sweep files and
JSON): "unseen" drew relation templates 8-11 and tower templates 4-5, the development
phrasings."""


def _build_vocab() -> tuple[str, ...]:
    words = RELATION_SPLIT.training_words() | TOWER_SPLIT.training_words()
    # Block colours right after the padding: block i has token id i + 1.
    return (PAD,) + BLOCK_NAMES + tuple(sorted(words - set(BLOCK_NAMES)))


VOCABULARY = language.Vocabulary(_build_vocab())
VOCAB = VOCABULARY.words
SENTENCE_TOKENS = 14
"""Fixed length of a compiled sentence (the longest template has 13 tokens)."""
MAX_RELATIONS = 3
MAX_TOKENS = 40
"""Fixed instruction length: room for three relations in the longest paraphrase (39 tokens)."""

RELATIONS = np.stack([VOCABULARY.compile(t, SLOTS, SENTENCE_TOKENS) for t in RELATION_TEMPLATES])
TOWERS = np.stack([VOCABULARY.compile(t, SLOTS, SENTENCE_TOKENS) for t in TOWER_TEMPLATES])


EVALUATION_LANGUAGES = LANGUAGES + (language.NATURAL,)
"""The Kuka world's evaluation languages: :data:`LANGUAGES` and the sealed natural-language set
("natural", ``envs.kuka.natural``: read only by a denoiser on pretrained text features; never
part of an "all")."""
EPISODE_LANGUAGES = EVALUATION_LANGUAGES + (language.BROAD,)
"""What an episode's instruction may be phrased in: an evaluation language, or the training
language ``broad``."""
CELL_TOKENS: tuple[str, ...] = VOCAB[:len(BLOCK_NAMES) + 1]
"""What a cell of condition channel 0 can hold: the padding id and the block colours (ids
0-4; a denoiser on pretrained text features embeds these only)."""


def check_phrasing(phrasing: str) -> str:
    """phrasing if it is one of EPISODE_LANGUAGES, else ValueError naming them."""
    if phrasing not in EPISODE_LANGUAGES:
        renamed = (f" ({phrasing!r} is now {RENAMED[phrasing]!r})" if phrasing in RENAMED
                   else "")
        raise ValueError(f"unknown language {phrasing!r}; expected one of "
                         f"{EPISODE_LANGUAGES}{renamed}")
    return phrasing


def current_language(name: str) -> str:
    """The current name of a recorded Kuka language name (:data:`RENAMED`: "unseen" ->
    "development"); any other name unchanged. For reading old metadata, never for flags."""
    return RENAMED.get(name, name)


def block_token(block):
    """Token id of block index i (0 red .. 3 yellow; ints, numpy or jax arrays)."""
    return block + 1


def is_block_token(ids):
    """Whether each token id names a block (ints, numpy or jax arrays)."""
    return (ids >= block_token(0)) & (ids <= block_token(len(BLOCK_NAMES) - 1))


def encode(text: str) -> np.ndarray:
    return VOCABULARY.encode(text, MAX_TOKENS)


def decode(ids) -> str:
    return VOCABULARY.decode(ids)


def tower_phrasings() -> tuple[str, ...]:
    """What ``Episode.phrasing[0]`` indexes: the tower sentence's phrasings, the grammar's
    (:data:`TOWER_TEMPLATES`) then the sealed natural set's (``natural.TOWERS``)."""
    from envs.kuka import natural

    return TOWER_TEMPLATES + natural.TOWERS


def relation_phrasings() -> tuple[str, ...]:
    """What ``Episode.phrasing[1:]`` indexes: the relation phrasings, the grammar's
    (:data:`RELATION_TEMPLATES`) then the sealed natural set's
    (``natural.relation_sentences()``; some are two sentences, "See the {bottom} block? Put
    the {top} block on top of it.")."""
    from envs.kuka import natural

    return RELATION_TEMPLATES + natural.relation_sentences()


def phrasing_pools(phrasing: str) -> tuple[np.ndarray, np.ndarray]:
    """(tower pool, relation pool) int32: the phrasings (indices of :func:`tower_phrasings`,
    :func:`relation_phrasings`) a sentence of the language draws from uniformly; "natural":
    the natural set's, after the grammar's."""
    check_phrasing(phrasing)
    if phrasing == language.NATURAL:
        return (np.arange(len(TOWER_TEMPLATES), len(tower_phrasings()), dtype=np.int32),
                np.arange(len(RELATION_TEMPLATES), len(relation_phrasings()), dtype=np.int32))
    return TOWER_SPLIT.pool(phrasing), RELATION_SPLIT.pool(phrasing)


def draw_phrasings(key, phrasing: str = "canonical"):
    """int32 (1 + MAX_RELATIONS,) an instruction's phrasings (``Episode.phrasing``): the tower
    sentence's (:func:`tower_phrasings`), then each relation sentence's
    (:func:`relation_phrasings`), drawn uniformly from the language's pools
    (:func:`phrasing_pools`); one drawn for every sentence, present or not. jit/vmap-able."""
    towers, relations = phrasing_pools(phrasing)
    k_tower, k_rel = jax.random.split(key)
    tower = language.draw_template(k_tower, towers)
    which = language.draw_template(k_rel, relations, (MAX_RELATIONS,))
    return jnp.concatenate([tower[None], which]).astype(jnp.int32)


def phrasing_tokens(phrasings, constraints, tower_sentence):
    """int32 (MAX_TOKENS,) the token ids of an instruction in the given phrasings (int
    (1 + MAX_RELATIONS,), :func:`draw_phrasings`); a natural-language phrasing's sentence is
    written in its canonical phrasing (its words are outside the vocabulary: only a denoiser
    on pretrained features reads the natural text). constraints int32 (MAX_RELATIONS, 2)
    (top, bottom), -1 rows absent; tower_sentence bool (). jit/vmap-able."""
    phrasings = jnp.asarray(phrasings)
    constraints = jnp.asarray(constraints)
    tower_k, relation_k = phrasings[0], phrasings[1:]
    tower = jnp.asarray(TOWERS)[jnp.where(tower_k < len(TOWER_TEMPLATES), tower_k, 0)]
    which = jnp.where(relation_k < len(RELATION_TEMPLATES), relation_k, 0)
    slots = block_token(jnp.maximum(constraints, 0))
    relations = jax.vmap(language.fill_slots)(jnp.asarray(RELATIONS)[which], slots)
    segments = jnp.concatenate([tower[None], relations])
    lengths = (segments != language.PAD_ID).sum(-1)
    present = jnp.concatenate([jnp.asarray(tower_sentence)[None], constraints[:, 0] >= 0])
    return language.concat_segments(segments, jnp.where(present, lengths, 0), MAX_TOKENS)


def instruction_tokens(key, constraints, tower_sentence, phrasing: str = "canonical"):
    """int32 (MAX_TOKENS,) an instruction's token ids; jit/vmap-able.

    constraints: int32 (MAX_RELATIONS, 2) (top, bottom) block indices, -1 rows are absent;
    tower_sentence: bool () starts with the tower sentence; phrasing (static, LANGUAGES): each
    sentence in its canonical phrasing, or in one drawn uniformly from the training
    paraphrases, the development phrasings or the sealed held-out phrasings; or (training
    only) "broad": the training paraphrases and the extras (:data:`EXTRA`); "natural": the
    canonical phrasing's tokens (:func:`phrasing_tokens`). The phrasings drawn are
    :func:`draw_phrasings`' of the same key.
    """
    return phrasing_tokens(draw_phrasings(key, phrasing), constraints, tower_sentence)


ROLES = ("top", "bottom")
"""The classes of :func:`token_roles`: a block named in a relation sentence is its upper or its
lower block, whatever the phrasing's word order."""


def token_roles(tokens, constraints, tower_sentence):
    """(roles int32 (L,), named bool (L,)) of an instruction's tokens; jit/vmap-able.

    tokens: int32 (L,) from :func:`instruction_tokens` for the same constraints (int32
    (MAX_RELATIONS, 2) (top, bottom), -1 rows absent, in sentence order) and tower_sentence
    (bool ()). A block's token in relation sentence j gets role 0 if it is that relation's
    top, 1 if its bottom (:data:`ROLES`); ``named`` marks those tokens (False elsewhere:
    other words, the tower sentence, padding).
    """
    tokens = jnp.asarray(tokens)
    constraints = jnp.asarray(constraints)
    ends = (tokens == VOCABULARY.word_to_id["."]).astype(jnp.int32)
    relation = jnp.cumsum(ends) - ends - jnp.asarray(tower_sentence, jnp.int32)
    rows = constraints[jnp.clip(relation, 0, constraints.shape[0] - 1)]
    is_top = tokens == block_token(rows[:, 0])
    is_bottom = tokens == block_token(rows[:, 1])
    named = (relation >= 0) & (rows[:, 0] >= 0) & (is_top | is_bottom)
    return jnp.where(is_bottom, 1, 0).astype(jnp.int32), named


def render(constraints, tower_sentence: bool, relation_templates=None, tower_template: int = 0):
    """Plain-Python rendering of an instruction (the reference for tests, and the text a
    denoiser on pretrained features reads): constraints ((top, bottom), ...) block indices (-1
    rows skipped), each present relation in relation_templates[k] (default canonical; indices
    of :func:`relation_phrasings`, the natural set's included), the tower sentence in
    tower_template (of :func:`tower_phrasings`)."""
    sentences = [tower_phrasings()[tower_template]] if tower_sentence else []
    rows = [(int(t), int(b)) for t, b in np.asarray(constraints).reshape(-1, 2) if t >= 0]
    templates = relation_templates or [0] * len(rows)
    phrasings = relation_phrasings()
    for (top, bottom), k in zip(rows, templates):
        sentences.append(language.render(phrasings[k], {
            "top": BLOCK_NAMES[top], "bottom": BLOCK_NAMES[bottom]}))
    return " ".join(sentences)


def sentence_templates(ids) -> list[tuple[str, int] | None]:
    """Which phrasing each sentence of an instruction (int token ids, numpy) is: ("tower", k)
    or ("relation", k), None for a sentence that is neither. Plain Python, for tests and
    checks of the training data (a batch at once: :func:`sentence_templates_batch`)."""
    return sentence_templates_batch(np.asarray(ids).reshape(1, -1))[0]


def split_sentences(ids) -> list[list[int]]:
    """Plain Python: the sentences of an instruction (int token ids), padding dropped, each
    ending with its "." (a last sentence without one is kept as it is)."""
    ids = [int(i) for i in np.asarray(ids).ravel() if int(i) != language.PAD_ID]
    stop = VOCABULARY.word_to_id["."]
    ends = [i + 1 for i, token in enumerate(ids) if token == stop]
    if ids and (not ends or ends[-1] != len(ids)):
        ends.append(len(ids))
    return [ids[a:b] for a, b in zip([0] + ends[:-1], ends)]


def sentence_templates_batch(tokens) -> list[list[tuple[str, int] | None]]:
    """:func:`sentence_templates` of each instruction of tokens int (N, L) (numpy), its
    sentences matched in one vmapped call per sentence kind."""
    per_instruction, rows = [], []
    for ids in np.asarray(tokens):
        sentences = split_sentences(ids)
        per_instruction.append([len(rows) + j if len(s) <= SENTENCE_TOKENS else None
                                for j, s in enumerate(sentences)])
        for sentence in sentences:
            row = np.zeros(SENTENCE_TOKENS, np.int32)
            row[:min(len(sentence), SENTENCE_TOKENS)] = sentence[:SENTENCE_TOKENS]
            rows.append(row)
    if not rows:
        return [[] for _ in per_instruction]
    rows = np.stack(rows)
    found = {kind: np.asarray(jax.vmap(lambda r, c=compiled: language.match_template(r, c)[0])(
        rows)) for kind, compiled in (("tower", TOWERS), ("relation", RELATIONS))}

    def which(j):
        if j is not None:
            for kind in ("tower", "relation"):
                if found[kind][j] >= 0:
                    return kind, int(found[kind][j])
        return None

    return [[which(j) for j in sentence_ids] for sentence_ids in per_instruction]
