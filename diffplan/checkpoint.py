"""Orbax checkpoints of diffusion-planner training runs, and loading EMA params for evaluation.

Layout: a checkpoint directory is an ``orbax.checkpoint.CheckpointManager`` root; each saved
step is a sub-directory named by the step number, written atomically (orbax writes to a
temporary directory and renames it on commit) and holding the items

    ema_params/   the EMA parameters (the ``params`` collection of the model), float32
    train_state/  only in training checkpoints: {"params", "opt_state", "step"}; the optimizer
                  state is stored as its list of leaves ("000000", "000001", ...) and rebuilt
                  from the caller's target structure, so any optax state works
    metadata/     JSON: {"format": ..., "kind": "train" | "eval", "step", "model_config",
                  "model_config_class", "model_class", "train_config", "extra",
                  "input_shapes": {"x": [1, H, W, C+G], "tokens": [1, L]}, ...}

Other files may live beside the step directories (``metrics.jsonl``, ``tb/``, ``config.json``):
the manager only looks at numerically named sub-directories. ``export_eval_checkpoint`` writes
the small kind of checkpoint shipped in the repository (EMA params + metadata only);
``load_params_for_eval`` reads both kinds.
"""
from __future__ import annotations

import hashlib
import importlib
import json
import logging
import os
import shutil
from typing import Any, Mapping, Optional

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

__all__ = [
    "FORMAT",
    "CorruptCheckpointError",
    "CheckpointWriteError",
    "verify_checkpoint",
    "save_checkpoint",
    "load_checkpoint",
    "latest_step",
    "all_steps",
    "read_metadata",
    "load_params_for_eval",
    "export_eval_checkpoint",
    "config_to_dict",
    "diff_dicts",
    "compare_param_shapes",
    "class_path",
    "abstract_params",
]

FORMAT = "diffplan-checkpoint/1"
MAX_TO_KEEP = 2
DIGEST_FILE = "diffplan_digest.json"
"""SHA-256 of every file of a saved step, written (atomically) once orbax has committed the
step; loading verifies it, so a truncated or altered file is reported instead of loading
silently wrong values (orbax alone does not notice a flipped byte in an array)."""


class CorruptCheckpointError(ValueError):
    """A checkpoint step exists but cannot be read back as it was written."""


class CheckpointWriteError(OSError):
    """A checkpoint could not be written (e.g. the disk is full); nothing of it was kept."""


# --------------------------------------------------------------------------- small helpers

def class_path(obj_or_cls: Any) -> str:
    """``"module:QualName"`` of a class (or of an instance's class)."""
    cls = obj_or_cls if isinstance(obj_or_cls, type) else type(obj_or_cls)
    return f"{cls.__module__}:{cls.__qualname__}"


def _import_path(path: str) -> Any:
    module, _, qual = path.partition(":")
    obj = importlib.import_module(module)
    for part in qual.split("."):
        obj = getattr(obj, part)
    return obj


def _json_normalise(value: Any) -> Any:
    """JSON round trip: tuples become lists, keys strings (what a stored config looks like)."""
    return json.loads(json.dumps(value))


def config_to_dict(config: Any) -> dict:
    """A config object (with ``to_dict()``), a dataclass, or a mapping -> JSON-normalised dict."""
    if config is None:
        return {}
    if hasattr(config, "to_dict"):
        d = config.to_dict()
    elif isinstance(config, Mapping):
        d = dict(config)
    else:
        import dataclasses
        if dataclasses.is_dataclass(config):
            d = dataclasses.asdict(config)
        else:
            raise ValueError(f"cannot turn a {type(config).__name__} into a config dict; "
                             "give an object with to_dict(), a dataclass or a dict")
    return _json_normalise(d)


def diff_dicts(stored: Any, requested: Any, prefix: str = "") -> list[str]:
    """Human-readable differences between two JSON-like values (empty list if equal)."""
    stored, requested = _json_normalise(stored), _json_normalise(requested)
    if isinstance(stored, dict) and isinstance(requested, dict):
        out = []
        for k in sorted(set(stored) | set(requested)):
            name = f"{prefix}.{k}" if prefix else str(k)
            if k not in stored:
                out.append(f"{name}: missing in stored, requested {requested[k]!r}")
            elif k not in requested:
                out.append(f"{name}: stored {stored[k]!r}, missing in requested")
            else:
                out.extend(diff_dicts(stored[k], requested[k], name))
        return out
    if stored != requested:
        return [f"{prefix or '<value>'}: stored {stored!r}, requested {requested!r}"]
    return []


class _ReadOnlyNotices(logging.Filter):
    """Drops orbax's notices that a manager opened read-only is read-only (every load of a
    shipped checkpoint printed two of them: not the user's business)."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not ("read_only=True" in message or "directory is read only" in message)


logging.getLogger("absl").addFilter(_ReadOnlyNotices())


def _manager(directory: str, *, read_only: bool = False,
             max_to_keep: Optional[int] = MAX_TO_KEEP) -> ocp.CheckpointManager:
    if read_only:
        max_to_keep = None
    options = ocp.CheckpointManagerOptions(
        max_to_keep=max_to_keep, enable_async_checkpointing=False, read_only=read_only,
        create=not read_only)
    handlers = {"ema_params": ocp.StandardCheckpointHandler(),
                "train_state": ocp.StandardCheckpointHandler(),
                "metadata": ocp.JsonCheckpointHandler()}
    return ocp.CheckpointManager(os.path.abspath(directory), options=options,
                                 item_handlers=handlers)


def all_steps(directory: str) -> list[int]:
    """The committed checkpoint steps in ``directory`` (sorted; [] if none / no directory)."""
    if not os.path.isdir(directory):
        return []
    with _manager(directory, read_only=True) as m:
        return sorted(int(s) for s in m.all_steps())


def latest_step(directory: str) -> Optional[int]:
    """The newest committed checkpoint step in ``directory``, or None."""
    steps = all_steps(directory)
    return steps[-1] if steps else None


def _file_digests(step_dir: str) -> dict[str, str]:
    out = {}
    for root, _, files in os.walk(step_dir):
        for name in files:
            path = os.path.join(root, name)
            rel = os.path.relpath(path, step_dir)
            if rel.startswith(DIGEST_FILE):  # the digest itself (or a torn write of it)
                continue
            h = hashlib.sha256()
            with open(path, "rb") as f:
                for block in iter(lambda: f.read(1 << 20), b""):
                    h.update(block)
            out[rel] = h.hexdigest()
    return out


def _write_digest(step_dir: str) -> None:
    digests = _file_digests(step_dir)
    tmp = os.path.join(step_dir, DIGEST_FILE + ".tmp")
    with open(tmp, "w") as f:
        json.dump(digests, f, indent=0, sort_keys=True)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, os.path.join(step_dir, DIGEST_FILE))


def verify_checkpoint(directory: str, step: Optional[int] = None) -> int:
    """Checks step ``step`` (default: the latest) of ``directory`` against its digest; returns
    the step. Raises FileNotFoundError (no such step) or CorruptCheckpointError (a file is
    missing, truncated or altered). Steps written before digests existed are accepted."""
    step = _resolve_step(directory, step)
    step_dir = os.path.join(directory, str(step))
    digest_path = os.path.join(step_dir, DIGEST_FILE)
    if not os.path.exists(digest_path):
        return step
    try:
        with open(digest_path) as f:
            expected = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        raise CorruptCheckpointError(f"checkpoint {directory!r} step {step}: its digest is "
                                     f"unreadable ({e})") from e
    found = _file_digests(step_dir)
    bad = sorted(k for k in expected if found.get(k) != expected[k])
    if bad:
        what = ", ".join(f"{k} ({'missing' if k not in found else 'altered'})" for k in bad[:3])
        raise CorruptCheckpointError(
            f"checkpoint {directory!r} step {step} is corrupted: {what}"
            + (f" and {len(bad) - 3} more files" if len(bad) > 3 else ""))
    return step


def _resolve_step(directory: str, step: Optional[int]) -> int:
    steps = all_steps(directory)
    if not steps:
        raise FileNotFoundError(f"no checkpoint found in {directory!r}")
    if step is None:
        return steps[-1]
    if int(step) not in steps:
        raise FileNotFoundError(f"no checkpoint for step {step} in {directory!r}; "
                                f"available steps: {steps}")
    return int(step)


def _flatten_opt_state(opt_state: Any) -> dict:
    return {f"{i:06d}": leaf for i, leaf in enumerate(jax.tree_util.tree_leaves(opt_state))}


def _path_shapes(tree: Any) -> dict[str, tuple[tuple[int, ...], str]]:
    out = {}
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        shape = tuple(int(d) for d in getattr(leaf, "shape", np.shape(leaf)))
        dtype = str(np.dtype(getattr(leaf, "dtype", np.asarray(leaf).dtype)))
        out[jax.tree_util.keystr(path)] = (shape, dtype)
    return out


def compare_param_shapes(stored: Any, expected: Any, what: str = "parameter") -> list[str]:
    """Differences (missing / unexpected entries, shape or dtype) between two param trees."""
    s, e = _path_shapes(stored), _path_shapes(expected)
    out = []
    for k in sorted(set(s) | set(e)):
        if k not in s:
            out.append(f"{what} {k} expected {e[k][0]} {e[k][1]} but missing in checkpoint")
        elif k not in e:
            out.append(f"{what} {k} {s[k][0]} in checkpoint but not in the model")
        elif s[k] != e[k]:
            out.append(f"{what} {k}: checkpoint {s[k][0]} {s[k][1]}, "
                       f"model expects {e[k][0]} {e[k][1]}")
    return out


def _abstract_from_metadata(tree_meta: Any, sharding) -> Any:
    """Orbax item metadata -> ShapeDtypeStruct tree placed with ``sharding``."""
    def to_sds(m):
        return jax.ShapeDtypeStruct(tuple(m.shape), m.dtype, sharding=sharding)
    tree = getattr(tree_meta, "tree", tree_meta)
    return jax.tree_util.tree_map(to_sds, tree, is_leaf=lambda x: hasattr(x, "shape")
                                  and hasattr(x, "dtype"))


def _abstract_like(tree: Any, default_sharding) -> Any:
    """ShapeDtypeStruct tree of ``tree`` keeping each leaf's sharding when it has one."""
    def to_sds(x):
        sharding = getattr(x, "sharding", None) or default_sharding
        return jax.ShapeDtypeStruct(tuple(x.shape), x.dtype, sharding=sharding)
    return jax.tree_util.tree_map(to_sds, tree)


# --------------------------------------------------------------------------- save / load

def save_checkpoint(directory: str, step: int, state: Any, metadata: Mapping[str, Any], *,
                    max_to_keep: Optional[int] = MAX_TO_KEEP) -> str:
    """Atomically writes checkpoint ``step`` into ``directory``; keeps the newest ``max_to_keep``.

    Args:
      directory: the checkpoint root (created if missing).
      step: the step number (a new one: saving an existing step raises ValueError).
      state: a ``diffplan.train.TrainState`` (a training checkpoint: params, EMA params,
        optimizer state, step) or any other pytree, taken as the EMA parameters alone (an
        evaluation checkpoint).
      metadata: JSON-serialisable dict (configs etc.); ``format``, ``kind`` and ``step`` are
        added.

    Returns:
      The path of the step directory.
    """
    from diffplan.train import TrainState  # local import: train imports this module

    step = int(step)
    if step < 0:
        raise ValueError(f"step must be >= 0, got {step}")
    meta = dict(_json_normalise(dict(metadata)))
    # Host copies: the arrays are small and replicated, and numpy arrays avoid orbax's
    # replica-parallel slicing of multi-device arrays, which breaks with jax 0.6.2
    # (orbax 0.12.8 uses ``jax.sharding.set_mesh`` as a context manager).
    state = jax.device_get(state)
    if isinstance(state, TrainState):
        items = {
            "ema_params": ocp.args.StandardSave(state.ema_params),
            "train_state": ocp.args.StandardSave({
                "params": state.params,
                "opt_state": _flatten_opt_state(state.opt_state),
                "step": np.asarray(state.step, np.int32),
            }),
        }
        meta["kind"] = "train"
    else:
        items = {"ema_params": ocp.args.StandardSave(state)}
        meta["kind"] = "eval"
    meta["format"] = FORMAT
    meta["step"] = step
    items["metadata"] = ocp.args.JsonSave(meta)
    with _manager(directory, max_to_keep=max_to_keep) as m:
        if step in m.all_steps():
            raise ValueError(f"checkpoint step {step} already exists in {directory!r}")
        step_dir = str(m.directory / str(step))
        try:
            m.save(step, args=ocp.args.Composite(**items), force=True)
            m.wait_until_finished()
            _write_digest(step_dir)
        except Exception as e:  # noqa: BLE001 - any failure: nothing of this step is kept
            _remove_partial(directory, step)
            older = [s for s in all_steps(directory) if s != step]
            raise CheckpointWriteError(
                f"could not write checkpoint step {step} to {directory!r} "
                f"({type(e).__name__}: {str(e).splitlines()[0][:200]}); "
                + (f"the last good checkpoint is step {older[-1]}" if older else
                   "no earlier checkpoint exists")) from e
        return step_dir


def _remove_partial(directory: str, step: int, patience: float = 5.0) -> None:
    """Deletes what a failed save of ``step`` left behind (orbax's temporary directory, or a
    committed step without its digest). Orbax's writer threads may still be finishing when
    the error surfaces, so this retries until nothing of the step is left (at most
    ``patience`` seconds)."""
    import time

    deadline = time.monotonic() + patience
    while True:
        left = [n for n in os.listdir(directory)
                if n == str(step) or n.startswith(f"{step}.orbax-checkpoint-tmp")]
        for name in left:
            shutil.rmtree(os.path.join(directory, name), ignore_errors=True)
        if not left or time.monotonic() > deadline:
            return
        time.sleep(0.1)


def _restore(manager, directory: str, step: int, args):
    """manager.restore, with orbax's and tensorstore's read errors as CorruptCheckpointError."""
    try:
        return manager.restore(step, args=args)
    except Exception as e:  # noqa: BLE001 - orbax/tensorstore raise many kinds
        raise CorruptCheckpointError(
            f"checkpoint {directory!r} step {step} cannot be read ({type(e).__name__}: "
            f"{str(e).splitlines()[0][:160] if str(e) else ''})") from e


def read_metadata(directory: str, step: Optional[int] = None) -> dict:
    """The JSON metadata of checkpoint ``step`` (default: the latest)."""
    step = verify_checkpoint(directory, step)
    try:
        with _manager(directory, read_only=True) as m:
            out = m.restore(step, args=ocp.args.Composite(metadata=ocp.args.JsonRestore()))
    except Exception as e:  # noqa: BLE001 - orbax/tensorstore raise many kinds
        raise CorruptCheckpointError(f"checkpoint {directory!r} step {step}: its metadata "
                                     f"cannot be read ({type(e).__name__})") from e
    meta = dict(out.get("metadata") or {})
    if meta.get("format") != FORMAT:
        raise ValueError(f"checkpoint {directory!r} step {step} has format "
                         f"{meta.get('format')!r}, expected {FORMAT!r}")
    return meta


def load_checkpoint(directory: str, step: Optional[int] = None, *, target: Any = None,
                    sharding=None) -> tuple[Any, dict]:
    """Loads checkpoint ``step`` (default: the latest) from ``directory``.

    Args:
      directory: a checkpoint root written by ``save_checkpoint`` / ``train``.
      step: which step; None for the latest.
      target: None, or a ``TrainState`` whose leaves are arrays or ``jax.ShapeDtypeStruct``
        (e.g. ``jax.eval_shape`` of the initial state), giving the structure of the optimizer
        state and where to place the arrays (each leaf's ``sharding``; else ``sharding``).
      sharding: placement for leaves without one (default: the first device).

    Returns:
      (state, metadata). With a target: a ``TrainState``. Without: a dict
      ``{"ema_params": ..., "train_state": {"params", "opt_state" (list of leaves), "step"}}``
      (``train_state`` only for training checkpoints).

    Raises:
      FileNotFoundError: no such checkpoint.
      ValueError: a target is given but the checkpoint holds no training state, or the shapes
        of the stored arrays differ from the target's (the mismatching entries are named).
    """
    from diffplan.train import TrainState

    step = _resolve_step(directory, step)
    sharding = sharding or jax.sharding.SingleDeviceSharding(jax.devices()[0])
    metadata = read_metadata(directory, step)  # verifies the digest
    with _manager(directory, read_only=True) as m:
        try:
            item_meta = m.item_metadata(step)
        except Exception as e:  # noqa: BLE001
            raise CorruptCheckpointError(f"checkpoint {directory!r} step {step}: its array "
                                         f"metadata cannot be read ({type(e).__name__})") from e
        has_train = metadata.get("kind") == "train"
        if target is None:
            items = {"ema_params": ocp.args.StandardRestore(
                _abstract_from_metadata(item_meta["ema_params"], sharding))}
            if has_train:
                items["train_state"] = ocp.args.StandardRestore(
                    _abstract_from_metadata(item_meta["train_state"], sharding))
            out = _restore(m, directory, step, ocp.args.Composite(**items))
            result = {"ema_params": out["ema_params"]}
            if has_train:
                ts = dict(out["train_state"])
                ts["opt_state"] = [ts["opt_state"][k] for k in sorted(ts["opt_state"])]
                result["train_state"] = ts
            return result, metadata

        if not isinstance(target, TrainState):
            raise ValueError(f"target must be a TrainState (or None), got {type(target).__name__}")
        if not has_train:
            raise ValueError(f"checkpoint {directory!r} step {step} is an evaluation checkpoint "
                             "(EMA params only) and holds no optimizer state to resume from")
        abstract = _abstract_like(target, sharding)
        opt_leaves, opt_def = jax.tree_util.tree_flatten(abstract.opt_state)
        ts_target = {"params": abstract.params, "opt_state": _flatten_opt_state(opt_leaves),
                     "step": jax.ShapeDtypeStruct((), jnp.int32, sharding=abstract.step.sharding)}
        stored_ts = getattr(item_meta["train_state"], "tree", item_meta["train_state"])
        stored_ema = getattr(item_meta["ema_params"], "tree", item_meta["ema_params"])
        problems = (compare_param_shapes(stored_ts["params"], ts_target["params"])
                    + compare_param_shapes(stored_ema, abstract.ema_params, "EMA parameter")
                    + compare_param_shapes(stored_ts["opt_state"], ts_target["opt_state"],
                                           "optimizer-state leaf"))
        if problems:
            raise ValueError(f"checkpoint {directory!r} step {step} does not match the target "
                             "state: " + "; ".join(problems))
        out = _restore(m, directory, step, ocp.args.Composite(
            ema_params=ocp.args.StandardRestore(abstract.ema_params),
            train_state=ocp.args.StandardRestore(ts_target)))
    ts = out["train_state"]
    opt_state = jax.tree_util.tree_unflatten(
        opt_def, [ts["opt_state"][k] for k in sorted(ts["opt_state"])])
    state = TrainState(params=ts["params"], ema_params=out["ema_params"], opt_state=opt_state,
                       step=ts["step"])
    return state, metadata


# --------------------------------------------------------------------------- evaluation

def _build_model(metadata: dict, config: Any):
    """Instantiates the stored model class with ``config`` (object or dict)."""
    try:
        model_cls = _import_path(metadata["model_class"])
    except Exception as e:  # noqa: BLE001 - report any import problem the same way
        raise ValueError(f"cannot import the checkpoint's model class "
                         f"{metadata.get('model_class')!r} ({e}); pass model=...") from e
    if isinstance(config, Mapping):
        try:
            cfg_cls = _import_path(metadata["model_config_class"])
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"cannot import the checkpoint's model config class "
                             f"{metadata.get('model_config_class')!r} ({e}); pass the config "
                             "object or model=...") from e
        config = cfg_cls.from_dict(dict(config))
    return model_cls(config)


def abstract_params(model, input_shapes: Mapping[str, Any]) -> Any:
    """``jax.eval_shape`` of ``model.init(...)["params"]`` for the given input shapes."""
    x_shape = tuple(input_shapes["x"])
    tok_shape = tuple(input_shapes["tokens"])

    def init():
        x = jnp.zeros(x_shape, jnp.float32)
        t = jnp.zeros(x_shape[:1], jnp.int32)
        tok = jnp.zeros(tok_shape, jnp.int32)
        return model.init(jax.random.PRNGKey(0), x, t, tok)["params"]

    return jax.eval_shape(init)


def load_params_for_eval(directory: str, model_config_expected: Any = None, *, model=None,
                         step: Optional[int] = None, sharding=None) -> tuple[Any, dict]:
    """The EMA parameters and metadata of a training or evaluation checkpoint.

    Args:
      directory: a checkpoint root (a training ``out_dir`` or an exported one).
      model_config_expected: optional model config (object with ``to_dict()`` or dict). If
        given, the stored model config must equal it, and the stored parameter shapes must
        equal those of an abstract init (``jax.eval_shape``) of the model built from it.
      model: optional flax module to check the parameter shapes against (default: the stored
        model class instantiated with ``model_config_expected``).
      step: which checkpoint (default: the latest).
      sharding: where to place the arrays (default: the first device).

    Returns:
      (ema_params, metadata): the ``params`` collection (use as ``{"params": ema_params}``).

    Raises:
      FileNotFoundError: no checkpoint in ``directory``.
      ValueError: the stored model config or parameter shapes differ (the differences are
        named in the message).
    """
    raw, metadata = load_checkpoint(directory, step, sharding=sharding)
    params = raw["ema_params"]
    if model_config_expected is not None:
        diffs = diff_dicts(metadata.get("model_config", {}),
                           config_to_dict(model_config_expected))
        if diffs:
            raise ValueError(f"model config mismatch for checkpoint {directory!r} "
                             f"(step {metadata['step']}): " + "; ".join(diffs))
    if model is None and model_config_expected is not None:
        model = _build_model(metadata, model_config_expected)
    if model is not None:
        if "input_shapes" not in metadata:
            raise ValueError(f"checkpoint {directory!r} metadata has no input_shapes; cannot "
                             "check parameter shapes")
        expected = abstract_params(model, metadata["input_shapes"])
        problems = compare_param_shapes(params, expected)
        if problems:
            raise ValueError(f"parameter shape mismatch for checkpoint {directory!r} "
                             f"(step {metadata['step']}): " + "; ".join(problems))
    return params, metadata


def export_eval_checkpoint(train_dir: str, out_dir: str, *, step: Optional[int] = None,
                           overwrite: bool = False) -> str:
    """Writes the EMA params + metadata of a training checkpoint as a small eval checkpoint.

    Args:
      train_dir: a training checkpoint root.
      out_dir: destination checkpoint root (e.g. ``checkpoints/p_mo2g``).
      step: which training step (default: the latest).
      overwrite: if ``out_dir`` already holds checkpoints, delete them first (otherwise a
        ValueError).

    Returns:
      The path of the written step directory.
    """
    params, metadata = load_params_for_eval(train_dir, step=step)
    existing = all_steps(out_dir)
    if existing:
        if not overwrite:
            raise ValueError(f"{out_dir!r} already holds checkpoints {existing}; "
                             "pass overwrite=True to replace them")
        for s in existing:
            shutil.rmtree(os.path.join(out_dir, str(s)))
    meta = {k: v for k, v in metadata.items() if k not in ("kind", "format", "step")}
    meta["exported_from"] = {"directory": os.path.abspath(train_dir), "step": metadata["step"]}
    params = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float32)
                                    if np.issubdtype(np.asarray(x).dtype, np.floating)
                                    else np.asarray(x), params)
    return save_checkpoint(out_dir, metadata["step"], params, meta, max_to_keep=None)
