"""Tests for diffplan.denoiser (tiny configs, CPU, fast)."""
import dataclasses
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan.denoiser import (Denoiser, DenoiserConfig, count_params, init_params,
                               make_denoise_fn)
from diffplan.unet import FAST_COMPILE_OPTIONS

TINY = DenoiserConfig(vocab_size=16, max_tokens=12, num_cond_channels=3, num_gen_channels=2,
                      grid_repr="embed", embed_dim=8, widths=(8, 16), num_res_blocks=1,
                      attn_levels=(1,), cross_attn_levels=(0, 1), text_dim=16, text_layers=1,
                      text_heads=2, groups=4, head_dim=8, mid_block=False)
B, H, W = 2, 8, 8


def jit(f):
    """jit without LLVM optimisation: these tiny models run in microseconds anyway."""
    return jax.jit(f, compiler_options=FAST_COMPILE_OPTIONS)


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


@functools.lru_cache(maxsize=None)
def build(grid_repr):
    """(model, initial variables, perturbed variables, jitted apply) for a grid_repr.

    Only the "embed" model is really initialised (an init costs a compile of ~10 s here);
    the "class_id" model starts from zeros (its output is then zero as well) and is perturbed.
    """
    cfg = dataclasses.replace(TINY, grid_repr=grid_repr)
    model = Denoiser(cfg)
    if grid_repr == "embed":
        variables = init_params(model, jax.random.PRNGKey(0), H, W)
    else:
        variables = jax.tree_util.tree_map(
            jnp.zeros_like, jax.eval_shape(model.init, jax.random.PRNGKey(0), make_x(), T, TOKENS))
    return model, variables, perturb(variables), jit(model.apply)


@pytest.fixture(scope="session", params=["embed", "class_id"])
def model_vars(request):
    return build(request.param)


@pytest.fixture(scope="session")
def embed_vars():
    return build("embed")


def test_output_shape_and_zero_init(model_vars):
    model, v0, v, apply = model_vars
    x = make_x()
    eps0 = apply(v0, x, T, TOKENS)
    assert eps0.shape == (B, H, W, 2) and eps0.dtype == jnp.float32
    assert np.all(np.asarray(eps0) == 0.0)  # the zero-initialised output conv
    if model.config.grid_repr == "embed":  # really initialised: only conv_out is zero
        p = v0["params"]
        assert np.all(np.asarray(p["unet"]["conv_out"]["kernel"]) == 0.0)
        assert np.abs(np.asarray(p["unet"]["conv_in"]["kernel"])).max() > 0.0
        assert np.abs(np.asarray(p["token_embed"]["embedding"])).max() > 0.0
    eps = apply(v, x, T, TOKENS)
    assert np.all(np.isfinite(np.asarray(eps))) and np.abs(np.asarray(eps)).max() > 1e-3
    assert count_params(v0) > 1000 and count_params(v0) == count_params(v0["params"])


def test_padding_invariance(embed_vars):
    model, _, v, apply = embed_vars
    x = make_x()
    eps_short = apply(v, x, T, TOKENS)
    eps_long = apply(v, x, T, jnp.pad(TOKENS, ((0, 0), (0, 6))))  # L = 12 = max_tokens
    np.testing.assert_allclose(eps_short, eps_long, atol=1e-5)
    # ... while a different word does change the prediction
    other = apply(v, x, T, TOKENS.at[0, 1].set(12))
    assert np.abs(np.asarray(other[0] - eps_short[0])).max() > 1e-4
    np.testing.assert_allclose(other[1], eps_short[1], atol=1e-5)  # per-example independence


def test_cell_ids_change_output(model_vars):
    model, _, v, apply = model_vars
    x = make_x()
    eps = apply(v, x, T, TOKENS)
    x2 = x.at[:, 2, 3, 0].set(13.0)
    assert np.abs(np.asarray(apply(v, x2, T, TOKENS) - eps)).max() > 1e-4


def test_jit_and_vmap(embed_vars):
    model, _, v, apply = embed_vars
    xs = jnp.stack([make_x(0), make_x(1)])
    f = jit(jax.vmap(lambda x, t, tok: model.apply(v, x, t, tok)))
    out = f(xs, jnp.stack([T, T]), jnp.stack([TOKENS, TOKENS]))
    assert out.shape == (2, B, H, W, 2)
    np.testing.assert_allclose(out[1], apply(v, xs[1], T, TOKENS), atol=1e-5)


def test_make_denoise_fn(embed_vars):
    model, _, v, apply = embed_vars
    x = make_x()
    # batch-1 tokens broadcast to the plan batch; a bare params tree is accepted
    fn = jit(make_denoise_fn(model, v["params"], TOKENS[:1]))
    full = fn(x, T)
    assert full.shape == x.shape
    c = model.config.num_cond_channels
    assert np.all(np.asarray(full[..., :c]) == 0.0)
    ref = apply(v, x, T, jnp.broadcast_to(TOKENS[:1], TOKENS.shape))
    np.testing.assert_allclose(full[..., c:], ref, atol=1e-5)
    assert np.abs(np.asarray(full[..., c:])).max() > 1e-3
    with pytest.raises(ValueError, match="tokens batch"):
        jax.eval_shape(make_denoise_fn(model, v, TOKENS), x[:1], T[:1])


def test_embed_table_is_shared(embed_vars):
    model, _, v, apply = embed_vars
    p = v["params"]
    embeds = [jax.tree_util.keystr(path) for path, _ in jax.tree_util.tree_flatten_with_path(p)[0]
              if "embedding" in jax.tree_util.keystr(path)]
    assert embeds == ["['token_embed']['embedding']"], embeds
    assert p["token_embed"]["embedding"].shape == (TINY.vocab_size, TINY.embed_dim)
    assert "token_embed" not in p["text_encoder"]
    x = make_x()  # cells use ids 1..5, TOKENS use words 7..11
    base = np.asarray(apply(v, x, T, TOKENS))

    def with_row(row):
        table = p["token_embed"]["embedding"]
        q = {**p, "token_embed": {"embedding": table.at[row].add(1.0)}}
        return np.asarray(apply({"params": q}, x, T, TOKENS))

    assert np.abs(with_row(3) - base).max() > 1e-4, "grid cells must use the table"
    assert np.abs(with_row(8) - base).max() > 1e-4, "instruction words must use the same table"
    np.testing.assert_array_equal(with_row(14), base)  # an unused id changes nothing


def test_class_id_has_no_cell_embedding():
    cfg = dataclasses.replace(TINY, grid_repr="class_id")
    p = jax.eval_shape(Denoiser(cfg).init, jax.random.PRNGKey(0), make_x(),
                       T, TOKENS)["params"]
    assert "token_embed" not in p
    assert p["text_encoder"]["token_embed"]["embedding"].shape == (16, 8)
    # the UNet's input conv sees C + G channels (a single scalar id channel)
    assert p["unet"]["conv_in"]["kernel"].shape[2] == cfg.num_channels
    p_embed = jax.eval_shape(Denoiser(TINY).init, jax.random.PRNGKey(0), make_x(), T,
                             TOKENS)["params"]
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
    # absolute positions (the default) are not recorded: older checkpoints' metadata matches
    assert "sentence_end_id" not in d
    per_sentence = dataclasses.replace(TINY, sentence_end_id=3)
    assert per_sentence.to_dict()["sentence_end_id"] == 3
    assert DenoiserConfig.from_dict(json.loads(json.dumps(per_sentence.to_dict()))) == per_sentence
    assert "token_classes" not in d  # likewise no token head
    headed = dataclasses.replace(TINY, token_classes=2)
    assert DenoiserConfig.from_dict(json.loads(json.dumps(headed.to_dict()))) == headed


@pytest.mark.parametrize("override, match", [
    (dict(grid_repr="onehot"), "grid_repr"),
    (dict(groups=3), "groups"),
    (dict(text_dim=15), "text_dim"),
    (dict(attn_levels=(5,)), "attn_levels"),
    (dict(cross_attn_levels=(-1,)), "cross_attn_levels"),
    (dict(vocab_size=1), "vocab_size"),
    (dict(num_gen_channels=0), "num_gen_channels"),
    (dict(widths=(8, 10)), "groups"),
    (dict(head_dim=3), "head_dim"),
    (dict(widths=8), "widths"),
    (dict(num_res_blocks=0), "num_res_blocks"),
    (dict(sentence_end_id=10 ** 6), "sentence_end_id"),
    (dict(sentence_end_id=-2), "sentence_end_id"),
    (dict(token_classes=-1), "token_classes"),
    (dict(token_classes=2.0), "token_classes"),
])
def test_bad_config_raises(override, match):
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(TINY, **override)


def test_bad_inputs_raise(model_vars):
    model, v0, _, _ = model_vars

    def run(x, t, tok):
        return jax.eval_shape(model.apply, v0, x, t, tok)

    t1 = jnp.zeros((1,), jnp.int32)
    with pytest.raises(ValueError, match="divisible by 2"):
        run(jnp.zeros((1, 7, 8, 5)), t1, TOKENS[:1])
    with pytest.raises(ValueError, match="C\\+G"):
        run(jnp.zeros((1, 8, 8, 4)), t1, TOKENS[:1])
    with pytest.raises(ValueError, match="max_tokens"):
        run(jnp.zeros((1, 8, 8, 5)), t1, jnp.ones((1, 13), jnp.int32))
    with pytest.raises(ValueError, match="tokens"):
        run(jnp.zeros((2, 8, 8, 5)), jnp.zeros((2,), jnp.int32), TOKENS[:1])
    with pytest.raises(ValueError, match="t must have shape"):
        run(jnp.zeros((1, 8, 8, 5)), jnp.zeros((2,), jnp.int32), TOKENS[:1])


def test_the_denoiser_is_registered_under_its_class_path():
    """Checkpoints name the network by class_path; loading finds it in diffplan.models."""
    from diffplan import models

    spec = models.lookup(models.class_path(Denoiser))
    assert spec.key == "diffplan.denoiser:Denoiser" and spec.model_cls is Denoiser
    assert spec.config_cls is DenoiserConfig
    assert spec.config_key == "diffplan.denoiser:DenoiserConfig"
    shapes = {"x": [2, 16, 16, 7], "tokens": [2, 5]}
    x, t, tokens = spec.inputs(shapes)
    assert (x.shape, t.shape, tokens.shape) == ((2, 16, 16, 7), (2,), (2, 5))
    assert (x.dtype, t.dtype, tokens.dtype) == (jnp.float32, jnp.int32, jnp.int32)


def test_token_loss_matches_numpy_cross_entropy():
    """diffplan.losses.token_loss: sum(w * CE) / #(w > 0), against a plain-numpy softmax; the
    labels of unweighted tokens (even out of range) never matter."""
    from diffplan.losses import Batch, token_loss

    rng = np.random.default_rng(0)
    logits = rng.normal(size=(3, 5, 4)).astype(np.float32)
    labels = rng.integers(0, 4, size=(3, 5)).astype(np.int32)
    weights = (rng.random((3, 5)) < 0.5) * rng.uniform(0.5, 2.0, (3, 5))
    labels_junk = np.where(weights > 0, labels, 99)
    batch = Batch(np.zeros((3, 2, 2, 3), np.float32), np.ones((3, 5), np.int32),
                  np.ones((3, 2, 2, 1), np.float32), labels_junk, weights.astype(np.float32))
    got = float(token_loss(None, lambda v, tokens: jnp.asarray(logits), batch))
    logp = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
    ce = -np.take_along_axis(logp, labels[..., None], -1)[..., 0]
    want = (weights * ce).sum() / (weights > 0).sum()
    np.testing.assert_allclose(got, want, rtol=1e-5)
    none = batch._replace(token_weights=np.zeros((3, 5), np.float32))
    assert float(token_loss(None, lambda v, tokens: jnp.asarray(logits), none)) == 0.0


def test_batch_token_labels_are_checked():
    from diffplan.losses import Batch, check_batch

    x0, tok, mask = np.zeros((2, 4, 4, 5)), np.ones((2, 6), np.int32), np.ones((2, 4, 4, 2))
    check_batch(Batch(x0, tok, mask), 2)
    check_batch(Batch(x0, tok, mask, np.zeros((2, 6), np.int32), np.ones((2, 6))), 2)
    with pytest.raises(ValueError, match="both or neither"):
        check_batch(Batch(x0, tok, mask, np.zeros((2, 6), np.int32)), 2)
    with pytest.raises(ValueError, match="token_weights must have the tokens' shape"):
        check_batch(Batch(x0, tok, mask, np.zeros((2, 6), np.int32), np.ones((2, 5))), 2)


def test_token_head_learns_labels_through_the_train_step():
    """A denoiser with token_classes: init creates ``token_head``; a batch with token labels
    adds their cross-entropy to the loss (metrics report both parts) and the head learns them;
    a denoiser without a head refuses such a batch with a one-line reason."""
    from diffplan.losses import Batch, make_train_step
    from diffplan.train_state import TrainConfig, init_train_state

    cfg = dataclasses.replace(TINY, token_classes=2)
    model = Denoiser(cfg)
    x0 = make_x(5)
    labels = (TOKENS % 2).astype(jnp.int32)  # a property of the word: learnable
    batch = Batch(x0, TOKENS, jnp.ones(x0.shape[:-1] + (2,)), labels,
                  (TOKENS > 0).astype(jnp.float32))
    tcfg = TrainConfig(steps=30, batch_size=B, lr=1e-2, warmup_steps=0, num_gen_channels=2)
    state = init_train_state(model, tcfg, batch)
    assert state.params["token_head"]["kernel"].shape == (cfg.text_dim, 2)
    step = make_train_step(model, tcfg)
    key = jax.random.PRNGKey(1)
    state, first = step(state, batch, key)
    np.testing.assert_allclose(float(first["loss"]),
                               float(first["diffusion_loss"]) + float(first["token_loss"]),
                               rtol=1e-5)
    for _ in range(25):
        state, m = step(state, batch, key)
    assert float(m["token_loss"]) < 0.5 * float(first["token_loss"])
    plain = Denoiser(TINY)
    with pytest.raises(ValueError, match="no token head"):
        jax.eval_shape(functools.partial(plain.apply, method="token_logits"),
                       build("embed")[1], TOKENS)
