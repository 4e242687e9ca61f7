"""Loading a checkpoint never imports or runs code that the checkpoint names.

A checkpoint's metadata names its network and config classes ("module:Class"); the loaders
look them up in the registry of diffplan.models and refuse any other name with one line,
before anything is imported. Each test plants modules that write a marker file when imported
-- one on sys.path, one shipped inside the checkpoint folder itself (reachable as a namespace
package from a directory on sys.path, as the repository root is) -- points a checkpoint at
them through every loading entry point, and checks the refusal and that no marker appears.
A control imports the modules at the end: the markers appear, so the test can fail.
"""
import importlib
import os
import sys

import jax
import numpy as np
import pytest

import diffplan
from diffplan import checkpoint as ckpt
from diffplan import models
from diffplan.train import ConfigMismatchError, TrainState, fit, run_metadata

from toy_denoiser import TinyConfig, TinyDenoiser

PAYLOAD = """
import pathlib
pathlib.Path({marker!r}).write_text("imported")


class Net:
    def __init__(self, config=None):
        pathlib.Path({marker!r}).write_text("called")


class Config:
    @classmethod
    def from_dict(cls, d):
        pathlib.Path({marker!r}).write_text("called")
"""

DENOISER_SHAPES = {"x": [1, 8, 8, 7], "tokens": [1, 4]}


@pytest.fixture
def planted(tmp_path, monkeypatch):
    """(root on sys.path, the checkpoint folder, {class key: marker path}) with two payloads:
    ``h1_planted_payload`` on sys.path and ``shipped.ckpt.payload`` inside the checkpoint."""
    root = tmp_path / "root"
    folder = root / "shipped" / "ckpt"
    folder.mkdir(parents=True)
    markers = {}
    for module, path in (("h1_planted_payload", root / "h1_planted_payload.py"),
                         ("shipped.ckpt.payload", folder / "payload.py")):
        marker = tmp_path / f"marker-{module}"
        path.write_text(PAYLOAD.format(marker=str(marker)))
        markers[module] = marker
    monkeypatch.syspath_prepend(str(root))
    importlib.invalidate_caches()
    yield root, str(folder), markers
    for module in (*markers, "shipped", "shipped.ckpt"):
        sys.modules.pop(module, None)


def _write(directory, model_class, config_class, train_state=None):
    meta = {"model_class": model_class, "model_config_class": config_class,
            "model_config": TinyConfig().to_dict(), "train_config": {"lr": 1.0},
            "extra": {}, "input_shapes": DENOISER_SHAPES}
    params = {"w": np.zeros(3, np.float32)}
    ckpt.save_checkpoint(directory, 1, params, meta, train_state=train_state)
    return meta


def _refused(call, match):
    with pytest.raises(ValueError, match=match) as info:
        call()
    assert "\n" not in str(info.value), str(info.value)
    return info.value


def _loaders(directory, tmp_path):
    """Every entry point that reads a checkpoint, by name."""
    state = TrainState(params={"w": np.zeros(3, np.float32)},
                       ema_params={"w": np.zeros(3, np.float32)}, opt_state=(),
                       step=np.zeros((), np.int32))
    return {
        "load_params_for_eval(config dict)":
            lambda: ckpt.load_params_for_eval(directory, TinyConfig().to_dict()),
        "load_params_for_eval(config object)":
            lambda: ckpt.load_params_for_eval(directory, TinyConfig()),
        "diffplan.load_denoiser": lambda: diffplan.load_denoiser(directory),
        "models.build_model": lambda: models.build_model(ckpt.read_metadata(directory)),
        "fit (resume)": lambda: fit(lambda s, k, d: (s, {"loss": 0.0}), lambda: state,
                                    steps=2, seed=0, out_dir=directory, progress=False,
                                    metadata=run_metadata(TinyDenoiser(TinyConfig()),
                                                          TinyConfig(), {}, DENOISER_SHAPES)),
    }


@pytest.mark.parametrize("where", ["h1_planted_payload", "shipped.ckpt.payload"])
@pytest.mark.parametrize("named", ["model", "config"])
def test_no_loader_imports_what_a_checkpoint_names(planted, tmp_path, where, named):
    root, folder, markers = planted
    directory = os.path.join(folder, "run")
    if named == "model":  # the network class itself is planted
        _write(directory, f"{where}:Net", f"{where}:Config")
        expect = r"model class '.*payload:Net' is not a registered network"
    else:  # a registered network with a planted config class
        _write(directory, "diffplan.denoiser:Denoiser", f"{where}:Config")
        expect = r"config class '.*payload:Config'"
    for name, call in _loaders(directory, tmp_path).items():
        if name.startswith("fit"):
            # Another run's checkpoint is never resumed: its metadata differs (and the class
            # strings are compared, not imported).
            with pytest.raises(ConfigMismatchError, match="model_class"):
                call()
        else:  # even with the caller's own config object, the names are refused
            _refused(call, expect)
        assert not any(m.exists() for m in markers.values()), f"{name} imported the payload"
    # What only reads arrays or metadata works and imports nothing either.
    params, meta = ckpt.load_params_for_eval(directory)
    np.testing.assert_array_equal(params["w"], np.zeros(3))
    ckpt.export_eval_checkpoint(directory, str(tmp_path / "exported"))
    ckpt.load_checkpoint(directory)
    assert not any(m.exists() for m in markers.values())
    assert where not in sys.modules
    # Control: the payload does write its marker when imported.
    importlib.import_module(where)
    assert markers[where].read_text() == "imported"


def test_the_refusal_names_what_to_do(monkeypatch):
    err = _refused(lambda: models.lookup("somewhere.else:Net"), "not a registered network")
    assert "register_model" in str(err) and "diffplan.denoiser:Denoiser" in str(err)
    monkeypatch.delitem(models._REGISTRY, "diffplan.baselines.dd:DDModel", raising=False)
    err = _refused(lambda: models.lookup("diffplan.baselines.dd:DDModel"),
                   "import diffplan.baselines.dd first")
    _refused(lambda: models.lookup(None), "None")
    _refused(lambda: models.spec_for_metadata({}), "None")


def test_registered_networks_load_by_their_key_and_aliases(tmp_path, monkeypatch):
    """A user's network registered under its class path loads from a config (object or dict)
    without model=; an alias maps a key of older checkpoints to the registered class."""
    monkeypatch.setattr(models, "_REGISTRY", dict(models._REGISTRY))
    models.register_model(ckpt.class_path(TinyDenoiser), TinyDenoiser, TinyConfig)
    model = TinyDenoiser(TinyConfig())
    params = ckpt.abstract_params(model, DENOISER_SHAPES)
    params = jax.tree_util.tree_map(lambda a: np.ones(a.shape, a.dtype), params)
    meta = run_metadata(model, TinyConfig(), {}, DENOISER_SHAPES)
    directory = str(tmp_path / "user")
    ckpt.save_checkpoint(directory, 3, params, meta)
    for config in (TinyConfig(), TinyConfig().to_dict()):
        loaded, _ = ckpt.load_params_for_eval(directory, config)
        assert jax.tree_util.tree_structure(loaded) == jax.tree_util.tree_structure(params)
    assert isinstance(models.build_model(meta), TinyDenoiser)
    from diffplan.denoiser import DenoiserConfig
    _refused(lambda: models.build_model(meta, DenoiserConfig()),
             "takes a toy_denoiser:TinyConfig")
    # The shipped BC/CQL checkpoints name the network's old module: an alias.
    models.register_model("diffplan.baselines.nets:GoalConvNet", TinyDenoiser, TinyConfig)
    assert models.lookup("diffplan.baselines.common:GoalConvNet").model_cls is TinyDenoiser
    assert models.ALIASES["diffplan.baselines.common:ConvNetConfig"] == \
        "diffplan.baselines.nets:ConvNetConfig"
    # load_denoiser wants a Denoiser.
    _refused(lambda: diffplan.load_denoiser(directory), "not a diffplan Denoiser")
    with pytest.raises(ValueError, match="must be a class"):
        models.register_model("k", TinyDenoiser, TinyConfig())


def test_shipped_checkpoints_name_known_keys():
    """Every shipped checkpoint names a network and config that the registry knows (or will,
    once its module is imported), so none needs an import by name."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    known = set(models.BUILTIN) | set(models.ALIASES)
    for rel in ("compile_gridworld", "kuka", "baselines/bc/1o1g", "baselines/bc/mo1g",
                "baselines/bc/p_mo2g", "baselines/cql/1o1g", "baselines/cql/mo1g",
                "baselines/cql/p_mo2g", "baselines/kuka/bc", "baselines/kuka/cql",
                "baselines/kuka/dd/diffusion", "baselines/kuka/dd/inverse_dynamics",
                "baselines/dd/diffusion", "baselines/dd/inverse_dynamics"):
        meta = ckpt.read_metadata(os.path.join(root, "checkpoints", rel))
        assert meta["model_class"] in known, (rel, meta["model_class"])
    assert models.lookup("diffplan.denoiser:Denoiser").config_key == \
        "diffplan.denoiser:DenoiserConfig"
