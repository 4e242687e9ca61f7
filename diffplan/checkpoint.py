"""Orbax checkpoints of any training-state pytree, and loading parameters for evaluation.

Layout: a checkpoint directory is an ``orbax.checkpoint.CheckpointManager`` root; each saved
step is a sub-directory named by the step number, written atomically (orbax writes to a
temporary directory and renames it on commit; then the digest below is written atomically)
and holding the items

    ema_params/   the evaluation parameters (the EMA of the ``params`` collection for the
                  denoiser, the network's params for the baselines), as saved
    train_state/  only in training checkpoints: the whole training state, any pytree, stored as
                  nested dicts keyed by its key path (``{"params": ..., "opt_state": {"0":
                  {"mu": ...}}, "step": ...}``) and restored onto the caller's target structure
    metadata/     JSON: {"format", "kind": "train" | "eval", "step", "model_config",
                  "model_config_class", "model_class", "train_config", "extra",
                  "input_shapes", ...}
    diffplan_digest.json   SHA-256 of every other file of the step

Other files may live beside the step directories (``metrics.jsonl``, ``tb/``, ``config.json``):
the manager only looks at numerically named sub-directories. ``export_eval_checkpoint`` writes
the small kind of checkpoint shipped in the repository (evaluation params + metadata only);
``load_params_for_eval`` reads both kinds. docs/checkpoints.md is the user's guide.

Formats: "diffplan-checkpoint/2" (written now) and "diffplan-checkpoint/1" differ only in the
layout of ``train_state/``: evaluation parameters of both load; the training state of a
format-1 checkpoint is refused (it cannot be resumed by this version).

Loading never imports what a checkpoint names: a network is built from the registry of
``diffplan.models`` or given by the caller (``model=``).
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from typing import Any, Mapping, Optional

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from diffplan import models

__all__ = [
    "FORMAT",
    "READABLE_FORMATS",
    "CorruptCheckpointError",
    "CheckpointWriteError",
    "verify_checkpoint",
    "save_checkpoint",
    "load_checkpoint",
    "latest_step",
    "all_steps",
    "SHIPPED_ROOT",
    "resolve_checkpoint",
    "read_metadata",
    "load_params_for_eval",
    "export_eval_checkpoint",
    "config_to_dict",
    "diff_dicts",
    "compare_param_shapes",
    "class_path",
    "abstract_params",
    "state_tree",
]

FORMAT = "diffplan-checkpoint/2"
READABLE_FORMATS = ("diffplan-checkpoint/1", FORMAT)
"""Format 1 stored the training state as {"params", "opt_state": its leaves, "step"}."""
MAX_TO_KEEP = 2
DIGEST_FILE = "diffplan_digest.json"
"""SHA-256 of every file of a saved step, written (atomically) once orbax has committed the
step; loading verifies it, so a truncated or altered file is reported instead of loading
silently wrong values (orbax alone does not notice a flipped byte in an array). It shows
integrity, not origin: see docs/checkpoints.md."""
EVAL_ITEM, STATE_ITEM, META_ITEM = "ema_params", "train_state", "metadata"

class_path = models.class_path


class CorruptCheckpointError(ValueError):
    """A checkpoint step exists but cannot be read back as it was written."""


class CheckpointWriteError(OSError):
    """A checkpoint could not be written (e.g. the disk is full); nothing of it was kept."""


# --------------------------------------------------------------------------- small helpers

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


def _other_processes() -> bool:
    """True in a multi-process run (``diffplan.distributed``); never starts JAX's backend."""
    return bool(jax.distributed.is_initialized()) and jax.process_count() > 1


def _manager(directory: str, *, read_only: bool = False,
             max_to_keep: Optional[int] = MAX_TO_KEEP) -> ocp.CheckpointManager:
    if read_only:
        max_to_keep = None
    extra = {}
    if _other_processes():
        # Multi-process runs have one writer (process 0, ``save_checkpoint``) and readers that
        # read on their own: each process's manager is a manager of that process alone (no
        # barriers with the others, which do not call it in step).
        me = jax.process_index()
        extra["multiprocessing_options"] = ocp.options.MultiprocessingOptions(
            primary_host=me, active_processes={me})
        if not read_only:
            os.makedirs(directory, exist_ok=True)
    options = ocp.CheckpointManagerOptions(
        max_to_keep=max_to_keep, enable_async_checkpointing=False, read_only=read_only,
        create=not read_only and not extra, **extra)
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


SHIPPED_ROOT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                            "checkpoints")
"""The repository's ``checkpoints/`` directory, beside the package: the shipped models."""


def resolve_checkpoint(directory: str) -> str:
    """Where the checkpoint ``directory`` is: the path as given (relative to the working
    directory) when it holds a checkpoint; else, for a relative path, the shipped one of that
    name found beside the package: ``"compile_gridworld"`` or
    ``"checkpoints/compile_gridworld"`` is ``SHIPPED_ROOT/compile_gridworld`` from any working
    directory. Raises FileNotFoundError with one line naming every place looked in."""
    candidates = [directory]
    if not os.path.isabs(directory):
        parts = os.path.normpath(directory).split(os.sep)
        if parts[0] == os.path.basename(SHIPPED_ROOT) and len(parts) > 1:
            parts = parts[1:]
        if parts[0] != os.pardir:
            candidates.append(os.path.join(SHIPPED_ROOT, *parts))
    for candidate in candidates:
        if latest_step(candidate) is not None:
            return candidate
    looked = " and ".join(repr(os.path.abspath(c)) for c in candidates)
    raise FileNotFoundError(f"no checkpoint in {directory!r} (looked in {looked})")


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



# --------------------------------------------------------------------------- pytree layout

def _key_name(entry: Any) -> str:
    for attr in ("key", "name", "idx"):  # DictKey / FlattenedIndexKey, GetAttrKey, SequenceKey
        if hasattr(entry, attr):
            return str(getattr(entry, attr))
    return str(entry)


def _leaf_paths(tree: Any) -> tuple[list[tuple[str, ...]], list[Any], Any]:
    """(path of every leaf as a tuple of names, the leaves, the tree's structure)."""
    with_path, treedef = jax.tree_util.tree_flatten_with_path(tree)
    paths = [tuple(_key_name(k) for k in path) or ("value",) for path, _ in with_path]
    return paths, [leaf for _, leaf in with_path], treedef


def state_tree(tree: Any) -> dict:
    """A pytree as nested dicts keyed by the names of its key path (how ``train_state/`` is
    stored): a ``TrainState`` becomes ``{"params": {...}, "ema_params": {...}, "opt_state":
    {"0": {"count": ..., "mu": {...}, ...}, ...}, "step": ...}``. Raises ValueError when two
    leaves would get the same path (e.g. a dict with keys 1 and "1")."""
    paths, leaves, _ = _leaf_paths(tree)
    out: dict = {}
    for path, leaf in zip(paths, leaves):
        node = out
        for name in path[:-1]:
            node = node.setdefault(name, {})
            if not isinstance(node, dict):
                raise ValueError(f"state entry {'/'.join(path)} collides with a leaf")
        if path[-1] in node:
            raise ValueError(f"two leaves of the state are both stored as {'/'.join(path)}")
        node[path[-1]] = leaf
    return out


def _get_path(tree: Mapping, path: tuple[str, ...]) -> Any:
    for name in path:
        tree = tree[name]
    return tree


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
        return jax.ShapeDtypeStruct(tuple(np.shape(x)), np.dtype(x.dtype), sharding=sharding)
    return jax.tree_util.tree_map(to_sds, tree)


def _host(tree: Any) -> Any:
    """Host (numpy) copies: the arrays are small and replicated, and numpy arrays avoid
    orbax's replica-parallel slicing of multi-device arrays, which breaks with jax 0.6.2
    (orbax 0.12.8 uses ``jax.sharding.set_mesh`` as a context manager)."""
    return jax.tree_util.tree_map(np.asarray, jax.device_get(tree))


# --------------------------------------------------------------------------- save / load

def save_checkpoint(directory: str, step: int, params: Any, metadata: Mapping[str, Any], *,
                    train_state: Any = None, max_to_keep: Optional[int] = MAX_TO_KEEP) -> str:
    """Atomically writes checkpoint ``step`` into ``directory``; keeps the newest ``max_to_keep``.

    Args:
      directory: the checkpoint root (created if missing).
      step: the step number (a new one: saving an existing step raises ValueError).
      params: the evaluation parameters (any pytree of arrays; what
        ``load_params_for_eval`` returns).
      metadata: JSON-serialisable dict (configs etc.); ``format``, ``kind`` and ``step`` are
        added.
      train_state: the whole training state to resume from (any pytree of arrays; restored
        with ``load_checkpoint(target=...)``), or None for an evaluation checkpoint.
      max_to_keep: older steps beyond this many are deleted (None: keep all).

    Returns:
      The path of the step directory. In a multi-process run (``diffplan.distributed``) every
      process calls it and only process 0 writes (the state is replicated, so its copy is the
      whole state); every process returns once the step is committed (a barrier).
    """
    step = int(step)
    if step < 0:
        raise ValueError(f"step must be >= 0, got {step}")
    if not _other_processes():
        return _save(directory, step, params, metadata, train_state, max_to_keep)
    from diffplan import distributed

    try:
        if jax.process_index() == 0:
            return _save(directory, step, params, metadata, train_state, max_to_keep)
        return os.path.join(os.path.abspath(directory), str(step))
    finally:
        distributed.barrier(f"diffplan checkpoint {os.path.abspath(directory)} {step}")


def _save(directory: str, step: int, params: Any, metadata: Mapping[str, Any],
          train_state: Any, max_to_keep: Optional[int]) -> str:
    meta = dict(_json_normalise(dict(metadata)))
    items = {EVAL_ITEM: ocp.args.StandardSave(_host(params))}
    if train_state is not None:
        items[STATE_ITEM] = ocp.args.StandardSave(state_tree(_host(train_state)))
    meta["kind"] = "eval" if train_state is None else "train"
    meta["format"] = FORMAT
    meta["step"] = step
    items[META_ITEM] = ocp.args.JsonSave(meta)
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


def read_metadata(directory: str, step: Optional[int] = None) -> dict:
    """The JSON metadata of checkpoint ``step`` (default: the latest), after verifying the
    step's digest. Raises ValueError for a format this version cannot read."""
    step = verify_checkpoint(directory, step)
    try:
        with _manager(directory, read_only=True) as m:
            out = m.restore(step, args=ocp.args.Composite(**{META_ITEM: ocp.args.JsonRestore()}))
    except Exception as e:  # noqa: BLE001 - orbax/tensorstore raise many kinds
        raise CorruptCheckpointError(f"checkpoint {directory!r} step {step}: its metadata "
                                     f"cannot be read ({type(e).__name__})") from e
    meta = dict(out.get(META_ITEM) or {})
    if meta.get("format") not in READABLE_FORMATS:
        raise ValueError(f"checkpoint {directory!r} step {step} has format "
                         f"{meta.get('format')!r}, expected one of {READABLE_FORMATS}")
    return meta


def _restore(directory: str, step: int, targets: Mapping[str, Any], sharding) -> dict:
    """The items ``targets`` names (item -> ShapeDtypeStruct tree, or None: as stored) of
    checkpoint ``step``; orbax's and tensorstore's read errors as CorruptCheckpointError."""
    with _manager(directory, read_only=True) as m:
        try:
            item_meta = m.item_metadata(step)
        except Exception as e:  # noqa: BLE001
            raise CorruptCheckpointError(f"checkpoint {directory!r} step {step}: its array "
                                         f"metadata cannot be read ({type(e).__name__})") from e
        args = {name: ocp.args.StandardRestore(
                    _abstract_from_metadata(item_meta[name], sharding) if target is None
                    else target)
                for name, target in targets.items()}
        try:
            return m.restore(step, args=ocp.args.Composite(**args))
        except Exception as e:  # noqa: BLE001 - orbax/tensorstore raise many kinds
            raise CorruptCheckpointError(
                f"checkpoint {directory!r} step {step} cannot be read ({type(e).__name__}: "
                f"{str(e).splitlines()[0][:160] if str(e) else ''})") from e


def _stored_shapes(directory: str, step: int, item: str) -> Any:
    with _manager(directory, read_only=True) as m:
        try:
            meta = m.item_metadata(step)[item]
        except Exception as e:  # noqa: BLE001
            raise CorruptCheckpointError(f"checkpoint {directory!r} step {step}: its array "
                                         f"metadata cannot be read ({type(e).__name__})") from e
    return getattr(meta, "tree", meta)


def _check_train_state(directory: str, metadata: Mapping[str, Any]) -> None:
    step = metadata["step"]
    if metadata.get("kind") != "train":
        raise ValueError(f"checkpoint {directory!r} step {step} is an evaluation checkpoint "
                         "(evaluation params only) and holds no training state to resume from")
    if metadata.get("format") != FORMAT:
        raise ValueError(f"checkpoint {directory!r} step {step} holds a training state in the "
                         f"older layout of {metadata.get('format')!r}, which this version "
                         "cannot resume (its evaluation params still load); start a new run")


def load_checkpoint(directory: str, step: Optional[int] = None, *, target: Any = None,
                    sharding=None) -> tuple[Any, dict]:
    """Loads checkpoint ``step`` (default: the latest) from ``directory``.

    Args:
      directory: a checkpoint root written by ``save_checkpoint``.
      step: which step; None for the latest.
      target: None, or a pytree of the training state's structure whose leaves are arrays
        or ``jax.ShapeDtypeStruct`` (e.g. ``jax.eval_shape`` of the initial state), giving
        the structure, shapes and where to place the arrays (each leaf's ``sharding``; else
        ``sharding``).
      sharding: placement for leaves without one (default: the first device).

    Returns:
      (state, metadata). With a target: the training state, of the target's structure.
      Without: a dict ``{"ema_params": ..., "train_state": nested dicts (see
      ``state_tree``)}`` (``train_state`` only for training checkpoints).

    Raises:
      FileNotFoundError: no such checkpoint.
      ValueError: a target is given but the checkpoint holds no training state (or one of an
        older format), or the stored arrays differ from the target's (the mismatching entries
        are named).
    """
    step = _resolve_step(directory, step)
    sharding = sharding or jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    metadata = read_metadata(directory, step)  # verifies the digest
    if target is None:
        names = [EVAL_ITEM]
        if metadata.get("kind") == "train":
            _check_train_state(directory, metadata)
            names.append(STATE_ITEM)
        out = _restore(directory, step, {name: None for name in names}, sharding)
        return {name: out[name] for name in names}, metadata

    _check_train_state(directory, metadata)
    abstract = _abstract_like(target, sharding)
    paths, leaves, treedef = _leaf_paths(abstract)
    nested = state_tree(abstract)
    problems = compare_param_shapes(_stored_shapes(directory, step, STATE_ITEM), nested,
                                    "state entry")
    if problems:
        raise ValueError(f"checkpoint {directory!r} step {step} does not match the target "
                         "state: " + "; ".join(problems))
    out = _restore(directory, step, {STATE_ITEM: nested}, sharding)[STATE_ITEM]
    return jax.tree_util.tree_unflatten(treedef, [_get_path(out, p) for p in paths]), metadata


# --------------------------------------------------------------------------- evaluation

def abstract_params(model, input_shapes: Mapping[str, Any]) -> Any:
    """``jax.eval_shape`` of ``model.init(...)["params"]`` for the stored input shapes (the
    inputs of the model's registered spec, ``diffplan.models.example_inputs``)."""
    inputs = models.example_inputs(model, input_shapes)

    def init():
        return model.init(jax.random.PRNGKey(0),
                          *(jnp.zeros(a.shape, a.dtype) for a in inputs))["params"]

    return jax.eval_shape(init)


def load_params_for_eval(directory: str, model_config_expected: Any = None, *, model=None,
                         step: Optional[int] = None, sharding=None) -> tuple[Any, dict]:
    """The evaluation parameters and metadata of a training or evaluation checkpoint.

    Args:
      directory: a checkpoint root (a training ``out_dir`` or an exported one).
      model_config_expected: optional model config (object with ``to_dict()`` or dict). If
        given, the stored model config must equal it, and the stored parameter shapes must
        equal those of an abstract init (``jax.eval_shape``) of the network built from it:
        the registered network the checkpoint names (``diffplan.models``; any other is
        refused before anything is imported), unless ``model`` is given.
      model: optional flax module to check the parameter shapes against.
      step: which checkpoint (default: the latest).
      sharding: where to place the arrays (default: the first device).

    Returns:
      (params, metadata): the ``params`` collection (use as ``{"params": params}``).

    Raises:
      FileNotFoundError: no checkpoint in ``directory``.
      ValueError: the stored model config or parameter shapes differ (the differences are
        named in the message), or the checkpoint names an unregistered network.
    """
    step = _resolve_step(directory, step)
    sharding = sharding or jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    metadata = read_metadata(directory, step)  # verifies the digest
    if model_config_expected is not None:
        diffs = diff_dicts(metadata.get("model_config", {}),
                           config_to_dict(model_config_expected))
        if diffs:
            raise ValueError(f"model config mismatch for checkpoint {directory!r} "
                             f"(step {step}): " + "; ".join(diffs))
        if model is None:
            model = models.build_model(metadata, model_config_expected)
    params = _restore(directory, step, {EVAL_ITEM: None}, sharding)[EVAL_ITEM]
    if model is not None:
        if "input_shapes" not in metadata:
            raise ValueError(f"checkpoint {directory!r} metadata has no input_shapes; cannot "
                             "check parameter shapes")
        expected = abstract_params(model, metadata["input_shapes"])
        problems = compare_param_shapes(params, expected)
        if problems:
            raise ValueError(f"parameter shape mismatch for checkpoint {directory!r} "
                             f"(step {step}): " + "; ".join(problems))
    return params, metadata


def export_eval_checkpoint(train_dir: str, out_dir: str, *, step: Optional[int] = None,
                           overwrite: bool = False) -> str:
    """Writes the evaluation params + metadata of a training checkpoint as a small eval
    checkpoint (float arrays as float32).

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
