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

import dataclasses
import re
from typing import Iterable, Mapping, Sequence

import numpy as np

PAD_ID = 0

UNSEEN = "unseen"
DEVELOPMENT = "development"
HELDOUT = "heldout"
LANGUAGES = ("canonical", "paraphrased", UNSEEN)
"""How an episode's instruction is phrased (the grid world's languages; a world names its own
with :meth:`TemplateSplit.languages`): ``canonical`` in each sentence's template 0 (the paper's
wording); ``paraphrased`` in a uniformly drawn training paraphrase (never template 0);
``unseen`` in a uniformly drawn held-out phrasing that no training batch ever contains (every
word of it occurs in a training phrasing: new wording, not new words)."""
NATURAL = "natural"
"""The sealed natural-language test sets (``envs/<world>/natural.py``): sentences as people type
them, never trained on and never chosen on; only a denoiser on pretrained text features
(``diffplan.instruction``) can read them."""
NEVER_TRAINED = (UNSEEN, DEVELOPMENT, HELDOUT, NATURAL)
"""Languages no training batch ever draws: a split's :attr:`TemplateSplit.unseen` phrasings,
named ``unseen`` (the grid world) or ``development`` (phrasings that were looked at to choose
things, so their rows are development numbers: the Kuka world), and its sealed held-out
phrasings (:attr:`TemplateSplit.sealed`, the language ``heldout``), and the sealed
natural-language sets (:data:`NATURAL`)."""
TRAINING = "mixed"
"""The phrasing of training examples (not an evaluation language): canonical half of the time,
otherwise a uniformly drawn training paraphrase (:meth:`TemplateSplit.pool`)."""
BROAD = "broad"
"""A training-only phrasing (not an evaluation language): a uniformly drawn training paraphrase
or training-only extra phrasing (:attr:`TemplateSplit.extra`), so that a denoiser can be
trained on more word orders while the ``paraphrased`` and ``unseen`` evaluation rows keep the
phrasings they always had."""

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


@dataclasses.dataclass(frozen=True)
class TemplateSplit:
    """Which phrasings of one sentence kind are canonical, trained on, or held out.

    templates: the phrasings (template 0 canonical); unseen: the indices held out of training
    (a fixed third, never 0), drawn by the language ``unseen_name`` ("unseen", or
    "development" where they were looked at to choose things); extra: indices of
    training-only phrasings, drawn only by the :data:`BROAD` training language (never by an
    evaluation language); sealed: indices of a sealed held-out set, drawn only by the
    language :data:`HELDOUT` (never trained on, nothing ever chosen on it). Every phrasing is
    made of the training phrasings' words (so that adding one leaves the vocabulary as it
    was). Raises ValueError if a held-out, extra or sealed phrasing has a word (slots
    excepted) that no training phrasing has, or if the indices are out of range or overlap.
    """

    templates: tuple[str, ...]
    unseen: tuple[int, ...]
    slots: tuple[str, ...] = ()
    extra: tuple[int, ...] = ()
    sealed: tuple[int, ...] = ()
    unseen_name: str = UNSEEN

    def __post_init__(self):
        n = len(self.templates)
        if len(set(self.templates)) != n:
            raise ValueError("templates must be distinct")
        if self.unseen_name not in (UNSEEN, DEVELOPMENT):
            raise ValueError(f"unseen_name must be {UNSEEN!r} or {DEVELOPMENT!r}, got "
                             f"{self.unseen_name!r}")
        if not all(0 < i < n for i in self.unseen) or len(set(self.unseen)) != len(self.unseen):
            raise ValueError(f"unseen must be distinct indices in 1..{n - 1}, got {self.unseen}")
        if not all(0 < i < n for i in self.extra) or len(set(self.extra)) != len(self.extra) \
                or set(self.extra) & set(self.unseen):
            raise ValueError(f"extra must be distinct indices in 1..{n - 1}, none held out, got "
                             f"{self.extra}")
        if not all(0 < i < n for i in self.sealed) or len(set(self.sealed)) != len(
                self.sealed) or set(self.sealed) & (set(self.unseen) | set(self.extra)):
            raise ValueError(f"sealed must be distinct indices in 1..{n - 1}, neither held out "
                             f"nor extra, got {self.sealed}")
        known = self.training_words()
        for kind, indices in (("held-out", self.unseen), ("extra", self.extra),
                              ("sealed", self.sealed)):
            for i in indices:
                new = sorted(template_words([self.templates[i]], self.slots) - known)
                if new:
                    raise ValueError(f"{kind} phrasing {self.templates[i]!r} has words no "
                                     f"training phrasing has: {new}")

    @property
    def training(self) -> tuple[int, ...]:
        """Template indices training draws from in every training language (canonical and the
        training paraphrases; the extra, held-out and sealed phrasings are not among them)."""
        excluded = set(self.unseen) | set(self.extra) | set(self.sealed)
        return tuple(i for i in range(len(self.templates)) if i not in excluded)

    @property
    def languages(self) -> tuple[str, ...]:
        """The evaluation languages this split answers to: canonical, paraphrased, the
        held-out phrasings' name (``unseen_name``) and, with a sealed set, :data:`HELDOUT`."""
        return ("canonical", "paraphrased", self.unseen_name) + (
            (HELDOUT,) if self.sealed else ())

    def training_words(self) -> set[str]:
        """Every word of the training phrasings (slots excepted): the vocabulary they need,
        which the held-out ones share."""
        return template_words([self.templates[i] for i in self.training], self.slots)

    def pool(self, language: str) -> np.ndarray:
        """int32 (P,) template indices an episode of ``language`` draws from uniformly
        (:attr:`languages`, or TRAINING: template 0 repeated once per training paraphrase,
        then the paraphrases, so that half of the draws are canonical; or BROAD: the training
        paraphrases and the extra phrasings)."""
        paraphrases = [i for i in self.training if i != 0]
        pools = {"canonical": [0], "paraphrased": paraphrases,
                 self.unseen_name: list(self.unseen),
                 TRAINING: [0] * len(paraphrases) + paraphrases,
                 BROAD: paraphrases + list(self.extra)}
        if self.sealed:
            pools[HELDOUT] = list(self.sealed)
        if language not in pools:
            raise ValueError(f"unknown language {language!r}; expected one of "
                             f"{self.languages + TRAINING_ONLY}")
        return np.asarray(pools[language], np.int32)


TRAINING_ONLY = (TRAINING, BROAD)
"""Phrasings only training draws (never an evaluation row)."""


def check_language(language: str, training: bool = True,
                   languages: Sequence[str] = LANGUAGES) -> str:
    """language if it is one of ``languages`` (default the grid world's LANGUAGES; or
    TRAINING_ONLY when ``training``), else ValueError."""
    allowed = tuple(languages) + (TRAINING_ONLY if training else ())
    if language not in allowed:
        raise ValueError(f"unknown language {language!r}; expected one of {allowed}")
    return language


def check_training_language(language: str, languages: Sequence[str] = LANGUAGES) -> str:
    """language if training may draw it (ValueError for :data:`NEVER_TRAINED`: the
    held-out, development and sealed phrasings never reach a training batch), checked as
    :func:`check_language` against ``languages`` (a world's evaluation languages)."""
    if language in NEVER_TRAINED:
        raise ValueError(f"training never draws the held-out ({language!r}) phrasings")
    return check_language(language, languages=languages)


def draw_template(key, pool, shape=()):
    """int32 ``shape`` template indices drawn uniformly from ``pool`` (int (P,), from
    :meth:`TemplateSplit.pool`); a one-entry pool consumes no randomness. jit-able."""
    import jax
    import jax.numpy as jnp

    pool = np.asarray(pool, np.int32)
    if len(pool) == 1:
        return jnp.full(shape, pool[0], jnp.int32)
    return jnp.asarray(pool)[jax.random.randint(key, shape, 0, len(pool))]


def check_dropout_rate(rate: float, name: str = "word dropout rate") -> float:
    """rate if it is a word dropout probability in [0, 1) (ValueError naming ``name`` else)."""
    if not 0 <= rate < 1:
        raise ValueError(f"{name} must be in [0, 1), got {rate}")
    return rate


def drop_words(key, tokens, rate: float, keep_ids):
    """Word dropout for training instructions: each word of tokens int (..., L) that is not
    padding and not among keep_ids (int (K,), e.g. the slot fillers: object names, compass
    directions) becomes padding with probability rate, independently. Positions do not move
    (the encoders mask padding, so a dropped word is a hole, not a shift). rate 0 returns
    tokens unchanged and consumes no randomness. jit-able."""
    import jax
    import jax.numpy as jnp

    check_dropout_rate(rate)
    tokens = jnp.asarray(tokens)
    if rate == 0:
        return tokens
    droppable = (tokens != PAD_ID) & ~jnp.isin(tokens, jnp.asarray(keep_ids, tokens.dtype))
    drop = jax.random.bernoulli(key, rate, tokens.shape) & droppable
    return jnp.where(drop, jnp.asarray(PAD_ID, tokens.dtype), tokens)


def match_template(tokens, compiled):
    """(index, slot tokens): which compiled template (int (N, L), slot markers negative; a
    numpy constant) the instruction tokens (int (L,)) are, and the token in each slot. index
    is -1 when none matches; slot tokens int32 (S,) (S = the number of distinct markers), 0
    where unmatched. jit-able in tokens; the first matching template wins, a slot's first
    occurrence is read."""
    import jax.numpy as jnp

    compiled = np.asarray(compiled)
    num_slots = int(-np.min(compiled, initial=0))
    compiled = jnp.asarray(compiled)
    tokens = jnp.asarray(tokens)
    fixed = compiled >= 0
    match = jnp.all(jnp.where(fixed, compiled == tokens[None], tokens[None] != PAD_ID), axis=-1)
    index = jnp.where(jnp.any(match), jnp.argmax(match), -1)
    row = compiled[jnp.maximum(index, 0)]
    slots = []
    for k in range(num_slots):
        at = row == -(k + 1)
        slots.append(jnp.where(jnp.any(at) & (index >= 0), tokens[jnp.argmax(at)], 0))
    return index.astype(jnp.int32), jnp.stack(slots).astype(jnp.int32) if slots else \
        jnp.zeros((0,), jnp.int32)


def slot_roles(tokens, compiled):
    """(roles int32 (L,), named bool (L,)): which slot each token of an instruction fills,
    read off the compiled template it matches (:func:`match_template`): slot marker -(k + 1)
    gives role k; ``named`` marks slot tokens (all False when no template matches). jit-able
    in tokens; the labels of an auxiliary token loss (``diffplan.losses.token_loss``)."""
    import jax.numpy as jnp

    index, _ = match_template(tokens, compiled)
    row = jnp.asarray(np.asarray(compiled))[jnp.maximum(index, 0)]
    named = (row < 0) & (index >= 0)
    return jnp.where(named, -row - 1, 0).astype(jnp.int32), named
