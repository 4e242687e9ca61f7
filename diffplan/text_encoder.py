"""A small pre-norm transformer encoder over instruction token ids (Flax linen), or over a
frozen pretrained encoder's token features (``context_dim > 0``).

Token id 0 is padding. The token-embedding table can be owned by the encoder or handed in
(``embed=...``), so that the denoiser's single ``nn.Embed`` embeds both the grid cells
(condition channel 0 holds cell token ids, CONVENTIONS.md) and the instruction words.

Shapes:
    tokens  (B, L)    int32, 0 = padding, L <= max_tokens
    output  features (B, L, dim) float32, mask (B, L) bool (True = real token)
Padding positions never influence real positions (key padding mask in every self-attention,
absolute learned positions starting at 0), so the features of an instruction do not depend on
how much padding follows it.

Positions: absolute (token i gets position i, the default), or per sentence when
``sentence_end_id`` names the token that ends a sentence (e.g. "."): a token's position counts
from the start of its sentence, and a learned embedding of the sentence's index is added. Then
the embedding of a sentence's words does not depend on how long the sentences before it are,
so a sentence reads the same wherever a multi-sentence instruction puts it.

Pretrained features (``context_dim = D > 0``): the input is float32 (B, L, D) token features
(``diffplan.instruction``), zero at padding; the mask is ``any(features != 0)``, and each token
is projected by a trainable Dense to ``dim`` and LayerNormed (params ``context_proj``,
``context_ln``) before the positions and layers, in place of the token table.

Sentence-local reading (``sentence_local=True``, with ``sentence_end_id``): every token attends
only to the tokens of its own sentence and no sentence-index embedding is added, so a sentence's
features are exactly the same whatever sentences stand before or after it (for tasks where a
word's meaning is fixed within its sentence).
"""
from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp
import flax.linen as nn

from diffplan.unet import MultiHeadAttention

__all__ = ["TextEncoderLayer", "TextEncoder", "sentence_positions"]


def sentence_positions(tokens: jax.Array, sentence_end_id: int) -> tuple[jax.Array, jax.Array]:
    """(position in its sentence, index of its sentence) of every token; both int32 (B, L).

    tokens: int (B, L). A sentence ends with (and includes) a token equal to sentence_end_id;
    the next token starts sentence index + 1 at position 0. Padding gets positions too (they
    are masked out of attention).
    """
    tokens = jnp.asarray(tokens)
    ends = (tokens == sentence_end_id).astype(jnp.int32)
    sentence = jnp.cumsum(ends, axis=1) - ends
    index = jnp.broadcast_to(jnp.arange(tokens.shape[1], dtype=jnp.int32), tokens.shape)
    after_end = jnp.pad(ends[:, :-1], ((0, 0), (1, 0))) > 0
    start = jax.lax.cummax(jnp.where(after_end, index, 0), axis=1)
    return index - start, sentence


class TextEncoderLayer(nn.Module):
    """Pre-norm layer: x + SelfAttn(LN x, mask); x + MLP(LN x).  (B, L, D) -> (B, L, D);
    mask bool (B, L) (keys) or (B, L, L) (per query, ``MultiHeadAttention``)."""

    num_heads: int
    mlp_ratio: int = 4

    @nn.compact
    def __call__(self, x: jax.Array, mask: jax.Array) -> jax.Array:
        d = x.shape[-1]
        x = x + MultiHeadAttention(self.num_heads, name="attn")(nn.LayerNorm(name="ln1")(x),
                                                                mask=mask)
        y = nn.Dense(self.mlp_ratio * d, name="mlp_in")(nn.LayerNorm(name="ln2")(x))
        return x + nn.Dense(d, name="mlp_out")(nn.gelu(y))


class TextEncoder(nn.Module):
    """Token ids -> contextual features and padding mask.

    Attributes:
      vocab_size: size of the token vocabulary (ids in [0, vocab_size)).
      max_tokens: maximum instruction length L (size of the positional table).
      dim: feature width D of the output.
      num_layers: transformer layers (0 = embeddings + positions + final LayerNorm only).
      num_heads: attention heads (must divide dim).
      embed_dim: width of the owned token table (default: dim); ignored when ``embed`` is given.
      embed: an optional shared ``nn.Embed`` module (the denoiser's table); if its width differs
        from ``dim`` a Dense projection is added.
      project: with context_dim: an optional shared module mapping the features (B, L, D) to
        some width (the denoiser's ``context_embed``, which also embeds its grid cells'
        names); a Dense ``embed_proj`` follows if that width differs from ``dim``. Default:
        the encoder's own Dense + LayerNorm to ``dim``.
      sentence_end_id: -1 (absolute positions), or the token id that ends a sentence: positions
        count within each sentence, plus a learned sentence-index table ``sentence_embed``
        (:func:`sentence_positions`).
      sentence_local: attention stays within each sentence and the sentence-index table is
        left out (requires sentence_end_id >= 0).
      context_dim: 0 (token ids), or D: the input is pretrained token features (B, L, D).

    Call: tokens (B, L) int32 (or features (B, L, context_dim) float32) -> (features (B, L,
    dim) float32, mask (B, L) bool).
    """

    vocab_size: int
    max_tokens: int
    dim: int = 64
    num_layers: int = 2
    num_heads: int = 4
    embed_dim: Optional[int] = None
    embed: Optional[nn.Module] = None
    project: Optional[nn.Module] = None
    sentence_end_id: int = -1
    sentence_local: bool = False
    context_dim: int = 0

    @nn.compact
    def __call__(self, tokens: jax.Array) -> tuple[jax.Array, jax.Array]:
        if self.dim % self.num_heads:
            raise ValueError(f"text dim={self.dim} is not divisible by num_heads={self.num_heads}")
        if self.context_dim and (self.sentence_end_id >= 0 or self.sentence_local):
            raise ValueError("per-sentence positions read token ids (sentence_end_id): not "
                             "with pretrained features (context_dim > 0)")
        x, mask = (self._project_features if self.context_dim else self._embed_tokens)(tokens)
        length = tokens.shape[1]
        attend = mask
        pos = self.param("pos_embed", nn.initializers.normal(0.02), (self.max_tokens, self.dim))
        if self.sentence_end_id < 0:
            x = x + pos[None, :length]
        else:
            position, sentence = sentence_positions(tokens, self.sentence_end_id)
            x = x + pos[position]
            if self.sentence_local:
                same = sentence[:, :, None] == sentence[:, None, :]
                attend = mask[:, :, None] & mask[:, None, :] & same
            else:
                sentences = self.param("sentence_embed", nn.initializers.normal(0.02),
                                       (self.max_tokens, self.dim))
                x = x + sentences[sentence]
        for i in range(self.num_layers):
            x = TextEncoderLayer(self.num_heads, name=f"layer{i}")(x, attend)
        x = nn.LayerNorm(name="ln_final")(x)
        return x, mask

    def _embed_tokens(self, tokens):
        """(embedded tokens (B, L, dim), mask) of token ids (B, L)."""
        if tokens.ndim != 2:
            raise ValueError(f"tokens must have shape (B, L), got {tokens.shape}")
        if tokens.shape[1] > self.max_tokens:
            raise ValueError(f"instruction length L={tokens.shape[1]} exceeds "
                             f"max_tokens={self.max_tokens}")
        if not jnp.issubdtype(tokens.dtype, jnp.integer):
            raise ValueError(f"tokens must be integer ids, got dtype {tokens.dtype} (this "
                             "encoder reads token ids, not pretrained features)")
        if self.sentence_local and self.sentence_end_id < 0:
            raise ValueError("sentence_local needs sentence_end_id (the token ending a sentence)")
        tokens = tokens.astype(jnp.int32)
        table = self.embed
        if table is None:
            table = nn.Embed(self.vocab_size, self.embed_dim or self.dim, name="token_embed")
        x = table(tokens)
        if x.shape[-1] != self.dim:
            x = nn.Dense(self.dim, name="embed_proj")(x)
        return x, tokens != 0

    def _project_features(self, features):
        """(projected features (B, L, dim), mask) of pretrained token features (B, L, D)."""
        if features.ndim != 3 or features.shape[-1] != self.context_dim:
            raise ValueError(f"this encoder reads pretrained token features (B, L, "
                             f"{self.context_dim}), got shape {features.shape}")
        if features.shape[1] > self.max_tokens:
            raise ValueError(f"instruction length L={features.shape[1]} exceeds "
                             f"max_tokens={self.max_tokens}")
        features = features.astype(jnp.float32)
        mask = jnp.any(features != 0, axis=-1)
        if self.project is None:
            x = nn.LayerNorm(name="context_ln")(nn.Dense(self.dim, name="context_proj")(features))
        else:
            x = self.project(features)
            if x.shape[-1] != self.dim:
                x = nn.Dense(self.dim, name="embed_proj")(x)
        return x, mask
