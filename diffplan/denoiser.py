"""The planning denoiser: a conditional UNet that predicts the noise of the generated channels.

Planning tensor (CONVENTIONS.md): x_t (B, H, W, C + G) float32, the C condition channels first
(channel 0 = cell token id stored as a float, channels 1..C-1 binary features), then the G
generated (noisy) channels. The model returns eps (B, H, W, G) for the generated channels only;
``make_denoise_fn`` wraps it into the full-shape ``denoise_fn(x_t, t)`` the sampler expects.

Grid representation (``DenoiserConfig.grid_repr``):
  "embed"    -- channel 0 is rounded to an int id and looked up in the token-embedding table,
                the SAME ``nn.Embed`` (params ``token_embed``) that embeds instruction words in
                the text encoder: the paper's learned "grid representation".
  "class_id" -- the paper's ablation baseline: channel 0 is fed as one scalar channel,
                id / (vocab_size - 1) in [0, 1]; cells are not embedded (the text encoder then
                owns its own table, params ``text_encoder/token_embed``).
The UNet cross-attends to the text encoder's output with the instruction's padding mask.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np
import flax.linen as nn

from diffplan.text_encoder import TextEncoder
from diffplan.unet import UNet, fast_init

__all__ = ["DenoiserConfig", "Denoiser", "make_denoise_fn", "count_params", "init_params",
           "GRID_REPRS"]

GRID_REPRS = ("embed", "class_id")
_TUPLE_FIELDS = ("widths", "attn_levels", "cross_attn_levels")


@dataclasses.dataclass(frozen=True)
class DenoiserConfig:
    """Hyper-parameters of the denoiser (frozen, hashable: usable as a jit static argument).

    Fields:
      vocab_size: token vocabulary size (cell ids and instruction ids in [0, vocab_size)).
      max_tokens: maximum instruction length L.
      num_cond_channels: C, condition channels including the id channel 0.
      num_gen_channels: G, generated channels (path, goal).
      grid_repr: "embed" (shared learned embedding of cell ids) or "class_id" (scalar id).
      embed_dim: width of the token-embedding table.
      widths: UNet channels per level; level i works at H / 2**i.
      num_res_blocks: residual blocks per UNet level.
      attn_levels: UNet levels with self-attention.
      cross_attn_levels: UNet levels with cross-attention to the instruction.
      text_dim, text_layers, text_heads: text encoder width, depth, heads.
      groups: GroupNorm groups (divides every width).
      head_dim: channels per attention head in the UNet.
      mid_block: UNet middle block (ResBlock, transformer, ResBlock) at the lowest level;
        off by default (it adds ~0.9M parameters and ~12% FLOPs to the default model).
    """

    vocab_size: int = 64
    max_tokens: int = 32
    num_cond_channels: int = 5
    num_gen_channels: int = 2
    grid_repr: str = "embed"
    embed_dim: int = 32
    widths: tuple[int, ...] = (32, 64, 128)
    num_res_blocks: int = 1
    attn_levels: tuple[int, ...] = (2,)
    cross_attn_levels: tuple[int, ...] = (1, 2)
    text_dim: int = 64
    text_layers: int = 2
    text_heads: int = 4
    groups: int = 8
    head_dim: int = 32
    mid_block: bool = False

    def __post_init__(self):
        for name in _TUPLE_FIELDS:
            value = getattr(self, name)
            if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
                raise ValueError(f"{name} must be a sequence of ints, got {value!r}")
            value = tuple(int(v) if isinstance(v, (int, np.integer)) else v for v in value)
            object.__setattr__(self, name, value)

        def positive(name, minimum=1):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < minimum:
                raise ValueError(f"{name} must be an int >= {minimum}, got {v!r}")

        positive("vocab_size", 2)
        positive("max_tokens")
        positive("num_cond_channels")
        positive("num_gen_channels")
        positive("embed_dim")
        positive("num_res_blocks")
        positive("text_dim")
        positive("text_layers", 0)
        positive("text_heads")
        positive("groups")
        positive("head_dim")
        if self.grid_repr not in GRID_REPRS:
            raise ValueError(f"grid_repr must be one of {GRID_REPRS}, got {self.grid_repr!r}")
        if self.text_dim % self.text_heads:
            raise ValueError(f"text_dim={self.text_dim} must be divisible by "
                             f"text_heads={self.text_heads}")
        if not isinstance(self.mid_block, bool):
            raise ValueError(f"mid_block must be a bool, got {self.mid_block!r}")
        # UNet checks: widths, groups, levels, head_dim.
        self.unet().validate()

    def unet(self) -> UNet:
        """The (unbound) UNet this config describes."""
        return UNet(out_channels=self.num_gen_channels, widths=self.widths,
                    num_res_blocks=self.num_res_blocks, attn_levels=self.attn_levels,
                    cross_attn_levels=self.cross_attn_levels, groups=self.groups,
                    head_dim=self.head_dim, mid_block=self.mid_block)

    @property
    def num_channels(self) -> int:
        """C + G, the last dimension of the planning tensor."""
        return self.num_cond_channels + self.num_gen_channels

    @property
    def min_size_multiple(self) -> int:
        """H and W must be multiples of this (2 ** (levels - 1))."""
        return 2 ** (len(self.widths) - 1)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dict (tuples as lists) for checkpoint metadata."""
        d = dataclasses.asdict(self)
        for name in _TUPLE_FIELDS:
            d[name] = list(d[name])
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "DenoiserConfig":
        """Inverse of ``to_dict``; unknown keys raise ValueError."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown DenoiserConfig fields: {unknown}")
        return cls(**dict(d))


class Denoiser(nn.Module):
    """eps-prediction network for the generated channels.

    Call: x_t (B, H, W, C+G) float32, t (B,) int32, tokens (B, L) int32 (0 = padding)
      -> eps (B, H, W, G) float32.
    H and W must be multiples of ``config.min_size_multiple``; L <= config.max_tokens.
    Parameters: ``token_embed`` (only for grid_repr "embed": shared by cells and words),
    ``text_encoder``, ``unet``.
    """

    config: DenoiserConfig

    def setup(self):
        cfg = self.config
        if cfg.grid_repr == "embed":
            self.token_embed = nn.Embed(cfg.vocab_size, cfg.embed_dim,
                                        embedding_init=nn.initializers.normal(1.0))
            shared = self.token_embed
        else:
            shared = None
        self.text_encoder = TextEncoder(vocab_size=cfg.vocab_size, max_tokens=cfg.max_tokens,
                                        dim=cfg.text_dim, num_layers=cfg.text_layers,
                                        num_heads=cfg.text_heads, embed_dim=cfg.embed_dim,
                                        embed=shared)
        self.unet = cfg.unet()

    def encode_grid(self, x_t: jax.Array) -> jax.Array:
        """(B, H, W, C+G) planning tensor -> (B, H, W, F) UNet input features.

        "embed": F = embed_dim + (C - 1) + G; "class_id": F = C + G.
        """
        cfg = self.config
        ids = x_t[..., 0]
        rest = x_t[..., 1:]
        if cfg.grid_repr == "embed":
            idx = jnp.clip(jnp.round(ids), 0, cfg.vocab_size - 1).astype(jnp.int32)
            cell = self.token_embed(idx)
        else:
            cell = (ids / (cfg.vocab_size - 1))[..., None]
        return jnp.concatenate([cell, rest], axis=-1)

    def __call__(self, x_t: jax.Array, t: jax.Array, tokens: jax.Array) -> jax.Array:
        cfg = self.config
        if x_t.ndim != 4 or x_t.shape[-1] != cfg.num_channels:
            raise ValueError(f"x_t must have shape (B, H, W, C+G={cfg.num_channels}), "
                             f"got {x_t.shape}")
        b, h, w, _ = x_t.shape
        m = cfg.min_size_multiple
        if h % m or w % m:
            raise ValueError(f"H and W must be divisible by {m} (2**(levels-1) for widths "
                             f"{cfg.widths}), got H={h}, W={w}")
        t = jnp.asarray(t)
        if t.shape != (b,):
            raise ValueError(f"t must have shape (B,) = ({b},), got {t.shape}")
        if tokens.ndim != 2 or tokens.shape[0] != b:
            raise ValueError(f"tokens must have shape (B={b}, L), got {tokens.shape}")
        x_t = x_t.astype(jnp.float32)
        context, mask = self.text_encoder(tokens)
        feats = self.encode_grid(x_t)
        return self.unet(feats, t, context, mask)


def init_params(model: Denoiser, key: jax.Array, height: int = 16, width: int = 16,
                num_tokens: int | None = None, batch_size: int = 1):
    """Initialise the model's variables on dummy inputs of the given size.

    Uses ``diffplan.unet.fast_init`` (cheap-to-compile initialisation; a plain
    ``model.init`` gives a different but equally valid draw). The parameter shapes do not
    depend on height/width/num_tokens/batch_size. Returns the variables dict
    ({"params": ...}) suitable for ``model.apply``.
    """
    cfg = model.config
    num_tokens = cfg.max_tokens if num_tokens is None else num_tokens
    x = jnp.zeros((batch_size, height, width, cfg.num_channels), jnp.float32)
    t = jnp.zeros((batch_size,), jnp.int32)
    tokens = jnp.ones((batch_size, num_tokens), jnp.int32)
    return fast_init(model, key, x, t, tokens)


def make_denoise_fn(model: Denoiser, params, tokens: jax.Array
                    ) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """Wrap the denoiser for ``diffplan.sample``.

    Args:
      model: a ``Denoiser``.
      params: its variables ({"params": ...}) or the bare params tree.
      tokens: (B, L) int32 instruction tokens (B = 1 broadcasts to the plan batch).
    Returns:
      denoise_fn(x_t (B, H, W, C+G), t (B,)) -> eps (B, H, W, C+G): zeros on the C condition
      channels, the model's prediction on the G generated channels.
    """
    variables = params if "params" in params else {"params": params}
    c = model.config.num_cond_channels

    def denoise_fn(x_t: jax.Array, t: jax.Array) -> jax.Array:
        toks = tokens
        if toks.shape[0] != x_t.shape[0]:
            if toks.shape[0] != 1:
                raise ValueError(f"tokens batch {toks.shape[0]} does not match x_t batch "
                                 f"{x_t.shape[0]}")
            toks = jnp.broadcast_to(toks, (x_t.shape[0],) + toks.shape[1:])
        eps = model.apply(variables, x_t, t, toks)
        zeros = jnp.zeros(x_t.shape[:-1] + (c,), eps.dtype)
        return jnp.concatenate([zeros, eps], axis=-1)

    return denoise_fn


def count_params(params) -> int:
    """Total number of scalars in a params (or variables) pytree."""
    return int(sum(np.prod(np.shape(x)) for x in jax.tree_util.tree_leaves(params)))
