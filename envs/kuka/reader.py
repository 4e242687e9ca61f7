"""The Kuka world's reader (``diffplan.reader``): which block of each relation sentence is
the upper one, read by learned taggers, and the instruction restated in its canonical
phrasing.

Training instructions (:func:`role_batch`) are drawn like the episodes' (one to three
relation sentences, a single one sometimes after the tower sentence) in the training
phrasings: canonical, the training paraphrases and the training-only extras
(``grammar.EXTRA``); never a held-out one. Labels are
``grammar.token_roles``: of each block word, whether it names its relation's upper or lower
block.

Restating (:func:`canonical_tokens`): a first sentence that names no block is the tower
sentence; in every other sentence with two block words the one the reader gives the higher
probability of being the upper block is the top, the other the bottom; the instruction is
rebuilt with ``grammar.instruction_tokens(..., "canonical")``. Inside jit, sentences with any
other number of block words are dropped; a user's own text goes through :func:`read_text`,
which refuses such a sentence with one line naming it instead.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

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


def canonical_tokens(tokens, p_top):
    """int32 (L,) tokens (int32 (L,), an instruction) restated canonically from p_top float32
    (L,), each token's probability of naming its relation's upper block; jit/vmap-able."""
    tokens = jnp.asarray(tokens, jnp.int32)
    sentence = sentence_positions(tokens[None], grammar.VOCABULARY.word_to_id["."])[1][0]
    block = grammar.is_block_token(tokens)
    words = tokens != language.PAD_ID
    tower = jnp.any(words & (sentence == 0)) & ~jnp.any(block & (sentence == 0))
    relation = sentence - tower.astype(jnp.int32)
    # relation sentences in order: the k-th sentence with exactly two block words is relation k
    counts = jnp.zeros(tokens.shape[0] + 1, jnp.int32).at[
        jnp.where(block, relation, tokens.shape[0])].add(1)[:-1]
    valid = counts == 2
    order = jnp.cumsum(valid) - 1
    index = jnp.arange(tokens.shape[0])
    rows = []
    for k in range(grammar.MAX_RELATIONS):
        j = jnp.argmax(valid & (order == k))
        present = jnp.any(valid & (order == k))
        here = block & (relation == j)
        top = jnp.argmax(jnp.where(here, p_top, -jnp.inf))
        bottom = jnp.argmax(jnp.where(here & (index != top), -p_top, -jnp.inf))
        pair = jnp.stack([tokens[top], tokens[bottom]]) - grammar.block_token(0)
        rows.append(jnp.where(present, pair, -1))
    constraints = jnp.stack(rows).astype(jnp.int32)
    return grammar.instruction_tokens(jax.random.PRNGKey(0), constraints, tower, "canonical")


def restate(config: ReaderConfig, params, tokens):
    """int32 (..., L): instructions tokens int32 (..., L) restated canonically by the reader
    (config, ensemble params); jit-able."""
    tokens = jnp.asarray(tokens, jnp.int32)
    lead = tokens.shape[:-1]
    flat = tokens.reshape((-1, tokens.shape[-1]))
    top = role_probabilities(config, params, flat)[..., grammar.ROLES.index("top")]
    return jax.vmap(canonical_tokens)(flat, top).reshape(lead + tokens.shape[-1:])


restate_jit = jax.jit(restate, static_argnums=0)
""":func:`restate` compiled (config static)."""


def read_rate(config: ReaderConfig, params, key, n: int, phrasing: str) -> float:
    """% of n random instructions in phrasing (drawn from key, as :func:`role_batch` draws)
    that the reader restates exactly as the canonical instruction of the same relations."""
    k_draw = jax.random.fold_in(key, 0)
    tokens, _, _ = _instructions(k_draw, n, phrasing)
    canonical, _, _ = _instructions(k_draw, n, "canonical")
    restated = restate_jit(config, params, tokens)
    return 100.0 * float(jnp.all(restated == canonical, -1).mean())


def check_readable(tokens) -> None:
    """ValueError naming the first sentence of an instruction (int tokens (L,), host-side) that
    :func:`canonical_tokens` could not restate: only a first sentence may name no block (the
    tower sentence); every other must name two different blocks; at most MAX_RELATIONS of
    them."""
    sentences = grammar.split_sentences(tokens)
    relations = 0
    for i, sentence in enumerate(sentences):
        blocks = [t for t in sentence if grammar.is_block_token(t)]
        if not blocks and i == 0 and len(sentences) > 1:
            continue
        if len(blocks) != 2 or blocks[0] == blocks[1]:
            raise ValueError(f"cannot read {grammar.decode(sentence)!r}: a relation sentence "
                             f"names two different blocks, this one names {len(blocks)}"
                             + (" (the same block twice)" if len(blocks) == 2 else ""))
        relations += 1
    if relations > grammar.MAX_RELATIONS:
        raise ValueError(f"the instruction has {relations} relation sentences, more than "
                         f"{grammar.MAX_RELATIONS}")


def read_text(config: ReaderConfig, params, text: str):
    """int32 (L,): a user's instruction text restated canonically by the reader; ValueError
    (one line) for a word outside the vocabulary or a sentence it could not restate
    (:func:`check_readable`)."""
    tokens = grammar.encode(text)
    check_readable(tokens)
    return restate_jit(config, params, jnp.asarray(tokens))
