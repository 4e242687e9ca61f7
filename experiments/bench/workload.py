"""What the UNet benchmark (experiments.bench_unet) times: a realistic planning batch and one
optimiser step of a DDPM loss."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from diffplan.denoiser import Denoiser, DenoiserConfig


def make_inputs(cfg: DenoiserConfig, batch: int, size: int, num_tokens: int, seed: int):
    """A realistic planning batch: (x (B,H,W,C+G), t (B,), tokens (B,L))."""
    k = jax.random.split(jax.random.PRNGKey(seed), 5)
    ids = jax.random.randint(k[0], (batch, size, size, 1), 0, cfg.vocab_size).astype(jnp.float32)
    feats = jax.random.bernoulli(k[1], 0.3, (batch, size, size, cfg.num_cond_channels - 1))
    gen = jnp.where(jax.random.bernoulli(k[2], 0.1, (batch, size, size, cfg.num_gen_channels)),
                    1.0, -1.0)
    x = jnp.concatenate([ids, feats.astype(jnp.float32), gen], axis=-1)
    t = jax.random.randint(k[3], (batch,), 0, 100)
    lengths = jax.random.randint(k[4], (batch, 1), 3, num_tokens + 1)
    tokens = jnp.where(jnp.arange(num_tokens)[None] < lengths,
                       4 + jnp.arange(num_tokens)[None] % (cfg.vocab_size - 4), 0)
    return x, t, tokens.astype(jnp.int32)


def make_train_step(model: Denoiser, optimizer, num_train_steps: int = 100):
    """(params, opt_state, x0, tokens, key) -> (params, opt_state, loss): one Adam step on the
    DDPM eps-MSE of the generated channels (condition channels held clean)."""
    c = model.config.num_cond_channels
    ab = jnp.linspace(0.999, 0.01, num_train_steps)  # alphas_cumprod stand-in: cost only

    def loss_fn(params, x0, tokens, key):
        kt, ke = jax.random.split(key)
        t = jax.random.randint(kt, (x0.shape[0],), 0, num_train_steps)
        eps = jax.random.normal(ke, x0.shape[:-1] + (x0.shape[-1] - c,))
        a = ab[t][:, None, None, None]
        x_t = jnp.concatenate([x0[..., :c], jnp.sqrt(a) * x0[..., c:] + jnp.sqrt(1 - a) * eps],
                              axis=-1)
        pred = model.apply({"params": params}, x_t, t, tokens)
        return jnp.mean(jnp.square(pred - eps))

    def step(params, opt_state, x0, tokens, key):
        loss, grads = jax.value_and_grad(loss_fn)(params, x0, tokens, key)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    return step
