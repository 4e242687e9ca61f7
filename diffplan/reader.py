"""A reader: small learned taggers that say which slot each slot word of an instruction fills.

A denoiser learns to read its instructions from the diffusion loss alone, and in a world where
the order of the words does not fix the roles (the Kuka world: "Put the red block below the
green block" means green on red) it reads phrasings it never saw no better than chance. A reader
is trained on the roles themselves: an ensemble of taggers (a :class:`TextEncoder` and a linear
head over R roles), each trained from its own seed on labelled instructions of the training
phrasings only, their role probabilities averaged. The world restates an instruction from the
roles read (``envs.<world>.reader``: which words fill slots, what a sentence is, how its
canonical phrasing is built), so the planner sees the phrasing it reads best.

Shapes: tokens int32 (..., L); role probabilities float32 (..., L, R); ensemble parameters are
the taggers' parameters stacked on a leading (E,) axis.

A saved reader is a checkpoint (``diffplan.checkpoint``) whose metadata holds the
:class:`ReaderConfig`; loading it builds the tagger from that config (nothing named in the
checkpoint is imported).
"""
from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from diffplan.text_encoder import TextEncoder

READER_KIND = "diffplan-reader/1"
"""The metadata marker of a saved reader."""


@dataclasses.dataclass(frozen=True)
class ReaderConfig:
    """One tagger's shape: vocabulary, instruction length L, roles R, encoder size;
    sentence_end_id: the token that ends a sentence (positions then count within sentences,
    ``TextEncoder.sentence_end_id``), -1 for absolute positions; sentence_local: 1 reads each
    sentence on its own (``TextEncoder.sentence_local``: a sentence's roles then do not depend
    on the sentences around it), 0 lets every token attend to the whole instruction."""

    vocab_size: int
    max_tokens: int
    num_roles: int
    dim: int = 64
    num_layers: int = 2
    num_heads: int = 4
    sentence_end_id: int = -1
    sentence_local: int = 0

    def __post_init__(self):
        for name in ("vocab_size", "max_tokens", "num_roles", "dim", "num_heads"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"ReaderConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.sentence_local not in (0, 1):
            raise ValueError(f"ReaderConfig.sentence_local must be 0 or 1, got "
                             f"{self.sentence_local}")
        if self.sentence_local and self.sentence_end_id < 0:
            raise ValueError("ReaderConfig.sentence_local=1 needs sentence_end_id (the token "
                             "that ends a sentence)")
        if self.num_roles < 2:
            raise ValueError(f"a reader tells at least 2 roles apart, got num_roles="
                             f"{self.num_roles}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "ReaderConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ValueError(f"unknown ReaderConfig fields {unknown}")
        return cls(**{k: int(v) for k, v in values.items()})


class Tagger(nn.Module):
    """tokens int32 (B, L) -> role logits float32 (B, L, R)."""

    config: ReaderConfig

    @nn.compact
    def __call__(self, tokens):
        c = self.config
        x, _ = TextEncoder(c.vocab_size, c.max_tokens, dim=c.dim, num_layers=c.num_layers,
                           num_heads=c.num_heads, sentence_end_id=c.sentence_end_id,
                           sentence_local=bool(c.sentence_local))(tokens)
        return nn.Dense(c.num_roles)(x)


def role_loss(logits, roles, named):
    """float32 (): mean cross-entropy of logits (..., L, R) against roles int (..., L) over the
    named (slot) tokens (bool (..., L))."""
    ce = optax.softmax_cross_entropy_with_integer_labels(logits, roles)
    return (ce * named).sum() / jnp.maximum(named.sum(), 1)


def train_tagger(config: ReaderConfig, batch_fn: Callable, seed: int, steps: int,
                 lr: float = 1e-3):
    """One tagger's parameters after ``steps`` Adam steps on ``batch_fn(key) -> (tokens int32
    (B, L), roles int32 (B, L), named bool (B, L))`` from seed (batch i from fold_in(key, i+1))."""
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    model = Tagger(config)
    key = jax.random.PRNGKey(seed)
    params = model.init(key, jnp.zeros((1, config.max_tokens), jnp.int32))
    opt = optax.adam(lr)

    @jax.jit
    def step(carry, i):
        params, opt_state = carry
        tokens, roles, named = batch_fn(jax.random.fold_in(key, i + 1))
        grads = jax.grad(lambda p: role_loss(model.apply(p, tokens), roles, named))(params)
        updates, opt_state = opt.update(grads, opt_state)
        return (optax.apply_updates(params, updates), opt_state), None

    # Compiled per tagger, as the shipped reader was trained: the same steps compiled as one
    # program shared by every seed differ in rounding, and the ensemble then reads the held-out
    # phrasings differently (90.0% instead of 85.2% restated; docs/results.md).
    run = jax.jit(lambda c: jax.lax.scan(step, c, jnp.arange(steps))[0])
    params, _ = run((params, opt.init(params)))
    return params


def train_reader(config: ReaderConfig, batch_fn: Callable, seeds: Sequence[int], steps: int,
                 lr: float = 1e-3, progress: Callable | None = None):
    """The ensemble's parameters (one tagger per seed, stacked on a leading (E,) axis);
    progress: optional callable run after each tagger."""
    seeds = list(seeds)
    if not seeds:
        raise ValueError("a reader needs at least one seed")
    trained = []
    for seed in seeds:
        trained.append(train_tagger(config, batch_fn, seed, steps, lr))
        if progress is not None:
            progress()
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trained)


def role_probabilities(config: ReaderConfig, params, tokens):
    """float32 (..., L, R): the ensemble's mean role probabilities of each token of tokens
    int32 (..., L); jit/vmap-able."""
    tokens = jnp.asarray(tokens, jnp.int32)
    lead = tokens.shape[:-1]
    flat = tokens.reshape((-1, tokens.shape[-1]))
    model = Tagger(config)
    probs = jax.vmap(lambda p: jax.nn.softmax(model.apply(p, flat), -1))(params)
    return probs.mean(0).reshape(lead + probs.shape[-2:])


def ensemble_size(params) -> int:
    return int(jax.tree.leaves(params)[0].shape[0])


def save_reader(directory: str, config: ReaderConfig, params, metadata: dict | None = None
                ) -> str:
    """Writes the reader (config, ensemble parameters, metadata: training command etc.) as an
    evaluation checkpoint in directory; returns the step directory."""
    from diffplan.checkpoint import save_checkpoint

    meta = dict(metadata or {})
    meta.update(reader=READER_KIND, reader_config=config.to_dict(),
                ensemble=ensemble_size(params))
    return save_checkpoint(directory, 0, jax.device_get(params), meta)


def load_reader(directory: str):
    """(ReaderConfig, ensemble parameters, metadata) of a reader saved by :func:`save_reader`;
    ValueError if the directory holds something else or its parameters do not have the
    shapes its config implies."""
    from diffplan.checkpoint import compare_param_shapes, load_checkpoint, read_metadata

    meta = read_metadata(directory)
    if meta.get("reader") != READER_KIND:
        raise ValueError(f"{directory} does not hold a reader (metadata reader="
                         f"{meta.get('reader')!r}, expected {READER_KIND!r})")
    config = ReaderConfig.from_dict(meta["reader_config"])
    e = int(meta["ensemble"])
    one = jax.eval_shape(lambda: Tagger(config).init(jax.random.PRNGKey(0), jnp.zeros(
        (1, config.max_tokens), jnp.int32)))
    expected = jax.tree.map(lambda s: jax.ShapeDtypeStruct((e,) + s.shape, s.dtype), one)
    state, _ = load_checkpoint(directory)
    params = state["ema_params"]
    problems = compare_param_shapes(params, expected, "reader parameter")
    if problems:
        raise ValueError(f"{directory}: " + "; ".join(problems))
    params = jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), params)
    return config, params, meta
