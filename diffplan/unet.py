"""A conditional 2-D UNet (Flax linen, NHWC, float32) for H x W planning maps.

A small re-implementation of the parts of diffusers' ``UNet2DConditionModel`` the paper uses
(appendix A): residual blocks with GroupNorm + SiLU and an added timestep embedding,
transformer blocks (self-attention and/or cross-attention to a text context with a key
padding mask) at chosen levels, strided-conv downsampling, nearest + conv upsampling, skip
connections, and a zero-initialised output convolution.

Shapes (B batch, H x W map, C channels, L context length, D context dim):
    x        (B, H, W, C_in)  float32
    t        (B,)             int or float timesteps
    context  (B, L, D)        float32, optional
    mask     (B, L)           bool, True = a real (non-padding) context token
    output   (B, H, W, C_out) float32

Level ``i`` (0-based) works at resolution (H / 2**i, W / 2**i) with ``widths[i]`` channels,
so H and W must be divisible by 2**(len(widths) - 1).
"""
from __future__ import annotations

import functools
import math
from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import flax.linen as nn

__all__ = [
    "fast_init",
    "timestep_embedding",
    "MultiHeadAttention",
    "ResBlock",
    "SpatialTransformer",
    "Downsample",
    "Upsample",
    "UNet",
]

_NEG_INF = -1e9  # finite: a fully masked row gives a uniform softmax, never NaN

# Compiler options for one-off computations (initialisation): XLA:CPU's LLVM optimisation
# dominates their compile time (tens of seconds for ~100 parameter initialisers) while their
# run time is negligible.
FAST_COMPILE_OPTIONS = {"xla_backend_optimization_level": 0,
                        "xla_llvm_disable_expensive_passes": True}


def fast_init(module: nn.Module, key: jax.Array, *args: jax.Array):
    """``module.init(key, *args)``, jitted and cheap to compile.

    ``key`` is an ordinary threefry key (``jax.random.PRNGKey(s)`` or ``jax.random.key(s)``).
    The parameter initialisers draw their bits from an ``unsafe_rbg`` key derived from it (one
    XLA RngBitGenerator op per parameter instead of an unrolled threefry hash each), and the
    computation is compiled without LLVM optimisation: on this 2-core CPU that cuts the
    compile time of an init several-fold, while its run time is negligible anyway.
    Deterministic for a given key and backend. Returns the variables dict.
    """
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    if key.shape != (2,):
        raise ValueError(f"fast_init expects a single threefry PRNG key, got shape {key.shape}")
    try:
        init = _cached_jitted_init(module)
    except TypeError:  # an unhashable module: no cross-call cache
        init = _jitted_init(module)
    return init(key, *args)


def _jitted_init(module: nn.Module):
    """The jitted, cheap-to-compile init of ``module``: (key_data (2,), *args) -> variables."""

    def init(key_data, *a):
        bits = jax.random.bits(jax.random.wrap_key_data(key_data), (4,), jnp.uint32)
        return module.init(jax.random.wrap_key_data(bits, impl="unsafe_rbg"), *a)

    return jax.jit(init, compiler_options=FAST_COMPILE_OPTIONS)


# One jitted init per (hashable, unbound) module, so repeated inits hit jit's cache.
_cached_jitted_init = functools.lru_cache(maxsize=64)(_jitted_init)


def timestep_embedding(t: jax.Array, dim: int, max_period: float = 10000.0) -> jax.Array:
    """Sinusoidal timestep embedding (cos first, like diffusers' ``flip_sin_to_cos``).

    Args:
      t: (B,) timesteps (int or float).
      dim: embedding size (even).
    Returns:
      (B, dim) float32.
    """
    if dim % 2:
        raise ValueError(f"timestep embedding dim must be even, got {dim}")
    half = dim // 2
    freqs = jnp.exp(-math.log(max_period) * jnp.arange(half, dtype=jnp.float32) / half)
    args = jnp.asarray(t, jnp.float32)[:, None] * freqs[None, :]
    return jnp.concatenate([jnp.cos(args), jnp.sin(args)], axis=-1)


class MultiHeadAttention(nn.Module):
    """Multi-head dot-product attention with fused projections.

    Self-attention (``context is None``) uses one fused (D -> 3D) qkv projection; cross-attention
    one (D -> D) query and one fused (D_ctx -> 2D) key/value projection.

    Call: x (B, Q, D), context (B, K, D_ctx) or None, mask bool (B, K) (the keys every query
    may attend to), (B, Q, K) (per query) or None -> (B, Q, D).
    Rows whose keys are all masked return exactly zero (no information leaks from padding).
    """

    num_heads: int

    @nn.compact
    def __call__(self, x: jax.Array, context: Optional[jax.Array] = None,
                 mask: Optional[jax.Array] = None) -> jax.Array:
        b, q_len, d = x.shape
        if d % self.num_heads:
            raise ValueError(f"attention dim {d} is not divisible by num_heads={self.num_heads}")
        dh = d // self.num_heads
        if context is None:
            qkv = nn.Dense(3 * d, use_bias=False, name="qkv")(x)
            q, k, v = jnp.split(qkv, 3, axis=-1)
        else:
            q = nn.Dense(d, use_bias=False, name="q")(x)
            kv = nn.Dense(2 * d, use_bias=False, name="kv")(context)
            k, v = jnp.split(kv, 2, axis=-1)
        k_len = k.shape[1]
        q = q.reshape(b, q_len, self.num_heads, dh) * (1.0 / math.sqrt(dh))
        k = k.reshape(b, k_len, self.num_heads, dh)
        v = v.reshape(b, k_len, self.num_heads, dh)
        logits = jnp.einsum("bqhd,bkhd->bhqk", q, k)
        if mask is not None:
            per_query = mask[:, None] if mask.ndim == 3 else mask[:, None, None, :]
            logits = jnp.where(per_query, logits, _NEG_INF)
        weights = jax.nn.softmax(logits, axis=-1)
        out = jnp.einsum("bhqk,bkhd->bqhd", weights, v).reshape(b, q_len, d)
        out = nn.Dense(d, name="out")(out)
        if mask is not None:
            live = jnp.any(mask, axis=-1)
            live = live[:, :, None] if mask.ndim == 3 else live[:, None, None]
            out = out * live.astype(out.dtype)
        return out


class ResBlock(nn.Module):
    """GroupNorm-SiLU-Conv3x3, + Dense(temb), GroupNorm-SiLU-Conv3x3, plus a (1x1) skip.

    Call: x (B, H, W, C_in), temb (B, T) -> (B, H, W, out_channels).
    """

    out_channels: int
    groups: int

    @nn.compact
    def __call__(self, x: jax.Array, temb: jax.Array) -> jax.Array:
        h = nn.silu(nn.GroupNorm(num_groups=self.groups, name="norm1")(x))
        h = nn.Conv(self.out_channels, (3, 3), padding=1, name="conv1")(h)
        h = h + nn.Dense(self.out_channels, name="temb")(nn.silu(temb))[:, None, None, :]
        h = nn.silu(nn.GroupNorm(num_groups=self.groups, name="norm2")(h))
        h = nn.Conv(self.out_channels, (3, 3), padding=1, name="conv2")(h)
        if x.shape[-1] != self.out_channels:
            x = nn.Conv(self.out_channels, (1, 1), name="skip")(x)
        return x + h


class SpatialTransformer(nn.Module):
    """Transformer block over the H*W positions of a feature map.

    GroupNorm -> Dense(proj_in) -> [x + SelfAttn(LN x)] -> [x + CrossAttn(LN x, context)]
    -> x + MLP(LN x) -> Dense(proj_out, zero-init) -> residual add to the input.

    Call: x (B, H, W, C), context (B, L, D) or None, mask (B, L) or None -> (B, H, W, C).
    """

    num_heads: int
    groups: int
    self_attn: bool = True
    cross_attn: bool = False
    mlp_ratio: int = 4

    @nn.compact
    def __call__(self, x: jax.Array, context: Optional[jax.Array] = None,
                 mask: Optional[jax.Array] = None) -> jax.Array:
        b, h, w, c = x.shape
        if self.cross_attn and context is None:
            raise ValueError("SpatialTransformer with cross_attn=True needs a context")
        y = nn.GroupNorm(num_groups=self.groups, name="norm")(x).reshape(b, h * w, c)
        y = nn.Dense(c, name="proj_in")(y)
        if self.self_attn:
            y = y + MultiHeadAttention(self.num_heads, name="self_attn")(
                nn.LayerNorm(name="ln_self")(y))
        if self.cross_attn:
            y = y + MultiHeadAttention(self.num_heads, name="cross_attn")(
                nn.LayerNorm(name="ln_cross")(y), context, mask)
        z = nn.LayerNorm(name="ln_mlp")(y)
        z = nn.Dense(self.mlp_ratio * c, name="mlp_in")(z)
        z = nn.Dense(c, name="mlp_out")(nn.gelu(z))
        y = y + z
        y = nn.Dense(c, kernel_init=nn.initializers.zeros, name="proj_out")(y)
        return x + y.reshape(b, h, w, c)


class Downsample(nn.Module):
    """3x3 conv with stride 2 (padding 1): (B, H, W, C) -> (B, H/2, W/2, C)."""

    channels: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        return nn.Conv(self.channels, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)),
                       name="conv")(x)


class Upsample(nn.Module):
    """Nearest-neighbour x2 then 3x3 conv: (B, H, W, C) -> (B, 2H, 2W, channels)."""

    channels: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        b, h, w, c = x.shape
        x = jnp.broadcast_to(x[:, :, None, :, None, :], (b, h, 2, w, 2, c))
        x = x.reshape(b, 2 * h, 2 * w, c)
        return nn.Conv(self.channels, (3, 3), padding=1, name="conv")(x)


def _check_levels(name: str, levels: Sequence[int], n: int) -> None:
    for lv in levels:
        if not isinstance(lv, int) or not 0 <= lv < n:
            raise ValueError(f"{name} entries must be level indices in [0, {n}), got {tuple(levels)}")
    if len(set(levels)) != len(levels):
        raise ValueError(f"{name} has duplicate levels: {tuple(levels)}")


class UNet(nn.Module):
    """Conditional UNet (diffusers ``UNet2DConditionModel`` layout, small).

    Attributes:
      out_channels: channels of the output map.
      widths: channels per level, e.g. (32, 64, 128); level i has resolution H/2**i.
      num_res_blocks: residual blocks per level on the way down (up: num_res_blocks + 1).
      attn_levels: levels whose transformer blocks have self-attention.
      cross_attn_levels: levels whose transformer blocks cross-attend to the context.
      groups: GroupNorm groups (must divide every width).
      head_dim: channels per attention head (must divide the widths of attention levels).
      mid_block: add the middle block (ResBlock, transformer, ResBlock) at the lowest level;
        its transformer uses self-/cross-attention if the lowest level does.
      temb_mult: the timestep MLP has widths[0] * temb_mult units.

    Layout: conv_in; per level i: num_res_blocks x (ResBlock [+ SpatialTransformer]) then a
    strided-conv Downsample (not after the last level); [mid block]; per level i from the
    lowest: (num_res_blocks + 1) x (concat skip, ResBlock [+ SpatialTransformer]) then an
    Upsample whose conv maps straight to widths[i - 1] (diffusers keeps widths[i]: twice the
    FLOPs at the 4x larger resolution); GroupNorm, SiLU, zero-initialised conv_out.

    Call: x (B, H, W, C_in) float32, t (B,), context (B, L, D) | None, mask (B, L) bool | None
      -> (B, H, W, out_channels) float32. The output conv is zero-initialised, so a fresh
      model outputs exactly zero.
    """

    out_channels: int
    widths: Sequence[int] = (32, 64, 128)
    num_res_blocks: int = 1
    attn_levels: Sequence[int] = (2,)
    cross_attn_levels: Sequence[int] = (1, 2)
    groups: int = 8
    head_dim: int = 32
    mid_block: bool = False
    temb_mult: int = 4

    def validate(self) -> None:
        """Raise ValueError on an inconsistent configuration."""
        widths = tuple(self.widths)
        if not widths or any((not isinstance(w, int)) or w <= 0 for w in widths):
            raise ValueError(f"widths must be a non-empty tuple of positive ints, got {widths}")
        if self.out_channels <= 0:
            raise ValueError(f"out_channels must be positive, got {self.out_channels}")
        if self.num_res_blocks < 1:
            raise ValueError(f"num_res_blocks must be >= 1, got {self.num_res_blocks}")
        if self.groups < 1 or any(w % self.groups for w in widths):
            raise ValueError(f"groups={self.groups} must divide every width {widths}")
        _check_levels("attn_levels", tuple(self.attn_levels), len(widths))
        _check_levels("cross_attn_levels", tuple(self.cross_attn_levels), len(widths))
        att = set(self.attn_levels) | set(self.cross_attn_levels)  # (the mid block's too)
        if self.head_dim < 1:
            raise ValueError(f"head_dim must be positive, got {self.head_dim}")
        for lv in sorted(att):
            if widths[lv] % self.head_dim:
                raise ValueError(f"head_dim={self.head_dim} must divide the width {widths[lv]} "
                                 f"of attention level {lv}")
        if widths[0] % 2 or self.temb_mult < 1:
            raise ValueError(f"widths[0]={widths[0]} must be even (timestep embedding) and "
                             f"temb_mult={self.temb_mult} >= 1")

    def _transformer(self, level: int, name: str) -> Optional[SpatialTransformer]:
        sa = level in tuple(self.attn_levels)
        ca = level in tuple(self.cross_attn_levels)
        if not (sa or ca):
            return None
        return SpatialTransformer(num_heads=self.widths[level] // self.head_dim, groups=self.groups,
                                  self_attn=sa, cross_attn=ca, name=name)

    @nn.compact
    def __call__(self, x: jax.Array, t: jax.Array, context: Optional[jax.Array] = None,
                 mask: Optional[jax.Array] = None) -> jax.Array:
        self.validate()
        widths = tuple(self.widths)
        n = len(widths)
        if x.ndim != 4:
            raise ValueError(f"UNet expects NHWC input (B, H, W, C), got shape {x.shape}")
        b, h, w, _ = x.shape
        f = 2 ** (n - 1)
        if h % f or w % f:
            raise ValueError(f"H and W must be divisible by 2**(levels-1) = {f} for widths "
                             f"{widths}, got H={h}, W={w}")
        if t.shape != (b,):
            raise ValueError(f"t must have shape (B,) = ({b},), got {t.shape}")
        if self.cross_attn_levels and context is None:
            raise ValueError("cross_attn_levels is non-empty but no context was given")
        if context is not None and mask is None:
            mask = jnp.ones(context.shape[:2], bool)

        tdim = widths[0] * self.temb_mult
        temb = timestep_embedding(t, widths[0])
        temb = nn.Dense(tdim, name="temb_in")(temb)
        temb = nn.Dense(tdim, name="temb_out")(nn.silu(temb))

        hcur = nn.Conv(widths[0], (3, 3), padding=1, name="conv_in")(x)
        skips = [hcur]
        for lv in range(n):
            for i in range(self.num_res_blocks):
                hcur = ResBlock(widths[lv], self.groups, name=f"down{lv}_res{i}")(hcur, temb)
                tr = self._transformer(lv, f"down{lv}_attn{i}")
                if tr is not None:
                    hcur = tr(hcur, context, mask)
                skips.append(hcur)
            if lv < n - 1:
                hcur = Downsample(widths[lv], name=f"down{lv}_downsample")(hcur)
                skips.append(hcur)

        if self.mid_block:
            hcur = ResBlock(widths[-1], self.groups, name="mid_res0")(hcur, temb)
            tr = self._transformer(n - 1, "mid_attn")
            if tr is not None:
                hcur = tr(hcur, context, mask)
            hcur = ResBlock(widths[-1], self.groups, name="mid_res1")(hcur, temb)

        for lv in reversed(range(n)):
            for i in range(self.num_res_blocks + 1):
                hcur = jnp.concatenate([hcur, skips.pop()], axis=-1)
                hcur = ResBlock(widths[lv], self.groups, name=f"up{lv}_res{i}")(hcur, temb)
                tr = self._transformer(lv, f"up{lv}_attn{i}")
                if tr is not None:
                    hcur = tr(hcur, context, mask)
            if lv > 0:
                # Upsample straight to the next level's width: half the FLOPs of keeping
                # widths[lv] (diffusers keeps it) at the 4x larger resolution.
                hcur = Upsample(widths[lv - 1], name=f"up{lv}_upsample")(hcur)
        assert not skips

        hcur = nn.silu(nn.GroupNorm(num_groups=self.groups, name="norm_out")(hcur))
        return nn.Conv(self.out_channels, (3, 3), padding=1, kernel_init=nn.initializers.zeros,
                       bias_init=nn.initializers.zeros, name="conv_out")(hcur)
