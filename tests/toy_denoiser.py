"""A tiny stand-in denoiser and a toy task shared by the training, checkpoint and sharding
tests (fast to compile; the real Denoiser has its own tests).

TinyDenoiser has the Denoiser call signature: (B, H, W, C+G), (B,), (B, L) -> (B, H, W, G).
toy_batch_fn(key, batch_size) -> diffplan.train.Batch on H x W = 8 x 8 maps: path = free cells,
goal = a corner chosen by the first token, so it is learnable from the conditions.
"""
import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

H = W = 8
C, G, L = 2, 2, 4


@dataclasses.dataclass(frozen=True)
class TinyConfig:
    features: int = 8
    vocab: int = 16
    gen: int = G

    def to_dict(self):
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d):
        return cls(**d)


class TinyDenoiser(nn.Module):
    """Three 3x3 convs plus token and time biases."""

    config: TinyConfig

    @nn.compact
    def __call__(self, x_t, t, tokens):
        c = self.config
        emb = nn.Embed(c.vocab, c.features)(tokens).mean(axis=1)
        tf = jnp.stack([jnp.sin(t / 10.0), jnp.cos(t / 10.0), t / 100.0], -1).astype(jnp.float32)
        h = nn.Conv(c.features, (3, 3))(x_t) + (emb + nn.Dense(c.features)(tf))[:, None, None]
        h = nn.Conv(c.features, (3, 3))(nn.silu(h))
        return nn.Conv(c.gen, (3, 3))(nn.silu(h))


def hash_uniform(key, shape):
    """Cheap deterministic U[0, 1) numbers from a PRNG key (an integer hash of the key data and
    the element index): toy data without threefry, which is slow to compile on CPU."""
    kd = jax.random.key_data(key).astype(jnp.uint32).reshape(-1)
    h = jnp.arange(int(np.prod(shape)), dtype=jnp.uint32) * jnp.uint32(0x9E3779B1) + kd[0]
    for mult, shift in ((0x85EBCA6B, 13), (0xC2B2AE35, 16), (0x27D4EB2F, 15)):
        h = (h ^ (h >> 16) ^ kd[1]) * jnp.uint32(mult)
        h = h ^ (h >> shift)
    return (h >> 8).astype(jnp.float32).reshape(shape) / float(1 << 24)


def toy_batch_fn(key, batch_size):
    """A Batch of batch_size toy examples (x0 (B, H, W, C+G), tokens (B, L), loss mask)."""
    from diffplan.train import Batch

    u = hash_uniform(key, (batch_size, H * W + L))
    obst = (u[:, :H * W] < 0.3).astype(jnp.float32).reshape(batch_size, H, W)
    tok = 1 + (u[:, H * W:] * 15).astype(jnp.int32)
    cell = jnp.where(obst > 0, 3.0, 2.0)
    path = jnp.where(obst > 0, -1.0, 1.0)
    corner = (tok[:, 0] % 2) * (H - 1)
    goal = jnp.where((jnp.arange(H)[None, :, None] == corner[:, None, None])
                     & (jnp.arange(W)[None, None, :] == 0), 1.0, -1.0)
    x0 = jnp.stack([cell, obst, path, goal], -1)
    return Batch(x0, tok, jnp.ones((batch_size, H, W, G), jnp.float32))
