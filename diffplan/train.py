"""The one training loop (``fit``), and the denoiser's training (``train``), a thin wrapper.

``fit(step_fn, init_fn, ...)`` runs any ``TrainState``-like pytree (fields ``step`` and
``ema_params``, the parameters evaluated) through ``state, metrics = step_fn(state, key,
data)`` with the key of step i a function of (seed, i) only (``step_key``), so a resumed run
computes exactly what an uninterrupted one would. It checkpoints (``diffplan.checkpoint``:
atomic, digests) every ``checkpoint_every`` steps and at the end, resumes from the newest
readable checkpoint in ``out_dir`` (a damaged one is moved aside; one of other settings is
refused, ``ConfigMismatchError``), logs ``out_dir/metrics.jsonl`` (and TensorBoard on request),
stops on a non-finite metric (``NonFiniteLossError``) and shows a progress bar. The denoiser
(``train``) and the baselines (BC, CQL, the DD-style planner) all train through it.

``train`` builds the denoiser's step (``diffplan.losses``: the masked denoising loss, AdamW,
EMA; ``diffplan.train_state``: config, state, keys), data parallel over all devices
(``diffplan.sharding``), with the batch of step i drawn as ``batch_fn(batch key, batch_size)``
from that step's key, and optional validation on fixed batches.
"""
from __future__ import annotations

import functools
import json
import os
import time
import warnings
from typing import Any, Callable, Mapping, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from diffplan import checkpoint as ckpt
from diffplan import distributed
from diffplan import sharding as shd
from diffplan.losses import (Batch, check_batch, diffusion_loss, make_train_step, make_val_loss,
                             with_sentences)
from diffplan.train_state import (PREDICTIONS, TrainConfig, TrainState, hashable,
                                  init_train_state, lr_schedule, make_optimizer, root_keys,
                                  step_key)

__all__ = [
    # the loop
    "fit", "FitResult", "run_metadata", "mean_metrics",
    "NonFiniteLossError", "OutputWriteError", "ConfigMismatchError",
    # the denoiser's training
    "train", "TrainResult", "checkpoint_metadata", "draw_batch",
    # re-exported from diffplan.train_state and diffplan.losses
    "Batch", "TrainConfig", "TrainState", "PREDICTIONS", "lr_schedule", "make_optimizer",
    "diffusion_loss", "init_train_state", "make_train_step", "step_key",
]

SYNC_EVERY = 16
"""The host checks for non-finite metrics (and bounds the queued steps) this often."""
RESUMABLE_FIELDS = ("checkpoint_every", "log_every", "val_every", "val_batches")
"""Train-config fields that do not change the computation: they may differ when resuming."""


class NonFiniteLossError(RuntimeError):
    """Training produced a non-finite loss (or other metric); nothing after the last good
    checkpoint was saved. Attributes: ``step`` (1-based count of the first failing step),
    ``last_checkpoint_step`` (None if none)."""

    def __init__(self, message: str, step: int, last_checkpoint_step: Optional[int]):
        super().__init__(message)
        self.step = step
        self.last_checkpoint_step = last_checkpoint_step


class OutputWriteError(OSError):
    """Training could not write its metrics log (e.g. the disk is full); the checkpoints saved
    before are intact."""


class ConfigMismatchError(ValueError):
    """``out_dir`` holds a checkpoint written with different configs than the requested ones."""


class FitResult(NamedTuple):
    """What ``fit`` returns: the final state, the seconds of optimisation over all runs of this
    out_dir (resumes included), and the last metrics record of this call (None if none)."""

    state: Any
    wall_time: float
    last_record: Optional[dict]


class TrainResult(NamedTuple):
    """What ``train`` returns: the final state, the last logged training loss (mean over the
    last logging window; None if no step ran in this call), and the last metrics record."""

    state: TrainState
    final_loss: Optional[float]
    last_metrics: Optional[dict]

    @property
    def ema_params(self):
        return self.state.ema_params


# ------------------------------------------------------------------------------- metadata

def run_metadata(model, model_config, train_config: Mapping, input_shapes: Mapping,
                 extra: Optional[Mapping] = None) -> dict:
    """The checkpoint metadata of a run (what resuming compares, what loading reads):
    ``{"model_config": dict, "model_config_class": "module:Class" (None for a dict config),
    "model_class": "module:Class" (the key of ``diffplan.models``), "train_config": dict,
    "extra": dict, "input_shapes": {name: [1, ...]}}``. ``model_config`` None: ``model.config``.
    """
    if model_config is None:
        model_config = getattr(model, "config", None)
    try:
        return ckpt.config_to_dict({
            "model_config": ckpt.config_to_dict(model_config),
            "model_config_class": (None if model_config is None
                                   or isinstance(model_config, Mapping)
                                   else ckpt.class_path(model_config)),
            "model_class": ckpt.class_path(model),
            "train_config": dict(train_config),
            "extra": dict(extra or {}),
            "input_shapes": dict(input_shapes),
        })
    except TypeError as e:
        raise ValueError(f"configs / extra metadata must be JSON-serialisable: {e}") from e


def checkpoint_metadata(model, model_config, train_config: TrainConfig, init_batch: Batch,
                        extra_metadata: Optional[Mapping[str, Any]] = None) -> dict:
    """The metadata ``train`` stores with every checkpoint: ``run_metadata`` with the
    denoiser's input shapes ``{"x": [1, H, W, C+G], "tokens": [1, L]}`` -- enough for
    ``diffplan.checkpoint.load_params_for_eval`` to rebuild the model and check shapes."""
    metadata = run_metadata(
        model, model_config, train_config.to_dict(),
        {"x": [1, *map(int, init_batch.x0.shape[1:])],
         "tokens": [1, *map(int, init_batch.tokens.shape[1:])]}, extra_metadata)
    G = train_config.num_gen_channels
    if metadata["model_config"].get("num_gen_channels", G) != G:
        raise ValueError(f"model config num_gen_channels="
                         f"{metadata['model_config']['num_gen_channels']} != train config "
                         f"num_gen_channels={G}")
    return metadata


# ------------------------------------------------------------------------------- resume

def _check_resume(meta: dict, requested: dict, out_dir: str) -> None:
    problems = []
    problems += ckpt.diff_dicts(meta.get("model_config", {}), requested["model_config"],
                                "model_config")
    stored_tc = {k: v for k, v in meta.get("train_config", {}).items()
                 if k not in RESUMABLE_FIELDS}
    req_tc = {k: v for k, v in requested["train_config"].items() if k not in RESUMABLE_FIELDS}
    problems += ckpt.diff_dicts(stored_tc, req_tc, "train_config")
    problems += ckpt.diff_dicts(meta.get("extra", {}), requested["extra"], "extra")
    problems += ckpt.diff_dicts(meta.get("input_shapes", {}), requested["input_shapes"],
                                "input_shapes")
    problems += ckpt.diff_dicts(meta.get("model_class"), requested["model_class"], "model_class")
    if problems:
        raise ConfigMismatchError(
            f"{out_dir!r} holds a checkpoint (step {meta.get('step')}) written with different "
            "settings than requested, so it cannot be resumed: " + "; ".join(problems)
            + ". Use a new out_dir or the stored settings.")


def _resume(out_dir: str, init_fn: Callable, metadata: dict, repl):
    """(step, state, stored metadata) of the newest readable checkpoint in out_dir, or
    (None, None, None) if there is none. A corrupted newer checkpoint is reported, moved aside
    (renamed ``corrupt-<step>-<time>``) and the previous one is used."""
    steps = ckpt.all_steps(out_dir)
    damaged = []
    for step in reversed(steps):
        try:
            stored = ckpt.read_metadata(out_dir, step)
            _check_resume(stored, ckpt.config_to_dict(metadata), out_dir)
            abstract = jax.eval_shape(init_fn)
            abstract = jax.tree_util.tree_map(
                lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=repl), abstract)
            state, _ = ckpt.load_checkpoint(out_dir, step, target=abstract)
        except ckpt.CorruptCheckpointError as e:
            damaged.append((step, e))
            continue
        if int(state.step) != step:
            raise ValueError(f"checkpoint {step} in {out_dir!r} holds step {int(state.step)}")
        for bad, error in damaged:
            aside = os.path.join(out_dir, f"corrupt-{bad}-{int(time.time())}")
            if distributed.is_writer():  # one process moves it (multi-process runs)
                os.replace(os.path.join(out_dir, str(bad)), aside)
            warnings.warn(f"{error}; moved it to {aside} and resumed from step {step}",
                          stacklevel=3)
        return step, state, stored
    if damaged:
        raise ckpt.CorruptCheckpointError(
            f"no readable checkpoint in {out_dir!r} (" + "; ".join(str(e) for _, e in damaged)
            + "): delete the directory to start over")
    return None, None, None


def _truncate_metrics(path: str, after_step: int) -> None:
    """Drops records with step > after_step (logged before a crash, replayed on resume)."""
    if not os.path.exists(path):
        return
    keep = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue  # a torn last line from a crash
            if int(rec.get("step", 0)) <= after_step:
                keep.append(line)
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write("".join(k + "\n" for k in keep))
    os.replace(tmp, path)


# ------------------------------------------------------------------------------- the loop

def mean_metrics(values: list[dict]) -> dict:
    """A logging window's record: the mean of every metric over the window's steps (values:
    one dict of host scalars per step)."""
    return {k: float(np.mean([v[k] for v in values])) for k in values[0]}


class _Window:
    """Per-step metrics (device scalars) since the last record; fetched to the host only at
    check points, so the loop does not wait for the device every step."""

    def __init__(self):
        self.pending = []  # (step, metrics on device)
        self.host = []  # (step, metrics on host)

    def add(self, step, metrics):
        self.pending.append((step, metrics))

    def fetch(self) -> Optional[tuple[int, list[str]]]:
        """(first step with a non-finite metric, their names), or None."""
        if self.pending:
            values = jax.device_get([m for _, m in self.pending])
            self.host += [(s, v) for (s, _), v in zip(self.pending, values)]
            self.pending = []
        for s, v in self.host:
            bad = sorted(k for k, x in v.items() if not np.all(np.isfinite(x)))
            if bad:
                return s, bad
        return None

    def take(self) -> list[dict]:
        values = [v for _, v in self.host]
        self.host = []
        return values


def _tensorboard(out_dir: str):
    try:
        from tensorboardX import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(os.path.join(out_dir, "tb"))


def fit(step_fn: Callable, init_fn: Callable, *, steps: int, seed: int, out_dir: str,
        metadata: Mapping, data: Any = None, checkpoint_every: int = 1000,
        log_every: int = 100, progress: bool = True, desc: str = "train", jit: bool = True,
        mesh=None, summarize: Callable[[list], dict] = mean_metrics,
        validate: Optional[Callable[[Any], Mapping[str, float]]] = None,
        validate_every: int = 0, callback: Optional[Callable[[int, Optional[dict]], None]] = None,
        tensorboard: bool = False) -> FitResult:
    """Runs ``state, metrics = step_fn(state, step_key(seed, i), data)`` for i from
    ``state.step`` to ``steps``, resuming from ``out_dir``.

    Args:
      step_fn: pure; metrics a dict of scalars with "loss".
      init_fn: ``init_fn() -> the initial state`` (a ``TrainState``, or any pytree with
        ``step`` and ``ema_params``); also the structure restored when resuming.
      steps: the total number of steps.
      seed: the keys' root (``step_key``).
      out_dir: checkpoints, ``config.json`` (the metadata), ``metrics.jsonl``, ``tb/``.
      metadata: JSON-serialisable run metadata (``run_metadata``), stored with every
        checkpoint; resuming requires the stored one to match (up to ``RESUMABLE_FIELDS``).
      data: a pytree of arrays passed to every step (e.g. a replay buffer; an argument, not a
        constant of the compiled step).
      checkpoint_every, log_every: a checkpoint (``state.ema_params`` for evaluation, the
        whole state to resume) / a metrics record every this many steps and at the end.
      progress, desc: a tqdm bar named ``desc``.
      jit: compile ``step_fn`` (False: it is already a composition of jitted functions).
      mesh: the states live replicated on this ``diffplan.sharding`` mesh (default: all
        devices).
      summarize: a record's metrics from the window's per-step host values (default: means).
      validate, validate_every: ``validate(state) -> {name: value}`` joins the record every
        this many steps and at the end (0: never).
      callback: ``callback(step, last record or None)`` after every record and checkpoint
        (once that step's checkpoint is written); it may raise to stop training.
      tensorboard: also log to ``out_dir/tb`` when tensorboardX is importable.

    Returns:
      ``FitResult(state, wall_time, last_record)``; records: ``{"step", <summary>,
      "steps_per_sec", "wall_time", <validation>}``.

    Raises:
      ConfigMismatchError (a ValueError): ``out_dir`` holds a checkpoint of other settings.
      NonFiniteLossError: a metric became NaN/inf (found at most ``SYNC_EVERY`` steps later,
        and before any record or checkpoint; the last good checkpoint stays intact).
      OutputWriteError: ``metrics.jsonl`` cannot be written.
    """
    mesh = shd.data_mesh() if mesh is None else mesh
    repl = shd.replicated_sharding(mesh)
    os.makedirs(out_dir, exist_ok=True)
    last_ckpt, state, stored = _resume(out_dir, init_fn, metadata, repl)
    # Multi-process runs (diffplan.distributed): every process resumes from the same step of a
    # directory all of them see; process 0 alone writes the log, checkpoints and bar.
    distributed.agree(-1 if last_ckpt is None else last_ckpt,
                      f"the checkpoint step each process resumes from in {out_dir!r}")
    writes = distributed.is_writer()
    progress, tensorboard = progress and writes, tensorboard and writes
    wall_before = float(stored.get("wall_time", 0.0)) if stored else 0.0
    if state is None:
        state = shd.replicate(init_fn(), mesh)
    start = int(state.step)
    metrics_path = os.path.join(out_dir, "metrics.jsonl")
    if writes:
        with open(os.path.join(out_dir, "config.json"), "w") as f:
            json.dump(ckpt.config_to_dict(metadata), f, indent=2, sort_keys=True)
        _truncate_metrics(metrics_path, start)
    if start >= steps:
        return FitResult(state, wall_before, None)

    run_step = jax.jit(step_fn) if jit else step_fn
    data_root = shd.replicate(root_keys(seed)[1], mesh)
    writer = _tensorboard(out_dir) if tensorboard else None
    bar = None
    if progress:
        from diffplan.progress import bar as progress_bar
        bar = progress_bar(total=steps, initial=start, desc=desc, dynamic_ncols=True)
    t0 = time.perf_counter()
    t_last, step_last = t0, start
    window, record = _Window(), None

    def check_finite(done):
        found = window.fetch()
        if found is None:
            return
        bad, names = found
        where = (f"the last good checkpoint is step {last_ckpt} in {out_dir!r} (left intact)"
                 if last_ckpt is not None else "no checkpoint had been saved yet")
        raise NonFiniteLossError(
            f"{desc} stopped: non-finite loss or metrics ({', '.join(names)}) at step {bad} "
            f"(detected at step {done} of {steps}); {where}. Check the data and the learning "
            "rate.", bad, last_ckpt)

    try:
        for i in range(start, steps):
            state, metrics = run_step(state, jax.random.fold_in(data_root, i), data)
            done = i + 1
            window.add(done, metrics)
            is_last = done == steps
            do_log = done % log_every == 0 or is_last
            do_ckpt = done % checkpoint_every == 0 or is_last
            do_val = validate is not None and (done % validate_every == 0 or is_last)
            if bar is not None:
                bar.update(1)
            if not (do_log or do_ckpt or do_val) and (done - start) % SYNC_EVERY:
                continue
            check_finite(done)
            if do_log or do_val:
                now = time.perf_counter()
                record = {"step": done, **summarize(window.take()),
                          "steps_per_sec": (done - step_last) / max(now - t_last, 1e-9),
                          "wall_time": wall_before + now - t0}
                if do_val:
                    record.update(validate(state))
                t_last, step_last = time.perf_counter(), done
                if writes:
                    _append_record(metrics_path, record, last_ckpt)
                if writer is not None:
                    for k, v in record.items():
                        if k != "step":
                            writer.add_scalar(f"train/{k}", v, done)
                if bar is not None:
                    bar.set_postfix(loss=f"{record['loss']:.4f}",
                                    steps_s=f"{record['steps_per_sec']:.2f}")
            if do_ckpt:
                meta = dict(metadata, wall_time=wall_before + time.perf_counter() - t0)
                if record is not None and "loss" in record:
                    meta["last_loss"] = record["loss"]
                t_save = time.perf_counter()
                ckpt.save_checkpoint(out_dir, done, state.ema_params, meta, train_state=state)
                last_ckpt = done
                t_last += time.perf_counter() - t_save  # steps/s measures training only
            if callback is not None and (do_log or do_val or do_ckpt):
                callback(done, record)
    finally:
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.close()
    return FitResult(state, wall_before + time.perf_counter() - t0, record)


def _append_record(path: str, record: dict, last_ckpt: Optional[int]) -> None:
    try:
        with open(path, "a") as f:
            f.write(json.dumps(record) + "\n")
    except OSError as e:
        raise OutputWriteError(
            f"could not append to {path} ({e.strerror or e}); "
            + (f"the last good checkpoint is step {last_ckpt}" if last_ckpt is not None
               else "no checkpoint had been saved yet")) from e


# ------------------------------------------------------------------------------- the denoiser

def with_sentence_shapes(init_batch: Batch, sentences=None) -> Batch:
    """The shapes of the batch the network reads (:func:`with_sentences`): unchanged without a
    sentence table; with one, tokens (B, S) sentence ids become float32 (B, L, D)."""
    init_batch = Batch(*init_batch)
    if sentences is None:
        return init_batch
    if len(init_batch.tokens.shape) != 2:
        raise ValueError("with a sentence table, batch_fn's tokens are sentence ids (B, S), got "
                         f"shape {tuple(init_batch.tokens.shape)}")
    return init_batch._replace(tokens=jax.ShapeDtypeStruct(
        (init_batch.tokens.shape[0], sentences.max_tokens, sentences.dim), jnp.float32))


@functools.partial(jax.jit, static_argnames=("batch_fn", "batch_size", "mesh"))
def draw_batch(key, sentences=None, *, batch_fn, batch_size, mesh):
    """(batch, loss key) of a step from its key: ``batch_fn(batch key, batch_size)``, its
    sentence ids assembled from ``sentences`` (an argument, not a constant) when given."""
    batch_key, loss_key = jax.random.split(key)
    batch = with_sentences(Batch(*batch_fn(batch_key, batch_size)), sentences)
    batch = shd.constrain_batch(batch, mesh)
    return batch, shd.constrain_replicated(loss_key, mesh)


def _denoiser_summary(values: list[dict]) -> dict:
    """The mean loss (and its parts, when the step reports them) of the window, its last
    gradient norm and learning rate."""
    record = {k: float(np.mean([float(v[k]) for v in values]))
              for k in ("loss", "diffusion_loss", "token_loss") if k in values[0]}
    return {**record, "grad_norm": float(values[-1]["grad_norm"]), "lr": float(values[-1]["lr"])}


def train(model, model_config, train_config: TrainConfig, batch_fn: Callable, out_dir: str, *,
          init_batch: Optional[Batch] = None, progress: bool = True,
          extra_metadata: Optional[Mapping[str, Any]] = None,
          val_batch_fn: Optional[Callable] = None, mesh=None, tensorboard: bool = True,
          callback: Optional[Callable[[int, dict], None]] = None,
          sentences=None, fixed_params: Optional[Mapping[str, Any]] = None) -> TrainResult:
    """Trains the denoiser ``model`` through ``fit`` (resuming from ``out_dir``).

    Args:
      model: flax linen module, ``model.apply({"params": p}, x_t (B,H,W,C+G), t (B,),
        tokens (B,L)) -> eps (B,H,W,G)``.
      model_config: its config (object with ``to_dict()``/``from_dict()``, or a dict); stored
        in the checkpoints together with the classes of model and config.
      train_config: a ``TrainConfig``.
      batch_fn: pure, jit-able ``batch_fn(key, batch_size) -> Batch``; called inside ``jit``
        with the batch key of the step (a function of (seed, step) only).
      out_dir: where checkpoints, ``config.json``, ``metrics.jsonl`` and ``tb/`` go.
      init_batch: a Batch (arrays or ShapeDtypeStructs) giving the input shapes; default
        ``batch_fn(key, 1)`` evaluated abstractly (``jax.eval_shape``).
      progress: show a tqdm bar (loss, steps/s).
      extra_metadata: JSON-serialisable dict stored with the checkpoints (e.g. data settings);
        must match when resuming.
      val_batch_fn: like ``batch_fn`` for validation (default ``batch_fn`` with fixed
        validation keys); used when ``train_config.val_every > 0``.
      mesh: a ``diffplan.sharding.data_mesh`` (default: all devices).
      tensorboard: also log to ``out_dir/tb`` if tensorboardX is importable.
      callback: as for ``fit``.
      sentences: None, or a ``diffplan.instruction.SentenceTable`` (a denoiser on pretrained
        features, ``DenoiserConfig.context_dim`` > 0): ``batch_fn``'s ``tokens`` are then
        sentence ids int32 (B, S) (-1 = absent), assembled into features (B, L, D) inside the
        jitted step (``diffplan.instruction.assemble``); the table is the step's data
        argument (``fit``'s ``data``), never a constant of the compiled program.
      fixed_params: None, or {name: array}: the model's constants (``frozen_*`` parameters,
        e.g. the denoiser's ``frozen_cell_features``) written into the initial parameters
        (``diffplan.train_state.init_train_state``); a resumed run keeps its checkpoint's.

    Returns:
      ``TrainResult(state, final_loss, last_metrics)``.

    Raises:
      ConfigMismatchError (a ValueError): ``out_dir`` holds a checkpoint of other settings.
      NonFiniteLossError: the loss became NaN/inf (the last good checkpoint stays intact).
      ValueError: batch size not divisible by the number of devices, bad batch shapes.
    """
    cfg = train_config
    if not isinstance(cfg, TrainConfig):
        raise ValueError(f"train_config must be a TrainConfig, got {type(cfg).__name__}")
    mesh = shd.data_mesh() if mesh is None else mesh
    shd.check_divisible(cfg.batch_size, mesh)
    init_key, _, val_root = root_keys(cfg.seed)
    if init_batch is None:
        init_batch = jax.eval_shape(lambda k: batch_fn(k, 1), init_key)
    init_batch = with_sentence_shapes(Batch(*init_batch), sentences)
    if sentences is not None:
        sentences = shd.replicate(sentences, mesh)
    check_batch(jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype),
                                       init_batch), cfg.num_gen_channels)
    metadata = checkpoint_metadata(model, model_config, cfg, init_batch, extra_metadata)
    hashable(model, "model")
    draw = functools.partial(draw_batch, batch_fn=hashable(batch_fn, "batch_fn"),
                             batch_size=cfg.batch_size, mesh=mesh)
    train_step = make_train_step(model, cfg, mesh=mesh)

    def step(state, key, data):
        return train_step.placed(state, *draw(key, data))

    validate = None
    if cfg.val_every > 0:
        val_loss = make_val_loss(model, cfg, val_batch_fn or batch_fn, val_root, mesh=mesh)

        def validate(state):
            return {"val_loss": float(val_loss(state.ema_params, sentences))}

    init = functools.partial(init_train_state, model, cfg, init_batch, fixed=fixed_params)
    result = fit(step, init, steps=cfg.steps,
                 seed=cfg.seed, out_dir=out_dir, metadata=metadata, data=sentences,
                 checkpoint_every=cfg.checkpoint_every, log_every=cfg.log_every,
                 progress=progress, jit=False, mesh=mesh, summarize=_denoiser_summary,
                 validate=validate, validate_every=cfg.val_every, callback=callback,
                 tensorboard=tensorboard)
    last = result.last_record
    return TrainResult(result.state, None if last is None else last["loss"], last)
