"""A small pre-norm transformer encoder over instruction token ids (Flax linen).

Token id 0 is padding. The token-embedding table can be owned by the encoder or handed in
(``embed=...``), so that the denoiser's single ``nn.Embed`` embeds both the grid cells
(condition channel 0 holds cell token ids, CONVENTIONS.md) and the instruction words.

Shapes:
    tokens  (B, L)    int32, 0 = padding, L <= max_tokens
    output  features (B, L, dim) float32, mask (B, L) bool (True = real token)
Padding positions never influence real positions (key padding mask in every self-attention,
absolute learned positions starting at 0), so the features of an instruction do not depend on
how much padding follows it.
"""
from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp
import flax.linen as nn

from diffplan.unet import MultiHeadAttention

__all__ = ["TextEncoderLayer", "TextEncoder"]


class TextEncoderLayer(nn.Module):
    """Pre-norm layer: x + SelfAttn(LN x, mask); x + MLP(LN x).  (B, L, D) -> (B, L, D)."""

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

    Call: tokens (B, L) int32 -> (features (B, L, dim) float32, mask (B, L) bool).
    """

    vocab_size: int
    max_tokens: int
    dim: int = 64
    num_layers: int = 2
    num_heads: int = 4
    embed_dim: Optional[int] = None
    embed: Optional[nn.Module] = None

    @nn.compact
    def __call__(self, tokens: jax.Array) -> tuple[jax.Array, jax.Array]:
        if self.dim % self.num_heads:
            raise ValueError(f"text dim={self.dim} is not divisible by num_heads={self.num_heads}")
        if tokens.ndim != 2:
            raise ValueError(f"tokens must have shape (B, L), got {tokens.shape}")
        b, length = tokens.shape
        if length > self.max_tokens:
            raise ValueError(f"instruction length L={length} exceeds max_tokens={self.max_tokens}")
        if not jnp.issubdtype(tokens.dtype, jnp.integer):
            raise ValueError(f"tokens must be integer ids, got dtype {tokens.dtype}")
        tokens = tokens.astype(jnp.int32)
        mask = tokens != 0
        table = self.embed
        if table is None:
            table = nn.Embed(self.vocab_size, self.embed_dim or self.dim, name="token_embed")
        x = table(tokens)
        if x.shape[-1] != self.dim:
            x = nn.Dense(self.dim, name="embed_proj")(x)
        pos = self.param("pos_embed", nn.initializers.normal(0.02), (self.max_tokens, self.dim))
        x = x + pos[None, :length]
        for i in range(self.num_layers):
            x = TextEncoderLayer(self.num_heads, name=f"layer{i}")(x, mask)
        x = nn.LayerNorm(name="ln_final")(x)
        return x, mask
