"""The reader (diffplan.reader, envs.kuka.reader): taggers of which block of a relation sentence
is the upper one, and instructions restated canonically from what they read."""
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from diffplan import language
from diffplan.reader import (ReaderConfig, load_reader, role_probabilities, save_reader,
                             train_reader)
from envs.kuka import grammar, reader
from experiments.kuka import reader as train_reader_cli
from experiments.harness.core import REPO_ROOT

PHRASINGS = ("canonical", "paraphrased", "development", language.BROAD)


@functools.lru_cache(maxsize=None)
def _restate_fn():
    return jax.jit(jax.vmap(reader.canonical_tokens))


@functools.lru_cache(maxsize=None)
def _draw(phrasing):
    return jax.jit(lambda k: reader._instructions(k, 16, phrasing))


def _constraints_of(tokens):
    """Plain Python: (tower sentence, [(top, bottom)]) read off the instruction's phrasings
    (grammar.sentence_templates; inverted phrasings name the lower block first)."""
    sentences = grammar.split_sentences(tokens)
    kinds = grammar.sentence_templates(np.asarray(tokens))
    tower, pairs = False, []
    for words, kind in zip(sentences, kinds):
        assert kind is not None
        if kind[0] == "tower":
            tower = True
            continue
        blocks = [w - 1 for w in words if 1 <= w <= 4]
        pairs.append(tuple(blocks[::-1]) if kind[1] in grammar.INVERTED else tuple(blocks))
    return tower, pairs


@settings(max_examples=8, deadline=None)
@given(st.sampled_from(PHRASINGS), st.integers(0, 2 ** 30))
def test_true_roles_restate_every_phrasing_canonically(phrasing, seed):
    """With the true roles (as probabilities), every instruction of every phrasing becomes the
    canonical instruction of the same relations, in the same order, with its tower sentence."""
    tokens, roles, named = _draw(phrasing)(jax.random.PRNGKey(seed))
    p_top = jnp.where(named, 1.0 - roles, 0.5)
    out = np.asarray(_restate_fn()(tokens, p_top))
    for before, after in zip(np.asarray(tokens), out):
        assert all(k is not None and k[1] == 0 for k in grammar.sentence_templates(after))
        assert _constraints_of(after) == _constraints_of(before)


def test_inverted_roles_swap_every_relation():
    tokens, roles, named = _draw("paraphrased")(jax.random.PRNGKey(3))
    out = np.asarray(_restate_fn()(tokens, jnp.where(named, roles, 0.5).astype(jnp.float32)))
    for before, after in zip(np.asarray(tokens), out):
        tower, pairs = _constraints_of(before)
        assert _constraints_of(after) == (tower, [(b, t) for t, b in pairs])


def test_training_batches_hold_no_held_out_phrasing_and_true_labels():
    tokens, roles, named = jax.jit(reader.role_batch)(jax.random.PRNGKey(0))
    assert tokens.shape == (reader.BATCH, grammar.MAX_TOKENS)
    held_out = set(grammar.RELATION_SPLIT.unseen)
    held_out_towers = set(grammar.TOWER_SPLIT.unseen)
    seen = set()
    for row, r, n in zip(np.asarray(tokens), np.asarray(roles), np.asarray(named)):
        for kind, k in grammar.sentence_templates(row):
            assert k not in (held_out if kind == "relation" else held_out_towers)
            seen.add((kind, k))
        tower, pairs = _constraints_of(row)
        blocks = [(int(t), int(rr)) for t, rr, nn in zip(row, r, n) if nn]
        want = [(top + 1, 0) if i % 2 == 0 else (bottom + 1, 1) for top, bottom in pairs
                for i in range(2)]
        assert sorted(blocks) == sorted(want)
    assert ("relation", 0) in seen and any(("relation", k) in seen for k in grammar.EXTRA)


def test_reader_config_refuses_bad_values():
    with pytest.raises(ValueError, match="num_roles"):
        ReaderConfig(vocab_size=5, max_tokens=4, num_roles=1)
    with pytest.raises(ValueError, match="max_tokens"):
        ReaderConfig(vocab_size=5, max_tokens=0, num_roles=2)
    with pytest.raises(ValueError, match="unknown ReaderConfig fields"):
        ReaderConfig.from_dict({"vocab_size": 5, "max_tokens": 4, "num_roles": 2, "x": 1})
    with pytest.raises(ValueError, match="sentence_end_id"):
        ReaderConfig(vocab_size=5, max_tokens=4, num_roles=2, sentence_local=1)
    with pytest.raises(ValueError, match="0 or 1"):
        ReaderConfig(vocab_size=5, max_tokens=4, num_roles=2, sentence_end_id=3,
                     sentence_local=2)
    # a reader saved before sentence_local existed loads as one that reads across sentences
    old = ReaderConfig.from_dict({"vocab_size": 5, "max_tokens": 4, "num_roles": 2})
    assert old.sentence_local == 0


@pytest.fixture(scope="module")
def tiny_reader():
    config = reader.reader_config(dim=16, num_layers=1, num_heads=2)
    return config, train_reader(config, reader.role_batch, [0, 1], 2)


def test_ensemble_probabilities_are_the_taggers_mean(tiny_reader):
    config, params = tiny_reader
    tokens = jnp.asarray(reader._instructions(jax.random.PRNGKey(1), 3, "development")[0])
    probs = role_probabilities(config, params, tokens)
    assert probs.shape == (3, grammar.MAX_TOKENS, 2)
    np.testing.assert_allclose(probs.sum(-1), 1.0, rtol=1e-5)
    each = [role_probabilities(config, jax.tree.map(lambda x, i=i: x[i:i + 1], params), tokens)
            for i in range(2)]
    np.testing.assert_allclose(probs, (each[0] + each[1]) / 2, rtol=1e-5, atol=1e-6)
    out = reader.restate(config, params, tokens[None])
    assert out.shape == (1, 3, grammar.MAX_TOKENS)


def test_saved_reader_loads_and_refuses_other_checkpoints(tiny_reader, tmp_path):
    config, params = tiny_reader
    save_reader(str(tmp_path / "r"), config, params, {"command": "test"})
    loaded, back, meta = load_reader(str(tmp_path / "r"))
    assert loaded == config and meta["ensemble"] == 2 and meta["command"] == "test"
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(back)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="does not hold a reader"):
        load_reader(os.path.join(REPO_ROOT, "checkpoints", "kuka"))


def test_train_reader_cli_end_to_end(tmp_path, capsys):
    out = tmp_path / "reader"
    result = train_reader_cli.main(["--out", str(out), "--seeds", "0", "--steps", "2",
                                    "--json", str(tmp_path / "r.json"), "--no-progress"])
    assert set(result["read"]) == {"canonical", "paraphrased", "development"}
    assert all(0.0 <= v <= 100.0 for v in result["read"].values())
    printed = capsys.readouterr().out
    assert "restated canonically" in printed and "development" in printed
    assert load_reader(str(out))[2]["read_validation"] == result["read"]
    with pytest.raises(SystemExit) as info:
        train_reader_cli.main(["--out", str(out), "--steps", "2", "--no-progress"])
    assert info.value.code == 2
    assert "not empty" in capsys.readouterr().err


def test_shipped_reader_loads_and_reads_development_phrasings():
    """checkpoints/kuka_reader (NOTE.md: 100.0 / 100.0 / 100.0 on these 1000 instructions)."""
    shipped = os.path.join(REPO_ROOT, "checkpoints", "kuka_reader")
    with open(os.path.join(shipped, "NOTE.md")) as f:
        assert "python -m experiments.train_reader" in f.read()
    config, params, meta = load_reader(shipped)
    assert config == reader.reader_config() and meta["ensemble"] == 5
    key = jax.random.PRNGKey(1000)
    rates = {p: reader.read_rate(config, params, key, 1000, p)
             for p in ("canonical", "paraphrased", "development")}
    assert rates["canonical"] == 100.0 and rates["paraphrased"] >= 99.0
    assert rates["development"] >= 99.0
    # the README's example, a development phrasing typed as text
    out = reader.read_text(config, params, "The red block should be below the green block.")
    assert grammar.decode(out) == "Stack the green block on top of the red block."


def test_read_text_restates_a_users_sentence_and_refuses_what_it_cannot_read(tiny_reader):
    config, params = tiny_reader
    text = "Build a tower of all four blocks. The red block goes under the green block."
    out = reader.read_text(config, params, text)
    assert out.shape == (grammar.MAX_TOKENS,) and out.dtype == jnp.int32
    assert grammar.decode(out).startswith("Build a tower of all four blocks.")
    reader.check_readable(grammar.encode(text))
    for bad, match in (("Put the red block on top of the block.", "names 1"),
                       ("Put the red block on the red block.", "same block twice"),
                       ("Put the red block on the blue block. Build a tower of all four blocks.",
                        "names 0"),
                       ("Build a tower of all four blocks.", "names 0"),
                       ("Put the red block on the banana.", "outside the vocabulary")):
        with pytest.raises(ValueError, match=match):
            reader.read_text(config, params, bad)
    four = " ".join(["Put the red block on the blue block."] * 4)
    with pytest.raises(ValueError, match="more than 3"):
        reader.check_readable(grammar.encode(four))
