"""The forward pass of a BERT encoder (Devlin et al. 2019) in pure jax.numpy: token ids in,
the last hidden state out, float32 throughout. No world, no files: the parameters are a
pytree that :mod:`diffplan.pretrained_text` builds from a Hugging Face-format directory.

Shapes: ids and mask ``(..., L)`` (any leading batch shape, or none), features
``(..., L, D)`` with ``D = config.hidden_size``. :func:`features` is pure: it runs under
``jit`` (``config`` static), ``vmap`` and ``lax.scan``.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

ACTIVATIONS = {
    "gelu": lambda x: jax.nn.gelu(x, approximate=False),
    "gelu_new": lambda x: jax.nn.gelu(x, approximate=True),
    "gelu_pytorch_tanh": lambda x: jax.nn.gelu(x, approximate=True),
    "relu": jax.nn.relu,
}
"""The ``hidden_act`` values of a BERT config this forward computes (Hugging Face's names:
``gelu`` is the exact, erf-based GELU)."""

PRECISION = jax.lax.Precision.HIGHEST
"""Every matrix product in full float32 (on accelerators the default may round to bf16)."""


@dataclasses.dataclass(frozen=True)
class BertConfig:
    """The architecture fields of a Hugging Face BERT ``config.json`` that the forward reads
    (hashable: a static argument of ``jit``)."""
    vocab_size: int
    hidden_size: int
    num_hidden_layers: int
    num_attention_heads: int
    intermediate_size: int
    max_position_embeddings: int
    type_vocab_size: int
    hidden_act: str = "gelu"
    layer_norm_eps: float = 1e-12

    def __post_init__(self):
        if self.hidden_act not in ACTIVATIONS:
            raise ValueError(f"hidden_act {self.hidden_act!r} is not supported; expected one "
                             f"of {sorted(ACTIVATIONS)}")
        if self.hidden_size % self.num_attention_heads:
            raise ValueError(f"hidden_size {self.hidden_size} is not a multiple of "
                             f"num_attention_heads {self.num_attention_heads}")


def param_shapes(config: BertConfig) -> dict:
    """The parameter pytree's structure, each leaf the shape of its array: ``embeddings``
    (``word`` (V, D), ``position`` (P, D), ``token_type`` (T, D), ``ln_scale``, ``ln_bias``
    (D,)) and ``layers``, every layer's arrays stacked on a leading axis of
    ``N = num_hidden_layers`` (``query``, ``key``, ``value``, ``attn_out`` kernels (N, D, D)
    stored (in, out); ``mlp_in`` (N, D, I), ``mlp_out`` (N, I, D); their ``*_bias``;
    ``attn_ln_*`` and ``mlp_ln_*`` (N, D)), so the forward scans over them."""
    d, i, n = config.hidden_size, config.intermediate_size, config.num_hidden_layers
    layer = {"query": (d, d), "query_bias": (d,), "key": (d, d), "key_bias": (d,),
             "value": (d, d), "value_bias": (d,), "attn_out": (d, d), "attn_out_bias": (d,),
             "attn_ln_scale": (d,), "attn_ln_bias": (d,), "mlp_in": (d, i), "mlp_in_bias": (i,),
             "mlp_out": (i, d), "mlp_out_bias": (d,), "mlp_ln_scale": (d,), "mlp_ln_bias": (d,)}
    embeddings = {"word": (config.vocab_size, d), "position": (config.max_position_embeddings, d),
                  "token_type": (config.type_vocab_size, d), "ln_scale": (d,), "ln_bias": (d,)}
    return {"embeddings": embeddings,
            "layers": {name: (n,) + shape for name, shape in layer.items()}}


def layer_norm(x, scale, bias, eps: float):
    """LayerNorm over the last axis, float32: x (..., D), scale and bias (D,)."""
    mean = jnp.mean(x, axis=-1, keepdims=True)
    var = jnp.mean(jnp.square(x - mean), axis=-1, keepdims=True)
    return (x - mean) * jax.lax.rsqrt(var + eps) * scale + bias


def dense(x, kernel, bias):
    """x (..., in) @ kernel (in, out) + bias (out,)."""
    return jnp.einsum("...i,io->...o", x, kernel, precision=PRECISION) + bias


def attention(x, key_mask, p: dict, config: BertConfig):
    """Multi-head self-attention: x float32 (..., L, D), key_mask bool (..., L) (False keys
    get no weight); returns the block's output after its residual LayerNorm, (..., L, D)."""
    heads = config.num_attention_heads
    head_dim = config.hidden_size // heads

    def split(y):  # (..., L, D) -> (..., H, L, d)
        return jnp.swapaxes(y.reshape(y.shape[:-1] + (heads, head_dim)), -2, -3)

    q = split(dense(x, p["query"], p["query_bias"]))
    k = split(dense(x, p["key"], p["key_bias"]))
    v = split(dense(x, p["value"], p["value_bias"]))
    scores = jnp.einsum("...qd,...kd->...qk", q, k, precision=PRECISION) / np.sqrt(head_dim)
    scores = jnp.where(key_mask[..., None, None, :], scores, jnp.finfo(jnp.float32).min)
    weights = jax.nn.softmax(scores, axis=-1)
    out = jnp.einsum("...qk,...kd->...qd", weights, v, precision=PRECISION)
    out = jnp.swapaxes(out, -2, -3)
    out = out.reshape(out.shape[:-2] + (config.hidden_size,))
    out = dense(out, p["attn_out"], p["attn_out_bias"])
    return layer_norm(out + x, p["attn_ln_scale"], p["attn_ln_bias"], config.layer_norm_eps)


def mlp(x, p: dict, config: BertConfig):
    """The feed-forward block with its residual LayerNorm: x (..., L, D) -> (..., L, D)."""
    h = ACTIVATIONS[config.hidden_act](dense(x, p["mlp_in"], p["mlp_in_bias"]))
    out = dense(h, p["mlp_out"], p["mlp_out_bias"])
    return layer_norm(out + x, p["mlp_ln_scale"], p["mlp_ln_bias"], config.layer_norm_eps)


def embed(params: dict, ids, config: BertConfig):
    """Word + absolute position + token type 0 embeddings, LayerNormed: ids int (..., L) ->
    float32 (..., L, D). Token i has position i."""
    e = params["embeddings"]
    length = ids.shape[-1]
    x = (jnp.take(e["word"], ids, axis=0) + e["position"][:length]
         + e["token_type"][0])
    return layer_norm(x, e["ln_scale"], e["ln_bias"], config.layer_norm_eps)


def features(params: dict, ids, mask, config: BertConfig):
    """The last hidden state of a BERT encoder: one feature vector per token.

    Args:
      params: the pytree of :func:`param_shapes`, float32 arrays.
      ids: int (..., L) token ids, ``[CLS] ... [SEP]`` then padding.
      mask: (..., L) bool or int, true for real tokens; every sequence has at least one.
      config: the architecture (static under ``jit``).

    Returns:
      float32 (..., L, D): the last layer's hidden state at real tokens, 0 at padding.
      Padding changes no real token's features (it is masked out of every attention).
    """
    if ids.shape[-1] > config.max_position_embeddings:
        raise ValueError(f"{ids.shape[-1]} tokens exceed the encoder's "
                         f"max_position_embeddings {config.max_position_embeddings}")
    mask = jnp.asarray(mask).astype(bool)
    x = embed(params, jnp.asarray(ids), config)

    def layer(x, p):
        return mlp(attention(x, mask, p, config), p, config), None

    x, _ = jax.lax.scan(layer, x, params["layers"])
    return jnp.where(mask[..., None], x, 0.0)
