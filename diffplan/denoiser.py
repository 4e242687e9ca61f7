"""The planning denoiser: a conditional UNet over the planning tensor, and a trained one ready
to plan with (:class:`LoadedDenoiser`, :func:`load_denoiser`).

Planning tensor: x_t (B, H, W, C + G) float32, the C condition channels first (channel 0 = cell
token id stored as a float, channels 1..C-1 binary features), then the G generated (noisy)
channels. The model returns its prediction (B, H, W, G) for the generated channels only: the
noise ("eps") or the clean plan ("x0"), as it was trained (``diffplan.train``).
``make_denoise_fn`` and ``LoadedDenoiser.eps_fn`` wrap it into the full-shape
``denoise_fn(x_t, t) -> eps`` the sampler expects, converting an x0 prediction into noise.

Grid representation (``DenoiserConfig.grid_repr``):
  "embed"    -- channel 0 is rounded to an int id and looked up in the token-embedding table,
                the SAME ``nn.Embed`` (params ``token_embed``) that embeds instruction words in
                the text encoder: the paper's learned "grid representation".
  "class_id" -- the paper's ablation baseline: channel 0 is fed as one scalar channel,
                id / (vocab_size - 1) in [0, 1]; cells are not embedded (the text encoder then
                owns its own table, params ``text_encoder/token_embed``).
The UNet cross-attends to the text encoder's output with the instruction's padding mask.

Instruction input (``DenoiserConfig.context_dim``):
  0          -- "tokens" are int32 (B, L) word ids of the world's vocabulary (every shipped
                checkpoint before the pretrained text encoder);
  D > 0      -- "tokens" are float32 (B, L, D) token features of a frozen pretrained text
                encoder (``diffplan.instruction``), zero at padding; the text encoder projects
                them (Dense + LayerNorm, then its ``text_layers`` layers). With grid_repr
                "embed" the ``token_embed`` table then embeds grid cells only (its
                ``vocab_size`` rows are the world's cell tokens; no word shares them).
  ``cell_context`` -- with features and "embed": each cell token also has the frozen encoder's
                features of its name (param ``frozen_cell_features`` (vocab_size, D), written
                once before training, read under stop_gradient). ONE projection
                (``context_embed``: Dense to embed_dim + LayerNorm) maps both a cell's name
                features and the instruction's token features, as the token model's single
                table embeds both cells and words: a cell named like a word of the instruction
                starts near it. ``token_embed`` (zero at init) adds a learned per-cell part.
  ``cell_lookup`` -- with ``cell_context``: each cell also receives what the instruction says
                about its name. Once per instruction, every cell token's name looks up the
                instruction's tokens by the cosine of their frozen (standardised) features,
                softmax(scale * (cos - threshold)) over the real tokens and a "not named" slot
                of logit 0, and reads a learned projection of the text encoder's output there
                (``lookup_value``; zero where the name is not in the instruction). The result,
                (vocab_size, embed_dim) per instruction (:class:`TextContext` ``cells``), is
                added to each cell's embedding: the name match the token model gets from its
                shared table is given here at initialisation instead of learned.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import flax.linen as nn
from flax import struct

from diffplan import models
from diffplan.schedule import Schedule
from diffplan.text_encoder import TextEncoder
from diffplan.unet import UNet, fast_init

__all__ = ["DenoiserConfig", "Denoiser", "make_denoise_fn", "count_params", "init_params",
           "GRID_REPRS", "LoadedDenoiser", "load_denoiser", "noise_from_x0", "ModuleApply",
           "TextContext"]

GRID_REPRS = ("embed", "class_id")
_TUPLE_FIELDS = ("widths", "attn_levels", "cross_attn_levels")
_LATER_FIELDS = {"sentence_end_id": -1, "token_classes": 0, "context_dim": 0,
                 "cell_context": False, "standardize": False, "cell_lookup": False}
"""DenoiserConfig fields newer than some checkpoints, and the default that means "absent"."""
PREDICTIONS = ("eps", "x0")
"""What a network predicts for the generated channels: the noise, or the clean plan x0."""


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
      sentence_end_id: -1 (the text encoder's positions are absolute), or the token id that
        ends a sentence: positions then count within each sentence (diffplan.text_encoder).
      mid_block: UNet middle block (ResBlock, transformer, ResBlock) at the lowest level;
        off by default (it adds ~0.9M parameters and ~12% FLOPs to the default model).
      token_classes: 0, or K > 0: a linear head ``token_head`` maps each instruction token's
        text-encoder features to K logits (:meth:`Denoiser.token_logits`), trained by an
        auxiliary loss where a batch labels tokens (``diffplan.losses.token_loss``), so the
        features the UNet cross-attends to must carry what the labels say. Planning never
        calls it.
      context_dim: 0 (the instruction is token ids), or D > 0: the instruction is the token
        features (B, L, D) of a frozen pretrained text encoder (``diffplan.instruction``),
        projected to ``text_dim`` (vocab_size then counts the grid's cell tokens only).
        Token labels (token_classes) and per-sentence positions (sentence_end_id) read token
        ids and are refused with it.
      cell_context: with context_dim > 0 and grid_repr "embed": cells are embedded from the
        frozen encoder's features of their names, through the projection the instruction's
        features go through (module docstring). The names' features are a parameter
        (``frozen_cell_features``) the training run writes once (``diffplan.train.train(...,
        fixed_params=...)``); a checkpoint carries them.
      standardize: with context_dim > 0: every real token's features (and with cell_context
        every cell name's) are standardised per dimension, (f - mean) / scale, before the
        projection, with constants of the training sentences' features (params
        ``frozen_feature_mean`` and ``frozen_feature_scale`` (D,), written before training);
        padding rows stay zero. The encoder's features are anisotropic (any two names share
        cosine 0.25), which standardising removes.
      cell_lookup: with cell_context: every cell token's name looks up the instruction's
        tokens whose frozen features resemble it and adds what the text encoder says there to
        the cell's embedding (module docstring; params ``lookup_value``, ``lookup_scale``,
        ``lookup_threshold``).
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
    sentence_end_id: int = -1
    token_classes: int = 0
    context_dim: int = 0
    cell_context: bool = False
    standardize: bool = False
    cell_lookup: bool = False

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
        positive("sentence_end_id", -1)
        if self.sentence_end_id >= self.vocab_size:
            raise ValueError(f"sentence_end_id must be -1 or a token id in [0, vocab_size="
                             f"{self.vocab_size}), got {self.sentence_end_id!r}")
        positive("token_classes", 0)
        positive("context_dim", 0)
        if self.context_dim and self.token_classes:
            raise ValueError("token_classes labels word tokens: a denoiser on pretrained "
                             "features (context_dim > 0) has none; use token_classes=0")
        if self.context_dim and self.sentence_end_id >= 0:
            raise ValueError("sentence_end_id numbers word tokens per sentence: a denoiser on "
                             "pretrained features (context_dim > 0) has none; use -1")
        if not isinstance(self.cell_context, bool):
            raise ValueError(f"cell_context must be a bool, got {self.cell_context!r}")
        if self.cell_context and not (self.context_dim and self.grid_repr == "embed"):
            raise ValueError("cell_context embeds cells by their names' pretrained features: it "
                             "needs context_dim > 0 and grid_repr 'embed'")
        if not isinstance(self.cell_lookup, bool):
            raise ValueError(f"cell_lookup must be a bool, got {self.cell_lookup!r}")
        if self.cell_lookup and not self.cell_context:
            raise ValueError("cell_lookup looks up the cells' names in the instruction: it needs "
                             "cell_context")
        if not isinstance(self.standardize, bool):
            raise ValueError(f"standardize must be a bool, got {self.standardize!r}")
        if self.standardize and not self.context_dim:
            raise ValueError("standardize applies to pretrained features: it needs "
                             "context_dim > 0")
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
        """JSON-friendly dict (tuples as lists) for checkpoint metadata. Fields added after
        checkpoints were shipped (:data:`_LATER_FIELDS`) are left out at their defaults, so the
        metadata of a checkpoint from before them still equals its config's (resuming,
        loading with an expected config)."""
        d = dataclasses.asdict(self)
        for name in _TUPLE_FIELDS:
            d[name] = list(d[name])
        for name, default in _LATER_FIELDS.items():
            if d[name] == default:
                del d[name]
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "DenoiserConfig":
        """Inverse of ``to_dict``; unknown keys raise ValueError."""
        return models.config_from_dict(cls, d)


class FeatureProjection(nn.Module):
    """Pretrained token features (..., D) -> (..., width): Dense then LayerNorm (params
    ``proj``, ``ln``). With ``DenoiserConfig.cell_context`` one instance maps both the
    instruction's features and the cells' name features."""

    width: int

    @nn.compact
    def __call__(self, features: jax.Array) -> jax.Array:
        return nn.LayerNorm(name="ln")(nn.Dense(self.width, name="proj")(
            features.astype(jnp.float32)))


class TextContext(NamedTuple):
    """An instruction as the UNet cross-attends to it: the text encoder's output, computed once
    (:meth:`Denoiser.encode_text`) and passed as the denoiser's ``tokens`` in place of the
    instruction (the planner does so for a denoiser on pretrained features: the text part of
    the network then runs once per episode, not at every denoiser call).

    features: float32 (..., L, text_dim); mask: bool (..., L), True at real tokens;
    cells: None, or with ``DenoiserConfig.cell_lookup`` float32 (..., vocab_size, embed_dim),
    what the instruction says about each cell token's name."""

    features: jax.Array
    mask: jax.Array
    cells: Any = None


class Denoiser(nn.Module):
    """eps-prediction network for the generated channels.

    Call: x_t (B, H, W, C+G) float32, t (B,) int32, tokens (B, L) int32 (0 = padding), or
      with ``config.context_dim`` = D pretrained token features (B, L, D) float32 (0 =
      padding), or their :class:`TextContext` (:meth:`encode_text`) -> eps (B, H, W, G)
      float32.
    H and W must be multiples of ``config.min_size_multiple``; L <= config.max_tokens.
    Parameters: ``token_embed`` (only for grid_repr "embed": shared by cells and words),
    ``text_encoder``, ``unet``, ``token_head`` when ``config.token_classes`` > 0, and with
    ``config.cell_context`` ``frozen_cell_features`` (vocab_size, D) and ``context_embed``.
    """

    config: DenoiserConfig

    def setup(self):
        cfg = self.config
        project = None
        if cfg.grid_repr == "embed":
            self.token_embed = nn.Embed(cfg.vocab_size, cfg.embed_dim, embedding_init=(
                nn.initializers.zeros if cfg.cell_context else nn.initializers.normal(1.0)))
            shared = self.token_embed
        else:
            shared = None
        if cfg.cell_context:
            self.cell_features = self.param("frozen_cell_features", nn.initializers.zeros,
                                            (cfg.vocab_size, cfg.context_dim))
            self.context_embed = FeatureProjection(cfg.embed_dim)
            project = self.context_embed
        if cfg.cell_lookup:
            self.lookup_value = nn.Dense(cfg.embed_dim)
            self.lookup_scale = self.param("lookup_scale", nn.initializers.constant(20.0), ())
            self.lookup_threshold = self.param("lookup_threshold",
                                               nn.initializers.constant(0.7), ())
        if cfg.standardize:
            self.feature_mean = self.param("frozen_feature_mean", nn.initializers.zeros,
                                           (cfg.context_dim,))
            self.feature_scale = self.param("frozen_feature_scale", nn.initializers.ones,
                                            (cfg.context_dim,))
        self.text_encoder = TextEncoder(vocab_size=cfg.vocab_size, max_tokens=cfg.max_tokens,
                                        dim=cfg.text_dim, num_layers=cfg.text_layers,
                                        num_heads=cfg.text_heads, embed_dim=cfg.embed_dim,
                                        embed=None if cfg.context_dim else shared,
                                        project=project,
                                        sentence_end_id=int(cfg.sentence_end_id),
                                        context_dim=int(cfg.context_dim))
        self.unet = cfg.unet()
        if cfg.token_classes:
            self.token_head = nn.Dense(cfg.token_classes)

    def token_logits(self, tokens: jax.Array) -> jax.Array:
        """tokens int32 (B, L) -> float32 (B, L, token_classes): the token head's logits on
        the text encoder's features (the context the UNet cross-attends to)."""
        if not self.config.token_classes:
            raise ValueError("this denoiser has no token head (DenoiserConfig.token_classes "
                             "is 0); a batch with token labels needs token_classes > 0")
        context, _ = self._text(tokens)
        return self.token_head(context)

    def _standardized(self, features: jax.Array) -> jax.Array:
        """(..., D) features standardised per dimension (``config.standardize``), all-zero
        rows (padding) left zero; as they are otherwise."""
        if not self.config.standardize:
            return features
        mean = jax.lax.stop_gradient(self.feature_mean)
        scale = jax.lax.stop_gradient(self.feature_scale)
        real = jnp.any(features != 0, axis=-1, keepdims=True)
        return jnp.where(real, (features.astype(jnp.float32) - mean) / scale, 0.0)

    def _text(self, tokens: jax.Array):
        """The text encoder's (features, mask) of token ids or (standardised) features."""
        if self.config.context_dim and tokens.ndim == 3:
            tokens = self._standardized(tokens)
        return self.text_encoder(tokens)

    def encode_text(self, tokens: jax.Array) -> TextContext:
        """The instruction's :class:`TextContext` (what the UNet cross-attends to): tokens
        (B, L) int32, or (B, L, D) features -> features (B, L, text_dim), mask (B, L), and
        with ``cell_lookup`` cells (B, vocab_size, embed_dim)."""
        context, mask = self._text(tokens)
        cells = self._lookup(tokens, context, mask) if self.config.cell_lookup else None
        return TextContext(context, mask, cells)

    def _lookup(self, tokens: jax.Array, context: jax.Array, mask: jax.Array) -> jax.Array:
        """(B, vocab_size, embed_dim): for each cell token's name, the softmax over the real
        tokens (and a "not named" slot of logit 0, value 0) of scale * (cos - threshold),
        the cosine between the name's and each token's frozen (standardised) features,
        weighting ``lookup_value`` of the text encoder's output ``context`` (B, L, text_dim).
        tokens: (B, L, D) features, mask (B, L)."""
        def unit(f):
            f = jax.lax.stop_gradient(self._standardized(f))
            return f / jnp.maximum(jnp.linalg.norm(f, axis=-1, keepdims=True), 1e-6)

        names = unit(self.cell_features)                                  # (V, D)
        cos = jnp.einsum("vd,bld->bvl", names, unit(tokens.astype(jnp.float32)))
        logits = self.lookup_scale * (cos - self.lookup_threshold)
        logits = jnp.where(mask[:, None, :], logits, -1e9)
        logits = jnp.concatenate([logits, jnp.zeros(logits.shape[:-1] + (1,))], axis=-1)
        weights = jax.nn.softmax(logits, axis=-1)[..., :-1]               # (B, V, L)
        named = jnp.any(self.cell_features != 0, axis=-1)                 # padding: no name
        weights = weights * named[None, :, None]
        return jnp.einsum("bvl,ble->bve", weights, self.lookup_value(context))

    def encode_grid(self, x_t: jax.Array, cells: jax.Array | None = None) -> jax.Array:
        """(B, H, W, C+G) planning tensor -> (B, H, W, F) UNet input features; cells: None, or
        (B, vocab_size, embed_dim) added to each cell's embedding by its token
        (``cell_lookup``).

        "embed": F = embed_dim + (C - 1) + G; "class_id": F = C + G.
        """
        cfg = self.config
        ids = x_t[..., 0]
        rest = x_t[..., 1:]
        if cfg.grid_repr == "embed":
            idx = jnp.clip(jnp.round(ids), 0, cfg.vocab_size - 1).astype(jnp.int32)
            cell = self.token_embed(idx)
            if cfg.cell_context:
                named = self.context_embed(self._standardized(
                    jax.lax.stop_gradient(self.cell_features)))  # (V, E)
                cell = cell + named[idx]
            if cells is not None:
                cell = cell + jax.vmap(lambda table, i: table[i])(cells, idx)
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
        if isinstance(tokens, TextContext):
            if tokens.features.shape[0] != b:
                raise ValueError(f"the text context has batch {tokens.features.shape[0]}, x_t "
                                 f"has {b}")
            context, mask, cells = tokens
            if cfg.cell_lookup and cells is None:
                raise ValueError("this denoiser looks up its cells' names in the instruction "
                                 "(cell_lookup): pass encode_text's TextContext, cells included")
        else:
            want = 3 if cfg.context_dim else 2
            if tokens.ndim != want or tokens.shape[0] != b:
                what = f"(B={b}, L, {cfg.context_dim}) pretrained features" if cfg.context_dim \
                    else f"(B={b}, L) token ids"
                raise ValueError(f"tokens must be {what}, got shape {tokens.shape}")
            context, mask, cells = self.encode_text(tokens)
        x_t = x_t.astype(jnp.float32)
        if self.config.token_classes and self.is_initializing():
            self.token_head(context)  # create its params with the rest
        feats = self.encode_grid(x_t, cells)
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
    tokens = (jnp.ones((batch_size, num_tokens, cfg.context_dim), jnp.float32)
              if cfg.context_dim else jnp.ones((batch_size, num_tokens), jnp.int32))
    return fast_init(model, key, x, t, tokens)


def make_denoise_fn(model: Denoiser, params, tokens: jax.Array, prediction: str = "eps",
                    schedule: Schedule | None = None
                    ) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """Wrap the denoiser for ``diffplan.sample``.

    Args:
      model: a ``Denoiser``.
      params: its variables ({"params": ...}) or the bare params tree.
      tokens: (B, L) int32 instruction tokens, or (B, L, D) float32 features for a denoiser
        with context_dim D (B = 1 broadcasts to the plan batch).
      prediction: what the network predicts, "eps" or "x0" (then ``schedule`` is needed to
        turn its clean-plan estimate into the noise the sampler expects).
      schedule: the schedule the network was trained with (prediction "x0" only).
    Returns:
      denoise_fn(x_t (B, H, W, C+G), t (B,)) -> eps (B, H, W, C+G): zeros on the C condition
      channels, the model's noise estimate on the G generated channels.
    """
    if prediction not in PREDICTIONS:
        raise ValueError(f"prediction must be one of {PREDICTIONS}, got {prediction!r}")
    if prediction == "x0" and schedule is None:
        raise ValueError("prediction='x0' needs the schedule the model was trained with")
    variables = params if "params" in params else {"params": params}
    c = model.config.num_cond_channels

    def denoise_fn(x_t: jax.Array, t: jax.Array) -> jax.Array:
        toks = tokens
        if toks.shape[0] != x_t.shape[0]:
            if toks.shape[0] != 1:
                raise ValueError(f"tokens batch {toks.shape[0]} does not match x_t batch "
                                 f"{x_t.shape[0]}")
            toks = jnp.broadcast_to(toks, (x_t.shape[0],) + toks.shape[1:])
        out = model.apply(variables, x_t, t, toks)
        return _sampler_eps(out, x_t, t, c, prediction, schedule)

    return denoise_fn


def _sampler_eps(out, x_t, t, c: int, prediction: str, schedule):
    """The full-shape noise estimate (zeros on the c condition channels) from a network's
    output on the generated channels, which predicts ``prediction``."""
    if prediction == "x0":
        out = noise_from_x0(x_t[..., c:], out, schedule.alphas_cumprod[t])
    return jnp.concatenate([jnp.zeros(x_t.shape[:-1] + (c,), out.dtype), out], axis=-1)


def count_params(params) -> int:
    """Total number of scalars in a params (or variables) pytree."""
    return int(sum(np.prod(np.shape(x)) for x in jax.tree_util.tree_leaves(params)))


# --------------------------------------------------------------------- planning with a model


def noise_from_x0(x_gen: jax.Array, x0_hat: jax.Array, alphas_cumprod_t: jax.Array) -> jax.Array:
    """The noise estimate implied by an x0 estimate: (x_t - sqrt(ab) x0) / sqrt(1 - ab).

    x_gen, x0_hat: (B, ..., G) the noisy generated channels and the predicted clean ones;
    alphas_cumprod_t: (B,) alpha-bar at each sample's timestep."""
    ab = alphas_cumprod_t.reshape((-1,) + (1,) * (x_gen.ndim - 1))
    return (x_gen - jnp.sqrt(ab) * x0_hat) / jnp.sqrt(1.0 - ab)


@dataclasses.dataclass(frozen=True)
class ModuleApply:
    """``(params, x_t, t, tokens) -> model.apply({"params": params}, x_t, t, tokens)``; hashable
    by the module (equal modules give equal functions: one compilation serves every checkpoint
    of the same architecture)."""

    model: Any

    def __call__(self, params, x_t, t, tokens):
        return self.model.apply({"params": params}, x_t, t, tokens)

    def prepare(self, params, tokens):
        """The model's :class:`TextContext` of tokens (B, ...) (:meth:`Denoiser.encode_text`)."""
        return self.model.apply({"params": params}, tokens, method="encode_text")


class LoadedDenoiser(struct.PyTreeNode):
    """Everything needed to plan with a trained denoiser (a pytree: params and schedule are
    leaves, the rest is static).

    params: the network's parameters. schedule: the diffusion schedule it was trained with.
    apply_fn: ``(params, x_t (B, H, W, C+G), t (B,), tokens (B, L)) -> (B, H, W, G)``, the
      network's prediction for the generated channels. prediction: what it predicts, "eps"
      (the noise) or "x0" (the clean plan). plan_shape: (H, W, G) of the plans it makes.
    num_cond_channels: C. model_config: the DenoiserConfig (None for other networks).
    """

    params: Any
    schedule: Schedule
    apply_fn: Callable = struct.field(pytree_node=False)
    prediction: str = struct.field(pytree_node=False, default="eps")
    plan_shape: tuple = struct.field(pytree_node=False, default=(16, 16, 2))
    num_cond_channels: int = struct.field(pytree_node=False, default=5)
    model_config: Any = struct.field(pytree_node=False, default=None)

    def __post_init__(self):
        if self.prediction not in PREDICTIONS:
            raise ValueError(f"prediction must be one of {PREDICTIONS}, got "
                             f"{self.prediction!r}")
        if len(tuple(self.plan_shape)) != 3:
            raise ValueError(f"plan_shape must be (H, W, G), got {self.plan_shape!r}")

    @property
    def num_gen_channels(self) -> int:
        return int(self.plan_shape[-1])

    def prepare(self, tokens):
        """What a planner keeps of one episode's instruction (tokens int32 (L,), or float32
        (L, D) features): the tokens as they are, or, for a denoiser on pretrained features
        (``DenoiserConfig.context_dim`` > 0), the :class:`TextContext` its UNet cross-attends
        to ((L, text_dim), (L,)): the text part of the network then runs once per episode
        instead of at every denoiser call."""
        if not getattr(self.model_config, "context_dim", 0) or not hasattr(self.apply_fn,
                                                                         "prepare"):
            return tokens
        context = self.apply_fn.prepare(self.params, jnp.asarray(tokens)[None])
        return jax.tree.map(lambda a: a[0], context)

    def eps_fn(self, tokens: jax.Array) -> Callable[[jax.Array, jax.Array], jax.Array]:
        """The ``denoise_fn(x_t (B, H, W, C+G), t (B,)) -> eps (B, H, W, C+G)`` that
        ``diffplan.sample`` expects (zeros on the condition channels), whatever the network
        predicts. tokens: int32 (B, L), float32 (B, L, D) features for a denoiser with
        context_dim D, or their TextContext (:meth:`prepare`) (B = 1 broadcasts)."""
        def denoise_fn(x_t, t):
            toks = jax.tree.map(lambda a: jnp.broadcast_to(a, (x_t.shape[0],) + a.shape[1:]),
                                tokens)
            out = self.apply_fn(self.params, x_t, t, toks)
            return _sampler_eps(out, x_t, t, self.num_cond_channels, self.prediction,
                                self.schedule)

        return denoise_fn


def load_denoiser(directory: str, step: int | None = None) -> LoadedDenoiser:
    """The trained denoiser of a checkpoint directory (a training run's or a shipped one):
    its network, evaluation (EMA) parameters, schedule (the cosine schedule of the
    checkpoint's ``train_config.num_train_timesteps``, as ``diffplan.train`` trains),
    prediction target and plan shape (from the stored input shapes).

    The network is the registered class the checkpoint names (``diffplan.models``), which must
    be a Denoiser; nothing the checkpoint names is imported.

    ``directory`` is a path, or the name of a shipped checkpoint (``"compile_gridworld"``;
    ``"checkpoints/compile_gridworld"`` also works outside the repository root): see
    ``diffplan.checkpoint.resolve_checkpoint``.

    Raises FileNotFoundError (no checkpoint there; one line naming where it looked) or
    ValueError (unreadable metadata, or a network that is not a registered diffplan
    Denoiser)."""
    from diffplan.checkpoint import load_params_for_eval, resolve_checkpoint
    from diffplan.schedule import cosine_schedule

    directory = resolve_checkpoint(directory)
    params, metadata = load_params_for_eval(directory, step=step)  # arrays and JSON only
    spec = models.spec_for_metadata(metadata)
    if not issubclass(spec.model_cls, Denoiser):
        raise ValueError(f"checkpoint {directory!r} holds a {spec.key!r} network, not a "
                         "diffplan Denoiser")
    try:
        config = spec.config_from_dict(metadata["model_config"])
        train_config = metadata.get("train_config", {})
        h, w, cg = metadata["input_shapes"]["x"][1:]
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"checkpoint {directory!r} does not describe a diffplan denoiser: "
                         f"{e}") from e
    return LoadedDenoiser(
        params=params, schedule=cosine_schedule(int(train_config.get("num_train_timesteps",
                                                                     100))),
        apply_fn=ModuleApply(spec.model_cls(config)),
        prediction=train_config.get("prediction", "eps"),
        plan_shape=(int(h), int(w), int(cg) - config.num_cond_channels),
        num_cond_channels=config.num_cond_channels, model_config=config)


models.register_model("diffplan.denoiser:Denoiser", Denoiser, DenoiserConfig)
