"""The frozen pretrained text encoder (diffplan.pretrained_text, diffplan.bert,
diffplan.subwords): its features equal the reference implementation's (transformers'
BertModel in PyTorch, tests/data/text_encoder_golden.npz, written by
tests/data/make_text_encoder_golden.py), its tokenizer is the tokenizers library's own, and the
loader reads nothing it cannot check. Two programs of the full encoder are compiled here: the
golden batch, and one vmapped through ``apply``."""
from __future__ import annotations

import json
import pathlib
import shutil
import string

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import safetensors.numpy
import tokenizers
from hypothesis import given, settings
from hypothesis import strategies as st

from diffplan import bert, pretrained_text, subwords
from diffplan.pretrained_text import load_text_encoder

GOLDEN = pathlib.Path(__file__).resolve().parent / "data" / "text_encoder_golden.npz"
SHIPPED = pretrained_text.SHIPPED


@pytest.fixture(scope="module")
def encoder():
    return load_text_encoder()


@pytest.fixture(scope="module")
def golden():
    with np.load(GOLDEN) as data:
        return {k: data[k] for k in data.files}


@pytest.fixture(scope="module")
def golden_features(encoder, golden):
    ids, mask = encoder.tokenize(list(golden["sentences"]))
    return ids, mask, np.asarray(encoder.features(ids, mask))


def one_line_error(excinfo) -> str:
    message = str(excinfo.value)
    assert "\n" not in message, message
    return message


def test_golden_features_equal_the_reference_implementation(golden, golden_features):
    ids, mask, feats = golden_features
    assert len(golden["sentences"]) >= 20
    np.testing.assert_array_equal(ids, golden["ids"])  # transformers' tokenizer's ids
    np.testing.assert_array_equal(mask, golden["mask"])
    assert feats.shape == golden["features"].shape == (len(ids), subwords.DEFAULT_LENGTH, 384)
    assert feats.dtype == np.float32
    assert np.max(np.abs(feats - golden["features"])) <= 1e-4
    assert np.all(feats[~mask] == 0)
    metadata = json.loads(str(golden["metadata"]))
    assert metadata["artifact_sha256"] == {k: v for k, v in load_manifest().items()
                                           if k in pretrained_text.FILES}


def load_manifest() -> dict:
    return json.loads((SHIPPED / pretrained_text.MANIFEST).read_text())["files"]


def test_tokenization_is_the_tokenizers_librarys(encoder):
    reference = tokenizers.Tokenizer.from_file(str(SHIPPED / "tokenizer.json"))
    reference.no_padding()
    sentences = ["Go to the apple first, then find the pear north-east of it.",
                 "Could you place green over yellow?", "unfathomably zxqv", "Ünïcödé café!"]
    ids, mask = encoder.tokenize(sentences, length=24)
    assert ids.dtype == np.int32 and mask.dtype == bool and ids.shape == (4, 24)
    for row, row_mask, sentence in zip(ids, mask, sentences):
        want = reference.encode(sentence).ids
        assert row[:len(want)].tolist() == want and row_mask.sum() == len(want)
        assert np.all(row[len(want):] == encoder.subwords.pad_id)
    single_ids, single_mask = encoder.tokenize(sentences[0], length=24)
    np.testing.assert_array_equal(single_ids, ids[0])
    np.testing.assert_array_equal(single_mask, mask[0])


def test_padding_changes_no_real_token_under_jit_and_vmap(encoder, golden_features):
    """Fewer padding columns (48 instead of 64), other ids in the padding, and apply vmapped
    over a leading axis: the real tokens' features stay those of the golden batch."""
    ids, mask, feats = golden_features
    garbage = np.where(mask, ids, (np.arange(ids.size).reshape(ids.shape) * 7919) % 30522)
    short = 48
    apply = jax.jit(jax.vmap(encoder.apply, in_axes=(None, 0, 0)))
    out = np.asarray(apply(encoder.params, garbage[:, :short].reshape(2, -1, short),
                           mask[:, :short].reshape(2, -1, short))).reshape(-1, short, 384)
    assert not mask[:, short:].any()
    np.testing.assert_allclose(out, feats[:, :short], atol=1e-5)
    assert np.all(out[~mask[:, :short]] == 0)


def test_shipped_artifact_loads_from_any_directory(monkeypatch, tmp_path, encoder):
    monkeypatch.chdir(tmp_path)
    again = load_text_encoder()
    assert again.sha256 == {k: v for k, v in load_manifest().items()
                            if k in pretrained_text.FILES}
    assert again.directory == encoder.directory == str(SHIPPED)
    assert again.config == encoder.config
    assert (again.config.num_hidden_layers, again.config.hidden_size) == (6, 384)
    leaves = jax.tree_util.tree_leaves(again.params)
    assert all(leaf.dtype == jnp.float32 for leaf in leaves)


def test_missing_shipped_artifact_names_where_it_looked(monkeypatch, tmp_path):
    monkeypatch.setattr(pretrained_text, "SHIPPED", tmp_path / "nowhere")
    with pytest.raises(ValueError) as e:
        load_text_encoder()
    assert str(tmp_path / "nowhere") in one_line_error(e)


def hf_directory(tmp_path: pathlib.Path, with_manifest: bool = False) -> pathlib.Path:
    """A Hugging Face-format copy of the shipped files (the weights linked, not copied)."""
    out = tmp_path / "hf"
    out.mkdir()
    for name in pretrained_text.FILES:
        if name == "model.safetensors":
            (out / name).symlink_to(SHIPPED / name)
        else:
            shutil.copy(SHIPPED / name, out / name)
    if with_manifest:
        shutil.copy(SHIPPED / pretrained_text.MANIFEST, out / pretrained_text.MANIFEST)
    return out


def test_a_hugging_face_directory_loads_with_its_hashes_recorded(tmp_path):
    directory = hf_directory(tmp_path)
    loaded = load_text_encoder(directory, expected_sha256=load_manifest())
    assert loaded.sha256 == {k: load_manifest()[k] for k in pretrained_text.FILES}


@pytest.mark.parametrize("pin", ["manifest", "expected_sha256"])
def test_a_bad_hash_is_refused(tmp_path, pin):
    directory = hf_directory(tmp_path, with_manifest=pin == "manifest")
    config = json.loads((directory / "config.json").read_text())
    config["num_hidden_layers"] = 5
    (directory / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError) as e:
        load_text_encoder(directory, expected_sha256=load_manifest() if pin != "manifest"
                          else None)
    assert "config.json has sha256" in one_line_error(e)


def test_a_missing_file_is_refused(tmp_path):
    directory = hf_directory(tmp_path)
    (directory / "tokenizer.json").unlink()
    with pytest.raises(ValueError) as e:
        load_text_encoder(directory)
    assert "lacks tokenizer.json" in one_line_error(e)


def test_pickle_weights_only_are_refused(tmp_path):
    directory = hf_directory(tmp_path)
    (directory / "model.safetensors").unlink()
    # what a pickle would run if it were unpickled: it must never be
    (directory / "pytorch_model.bin").write_bytes(b"cos\nsystem\n(S'touch pwned'\ntR.")
    with pytest.raises(ValueError) as e:
        load_text_encoder(directory)
    message = one_line_error(e)
    assert "lacks model.safetensors" in message and "never pickle" in message
    assert not (pathlib.Path.cwd() / "pwned").exists()


@pytest.mark.parametrize("change, words", [
    ({"model_type": "gpt2"}, "unsupported architecture"),
    ({"auto_map": {"AutoModel": "modeling.Evil"}, "trust_remote_code": True}, "custom code"),
    ({"position_embedding_type": "relative_key"}, "unsupported architecture"),
])
def test_an_unsupported_config_is_refused(tmp_path, change, words):
    directory = hf_directory(tmp_path)
    config = json.loads((directory / "config.json").read_text())
    (directory / "config.json").write_text(json.dumps({**config, **change}))
    with pytest.raises(ValueError) as e:
        load_text_encoder(directory)
    assert words in one_line_error(e)


TINY = {"model_type": "bert", "vocab_size": 30522, "hidden_size": 8, "num_hidden_layers": 2,
        "num_attention_heads": 2, "intermediate_size": 16, "max_position_embeddings": 32,
        "type_vocab_size": 2, "hidden_act": "gelu_new", "layer_norm_eps": 1e-12}


def tiny_tensors(config: bert.BertConfig, prefix: str) -> dict[str, np.ndarray]:
    """Random weights of a BertForMaskedLM-style checkpoint (``bert.`` names, torch
    (out, in) Linear weights, TensorFlow-era gamma/beta LayerNorms) of the given config."""
    rng = np.random.default_rng(0)
    d, i = config.hidden_size, config.intermediate_size
    shapes = {"embeddings.word_embeddings.weight": (config.vocab_size, d),
              "embeddings.position_embeddings.weight": (config.max_position_embeddings, d),
              "embeddings.token_type_embeddings.weight": (config.type_vocab_size, d),
              "embeddings.LayerNorm.gamma": (d,), "embeddings.LayerNorm.beta": (d,),
              "cls.predictions.bias": (config.vocab_size,)}
    for n in range(config.num_hidden_layers):
        for name, shape in {"attention.self.query": (d, d), "attention.self.key": (d, d),
                            "attention.self.value": (d, d), "attention.output.dense": (d, d),
                            "intermediate.dense": (i, d), "output.dense": (d, i)}.items():
            shapes[f"encoder.layer.{n}.{name}.weight"] = shape
            shapes[f"encoder.layer.{n}.{name}.bias"] = shape[:1]
        for name in ("attention.output.LayerNorm", "output.LayerNorm"):
            shapes[f"encoder.layer.{n}.{name}.weight"] = (d,)
            shapes[f"encoder.layer.{n}.{name}.bias"] = (d,)
    return {(prefix + k if not k.startswith("cls") else k):
            rng.normal(size=s).astype(np.float32) for k, s in shapes.items()}


def tiny_directory(tmp_path, drop: str | None = None) -> pathlib.Path:
    out = tmp_path / "tiny"
    out.mkdir()
    (out / "config.json").write_text(json.dumps(TINY))
    shutil.copy(SHIPPED / "tokenizer.json", out / "tokenizer.json")
    tensors = tiny_tensors(bert.BertConfig(**{k: v for k, v in TINY.items()
                                              if k != "model_type"}), "bert.")
    tensors.pop(drop, None)
    safetensors.numpy.save_file(tensors, str(out / "model.safetensors"))
    return out


def test_another_bert_loads_and_runs_batched_or_not(tmp_path):
    """A task model's checkpoint (``bert.`` prefix, gamma/beta, a head to ignore) of other
    sizes: the forward reads its shapes from config.json; one instruction, unbatched, gets
    the features of its row in a batch."""
    tiny = load_text_encoder(tiny_directory(tmp_path))
    ids, mask = tiny.tokenize(["Stack blue on red.", "go"], length=12)
    feats = np.asarray(tiny.features(ids, mask))
    assert feats.shape == (2, 12, 8) and np.all(np.isfinite(feats))
    one = np.asarray(jax.jit(tiny.apply)(tiny.params, *tiny.tokenize("go", length=12)))
    np.testing.assert_allclose(one, feats[1], atol=1e-5)
    with pytest.raises(ValueError) as e:
        tiny.tokenize(["word " * 31])
    assert "outside 2..32" in one_line_error(e)


def test_a_missing_tensor_is_refused(tmp_path):
    with pytest.raises(ValueError) as e:
        load_text_encoder(tiny_directory(tmp_path, drop="bert.encoder.layer.1.output.dense.bias"))
    assert "encoder.layer.1.output.dense.bias" in one_line_error(e)


@pytest.mark.parametrize("texts, words", [
    ([""], "instruction 0 is empty"),
    (["Go to the apple.", "   \t\n"], "instruction 1 is empty"),
    (["\u200b"], "instruction 0 is empty"),
    ([], "empty batch"),
    (["put the red block on the green block " * 8], "over the limit of 64"),
])
def test_only_empty_or_overlong_instructions_are_refused(encoder, texts, words):
    with pytest.raises(ValueError) as e:
        encoder.tokenize(texts)
    assert words in one_line_error(e)


def whole_words(encoder) -> list[str]:
    """Every vocabulary entry that is a word of letters (one token each)."""
    vocab = encoder.subwords.tokenizer.get_vocab()
    return sorted(w for w in vocab if w.isalpha() and w.isascii())


@pytest.fixture(scope="module")
def words(encoder):
    return whole_words(encoder)


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_any_words_up_to_the_limit_are_accepted(encoder, words, data):
    """Up to 61 words of the vocabulary (one token each), any case, a closing mark: at most
    64 tokens, never refused."""
    chosen = data.draw(st.lists(st.tuples(st.sampled_from(words), st.booleans()),
                                min_size=1, max_size=61))
    text = " ".join(w.upper() if upper else w.capitalize() for w, upper in chosen)
    text += data.draw(st.sampled_from(["", ".", "?", "!"]))
    ids, mask = encoder.tokenize([text])
    assert mask.sum() <= subwords.DEFAULT_LENGTH and ids.max() < encoder.config.vocab_size


@settings(max_examples=200, deadline=None)
@given(text=st.text(alphabet=st.characters(codec="utf-8"), max_size=80)
       | st.text(alphabet=string.printable, max_size=300))
def test_any_text_is_tokenized_or_refused_for_emptiness_or_length(encoder, text):
    try:
        ids, mask = encoder.tokenize(text)
    except ValueError as e:
        message = str(e)
        assert "\n" not in message
        assert "is empty" in message or "over the limit of 64" in message, message
        return
    assert ids.shape == mask.shape == (subwords.DEFAULT_LENGTH,)
    assert mask[0] and 0 <= ids.min() and ids.max() < encoder.config.vocab_size
