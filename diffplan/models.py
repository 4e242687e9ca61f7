"""The network classes a checkpoint may name: a registry keyed by the strings checkpoints store.

A checkpoint's metadata names its network and config classes as ``"module:QualName"`` strings
(``model_class``, ``model_config_class``; :func:`class_path` writes them). Loading never imports
or calls what a checkpoint names: the strings are looked up here, among classes that code the
user chose to import has registered, and a checkpoint naming any other class is refused with
one line (:class:`UnknownModelError`, a ValueError) before anything is imported. (An allow-list
of module names to import lazily would close an import circle: the networks' modules import
the training loop, which imports the checkpoints. So every network registers itself where it
is defined.)

Registered by diffplan itself: ``diffplan.denoiser`` registers the Denoiser (``import
diffplan`` does it); the baselines' modules (``diffplan.baselines.nets``, ``.dd``) register their
networks when imported; :data:`BUILTIN` names the module to import for each, and
:data:`ALIASES` maps keys stored by shipped checkpoints written before a class moved.

Your own network::

    from diffplan.models import class_path, register_model
    register_model(class_path(MyNet), MyNet, MyNetConfig)   # MyNet(config) builds it

or pass ``model=`` to the loader. ``MyNetConfig`` needs ``to_dict()`` and ``from_dict()``
(or is a dataclass).
"""
from __future__ import annotations

import dataclasses
import types
from typing import Any, Callable, Mapping, Optional, Sequence

import jax
import jax.numpy as jnp

__all__ = ["ModelSpec", "UnknownModelError", "ALIASES", "BUILTIN", "class_path",
           "register_model", "registered", "lookup", "spec_for_metadata", "build_model",
           "denoiser_inputs", "example_inputs"]

InputsFn = Callable[[Mapping[str, Sequence[int]]], tuple]

ALIASES = types.MappingProxyType({
    # The shipped BC and CQL checkpoints were written when the network lived in common.py.
    "diffplan.baselines.common:GoalConvNet": "diffplan.baselines.nets:GoalConvNet",
    "diffplan.baselines.common:ConvNetConfig": "diffplan.baselines.nets:ConvNetConfig",
})
"""Key stored by older checkpoints -> the key its class is registered under now."""

BUILTIN = types.MappingProxyType({
    "diffplan.denoiser:Denoiser": "diffplan.denoiser",
    "diffplan.baselines.nets:GoalConvNet": "diffplan.baselines.nets",
    "diffplan.baselines.dd:DDModel": "diffplan.baselines.dd",
    "diffplan.baselines.dd:InverseDynamics": "diffplan.baselines.dd",
    "diffplan.baselines.goal:GoalClassifier": "diffplan.baselines.goal",
})
"""diffplan's own networks -> the module whose import registers them (for error messages)."""


class UnknownModelError(ValueError):
    """A checkpoint names a network (or config) class that is not registered."""


def class_path(obj_or_cls: Any) -> str:
    """``"module:QualName"`` of a class (or of an instance's class): the registry key."""
    cls = obj_or_cls if isinstance(obj_or_cls, type) else type(obj_or_cls)
    return f"{cls.__module__}:{cls.__qualname__}"


def config_from_dict(cls: type, d: Mapping[str, Any]) -> Any:
    """``cls(**d)`` for a config dataclass read from a checkpoint's metadata; keys that are not
    fields of cls raise ValueError (one line, naming them)."""
    unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
    if unknown:
        raise ValueError(f"unknown {cls.__name__} fields: {unknown}")
    return cls(**dict(d))


def denoiser_inputs(input_shapes: Mapping[str, Sequence[int]]) -> tuple:
    """The inputs of a network called like the Denoiser, ``(x_t, t, tokens)``, from the
    stored ``input_shapes`` ``{"x": [B, H, W, C+G], "tokens": [B, L]}``: float32 x, int32 t
    (B,), int32 tokens (as ``jax.ShapeDtypeStruct``); tokens ``[B, L, D]`` are pretrained
    features, float32."""
    x = tuple(int(d) for d in input_shapes["x"])
    tokens = tuple(int(d) for d in input_shapes["tokens"])
    return (jax.ShapeDtypeStruct(x, jnp.float32), jax.ShapeDtypeStruct(x[:1], jnp.int32),
            jax.ShapeDtypeStruct(tokens, jnp.float32 if len(tokens) == 3 else jnp.int32))


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """A registered network: ``model_cls(config)`` builds it, ``config_cls.from_dict(d)`` (or
    ``config_cls(**d)``) its config; ``inputs(input_shapes)`` gives the example inputs of its
    ``init`` (``jax.ShapeDtypeStruct`` tuple) from a checkpoint's stored ``input_shapes``."""

    key: str
    model_cls: type
    config_cls: type
    config_key: str
    inputs: InputsFn = denoiser_inputs

    def config_from_dict(self, d: Mapping[str, Any]) -> Any:
        if hasattr(self.config_cls, "from_dict"):
            return self.config_cls.from_dict(dict(d))
        return self.config_cls(**dict(d))


_REGISTRY: dict[str, ModelSpec] = {}


def register_model(key: str, model_cls: type, config_cls: type, *,
                   inputs: Optional[InputsFn] = None) -> ModelSpec:
    """Registers ``model_cls`` (built as ``model_cls(config)``) and its config class under
    ``key``, the ``model_class`` string its checkpoints store (``class_path(model_cls)``; the
    config's key is ``class_path(config_cls)``). ``inputs``: see :class:`ModelSpec` (default:
    the Denoiser's ``(x_t, t, tokens)``). Registering a key again replaces its entry."""
    if not isinstance(key, str) or not key:
        raise ValueError(f"register_model: key must be a non-empty string, got {key!r}")
    for what, cls in (("model_cls", model_cls), ("config_cls", config_cls)):
        if not isinstance(cls, type):
            raise ValueError(f"register_model: {what} must be a class, got {cls!r}")
    spec = ModelSpec(key, model_cls, config_cls, class_path(config_cls),
                     denoiser_inputs if inputs is None else inputs)
    _REGISTRY[key] = spec
    return spec


def registered() -> tuple[str, ...]:
    """The registered keys, sorted."""
    return tuple(sorted(_REGISTRY))


def lookup(key: Any) -> ModelSpec:
    """The registered network of ``key`` (an alias of :data:`ALIASES` is followed). Raises
    UnknownModelError, naming what to do, for any other string; nothing is imported."""
    current = ALIASES.get(key, key) if isinstance(key, str) else key
    spec = _REGISTRY.get(current) if isinstance(current, str) else None
    if spec is not None:
        return spec
    if current in BUILTIN:
        hint = f"import {BUILTIN[current]} first, which registers it"
    else:
        hint = (f"registered: {', '.join(registered()) or 'none'}; register yours with "
                "diffplan.models.register_model")
    raise UnknownModelError(f"model class {key!r} is not a registered network ({hint}), or pass "
                            "model=...; loading never imports a class a checkpoint names")


def spec_for_metadata(metadata: Mapping[str, Any]) -> ModelSpec:
    """The registered network a checkpoint's metadata names (``model_class``), whose config
    class must be the one it stores (``model_config_class``, when stored). Raises
    UnknownModelError otherwise."""
    spec = lookup(metadata.get("model_class"))
    stored = metadata.get("model_config_class")
    if stored is not None and ALIASES.get(stored, stored) != spec.config_key:
        raise UnknownModelError(f"checkpoint names config class {stored!r}, but network "
                                f"{spec.key!r} is registered with config {spec.config_key!r}; "
                                "loading never imports a class a checkpoint names")
    return spec


def build_model(metadata: Mapping[str, Any], config: Any = None) -> Any:
    """``model_cls(config)`` of the network the metadata names (see :func:`spec_for_metadata`).
    config: a config object, a dict (through the registered config class), or None (the
    stored ``model_config``)."""
    spec = spec_for_metadata(metadata)
    if config is None:
        config = metadata.get("model_config", {})
    if isinstance(config, Mapping):
        config = spec.config_from_dict(config)
    elif not isinstance(config, spec.config_cls):
        raise ValueError(f"the config is a {class_path(config)}, but the checkpoint's network "
                         f"{spec.key!r} takes a {spec.config_key}")
    return spec.model_cls(config)


def example_inputs(model: Any, input_shapes: Mapping[str, Sequence[int]]) -> tuple:
    """The example inputs of ``model.init`` for the stored ``input_shapes``: those of the
    registered spec of ``type(model)``, else the Denoiser's ``(x_t, t, tokens)``."""
    for spec in _REGISTRY.values():
        if spec.model_cls is type(model):
            return spec.inputs(input_shapes)
    return denoiser_inputs(input_shapes)
