"""Tests for diffplan.denoiser (tiny configs, CPU, fast)."""
import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan.denoiser import (Denoiser, DenoiserConfig, count_params, init_params,
                               make_denoise_fn)

TINY = DenoiserConfig(vocab_size=16, max_tokens=12, num_cond_channels=3, num_gen_channels=2,
                      grid_repr="embed", embed_dim=8, widths=(8, 16), num_res_blocks=1,
                      attn_levels=(1,), cross_attn_levels=(0, 1), text_dim=16, text_layers=1,
                      text_heads=2, groups=4, head_dim=8)
B, H, W = 2, 8, 8


def perturb(variables, scale=0.2, seed=1):
    leaves, treedef = jax.tree_util.tree_flatten(variables)
    keys = jax.random.split(jax.random.PRNGKey(seed), len(leaves))
    leaves = [p + scale * jax.random.normal(k, p.shape, p.dtype) for p, k in zip(leaves, keys)]
    return jax.tree_util.tree_unflatten(treedef, leaves)


def make_x(seed=0, b=B, h=H, w=W, cfg=TINY):
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(seed), 3)
    ids = jax.random.randint(k1, (b, h, w), 1, 6).astype(jnp.float32)  # ids 1..5 only
    feats = jax.random.bernoulli(k2, 0.3, (b, h, w, cfg.num_cond_channels - 1)).astype(
        jnp.float32)
    gen = jax.random.normal(k3, (b, h, w, cfg.num_gen_channels))
    return jnp.concatenate([ids[..., None], feats, gen], axis=-1)


TOKENS = jnp.array([[7, 8, 9, 0, 0, 0], [10, 11, 0, 0, 0, 0]], jnp.int32)  # words 7..11
T = jnp.array([3, 40], jnp.int32)


@pytest.fixture(scope="session", params=["embed", "class_id"])
def model_vars(request):
    cfg = dataclasses.replace(TINY, grid_repr=request.param)
    model = Denoiser(cfg)
    variables = init_params(model, jax.random.PRNGKey(0), H, W)
    return model, variables, perturb(variables), jax.jit(model.apply)


def test_output_shape_and_zero_init(model_vars):
    model, v0, v, apply = model_vars
    x = make_x()
    eps0 = apply(v0, x, T, TOKENS)
    assert eps0.shape == (B, H, W, 2) and eps0.dtype == jnp.float32
    assert np.all(np.asarray(eps0) == 0.0)
    eps = apply(v, x, T, TOKENS)
    assert np.all(np.isfinite(np.asarray(eps))) and np.abs(np.asarray(eps)).max() > 1e-3
    assert count_params(v0) > 1000 and count_params(v0) == count_params(v0["params"])


def test_padding_invariance(model_vars):
    model, _, v, apply = model_vars
    x = make_x()
    eps_short = apply(v, x, T, TOKENS[:, :4])
    eps_long = apply(v, x, T, jnp.pad(TOKENS, ((0, 0), (0, 6))))  # L = 12 = max_tokens
    np.testing.assert_allclose(eps_short, eps_long, atol=1e-5)
    # ... while a different word does change the prediction
    other = apply(v, x, T, TOKENS.at[0, 1].set(12)[:, :4])
    assert np.abs(np.asarray(other[0] - eps_short[0])).max() > 1e-4
    np.testing.assert_allclose(other[1], eps_short[1], atol=1e-5)  # per-example independence


def test_cell_ids_change_output(model_vars):
    model, _, v, apply = model_vars
    x = make_x()
    eps = apply(v, x, T, TOKENS)
    x2 = x.at[:, 2, 3, 0].set(13.0)
    assert np.abs(np.asarray(apply(v, x2, T, TOKENS) - eps)).max() > 1e-4


def test_jit_and_vmap(model_vars):
    model, _, v, apply = model_vars
    xs = jnp.stack([make_x(0), make_x(1)])
    f = jax.jit(jax.vmap(lambda x, t, tok: model.apply(v, x, t, tok)))
    out = f(xs, jnp.stack([T, T]), jnp.stack([TOKENS, TOKENS]))
    assert out.shape == (2, B, H, W, 2)
    np.testing.assert_allclose(out[1], apply(v, xs[1], T, TOKENS), atol=1e-5)


def test_make_denoise_fn(model_vars):
    model, _, v, apply = model_vars
    x = make_x()
    fn = jax.jit(make_denoise_fn(model, v, TOKENS))
    full = fn(x, T)
    assert full.shape == x.shape
    c = model.config.num_cond_channels
    assert np.all(np.asarray(full[..., :c]) == 0.0)
    np.testing.assert_allclose(full[..., c:], apply(v, x, T, TOKENS), atol=1e-6)
    assert np.abs(np.asarray(full[..., c:])).max() > 1e-3
    # batch-1 tokens broadcast to the plan batch; bare params tree accepted
    fn1 = make_denoise_fn(model, v["params"], TOKENS[:1])
    np.testing.assert_allclose(fn1(x, T)[..., c:],
                               apply(v, x, T, jnp.broadcast_to(TOKENS[:1], TOKENS.shape)),
                               atol=1e-5)


def test_embed_table_is_shared():
    model = Denoiser(TINY)
    v = perturb(init_params(model, jax.random.PRNGKey(0), H, W))
    p = v["params"]
    embeds = [jax.tree_util.keystr(path) for path, _ in
              jax.tree_util.tree_flatten_with_path(p)[0] if "embedding" in jax.tree_util.keystr(path)]
    assert embeds == ["['token_embed']['embedding']"], embeds
    assert p["token_embed"]["embedding"].shape == (TINY.vocab_size, TINY.embed_dim)
    assert "token_embed" not in p["text_encoder"]
    x = make_x()

    def out(params):
        return jnp.sum(model.apply({"params": params}, x, T, TOKENS) ** 2)

    g = jax.grad(out)(p)["token_embed"]["embedding"]
    gnorm = np.linalg.norm(np.asarray(g), axis=-1)
    assert np.all(gnorm[1:6] > 0), "grid-cell ids 1..5 must use the table"
    assert np.all(gnorm[7:12] > 0), "instruction words 7..11 must use the same table"
    assert np.all(gnorm[12:] == 0) and gnorm[6] == 0  # unused ids get no gradient


def test_class_id_has_no_cell_embedding():
    cfg = dataclasses.replace(TINY, grid_repr="class_id")
    p = init_params(Denoiser(cfg), jax.random.PRNGKey(0), H, W)["params"]
    assert "token_embed" not in p
    assert p["text_encoder"]["token_embed"]["embedding"].shape == (16, 8)
    # the UNet's input conv sees C + G channels (a single scalar id channel)
    assert p["unet"]["conv_in"]["kernel"].shape[2] == cfg.num_channels
    p_embed = init_params(Denoiser(TINY), jax.random.PRNGKey(0), H, W)["params"]
    assert p_embed["unet"]["conv_in"]["kernel"].shape[2] == (
        TINY.embed_dim + TINY.num_cond_channels - 1 + TINY.num_gen_channels)


def test_config_dict_roundtrip_and_hash():
    d = TINY.to_dict()
    assert isinstance(d["widths"], list)
    restored = DenoiserConfig.from_dict(json.loads(json.dumps(d)))
    assert restored == TINY and hash(restored) == hash(TINY)
    assert isinstance(restored.widths, tuple)
    with pytest.raises(ValueError, match="unknown DenoiserConfig fields"):
        DenoiserConfig.from_dict({**d, "bogus": 1})
    assert hash(DenoiserConfig()) == hash(DenoiserConfig())


@pytest.mark.parametrize("override, match", [
    (dict(grid_repr="onehot"), "grid_repr"),
    (dict(groups=3), "groups"),
    (dict(text_dim=15), "text_dim"),
    (dict(attn_levels=(5,)), "attn_levels"),
    (dict(cross_attn_levels=(-1,)), "cross_attn_levels"),
    (dict(vocab_size=1), "vocab_size"),
    (dict(num_gen_channels=0), "num_gen_channels"),
    (dict(widths=(8, 12)), "groups"),
    (dict(head_dim=3), "head_dim"),
    (dict(widths=8), "widths"),
    (dict(num_res_blocks=0), "num_res_blocks"),
])
def test_bad_config_raises(override, match):
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(TINY, **override)


def test_bad_inputs_raise(model_vars):
    model, v0, _, _ = model_vars
    with pytest.raises(ValueError, match="divisible"):
        model.apply(v0, jnp.zeros((1, 6, 8, 5)), jnp.zeros((1,), jnp.int32), TOKENS[:1])
    with pytest.raises(ValueError, match="C\\+G"):
        model.apply(v0, jnp.zeros((1, 8, 8, 4)), jnp.zeros((1,), jnp.int32), TOKENS[:1])
    with pytest.raises(ValueError, match="max_tokens"):
        model.apply(v0, jnp.zeros((1, 8, 8, 5)), jnp.zeros((1,), jnp.int32),
                    jnp.ones((1, 13), jnp.int32))
    with pytest.raises(ValueError, match="tokens"):
        model.apply(v0, jnp.zeros((2, 8, 8, 5)), jnp.zeros((2,), jnp.int32), TOKENS[:1])
