"""Tests for diffplan.unet and diffplan.text_encoder (tiny configs, CPU, fast)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hypothesis import given, settings, strategies as st

from diffplan.text_encoder import TextEncoder, sentence_positions
from diffplan.unet import FAST_COMPILE_OPTIONS, MultiHeadAttention, UNet, timestep_embedding

TINY = dict(out_channels=2, widths=(8, 16), num_res_blocks=1, attn_levels=(1,),
            cross_attn_levels=(1,), groups=4, head_dim=8, mid_block=False)


def jit(f):
    """jit without LLVM optimisation: these tiny models run in microseconds anyway."""
    return jax.jit(f, compiler_options=FAST_COMPILE_OPTIONS)


def random_variables(module, *args, seed=0):
    """Random (non-trivial, well-scaled) variables with the structure of ``module.init``.

    Built on the host from ``jax.eval_shape`` (no compile): the zero-initialised layers get
    random values too. The real initialisation is tested in test_denoiser.py.
    """
    shapes = jax.eval_shape(module.init, jax.random.PRNGKey(0), *args)
    rng = np.random.default_rng(seed)

    def draw(path, leaf):
        name = jax.tree_util.keystr(path[-1:])
        std = 1.0 / np.sqrt(np.prod(leaf.shape[:-1])) if "kernel" in name else 0.1
        base = 1.0 if "scale" in name else 0.0
        return jnp.asarray(base + std * rng.standard_normal(leaf.shape), leaf.dtype)

    return jax.tree_util.tree_map_with_path(draw, shapes)


@pytest.fixture(scope="session")
def tiny_unet():
    model = UNet(**TINY)
    x = jnp.zeros((2, 8, 12, 3))
    t = jnp.zeros((2,), jnp.int32)
    ctx = jnp.zeros((2, 5, 16))
    variables = random_variables(model, x, t, ctx, jnp.ones((2, 5), bool))
    return model, variables, jit(model.apply)


def _inputs(b=2, h=8, w=12, c=3, length=5, seed=0):
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    x = jax.random.normal(k1, (b, h, w, c))
    t = jnp.arange(b, dtype=jnp.int32) * 7
    ctx = jax.random.normal(k2, (b, length, 16))
    mask = jnp.ones((b, length), bool)
    return x, t, ctx, mask


def test_timestep_embedding_shape_and_values():
    e = timestep_embedding(jnp.array([0, 5]), 8)
    assert e.shape == (2, 8)
    np.testing.assert_allclose(e[0], np.r_[np.ones(4), np.zeros(4)], atol=1e-6)
    assert not np.allclose(e[0], e[1])
    with pytest.raises(ValueError, match="even"):
        timestep_embedding(jnp.array([0]), 7)


def test_unet_shape_and_zero_output_conv(tiny_unet):
    model, variables, apply = tiny_unet
    x, t, ctx, mask = _inputs()
    y = apply(variables, x, t, ctx, mask)
    assert y.shape == (2, 8, 12, 2) and y.dtype == jnp.float32
    assert np.abs(np.asarray(y)).max() > 1e-3
    assert np.all(np.isfinite(np.asarray(y)))
    # with the output conv at its (zero) initial value the UNet outputs exactly zero
    p = variables["params"]
    zero_out = {"params": {**p, "conv_out": jax.tree_util.tree_map(jnp.zeros_like,
                                                                     p["conv_out"])}}
    assert np.all(np.asarray(apply(zero_out, x, t, ctx, mask)) == 0.0)
    shapes = jax.eval_shape(model.init, jax.random.PRNGKey(0), x, t, ctx, mask)
    assert shapes["params"]["conv_out"]["kernel"].shape == (3, 3, 8, 2)


def test_unet_depends_on_t_and_context(tiny_unet):
    model, v, apply = tiny_unet
    x, t, ctx, mask = _inputs()
    y = apply(v, x, t, ctx, mask)
    assert not np.allclose(y, apply(v, x, t + 10, ctx, mask), atol=1e-4)
    assert not np.allclose(y, apply(v, x, t, ctx + 1.0, mask), atol=1e-4)


def test_unet_vmap_matches_loop(tiny_unet):
    model, v, apply = tiny_unet
    x, t, ctx, mask = _inputs(b=2)
    xs = jnp.stack([x, x[::-1]])
    ts = jnp.stack([t, t[::-1]])
    ctxs = jnp.stack([ctx, ctx[::-1]])
    masks = jnp.stack([mask, mask])
    f = jit(jax.vmap(lambda a, b, c, d: model.apply(v, a, b, c, d)))
    ys = f(xs, ts, ctxs, masks)
    assert ys.shape == (2, 2, 8, 12, 2)
    np.testing.assert_allclose(ys[1], apply(v, x[::-1], t[::-1], ctx[::-1], mask), atol=1e-5)


@pytest.mark.parametrize("hw", [(7, 8), (8, 5)])
def test_unet_bad_hw_raises(tiny_unet, hw):
    model, variables, _ = tiny_unet
    x = jnp.zeros((1, *hw, 3))
    with pytest.raises(ValueError, match="divisible by 2"):
        jax.eval_shape(model.apply, variables, x, jnp.zeros((1,), jnp.int32),
                       jnp.zeros((1, 5, 16)))


@pytest.mark.parametrize("override, match", [
    (dict(groups=3), "groups"),
    (dict(attn_levels=(2,)), "attn_levels"),
    (dict(cross_attn_levels=(0, 0)), "duplicate"),
    (dict(head_dim=5), "head_dim"),
    (dict(widths=()), "widths"),
    (dict(num_res_blocks=0), "num_res_blocks"),
])
def test_unet_bad_config_raises(override, match):
    with pytest.raises(ValueError, match=match):
        UNet(**{**TINY, **override}).validate()


def test_attention_padding_mask():
    att = MultiHeadAttention(num_heads=2)
    x = jax.random.normal(jax.random.PRNGKey(0), (1, 4, 8))
    ctx = jax.random.normal(jax.random.PRNGKey(1), (1, 6, 8))
    v = random_variables(att, x, ctx)
    apply = jit(att.apply)
    mask = jnp.array([[True, True, True, False, False, False]])
    y = apply(v, x, ctx, mask)
    # padded keys carry arbitrary values: the output must not change
    ctx2 = ctx.at[:, 3:].set(100.0)
    np.testing.assert_allclose(y, apply(v, x, ctx2, mask), atol=1e-6)
    # truncating the padding gives the same output
    np.testing.assert_allclose(y, apply(v, x, ctx[:, :3], mask[:, :3]), atol=1e-5)
    # a fully padded context contributes exactly nothing
    y0 = apply(v, x, ctx, jnp.zeros_like(mask))
    assert np.all(np.asarray(y0) == 0.0)
    # real keys do matter
    assert not np.allclose(y, apply(v, x, ctx.at[:, 0].set(5.0), mask), atol=1e-4)


def test_text_encoder_shapes_padding_and_limits():
    enc = TextEncoder(vocab_size=20, max_tokens=10, dim=16, num_layers=2, num_heads=2)
    tok = jnp.array([[5, 6, 7, 0, 0, 0], [9, 0, 0, 0, 0, 0]], jnp.int32)
    v = random_variables(enc, tok)
    assert "token_embed" in v["params"] and "pos_embed" in v["params"]
    assert v["params"]["pos_embed"].shape == (10, 16)
    apply = jit(enc.apply)
    feats, mask = apply(v, tok)
    assert feats.shape == (2, 6, 16) and mask.shape == (2, 6)
    np.testing.assert_array_equal(mask, tok != 0)
    feats_short, _ = apply(v, tok[:, :3])
    np.testing.assert_allclose(feats[:, :3][mask[:, :3]], feats_short[mask[:, :3]], atol=1e-5)
    with pytest.raises(ValueError, match="max_tokens"):
        jax.eval_shape(enc.apply, v, jnp.ones((1, 11), jnp.int32))
    with pytest.raises(ValueError, match="num_heads"):
        jax.eval_shape(TextEncoder(vocab_size=20, max_tokens=10, dim=15, num_heads=2).init,
                       jax.random.PRNGKey(0), tok)


def _sentence_positions_oracle(tokens, end_id):
    """Plain-Python (position in sentence, sentence index) of every token."""
    positions, sentences = np.zeros_like(tokens), np.zeros_like(tokens)
    for b, row in enumerate(tokens):
        position = sentence = 0
        for i, token in enumerate(row):
            positions[b, i], sentences[b, i] = position, sentence
            position += 1
            if token == end_id:
                position, sentence = 0, sentence + 1
    return positions, sentences


@settings(max_examples=40, deadline=None)
@given(st.lists(st.lists(st.integers(0, 4), min_size=1, max_size=9), min_size=1, max_size=3))
def test_sentence_positions_match_a_plain_python_oracle(rows):
    width = max(len(r) for r in rows)
    tokens = np.array([r + [0] * (width - len(r)) for r in rows], np.int32)
    position, sentence = sentence_positions(jnp.asarray(tokens), 3)
    want_position, want_sentence = _sentence_positions_oracle(tokens, 3)
    np.testing.assert_array_equal(position, want_position)
    np.testing.assert_array_equal(sentence, want_sentence)


def test_sentence_positions_make_a_sentence_independent_of_the_ones_before():
    """With per-sentence positions (and no attention layers), the last sentence's features do
    not change when the sentence before it gets longer; with absolute positions they do."""
    end = 1
    short = jnp.array([[5, 6, end, 7, 8, end, 0, 0]], jnp.int32)
    long = jnp.array([[5, 9, 6, end, 7, 8, end, 0]], jnp.int32)
    for end_id, same in ((end, True), (-1, False)):
        enc = TextEncoder(vocab_size=12, max_tokens=8, dim=8, num_layers=0, num_heads=2,
                          sentence_end_id=end_id)
        v = random_variables(enc, short)
        assert ("sentence_embed" in v["params"]) == (end_id >= 0)
        a, _ = enc.apply(v, short)
        b, _ = enc.apply(v, long)
        assert np.allclose(a[0, 3:6], b[0, 4:7], atol=1e-5) == same


def test_per_query_mask_equals_key_mask_when_broadcast_and_zeroes_dead_rows():
    """A (B, Q, K) mask that repeats a (B, K) key mask gives the same attention; a query whose
    keys are all masked gets exactly zero."""
    attn = MultiHeadAttention(num_heads=2)
    x = jax.random.normal(jax.random.PRNGKey(1), (2, 5, 8))
    keys = jnp.array([[1, 1, 1, 0, 0], [1, 0, 1, 1, 1]], bool)
    v = random_variables(attn, x)
    by_key = attn.apply(v, x, mask=keys)
    per_query = jnp.broadcast_to(keys[:, None, :], (2, 5, 5))
    np.testing.assert_allclose(attn.apply(v, x, mask=per_query), by_key, atol=1e-6)
    dead = per_query.at[0, 2].set(False)
    out = attn.apply(v, x, mask=dead)
    assert np.all(np.asarray(out[0, 2]) == 0.0)
    np.testing.assert_allclose(out[1], by_key[1], atol=1e-6)


@settings(max_examples=15, deadline=None)
@given(st.lists(st.integers(2, 11), min_size=0, max_size=4),
       st.lists(st.integers(2, 11), min_size=0, max_size=4))
def test_sentence_local_encoder_reads_a_sentence_the_same_wherever_it_stands(before, after):
    """With sentence_local, a sentence's features (after attention layers) are the same
    whatever sentences come before and after it; without it, a sentence before changes them."""
    end = 1
    middle = [5, 6, 7, end]
    prefix = before + [end] if before else []
    suffix = after + [end] if after else []
    row = prefix + middle + suffix
    tokens = jnp.asarray([row + [0] * (16 - len(row))], jnp.int32)
    alone = jnp.asarray([middle + [0] * (16 - len(middle))], jnp.int32)
    enc = TextEncoder(vocab_size=12, max_tokens=16, dim=8, num_layers=2, num_heads=2,
                      sentence_end_id=end, sentence_local=True)
    v = random_variables(enc, alone)
    assert "sentence_embed" not in v["params"]
    a, _ = enc.apply(v, alone)
    b, _ = enc.apply(v, tokens)
    np.testing.assert_allclose(a[0, :4], b[0, len(prefix):len(prefix) + 4], atol=1e-5)
    if prefix:
        shared = TextEncoder(vocab_size=12, max_tokens=16, dim=8, num_layers=2, num_heads=2,
                             sentence_end_id=end)
        w = random_variables(shared, alone)
        c, _ = shared.apply(w, alone)
        d, _ = shared.apply(w, tokens)
        assert not np.allclose(c[0, :4], d[0, len(prefix):len(prefix) + 4], atol=1e-5)


def test_sentence_local_needs_a_sentence_end():
    enc = TextEncoder(vocab_size=12, max_tokens=8, dim=8, num_heads=2, sentence_local=True)
    with pytest.raises(ValueError, match="sentence_end_id"):
        jax.eval_shape(enc.init, jax.random.PRNGKey(0), jnp.ones((1, 4), jnp.int32))
