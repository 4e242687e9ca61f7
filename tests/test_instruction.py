"""Instructions as pretrained text features (diffplan.instruction) and the grid world's
sentences (envs.gridworld.sentences): sentence splitting, the table path equal to the text path
bit for bit, the map from an episode to its sentences, the length limit (measured on every
phrasing set, the sealed natural set counted only), the features denoiser's mask, the planner's
input check, one-line refusals, the sealed natural set never reaching a training table, and no
refusal of any word string within the limit."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from diffplan.instruction import (InstructionEncoder, SentenceTable, assemble, assemble_batch, cell_names,
                                  split_sentences)
from diffplan.pretrained_text import load_text_encoder
from envs.gridworld import grammar, natural, sentences
from envs.gridworld.sentences import FEATURE_TOKENS

CLASSES = (1, 4, 8, 9, 11)
"""apple, lettuce, broccoli, strawberry, pear: several split into more than one wordpiece."""


def one_line(excinfo) -> str:
    message = str(excinfo.value)
    assert "\n" not in message, message
    return message


@pytest.fixture(scope="module")
def text_encoder():
    return load_text_encoder()


@pytest.fixture(scope="module")
def encoder(text_encoder, tmp_path_factory):
    return InstructionEncoder(text_encoder, FEATURE_TOKENS,
                              cache_dir=str(tmp_path_factory.mktemp("text-features")))


@pytest.fixture(scope="module")
def small(encoder):
    """Every phrasing (canonical, training, held-out; both meanings) with five classes: the
    index and its table."""
    index = sentences.sentence_index({kind: range(grammar.NUM_TEMPLATES)
                                      for kind in sentences.KINDS}, CLASSES)
    return index, encoder.table(index.sentences)


def test_split_sentences():
    assert split_sentences("First, go to the apple. Then, go north to find the pear.") == [
        "First, go to the apple.", "Then, go north to find the pear."]
    assert split_sentences("  go to the apple then go north  ") == ["go to the apple then go north"]
    assert split_sentences("Can you? Go!  Now.") == ["Can you?", "Go!", "Now."]
    assert split_sentences("Really?! Go.") == ["Really?!", "Go."]
    assert split_sentences("Walk 3.5 cells, e.g.north.") == ["Walk 3.5 cells, e.g.north."]
    assert split_sentences("Go.\nThen stop") == ["Go.", "Then stop"]
    assert split_sentences("   ") == []


def test_table_path_equals_text_path_for_random_instructions(encoder, small):
    index, table = small
    rng = np.random.default_rng(0)
    fn = jax.jit(lambda t, ids: assemble_batch(t, ids))
    texts, ids = [], []
    for _ in range(200):
        kind = bool(rng.integers(2))
        template = int(rng.integers(grammar.NUM_TEMPLATES))
        ref, target = rng.choice(CLASSES, 2, replace=False) if kind else (0, rng.choice(CLASSES))
        direction = int(rng.integers(8)) if kind else -1
        setting = "p_mo2g" if kind else "mo1g"
        texts.append(grammar.render(setting, template, int(ref), int(target), direction))
        ids.append(np.asarray(index.ids(kind, template, int(ref), int(target), direction)))
    got = np.asarray(fn(table, np.stack(ids)))
    want = encoder.encode(texts)
    assert got.shape == want.shape == (200, FEATURE_TOKENS, 384)
    assert np.max(np.abs(got - want)) <= 1e-6
    np.testing.assert_array_equal(got, want)  # in fact bit for bit
    # The table read back from the disk cache by another encoder gives the same features.
    again = InstructionEncoder(encoder.encoder, FEATURE_TOKENS, cache_dir=encoder.cache_dir)
    np.testing.assert_array_equal(np.asarray(again.table(index.sentences).features),
                                  np.asarray(table.features))
    # Absent entries (-1) are skipped wherever they stand; tokens past L are dropped.
    a, b = ids[0][0], ids[1][0]
    np.testing.assert_array_equal(np.asarray(assemble(table, np.array([-1, a, -1, b]))),
                                  np.asarray(assemble(table, np.array([a, b, -1, -1]))))
    long = np.asarray(assemble(table, np.full(8, a)))
    assert long.shape == (FEATURE_TOKENS, 384) and np.any(long[-1] != 0)


def test_a_sentence_reads_the_same_in_every_batch(encoder):
    """A sentence's features do not depend on the instructions computed beside it."""
    one = encoder.encode("Go to the apple first. The pear is north of it.")
    fresh = InstructionEncoder(encoder.encoder, FEATURE_TOKENS, cache_dir=encoder.cache_dir)
    batch = fresh.encode(["Walk over there, then stop and wait for a while please.",
                          "Go to the apple first. The pear is north of it.", "Hi."])
    np.testing.assert_array_equal(batch[1], one)
    mask = np.any(one != 0, -1)
    n = encoder.length("Go to the apple first. The pear is north of it.")
    assert mask.sum() == n and mask[:n].all()


def test_training_index_maps_episodes_to_their_rendered_sentences():
    index = sentences.training_index()
    templates = sentences.training_templates()
    assert templates == {True: tuple(range(8)), False: tuple(range(8))}
    rng = np.random.default_rng(1)
    lookup = jax.jit(index.ids, static_argnums=0)
    for _ in range(300):
        kind = bool(rng.integers(2))
        template = int(rng.choice(templates[kind]))
        ref, target = rng.choice(np.arange(1, 16), 2, replace=False)
        ref, direction = (int(ref), int(rng.integers(8))) if kind else (0, -1)
        setting = "p_mo2g" if kind else "mo1g"
        rows = np.asarray(lookup(kind, template, ref, int(target), direction))
        text = grammar.render(setting, template, ref, int(target), direction)
        assert [index.sentences[r] for r in rows if r >= 0] == split_sentences(text)
    # A held-out or natural-language template maps to no training sentence.
    for template in (8, 11, grammar.NUM_TEMPLATES, grammar.NUM_TEMPLATES + 5):
        assert np.all(np.asarray(index.ids(True, template, 1, 2, 3)) == -1)


def test_the_longest_instruction_of_every_phrasing_set_fits_in_L(text_encoder):
    """L (FEATURE_TOKENS) was chosen on this count: the longest instruction (wordpieces, each
    sentence's [CLS] and [SEP]) of the training, held-out and natural phrasings in every
    filling. Of the sealed natural set only the length of each rendered sentence is read."""
    count = InstructionEncoder(text_encoder, FEATURE_TOKENS)
    longest = 0
    for kind in sentences.KINDS:
        setting = "p_mo2g" if kind else "mo1g"
        for template in range(len(grammar.all_phrasings(kind))):
            texts = [grammar.render(setting, template, *f) for f in sentences.fillings(kind)]
            longest = max(longest, max(count.length(t) for t in texts))
    assert longest == 32 <= FEATURE_TOKENS


def features_denoiser(**overrides):
    """A tiny denoiser on pretrained features, its parameters perturbed (at initialisation the
    attention's output projections are zero: the text would change nothing)."""
    from diffplan.denoiser import Denoiser, DenoiserConfig, init_params
    from experiments.harness.recipes import MODEL_SIZES

    cfg = DenoiserConfig(vocab_size=len(grammar.CELL_TOKENS), max_tokens=FEATURE_TOKENS,
                         num_cond_channels=5, num_gen_channels=3, context_dim=384,
                         **{**MODEL_SIZES["tiny"], **overrides})
    model = Denoiser(cfg)
    variables = init_params(model, jax.random.PRNGKey(0))
    leaves, tree = jax.tree.flatten(variables)
    keys = jax.random.split(jax.random.PRNGKey(5), len(leaves))
    return model, jax.tree.unflatten(tree, [x + 0.1 * jax.random.normal(k, x.shape)
                                            for x, k in zip(leaves, keys)])


def test_padding_rows_do_not_change_the_features_denoisers_output():
    model, variables = features_denoiser()
    key = jax.random.PRNGKey(1)
    x = jax.random.normal(key, (2, 16, 16, 8))
    feats = jax.random.normal(jax.random.fold_in(key, 1), (2, FEATURE_TOKENS, 384))
    feats = feats.at[0, 20:].set(0.0).at[1, 9:].set(0.0)
    t = jnp.array([3, 70])
    out = model.apply(variables, x, t, feats)
    shorter = model.apply(variables, x, t, feats[:, :24])  # fewer padding rows
    np.testing.assert_allclose(np.asarray(out), np.asarray(shorter), atol=1e-5)
    changed = model.apply(variables, x, t, feats.at[1, 5].add(1.0))  # a real token matters
    assert np.abs(np.asarray(changed - out))[1].max() > 1e-4
    np.testing.assert_array_equal(np.asarray(changed[0]), np.asarray(out[0]))
    # The grid cells keep their own embedding: one row per cell token, none for words.
    assert variables["params"]["token_embed"]["embedding"].shape[0] == len(grammar.CELL_TOKENS)


def test_name_features_are_the_mean_of_the_names_wordpieces(encoder):
    """A cell's name features: the encoder's output on the name alone, averaged over its
    wordpieces without [CLS] / [SEP] (plain numpy on the sentence features); "" is zeros."""
    names = cell_names(grammar.CELL_TOKENS)
    assert names[:4] == ("", "unseen", "empty", "obstacle")
    assert names[4:] == tuple(grammar.CELL_TOKENS[4:])
    table = sentences.cell_features(encoder)
    assert table.shape == (len(grammar.CELL_TOKENS), encoder.dim) and table.dtype == np.float32
    np.testing.assert_array_equal(table[0], 0.0)
    for i in (1, 4, 11):  # "unseen", "apple", "broccoli": one and several wordpieces
        rows = np.asarray(encoder.sentence_features([names[i]])[0], np.float32)
        assert len(rows) == len(encoder.pieces([names[i]])[0]) >= 3
        np.testing.assert_allclose(table[i], rows[1:-1].mean(axis=0), rtol=0, atol=1e-6)
    # Distinct names, distinct rows.
    assert len({row.tobytes() for row in table}) == len(names)


def test_cells_named_by_features_share_the_instructions_projection():
    """cell_context: a cell's embedding is the shared projection of its name's features (plus
    a learned part, zero at init); the text encoder has no projection of its own; the names'
    features get no gradient and no weight decay, and init_train_state writes them."""
    from diffplan.denoiser import Denoiser, DenoiserConfig
    from diffplan.train_state import TrainConfig, _decay_mask, init_train_state
    from types import SimpleNamespace

    model, variables = features_denoiser(cell_context=True)
    params = variables["params"]
    assert "context_proj" not in params["text_encoder"] and "context_embed" in params
    assert params["frozen_cell_features"].shape == (len(grammar.CELL_TOKENS), 384)
    ids = jnp.arange(len(grammar.CELL_TOKENS), dtype=jnp.float32).reshape(1, 1, -1, 1)
    fresh = Denoiser(model.config).init(jax.random.PRNGKey(0), jnp.zeros((1, 8, 8, 8)),
                                        jnp.zeros((1,), jnp.int32),
                                        jnp.ones((1, 4, 384)))["params"]
    np.testing.assert_array_equal(np.asarray(fresh["token_embed"]["embedding"]), 0.0)
    cells = model.apply(variables, jnp.pad(ids, ((0, 0), (0, 0), (0, 0), (0, 7))),
                        method=Denoiser.encode_grid)[0, 0, :, :model.config.embed_dim]
    proj = model.apply(variables, params["frozen_cell_features"],
                       method=lambda m, f: m.context_embed(f))
    np.testing.assert_allclose(np.asarray(cells), np.asarray(
        proj + params["token_embed"]["embedding"]), atol=1e-5)

    x = jax.random.normal(jax.random.PRNGKey(1), (2, 16, 16, 8))
    x = x.at[..., 0].set(jax.random.randint(jax.random.PRNGKey(2), (2, 16, 16), 0, 19))
    feats = jax.random.normal(jax.random.PRNGKey(3), (2, FEATURE_TOKENS, 384))
    grads = jax.grad(lambda p: jnp.sum(model.apply({"params": p}, x, jnp.array([3, 9]),
                                                   feats) ** 2))(params)
    np.testing.assert_array_equal(np.asarray(grads["frozen_cell_features"]), 0.0)
    assert float(jnp.abs(grads["context_embed"]["proj"]["kernel"]).max()) > 0
    mask = _decay_mask(params)
    assert mask["frozen_cell_features"] is False and mask["context_embed"]["proj"]["kernel"]

    table = np.random.default_rng(0).normal(size=(len(grammar.CELL_TOKENS), 384))
    init = SimpleNamespace(x0=jax.ShapeDtypeStruct((1, 16, 16, 8), jnp.float32),
                           tokens=jax.ShapeDtypeStruct((1, FEATURE_TOKENS, 384), jnp.float32))
    state = init_train_state(model, TrainConfig(steps=10, warmup_steps=1, batch_size=2, num_gen_channels=3),
                             init, fixed={"frozen_cell_features": table})
    np.testing.assert_allclose(np.asarray(state.params["frozen_cell_features"]), table,
                               rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(state.ema_params["frozen_cell_features"]),
                                  np.asarray(state.params["frozen_cell_features"]))
    with pytest.raises(ValueError, match="only constants"):
        init_train_state(model, TrainConfig(steps=10, warmup_steps=1, batch_size=2, num_gen_channels=3), init,
                         fixed={"unet": table})
    with pytest.raises(ValueError, match="must have shape"):
        init_train_state(model, TrainConfig(steps=10, warmup_steps=1, batch_size=2, num_gen_channels=3), init,
                         fixed={"frozen_cell_features": table[:3]})
    with pytest.raises(ValueError, match="cell_context"):
        DenoiserConfig(vocab_size=19, context_dim=0, cell_context=True)


def test_standardized_features_equal_standardizing_by_hand(small):
    """standardize: a denoiser reads (f - mean) / scale at real tokens and zeros at padding,
    i.e. exactly what the same network without it reads of hand-standardised features; its
    constants are the training table's per-dimension statistics (plain numpy)."""
    import dataclasses

    from diffplan.denoiser import Denoiser
    from diffplan.instruction import feature_statistics, fixed_text_params

    _, table = small
    mean, scale = feature_statistics(table)
    rows = np.asarray(table.features, np.float32)
    np.testing.assert_allclose(mean, rows.mean(axis=0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(scale, np.maximum(rows.std(axis=0), 1e-3), rtol=1e-5)

    model, variables = features_denoiser(standardize=True, cell_context=True)
    params = {**variables["params"], "frozen_feature_mean": jnp.asarray(mean),
              "frozen_feature_scale": jnp.asarray(scale)}
    plain = Denoiser(dataclasses.replace(model.config, standardize=False))
    plain_params = {k: v for k, v in params.items() if not k.startswith("frozen_feature")}
    x = jax.random.normal(jax.random.PRNGKey(1), (2, 16, 16, 8))
    x = x.at[..., 0].set(jax.random.randint(jax.random.PRNGKey(2), (2, 16, 16), 0, 19))
    feats = jax.random.normal(jax.random.PRNGKey(3), (2, FEATURE_TOKENS, 384))
    feats = feats.at[0, 20:].set(0.0).at[1, 9:].set(0.0)
    t = jnp.array([3, 70])
    by_hand = np.where(np.any(np.asarray(feats) != 0, -1, keepdims=True),
                       (np.asarray(feats) - mean) / scale, 0.0).astype(np.float32)
    plain_params["frozen_cell_features"] = (params["frozen_cell_features"] - mean) / scale
    np.testing.assert_allclose(
        np.asarray(model.apply({"params": params}, x, t, feats)),
        np.asarray(plain.apply({"params": plain_params}, x, t, jnp.asarray(by_hand))),
        atol=2e-4)
    names = fixed_text_params(dataclasses.replace(model.config, cell_context=False),
                              grammar.CELL_TOKENS, lambda: pytest.fail("encoder not needed"),
                              lambda: table)
    assert set(names) == {"frozen_feature_mean", "frozen_feature_scale"}
    assert fixed_text_params(dataclasses.replace(model.config, standardize=False,
                                                 cell_context=False), (), None, None) is None


def test_cell_lookup_equals_a_numpy_oracle_and_finds_the_named_token():
    """cell_lookup: each cell token's name looks up the instruction's tokens by the cosine of
    their standardised frozen features, softmax(scale * (cos - threshold)) beside a "not
    named" slot of logit 0, and reads lookup_value of the text encoder's output there (plain
    numpy below); a cell's embedding gains its name's row. A token carrying a name's own
    features takes most of that name's weight at initialisation; padding, an unnamed cell
    token (row 0) and the planner's precomputed context change nothing."""
    from diffplan.denoiser import Denoiser, DenoiserConfig

    model, variables = features_denoiser(cell_context=True, standardize=True, cell_lookup=True)
    rng = np.random.default_rng(0)
    names = rng.normal(size=(len(grammar.CELL_TOKENS), 384)).astype(np.float32)
    names[0] = 0.0
    mean = rng.normal(size=384).astype(np.float32) * 0.1
    scale = rng.uniform(0.5, 2.0, size=384).astype(np.float32)
    params = {**variables["params"], "frozen_cell_features": jnp.asarray(names),
              "frozen_feature_mean": jnp.asarray(mean),
              "frozen_feature_scale": jnp.asarray(scale),
              "lookup_scale": jnp.asarray(20.0), "lookup_threshold": jnp.asarray(0.7)}
    feats = rng.normal(size=(2, FEATURE_TOKENS, 384)).astype(np.float32)
    feats[0, 3] = names[6] + 0.05 * rng.normal(size=384)  # "banana", almost as it is alone
    feats[0, 12:] = 0.0
    feats[1, 9:] = 0.0
    ctx = model.apply({"params": params}, jnp.asarray(feats), method=Denoiser.encode_text)
    assert ctx.cells.shape == (2, len(grammar.CELL_TOKENS), model.config.embed_dim)

    def unit(f):
        f = np.where(np.any(f != 0, -1, keepdims=True), (f - mean) / scale, 0.0)
        return f / np.maximum(np.linalg.norm(f, axis=-1, keepdims=True), 1e-6)

    real = np.any(feats != 0, -1)
    logits = 20.0 * (np.einsum("vd,bld->bvl", unit(names), unit(feats)) - 0.7)
    logits = np.where(real[:, None], logits, -np.inf)
    full = np.concatenate([logits, np.zeros(logits.shape[:-1] + (1,))], -1)
    weights = np.exp(full - full.max(-1, keepdims=True))
    weights = (weights / weights.sum(-1, keepdims=True))[..., :-1]
    weights[:, 0] = 0.0
    dense = params["lookup_value"]
    values = np.asarray(ctx.features) @ np.asarray(dense["kernel"]) + np.asarray(dense["bias"])
    np.testing.assert_allclose(np.asarray(ctx.cells), np.einsum("bvl,ble->bve", weights, values),
                               atol=2e-4)
    assert weights[0, 6, 3] > 0.9 and weights[0, 6].sum() < 0.999  # found; the rest is small
    np.testing.assert_array_equal(np.asarray(ctx.cells[:, 0]), 0.0)

    x = jax.random.normal(jax.random.PRNGKey(1), (2, 16, 16, 8))
    x = x.at[..., 0].set(jax.random.randint(jax.random.PRNGKey(2), (2, 16, 16), 0, 19))
    base = model.apply({"params": params}, x, method=Denoiser.encode_grid)
    looked = model.apply({"params": params}, x, ctx.cells, method=Denoiser.encode_grid)
    idx = np.asarray(x[..., 0]).astype(int)
    e = model.config.embed_dim
    np.testing.assert_allclose(np.asarray(looked - base)[..., :e],
                               np.asarray(ctx.cells)[np.arange(2)[:, None, None], idx],
                               atol=1e-5)
    t = jnp.array([3, 70])
    np.testing.assert_allclose(np.asarray(model.apply({"params": params}, x, t, ctx)),
                               np.asarray(model.apply({"params": params}, x, t,
                                                      jnp.asarray(feats))), atol=1e-5)
    with pytest.raises(ValueError, match="cells included"):
        model.apply({"params": params}, x, t, ctx._replace(cells=None))
    with pytest.raises(ValueError, match="cell_lookup"):
        DenoiserConfig(vocab_size=19, context_dim=384, cell_lookup=True)


def test_planner_takes_features_once_and_refuses_the_wrong_input():
    """Planner.init keeps the text context the UNet cross-attends to (computed once per
    episode); a denoiser call on it equals one on the features themselves."""
    from diffplan.denoiser import LoadedDenoiser, ModuleApply, TextContext
    from diffplan.planner import Planner, PlannerConfig
    from diffplan.schedule import cosine_schedule

    model, variables = features_denoiser()
    den = LoadedDenoiser(params=variables["params"], schedule=cosine_schedule(100),
                         apply_fn=ModuleApply(model), plan_shape=(16, 16, 3),
                         model_config=model.config)
    planner = Planner(den, PlannerConfig(mode="one_shot", num_steps=2))
    key = jax.random.PRNGKey(3)
    feats = jax.random.normal(key, (2, FEATURE_TOKENS, 384)).at[:, 17:].set(0.0)
    state = jax.vmap(planner.init)(jax.random.split(jax.random.PRNGKey(0), 2), feats)
    assert isinstance(state.tokens, TextContext)
    assert state.tokens.features.shape == (2, FEATURE_TOKENS, model.config.text_dim)
    np.testing.assert_array_equal(np.asarray(state.tokens.mask), np.asarray(
        jnp.any(feats != 0, -1)))
    x = jax.random.normal(jax.random.fold_in(key, 1), (2, 16, 16, 8))
    t = jnp.array([5, 50])
    direct = den.eps_fn(feats)(x, t)
    prepared = den.eps_fn(state.tokens)(x, t)
    np.testing.assert_allclose(np.asarray(prepared), np.asarray(direct), atol=1e-4)
    plan, _ = jax.vmap(planner.plan)(state, jnp.zeros((2, 16, 16, 5)))
    assert plan.shape == (2, 16, 16, 3) and np.all(np.isfinite(np.asarray(plan)))
    batch_plans, _ = planner.plan_batch(state, jnp.zeros((2, 16, 16, 5)))
    np.testing.assert_allclose(np.asarray(batch_plans), np.asarray(plan), atol=1e-4)
    with pytest.raises(ValueError) as e:
        planner.init(jax.random.PRNGKey(0), jnp.ones(24, jnp.int32))
    assert "reads pretrained features" in one_line(e)
    tokens_den = den.replace(model_config=model.config.__class__(context_dim=0))
    with pytest.raises(ValueError) as e:
        Planner(tokens_den, PlannerConfig(mode="one_shot", num_steps=2)).init(
            jax.random.PRNGKey(0), feats)
    assert "int32 (L,)" in one_line(e)


def test_one_line_refusals(encoder):
    from diffplan.denoiser import DenoiserConfig
    from envs.gridworld.training import Recipe

    for kwargs, words in (({"token_classes": 3}, "token_classes"),
                          ({"sentence_end_id": 5}, "sentence_end_id")):
        with pytest.raises(ValueError) as e:
            DenoiserConfig(context_dim=384, **kwargs)
        assert words in one_line(e)
    for kwargs, words in (({"word_dropout": 0.1}, "word dropout"),
                          ({"role_loss_weight": 0.1}, "role loss"),
                          ({"text": "bert"}, "text must be")):
        with pytest.raises(ValueError) as e:
            Recipe(**{"text": "pretrained", **kwargs})
        assert words in one_line(e)
    for text, words in (("", "empty"), ("  \n ", "empty"),
                        ("apple " * 50, f"over the limit of {FEATURE_TOKENS}")):
        with pytest.raises(ValueError) as e:
            encoder.encode(text)
        assert words in one_line(e)
    with pytest.raises(ValueError) as e:
        encoder.encode(["Go to the apple.", 3])
    assert "str" in one_line(e)


def test_the_natural_set_never_reaches_a_training_table():
    """Training draws only training phrasings: the recipe refuses the natural (and held-out)
    languages, the training index holds training templates only, and a table of any other
    template is refused (planted: natural and held-out template indices are caught)."""
    from envs.gridworld.training import Recipe, make_mixture_batch_fn

    for language in ("natural", "unseen"):
        with pytest.raises(ValueError) as e:
            Recipe(language=language, text="pretrained")
        assert "never draws" in one_line(e)
        with pytest.raises(ValueError):
            make_mixture_batch_fn(language=language, text="pretrained")
    index = sentences.training_index()
    assert index.templates == sentences.training_templates()
    natural_templates = set(grammar.template_pool("p_mo2g", "natural").tolist())
    assert natural_templates == set(range(12, 12 + len(natural.sentences(True))))
    for kind, used in index.templates.items():
        assert not set(used) & (natural_templates | set(grammar.UNSEEN_TEMPLATES))
    sentences.check_training_templates(sentences.training_templates())  # the real one passes
    for planted in ({True: (0, 1, grammar.NUM_TEMPLATES)}, {False: (0, 9)}):
        with pytest.raises(ValueError) as e:
            sentences.check_training_templates(planted)
        assert "not training phrasings" in one_line(e)
    # A recipe's batches index this table only, with the rows of training phrasings.
    fn = make_mixture_batch_fn(language="mixed", text="pretrained")
    ids = np.asarray(jax.jit(fn, static_argnums=1)(jax.random.PRNGKey(0), 64).tokens)
    assert ids.shape[0] == 64 and ids.min() >= -1 and ids.max() < len(index.sentences)
    assert np.all(ids[:, 0] >= 0)


@pytest.fixture(scope="module")
def words(text_encoder):
    vocab = text_encoder.subwords.tokenizer.get_vocab()
    return sorted(w for w in vocab if not w.startswith(("##", "[")) and w.isprintable()
                  and w.strip() == w and w)


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_random_word_strings_within_the_limit_are_never_refused(encoder, words, data):
    """Any string of the vocabulary's words (30,000 of them, punctuation included) up to L
    wordpieces is encoded, with exactly its wordpieces marked real."""
    picked = data.draw(st.lists(st.sampled_from(words), min_size=1, max_size=40))
    while len(picked) > 1 and encoder.length(" ".join(picked)) > FEATURE_TOKENS:
        picked = picked[:-1]
    text = " ".join(picked)
    if encoder.length(text) > FEATURE_TOKENS:  # one word over the limit on its own
        return
    feats = encoder.encode(text)
    assert feats.shape == (FEATURE_TOKENS, 384)
    assert np.any(feats != 0, -1).sum() == encoder.length(text)
