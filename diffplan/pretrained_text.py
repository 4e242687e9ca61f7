"""A frozen pretrained text encoder: the shipped all-MiniLM-L6-v2 (``checkpoints/text_encoder``)
or any Hugging Face-format directory of a BERT encoder, read without running anything in it.

    encoder = load_text_encoder()                       # the shipped one, from any directory
    ids, mask = encoder.tokenize(["Put the red block on the green one, please."])
    feats = encoder.features(ids, mask)                 # float32 (1, 64, 384)

What is read: ``config.json`` and ``tokenizer.json`` (JSON) and ``model.safetensors`` (raw
tensors); never a pickle (``pytorch_model.bin``), never code a config names (``auto_map``,
which custom-code models carry, is refused). Each file is read once, its sha256 recorded
(:attr:`PretrainedTextEncoder.sha256`) and checked against the directory's ``manifest.json``
where it has one, and against ``expected_sha256`` where the caller gives them.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import pathlib
from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np
import safetensors.numpy

from diffplan import bert, subwords

FILES = ("config.json", "model.safetensors", "tokenizer.json")
"""What a directory must hold."""
MANIFEST = "manifest.json"
"""Optional: ``{"files": {name: sha256 hex}}``; where present it must list every file read."""
PICKLES = ("pytorch_model.bin", "tf_model.h5", "flax_model.msgpack", "model.ckpt.index")
"""Weight files of other formats, named in the refusal of a directory with no safetensors."""
SHIPPED = pathlib.Path(__file__).resolve().parent.parent / "checkpoints" / "text_encoder"
"""The shipped artifact, found beside the package (``experiments.derive_text_encoder``)."""
MODEL_TYPES = ("bert",)


@dataclasses.dataclass(frozen=True, eq=False)
class PretrainedTextEncoder:
    """A loaded encoder: its architecture, its parameters (a pytree of float32 arrays, see
    :func:`diffplan.bert.param_shapes`), its tokenizer, where it came from and the sha256 of
    each file read."""
    config: bert.BertConfig
    params: dict
    subwords: subwords.Subwords
    directory: str
    sha256: Mapping[str, str]

    def tokenize(self, texts, length: int = subwords.DEFAULT_LENGTH):
        """Instructions -> (ids int32, mask bool), (B, length), or (length,) for one string
        (:meth:`diffplan.subwords.Subwords.tokenize`: only an empty or overlong one refused)."""
        return self.subwords.tokenize(texts, length)

    def apply(self, params: dict, ids, mask):
        """The pure forward: params (the pytree), ids int (..., L), mask (..., L) -> float32
        (..., L, D) token features, 0 at padding. Pass params as an argument under your own
        ``jit`` (closing over them would compile the weights in as constants)."""
        return bert.features(params, ids, mask, self.config)

    def features(self, ids, mask):
        """Token features of tokenized instructions with this encoder's params, jitted:
        ids int (..., L), mask (..., L) -> float32 (..., L, D), the last hidden state, 0 at
        padding. Called on concrete arrays it computes only the first columns that hold every
        real token (a multiple of :data:`COLUMNS`; an instruction of 15 tokens costs a quarter
        of one of 64) and pads the rest with zeros: padding changes no real token's features.
        Under ``jit`` or ``vmap`` it computes all L columns."""
        if isinstance(ids, jax.core.Tracer) or isinstance(mask, jax.core.Tracer):
            return _jitted_features(self.params, ids, mask, config=self.config)
        ids, mask = np.asarray(ids), np.asarray(mask).astype(bool)
        length = ids.shape[-1]
        used = min(length, -(-used_columns(mask) // COLUMNS) * COLUMNS)
        out = _jitted_features(self.params, ids[..., :used], mask[..., :used],
                               config=self.config)
        return jnp.pad(out, [(0, 0)] * (ids.ndim - 1) + [(0, length - used), (0, 0)])

    def encode(self, texts, length: int = subwords.DEFAULT_LENGTH):
        """(features float32 (B, length, D), mask bool (B, length)) of instructions; a single
        string gives (length, D) and (length,)."""
        ids, mask = self.tokenize(texts, length)
        return self.features(ids, mask), mask


_jitted_features = jax.jit(bert.features, static_argnames="config")
COLUMNS = 16
"""Granularity of the columns :meth:`PretrainedTextEncoder.features` computes (one compiled
program per multiple of it, at most L / 16 of them)."""


def used_columns(mask: np.ndarray) -> int:
    """1 + the last column any row of mask (..., L) marks real, at least 1."""
    columns = np.flatnonzero(mask.reshape(-1, mask.shape[-1]).any(axis=0))
    return int(columns[-1]) + 1 if columns.size else 1


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def resolve_directory(directory=None) -> pathlib.Path:
    """The directory to load: the given one, or the shipped artifact. ValueError (one line,
    naming where it looked) if it is not a directory."""
    path = SHIPPED if directory is None else pathlib.Path(directory)
    if not path.is_dir():
        what = "the shipped text encoder" if directory is None else "text encoder directory"
        raise ValueError(f"{what} not found: {path} is not a directory")
    return path


def read_files(path: pathlib.Path) -> dict[str, bytes]:
    """The bytes of each of :data:`FILES` in path; ValueError (one line) naming the missing
    ones (and the pickle-format weights that are never read in place of safetensors)."""
    missing = [name for name in FILES if not (path / name).is_file()]
    if missing:
        others = [name for name in PICKLES if (path / name).exists()]
        hint = (f" (it has {', '.join(others)}: only safetensors weights are read, never "
                f"pickle or other formats)" if others else "")
        raise ValueError(f"{path} lacks {', '.join(missing)}{hint}")
    return {name: (path / name).read_bytes() for name in FILES}


def check_hashes(hashes: Mapping[str, str], expected: Mapping[str, str], source: str) -> None:
    """ValueError (one line) unless every file of ``hashes`` has the sha256 ``expected`` lists
    (source names the list in the message)."""
    for name, digest in hashes.items():
        if name not in expected:
            raise ValueError(f"{source} lists no sha256 for {name}")
        if str(expected[name]).lower() != digest:
            raise ValueError(f"{name} has sha256 {digest}, {source} expects {expected[name]}")


def manifest_hashes(path: pathlib.Path) -> dict[str, str] | None:
    """The ``files`` mapping of path's manifest.json, None if it has none."""
    if not (path / MANIFEST).is_file():
        return None
    try:
        files = json.loads((path / MANIFEST).read_text())["files"]
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path / MANIFEST} is not a manifest with a 'files' mapping "
                         f"({type(e).__name__})") from None
    if not isinstance(files, dict):
        raise ValueError(f"{path / MANIFEST}: 'files' is not a mapping")
    return files


def parse_config(data: bytes) -> tuple[bert.BertConfig, dict]:
    """(BertConfig, the raw dict) of a config.json; ValueError (one line) for an architecture
    this forward does not compute, or a config that names code."""
    try:
        raw = json.loads(data)
    except ValueError as e:
        raise ValueError(f"config.json is not JSON: {e}") from None
    if not isinstance(raw, dict):
        raise ValueError("config.json is not a JSON object")
    if raw.get("model_type") not in MODEL_TYPES:
        raise ValueError(f"unsupported architecture: config.json has model_type "
                         f"{raw.get('model_type')!r}; supported: {', '.join(MODEL_TYPES)}")
    if "auto_map" in raw:
        raise ValueError("config.json names custom code (auto_map): only the built-in BERT "
                         "architecture is read, no code from a model directory")
    position = raw.get("position_embedding_type", "absolute")
    if position != "absolute":
        raise ValueError(f"unsupported architecture: position_embedding_type {position!r} "
                         f"(only 'absolute')")
    kinds = {"hidden_act": str, "layer_norm_eps": float}
    names = [f.name for f in dataclasses.fields(bert.BertConfig)]
    try:
        values = {k: kinds.get(k, int)(raw[k]) for k in names if k in raw}
    except (TypeError, ValueError) as e:
        raise ValueError(f"config.json has a BERT field of the wrong kind: {e}") from None
    try:
        return bert.BertConfig(**values), raw
    except TypeError as e:
        raise ValueError(f"config.json lacks a BERT field: {e}") from None


def tensor_name(key: str) -> str:
    """A checkpoint's tensor name in BertModel's own naming: without the ``bert.`` prefix of
    task models, TensorFlow-era ``gamma``/``beta`` as ``weight``/``bias``."""
    key = key.removeprefix("bert.")
    if key.endswith("LayerNorm.gamma"):
        key = key[:-len("gamma")] + "weight"
    if key.endswith("LayerNorm.beta"):
        key = key[:-len("beta")] + "bias"
    return key


LAYER_TENSORS = {
    "query": "attention.self.query", "key": "attention.self.key",
    "value": "attention.self.value", "attn_out": "attention.output.dense",
    "mlp_in": "intermediate.dense", "mlp_out": "output.dense",
}
LAYER_NORMS = {"attn_ln": "attention.output.LayerNorm", "mlp_ln": "output.LayerNorm"}


def bert_params(tensors: Mapping[str, np.ndarray], config: bert.BertConfig) -> dict:
    """The forward's parameter pytree (float32) from a BertModel's named tensors (torch
    ``Linear`` weights are (out, in); the pytree's kernels (in, out)). Tensors the forward
    does not use (the pooler, heads) are ignored; ValueError (one line) for a missing one or
    a wrong shape."""
    named = {tensor_name(k): v for k, v in tensors.items()}

    def get(name, transpose=False):
        if name not in named:
            raise ValueError(f"model.safetensors lacks the tensor {name!r}")
        value = np.asarray(named[name], np.float32)
        return value.T if transpose else value

    e = "embeddings."
    params = {"embeddings": {
        "word": get(e + "word_embeddings.weight"),
        "position": get(e + "position_embeddings.weight"),
        "token_type": get(e + "token_type_embeddings.weight"),
        "ln_scale": get(e + "LayerNorm.weight"), "ln_bias": get(e + "LayerNorm.bias")}}
    layers = {}
    for ours, theirs in LAYER_TENSORS.items():
        layers[ours] = stack(get, theirs + ".weight", config, transpose=True)
        layers[ours + "_bias"] = stack(get, theirs + ".bias", config)
    for ours, theirs in LAYER_NORMS.items():
        layers[ours + "_scale"] = stack(get, theirs + ".weight", config)
        layers[ours + "_bias"] = stack(get, theirs + ".bias", config)
    params["layers"] = layers
    expected = jax.tree_util.tree_leaves(bert.param_shapes(config), is_leaf=_is_shape)
    for (where, value), want in zip(jax.tree_util.tree_leaves_with_path(params), expected):
        if value.shape != want:
            raise ValueError(f"model.safetensors: {jax.tree_util.keystr(where)} has shape "
                             f"{value.shape}, config.json implies {want}")
    return jax.tree_util.tree_map(jnp.asarray, params)


def stack(get, name: str, config: bert.BertConfig, transpose: bool = False) -> np.ndarray:
    """Tensor ``encoder.layer.{i}.<name>`` of every layer, stacked on a leading axis."""
    return np.stack([get(f"encoder.layer.{i}.{name}", transpose)
                     for i in range(config.num_hidden_layers)])


def _is_shape(x) -> bool:
    return isinstance(x, tuple) and all(isinstance(n, int) for n in x)


def load_text_encoder(directory=None, expected_sha256: Mapping[str, str] | None = None
                      ) -> PretrainedTextEncoder:
    """Load a BERT text encoder: the shipped artifact (directory None) or a Hugging Face-format
    directory (config.json, model.safetensors, tokenizer.json).

    expected_sha256: optional {file name: sha256 hex} the files must have (a pin of your own,
    beside the directory's manifest.json if it has one).
    Raises ValueError (one line): directory not found, a file missing, a hash mismatch, an
    unsupported architecture or unreadable file.
    """
    path = resolve_directory(directory)
    data = read_files(path)
    hashes = {name: sha256_hex(blob) for name, blob in data.items()}
    manifest = manifest_hashes(path)
    if manifest is None and directory is None:
        raise ValueError(f"the shipped text encoder at {path} has no {MANIFEST} to check "
                         f"its files against")
    if manifest is not None:
        check_hashes(hashes, manifest, f"{path / MANIFEST}")
    if expected_sha256 is not None:
        check_hashes(hashes, expected_sha256, "expected_sha256")
    config, raw = parse_config(data["config.json"])
    try:
        tensors = safetensors.numpy.load(data["model.safetensors"])
    except Exception as e:  # the Rust reader raises its own error types
        raise ValueError(f"{path / 'model.safetensors'} is not readable safetensors: "
                         f"{type(e).__name__}") from None
    params = bert_params(tensors, config)
    pad = raw.get("pad_token_id")
    words = subwords.read_subwords(data["tokenizer.json"].decode("utf-8"), config.vocab_size,
                                   config.max_position_embeddings,
                                   None if pad is None else int(pad))
    return PretrainedTextEncoder(config, params, words, str(path), dict(hashes))
