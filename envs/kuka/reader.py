"""The Kuka world's reader (``diffplan.reader``): which block of each relation sentence is
the upper one, read by learned taggers, and the instruction restated in its canonical
phrasing.

Training instructions (:func:`role_batch`) are drawn like the episodes' (one to three
relation sentences, a single one sometimes after the tower sentence) in the training
phrasings: canonical, the training paraphrases and the training-only extras
(``grammar.EXTRA``); never a development or sealed held-out one. Labels are
``grammar.token_roles``: of each block word, whether it names its relation's upper or lower
block.

Restating (:func:`canonical_tokens`): a first sentence that names no block, followed by another,
is the tower sentence; in every other sentence (a relation sentence) the block word the reader
gives the higher probability of being the upper block is the top, the other the bottom; the
instruction is rebuilt with ``grammar.instruction_tokens(..., "canonical")``. The reader never
changes an instruction silently: a sentence it cannot restate (:data:`PROBLEMS`: other than two
block words, the same block twice, a relation sentence that opens with a preposition, which no
training phrasing does, or two block words read as the same role), an instruction with no
relation or more than MAX_RELATIONS of them, is flagged inside jit (:func:`read_episodes`: the
episode is not acted on and counts as failed) and refused in one line by :func:`read_text`.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffplan import language
from diffplan.reader import ReaderConfig, role_probabilities
from diffplan.text_encoder import sentence_positions
from envs.kuka import grammar, scene

BATCH = 128
"""Instructions per training batch."""
STEPS = 2000
"""Training steps per tagger (about two minutes each here)."""
SEEDS = (0, 1, 2, 3, 4)
"""The shipped reader's taggers."""


def reader_config(**overrides) -> ReaderConfig:
    """The Kuka reader's tagger: the instruction's vocabulary and length, the roles
    ``grammar.ROLES``, positions counted within sentences, each sentence read on its own (which
    block is the upper one is decided within its relation sentence, so a phrasing read right
    in one place is read right in every place)."""
    values = dict(vocab_size=len(grammar.VOCAB), max_tokens=grammar.MAX_TOKENS,
                  num_roles=len(grammar.ROLES),
                  sentence_end_id=grammar.VOCABULARY.word_to_id["."], sentence_local=1)
    values.update(overrides)
    return ReaderConfig(**values)


def _instructions(key, n: int, phrasing: str):
    """n random instructions of phrasing: (tokens int32 (n, L), roles, named)."""
    k_count, k_tower, k_pairs, k_words = jax.random.split(key, 4)
    count = jax.random.randint(k_count, (n,), 1, grammar.MAX_RELATIONS + 1)
    pairs = jax.vmap(lambda k: jax.vmap(
        lambda kk: jax.random.permutation(kk, scene.NUM_BLOCKS)[:2])(
        jax.random.split(k, grammar.MAX_RELATIONS)))(jax.random.split(k_pairs, n))
    rows = jnp.arange(grammar.MAX_RELATIONS)[None, :, None] < count[:, None, None]
    constraints = jnp.where(rows, pairs, -1).astype(jnp.int32)
    tower = jax.random.bernoulli(k_tower, 0.5, (n,)) & (count == 1)  # as in the episodes
    tokens = jax.vmap(lambda k, c, t: grammar.instruction_tokens(k, c, t, phrasing))(
        jax.random.split(k_words, n), constraints, tower)
    roles, named = jax.vmap(grammar.token_roles)(tokens, constraints, tower)
    return tokens, roles, named


def role_batch(key, n: int = BATCH):
    """A training batch of n instructions: a quarter canonical, a quarter in the training
    paraphrases, half in the broad phrasings (paraphrases and extras): (tokens int32 (n, L),
    roles int32 (n, L) 1 where the token names a lower block, named bool (n, L) block words of
    relation sentences); jit-able."""
    keys = jax.random.split(key, 3)
    sizes = (n // 4, n // 4, n - 2 * (n // 4))
    parts = [_instructions(k, m, phrasing) for k, m, phrasing in
             zip(keys, sizes, ("canonical", "paraphrased", language.BROAD))]
    return tuple(jnp.concatenate(xs) for xs in zip(*parts))


PREPOSITIONS = ("above", "below", "beneath", "into", "of", "on", "onto", "under", "with")
"""The vocabulary's prepositions. No training, extra or development phrasing opens a relation
sentence with one, so the taggers never learnt to read such a sentence: the reader refuses it
(a rule fixed from the training phrasings, not chosen on any held-out phrasing)."""
PROBLEMS = ("", "names {blocks} block words, not two", "names the same block twice",
            "opens with a preposition ({first!r}): the reader was never trained on such a "
            "sentence and refuses it", "its two blocks are read as the same one (both the "
            "upper or both the lower block)")
"""Why a relation sentence cannot be restated, by the codes of :func:`sentence_problems`."""
_PREPOSITION_IDS = np.array([grammar.VOCABULARY.word_to_id[w] for w in PREPOSITIONS])
_STOP = grammar.VOCABULARY.word_to_id["."]


def sentence_problems(tokens, p_top=None):
    """What an instruction says and what keeps it from being restated; jit/vmap-able.

    tokens int32 (L,); p_top float32 (L,) each token's probability of naming its relation's
    upper block (None: the sentence's words only, no role checked). Returns (problems int32
    (L,): for sentence j of the instruction, the code of :data:`PROBLEMS` (0: it can be
    restated; the tower sentence and absent sentences 0); tower bool (): the instruction opens
    with the tower sentence; relation int32 (L,): each token's relation sentence (-1 in the
    tower sentence); relations int32 (): how many relation sentences)."""
    tokens = jnp.asarray(tokens, jnp.int32)
    n = tokens.shape[0]
    position, sentence = (x[0] for x in sentence_positions(tokens[None], _STOP))
    block, words = grammar.is_block_token(tokens), tokens != language.PAD_ID
    tower = (jnp.any(words & (sentence == 0)) & ~jnp.any(block & (sentence == 0))
             & jnp.any(words & (sentence == 1)))
    segment = jnp.where(words, sentence, n)

    def per_sentence(values, reduce="add", fill=0):
        out = jnp.full(n + 1, fill, jnp.int32)
        return getattr(out.at[segment], reduce)(values.astype(jnp.int32))[:n]

    is_relation = (per_sentence(words, "max") > 0) & ~(tower & (jnp.arange(n) == 0))
    blocks = per_sentence(block)
    low = per_sentence(jnp.where(block, tokens, n), "min", n)
    high = per_sentence(jnp.where(block, tokens, -1), "max", -1)
    first = per_sentence(jnp.where(position == 0, tokens, 0))
    problems = jnp.where(blocks != 2, 1, jnp.where(low == high, 2, jnp.where(
        jnp.isin(first, _PREPOSITION_IDS), 3, 0)))
    if p_top is not None:
        tops = per_sentence(block & (jnp.asarray(p_top) > 0.5))
        problems = jnp.where((problems == 0) & (tops != 1), 4, problems)
    relation = jnp.where(tower & (sentence == 0), -1, sentence - tower.astype(jnp.int32))
    return (jnp.where(is_relation, problems, 0).astype(jnp.int32), tower, relation,
            is_relation.sum().astype(jnp.int32))


def canonical_tokens(tokens, p_top):
    """(int32 (L,) tokens (int32 (L,), an instruction) restated canonically from p_top float32
    (L,), each token's probability of naming its relation's upper block; unread bool (): the
    instruction cannot be restated (:func:`sentence_problems`, or no relation sentence, or
    more than MAX_RELATIONS), its restated tokens then meaningless); jit/vmap-able."""
    tokens = jnp.asarray(tokens, jnp.int32)
    problems, tower, relation, count = sentence_problems(tokens, p_top)
    unread = jnp.any(problems != 0) | (count == 0) | (count > grammar.MAX_RELATIONS)
    block = grammar.is_block_token(tokens)
    index = jnp.arange(tokens.shape[0])
    rows = []
    for k in range(grammar.MAX_RELATIONS):
        here = block & (relation == k)
        top = jnp.argmax(jnp.where(here, p_top, -jnp.inf))
        bottom = jnp.argmax(jnp.where(here & (index != top), -p_top, -jnp.inf))
        pair = jnp.stack([tokens[top], tokens[bottom]]) - grammar.block_token(0)
        rows.append(jnp.where(k < count, pair, -1))
    constraints = jnp.stack(rows).astype(jnp.int32)
    restated = grammar.instruction_tokens(jax.random.PRNGKey(0), constraints, tower,
                                          "canonical")
    return restated, unread


def restate(config: ReaderConfig, params, tokens):
    """(int32 (..., L), unread bool (...)): instructions tokens int32 (..., L) restated
    canonically by the reader (config, ensemble params), and which of them it could not
    restate (:func:`canonical_tokens`); jit-able."""
    tokens = jnp.asarray(tokens, jnp.int32)
    lead = tokens.shape[:-1]
    flat = tokens.reshape((-1, tokens.shape[-1]))
    top = role_probabilities(config, params, flat)[..., grammar.ROLES.index("top")]
    restated, unread = jax.vmap(canonical_tokens)(flat, top)
    return restated.reshape(lead + tokens.shape[-1:]), unread.reshape(lead)


restate_jit = jax.jit(restate, static_argnums=0)
""":func:`restate` compiled (config static)."""


def read_episodes(reader, episodes):
    """(episodes, unread bool (B,)): a batch of Episodes (leading (B,) axis) whose
    instructions the reader (ReaderConfig, params; None: no reader, nothing flagged) restated
    canonically. An episode it could not restate is flagged and allowed no placement
    (max_steps 0: the arm does nothing, so, every block starting on the floor, none of its
    instructed relations holds and it counts as failed)."""
    if reader is None:
        return episodes, np.zeros(episodes.tokens.shape[0], bool)
    tokens, unread = restate_jit(*reader, episodes.tokens)
    return episodes.replace(tokens=tokens, max_steps=jnp.where(
        unread, 0, episodes.max_steps).astype(episodes.max_steps.dtype)), unread


def read_rate(config: ReaderConfig, params, key, n: int, phrasing: str) -> float:
    """% of n random instructions in phrasing (drawn from key, as :func:`role_batch` draws)
    that the reader restates exactly as the canonical instruction of the same relations (an
    instruction it refuses is not restated)."""
    k_draw = jax.random.fold_in(key, 0)
    tokens, _, _ = _instructions(k_draw, n, phrasing)
    canonical, _, _ = _instructions(k_draw, n, "canonical")
    restated, unread = restate_jit(config, params, tokens)
    return 100.0 * float((jnp.all(restated == canonical, -1) & ~unread).mean())


_problems_jit = jax.jit(sentence_problems)


def check_readable(tokens, p_top=None) -> None:
    """ValueError (one line) naming the first sentence of an instruction (int tokens (L,),
    host-side) that :func:`canonical_tokens` could not restate and why (:data:`PROBLEMS`;
    p_top float (L,): the roles read, checked too when given), or saying that it names no
    relation or more than MAX_RELATIONS of them. Only a first sentence followed by another may
    name no block (the tower sentence)."""
    problems, _, _, count = jax.device_get(_problems_jit(jnp.asarray(tokens, jnp.int32), p_top))
    for sentence, code in zip(grammar.split_sentences(tokens), problems):
        if code:
            blocks = sum(bool(grammar.is_block_token(t)) for t in sentence)
            why = PROBLEMS[code].format(blocks=blocks, first=grammar.VOCAB[sentence[0]])
            raise ValueError(f"cannot read {grammar.decode(sentence)!r}: a relation sentence "
                             f"names two different blocks as the upper and the lower one; "
                             f"this one {why}")
    if not 1 <= count <= grammar.MAX_RELATIONS:
        raise ValueError(f"the instruction has {count} relation sentences; the reader restates "
                         f"at least 1 and no more than {grammar.MAX_RELATIONS}")


def read_text(config: ReaderConfig, params, text: str):
    """int32 (L,): a user's instruction text restated canonically by the reader; ValueError
    (one line) for a word outside the vocabulary or an instruction it could not restate
    (:func:`check_readable`: what it says, then the roles it reads)."""
    tokens = grammar.encode(text)
    check_readable(tokens)
    p_top = role_probabilities(config, params, jnp.asarray(tokens))[
        ..., grammar.ROLES.index("top")]
    check_readable(tokens, p_top)
    restated, unread = restate_jit(config, params, jnp.asarray(tokens))
    if bool(unread):  # every reason is named above; this is the jit side agreeing
        raise ValueError(f"cannot read {text!r}")
    return restated
