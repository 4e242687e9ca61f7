"""Tests of diffplan.checkpoint: round trips, retention, eval export, mismatch errors."""
import dataclasses
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan import checkpoint as ckpt
from diffplan.train import Batch, TrainConfig, TrainState, checkpoint_metadata, init_train_state

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
from toy_denoiser import C, G, H, L, W, TinyConfig, TinyDenoiser

CFG = TrainConfig(steps=10, batch_size=4, warmup_steps=1)
SHAPES = Batch(jax.ShapeDtypeStruct((1, H, W, C + G), jnp.float32),
               jax.ShapeDtypeStruct((1, L), jnp.int32),
               jax.ShapeDtypeStruct((1, H, W, G), jnp.float32))


def leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


def assert_trees_equal(a, b):
    la, lb = leaves(a), leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        assert x.shape == y.shape and x.dtype == y.dtype
        np.testing.assert_array_equal(x, y)


@pytest.fixture(scope="module")
def model():
    return TinyDenoiser(TinyConfig())


@pytest.fixture(scope="module")
def state(model):
    """A TrainState with distinct, non-trivial values in every part."""
    s0 = init_train_state(model, CFG, SHAPES)

    def bump(x):
        return x + (jnp.asarray(0.25, x.dtype) if jnp.issubdtype(x.dtype, jnp.floating) else 3)

    @jax.jit
    def perturb(s):
        return TrainState(params=s.params,
                          ema_params=jax.tree_util.tree_map(lambda p: p * 0.5, s.params),
                          opt_state=jax.tree_util.tree_map(bump, s.opt_state), step=s.step + 5)

    return perturb(s0)


@pytest.fixture(scope="module")
def metadata(model):
    return checkpoint_metadata(model, TinyConfig(), CFG, SHAPES, {"task": "toy"})


@pytest.fixture(scope="module")
def train_dir(tmp_path_factory, state, metadata):
    d = str(tmp_path_factory.mktemp("ckpt"))
    ckpt.save_checkpoint(d, 5, state.ema_params, metadata, train_state=state)
    return d


def test_train_checkpoint_round_trip(train_dir, state, model):
    assert ckpt.latest_step(train_dir) == 5 and ckpt.all_steps(train_dir) == [5]
    target = jax.eval_shape(lambda: init_train_state(model, CFG, SHAPES))
    restored, meta = ckpt.load_checkpoint(train_dir, target=target)
    assert isinstance(restored, TrainState)
    assert_trees_equal(restored.params, state.params)
    assert_trees_equal(restored.ema_params, state.ema_params)
    assert_trees_equal(restored.opt_state, state.opt_state)
    struct = jax.tree_util.tree_structure
    assert struct(restored.opt_state) == struct(state.opt_state)
    assert int(restored.step) == 5
    assert meta["kind"] == "train" and meta["step"] == 5 and meta["extra"] == {"task": "toy"}
    assert meta["model_class"].endswith(":TinyDenoiser")
    assert meta["format"] == ckpt.FORMAT
    # Without a target: plain dicts, the state's entries named by their key paths.
    raw, _ = ckpt.load_checkpoint(train_dir, 5)
    assert_trees_equal(raw["ema_params"], state.ema_params)
    assert sorted(raw["train_state"]) == ["ema_params", "opt_state", "params", "step"]
    assert_trees_equal(raw["train_state"]["params"], state.params)
    assert_trees_equal(raw["train_state"], ckpt.state_tree(state))
    assert int(raw["train_state"]["step"]) == 5


def test_keeps_latest_two_and_refuses_to_overwrite(tmp_path, state, metadata):
    d = str(tmp_path / "keep")
    assert ckpt.latest_step(d) is None
    for s in (1, 2, 3):
        ckpt.save_checkpoint(d, s, state.ema_params, metadata, train_state=state)
    assert ckpt.all_steps(d) == [2, 3]
    assert not any(n.startswith("1") for n in os.listdir(d))
    with pytest.raises(ValueError, match="already exists"):
        ckpt.save_checkpoint(d, 3, state.ema_params, metadata, train_state=state)
    with pytest.raises(FileNotFoundError, match="step 7"):
        ckpt.load_checkpoint(d, 7)
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        ckpt.load_params_for_eval(str(tmp_path / "empty"))


def test_mismatched_config_or_shapes_raise_value_error(train_dir, state, model):
    params, meta = ckpt.load_params_for_eval(train_dir, TinyConfig(), model=model)
    assert_trees_equal(params, state.ema_params)
    with pytest.raises(ValueError, match=r"model config mismatch.*features: stored 8, "
                                         r"requested 16"):
        ckpt.load_params_for_eval(train_dir, TinyConfig(features=16), model=model)
    with pytest.raises(ValueError, match=r"vocab: stored 16, requested 32"):
        ckpt.load_params_for_eval(train_dir, {"features": 8, "vocab": 32}, model=model)
    # Same config, different architecture: the mismatching parameter is named with shapes.
    wide = TinyDenoiser(TinyConfig(features=12))
    with pytest.raises(ValueError, match=r"parameter shape mismatch.*Conv_0.*kernel.*"
                                         r"checkpoint \(3, 3, 4, 8\).*expects \(3, 3, 4, 12\)"):
        ckpt.load_params_for_eval(train_dir, model=wide)
    # Resuming into a differently shaped state is refused the same way.
    target = jax.eval_shape(lambda: init_train_state(wide, CFG, SHAPES))
    with pytest.raises(ValueError, match=r"does not match the target state.*Conv_0.*kernel"):
        ckpt.load_checkpoint(train_dir, target=target)


def test_export_eval_checkpoint_is_small_and_loads(train_dir, state, model, tmp_path):
    out = str(tmp_path / "eval")
    path = ckpt.export_eval_checkpoint(train_dir, out)
    assert sorted(n for n in os.listdir(path) if not n.startswith("_") and "." not in n) == \
        ["ema_params", "metadata"]

    def size(p):
        return sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(p) for f in fs)

    assert size(path) < size(os.path.join(train_dir, "5"))
    params, meta = ckpt.load_params_for_eval(out, TinyConfig(), model=model)
    assert_trees_equal(params, state.ema_params)
    assert all(x.dtype == np.float32 for x in leaves(params))
    assert meta["kind"] == "eval" and meta["step"] == 5
    assert meta["train_config"] == CFG.to_dict() and meta["exported_from"]["step"] == 5
    target = jax.eval_shape(lambda: init_train_state(model, CFG, SHAPES))
    with pytest.raises(ValueError, match="evaluation checkpoint"):
        ckpt.load_checkpoint(out, target=target)
    with pytest.raises(ValueError, match="overwrite=True"):
        ckpt.export_eval_checkpoint(train_dir, out)
    ckpt.export_eval_checkpoint(train_dir, out, overwrite=True)
    assert ckpt.all_steps(out) == [5]

    # A fresh process loads it (no model needed to read the params).
    code = ("import json, numpy as np, jax; from diffplan.checkpoint import load_params_for_eval;"
            f"p, m = load_params_for_eval({out!r});"
            "print(json.dumps([m['step'], float(sum(np.abs(np.asarray(x)).sum() "
            "for x in jax.tree_util.tree_leaves(p)))]))")
    env = dict(os.environ, PYTHONPATH=REPO, JAX_PLATFORMS="cpu")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         cwd=REPO, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    step, total = json.loads(res.stdout.strip().splitlines()[-1])
    assert step == 5
    np.testing.assert_allclose(total, sum(np.abs(x).sum() for x in leaves(state.ema_params)),
                               rtol=1e-6)


def test_real_denoiser_checkpoint(tmp_path):
    import diffplan.denoiser as den  # our own module: a broken import must fail, not skip
    mc = den.DenoiserConfig(vocab_size=16, max_tokens=L, num_cond_channels=C, num_gen_channels=G,
                            embed_dim=8, widths=(8, 16), num_res_blocks=1, attn_levels=(),
                            cross_attn_levels=(1,), text_dim=8, text_layers=1, text_heads=2,
                            groups=4, head_dim=8, mid_block=False)
    model = den.Denoiser(mc)
    meta = checkpoint_metadata(model, mc, CFG, SHAPES)
    assert meta["model_class"] == "diffplan.denoiser:Denoiser"
    assert meta["model_config_class"] == "diffplan.denoiser:DenoiserConfig"
    abstract = ckpt.abstract_params(model, meta["input_shapes"])  # no compilation
    params = jax.tree_util.tree_map(lambda a: np.full(a.shape, 0.5, a.dtype), abstract)
    d = str(tmp_path / "real")
    ckpt.save_checkpoint(d, 100, params, meta)  # an eval checkpoint (params only)
    # The model class is rebuilt from the metadata, from a config object or a dict.
    loaded, m = ckpt.load_params_for_eval(d, mc)
    assert_trees_equal(loaded, params)
    assert m["kind"] == "eval"
    ckpt.load_params_for_eval(d, json.loads(json.dumps(mc.to_dict())))
    with pytest.raises(ValueError, match=r"widths: stored \[8, 16\], requested \[8, 32\]"):
        ckpt.load_params_for_eval(d, dataclasses.replace(mc, widths=(8, 32)))
    with pytest.raises(ValueError, match="parameter shape mismatch"):
        ckpt.load_params_for_eval(d, model=den.Denoiser(dataclasses.replace(mc, embed_dim=16)))


# ------------------------------------------------------------------------------- any pytree

@jax.tree_util.register_pytree_with_keys_class
class _Twice:
    """A pytree node whose two children have the same key name."""

    def __init__(self, a, b):
        self.a, self.b = a, b

    def tree_flatten_with_keys(self):
        key = jax.tree_util.DictKey("x")
        return ((key, self.a), (key, self.b)), None

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(*children)


def test_any_pytree_state_round_trips_onto_its_target(tmp_path):
    """The training state need not be a TrainState: dicts, tuples, named tuples and None
    leaves (empty subtrees) restore onto the caller's target structure."""
    import collections

    Moments = collections.namedtuple("Moments", "mu nu")
    state = {"net": {"w": np.arange(6, dtype=np.float32).reshape(2, 3)},
             "opt": (Moments(np.ones(3, np.float32), np.full(3, 2.0, np.float32)), None, ()),
             "count": np.int32(7)}
    d = str(tmp_path / "tree")
    ckpt.save_checkpoint(d, 7, {"w": state["net"]["w"]}, {"note": "tree"}, train_state=state)
    restored, meta = ckpt.load_checkpoint(d, target=jax.eval_shape(lambda: state))
    assert jax.tree_util.tree_structure(restored) == jax.tree_util.tree_structure(state)
    assert_trees_equal(restored, state)
    assert meta["kind"] == "train" and meta["note"] == "tree"
    raw, _ = ckpt.load_checkpoint(d)
    assert sorted(raw["train_state"]) == ["count", "net", "opt"]
    np.testing.assert_array_equal(raw["train_state"]["opt"]["0"]["nu"], state["opt"][0].nu)
    # Another structure is refused, naming the entry.
    other = dict(state, net={"w": np.zeros((3, 3), np.float32)})
    with pytest.raises(ValueError, match=r"does not match the target state.*net.*w.*\(2, 3\)"):
        ckpt.load_checkpoint(d, target=other)


def test_state_tree_names_leaves_by_path_and_refuses_collisions():
    tree = {"a": [np.zeros(2), {"b": np.ones(1)}], "c": np.int32(1)}
    nested = ckpt.state_tree(tree)
    assert sorted(nested) == ["a", "c"] and sorted(nested["a"]) == ["0", "1"]
    assert nested["a"]["1"]["b"] is tree["a"][1]["b"]
    with pytest.raises(ValueError, match="both stored as twice/x"):
        ckpt.state_tree({"twice": _Twice(np.zeros(1), np.ones(1))})


def test_training_state_of_the_older_format_is_refused_in_one_line(tmp_path, state, metadata,
                                                                   monkeypatch, model):
    d = str(tmp_path / "old")
    monkeypatch.setattr(ckpt, "FORMAT", "diffplan-checkpoint/1")
    ckpt.save_checkpoint(d, 5, state.ema_params, metadata, train_state=state)
    monkeypatch.undo()
    assert ckpt.read_metadata(d)["format"] == "diffplan-checkpoint/1"
    target = jax.eval_shape(lambda: init_train_state(model, CFG, SHAPES))
    for call in (lambda: ckpt.load_checkpoint(d, target=target), lambda: ckpt.load_checkpoint(d)):
        with pytest.raises(ValueError, match="older layout") as info:
            call()
        assert "\n" not in str(info.value)
    params, _ = ckpt.load_params_for_eval(d)  # its evaluation params still load
    assert_trees_equal(params, state.ema_params)


SHIPPED_PARAMS_SHA256 = {
    # SHA-256 over (key path, dtype, shape, bytes) of every array load_params_for_eval returns,
    # measured with the loader before the checkpoint code became generic over pytrees (the
    # per-setting BCs and CQLs and the Kuka baselines: with the loader of the commit that
    # shipped them).
    "compile_gridworld": "c509cb4abaf8cf405181d1316a84f9ab4e1421adcb7f91d5dfc479dedeb61ed7",
    "kuka": "4c7181f0fa4815f57f5ae3c336dcce8f3f0259b6f6a88fed2d04b98b327326b4",
    "baselines/bc/1o1g": "4b594fce64a1db88373af856742d34b3eb8c0478f3baa8f970a444d719757699",
    "baselines/bc/mo1g": "7d0ab37b07ed4fd8a7ccee4a5c8ae069af021b7db70988cbb7ac8b3c26d31b1e",
    "baselines/bc/p_mo2g": "ac0172ff639bf9eb5bbee963c1990877cf5d85fe63bdf468e8d4d6f457a041d5",
    "baselines/kuka/bc": "07ef07cea1891e3522c56182e1d7c9b9ca369e7f5e1243b650fd5e705257b910",
    "baselines/kuka/cql": "1694476bcd1d6bf91f8686d31e62bbbc4730792e7f517fc3cf05e4c7612d2861",
    "baselines/kuka/dd/diffusion":
        "209b26ee3fc32a4af18a5832d3a44bb7446cb126545925de63119355ff5fd152",
    "baselines/kuka/dd/inverse_dynamics":
        "3d96e23620144b890ef05cb6e7989845a3b0626d55df6ac2e033b6e5b295c722",
    "baselines/cql/1o1g": "98c69a3300dc2ae8e9c05738753fe5ba0319d9cdea50d07b4784504245dade7e",
    "baselines/cql/mo1g": "2f0420dcc1ce00945012ba8e7d9094946c06f3f2c427cee67ebeb27b358342fe",
    "baselines/cql/p_mo2g": "e0c4f17062d5548cdbf8f6fcf7fb5b5f17bec049bfa3a767480385a2d3036351",
    "baselines/dd/diffusion": "58c3dd84d47decea6ec0cd8cd447e88147c27b912ce675de2d851a93d862e46e",
    "baselines/dd/inverse_dynamics":
        "d9655b85d5336134d4268407a54a07b7e925c24f5331bcbb37e5aa4225d6277f",
}


def _tree_sha256(tree):
    import hashlib

    h = hashlib.sha256()
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        a = np.asarray(leaf)
        for part in (jax.tree_util.keystr(path), str(a.dtype), str(a.shape)):
            h.update(part.encode())
        h.update(a.tobytes())
    return h.hexdigest()


@pytest.mark.parametrize("rel", sorted(SHIPPED_PARAMS_SHA256))
def test_shipped_checkpoints_verify_and_load_bit_identically(rel):
    import diffplan

    directory = os.path.join(REPO, "checkpoints", rel)
    step = ckpt.verify_checkpoint(directory)
    params, meta = ckpt.load_params_for_eval(directory)
    assert meta["kind"] == "eval" and meta["step"] == step
    assert _tree_sha256(params) == SHIPPED_PARAMS_SHA256[rel]
    if meta["model_class"] == "diffplan.denoiser:Denoiser":
        assert _tree_sha256(diffplan.load_denoiser(directory).params) == \
            SHIPPED_PARAMS_SHA256[rel]
