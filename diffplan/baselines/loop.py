"""The optimisation loop of the non-diffusion baselines (BC, CQL, the DD-style planner's inverse
dynamics): ``step_fn`` repeated with checkpoints, resume and a progress bar.

The diffusion model of the DD-style planner trains with ``diffplan.train.train`` itself; this
loop reuses its pieces: the state is a ``diffplan.train.TrainState`` (params, ema_params --
the CQL target network, a copy of params for the others -- opt_state, step), saved with
``diffplan.checkpoint.save_checkpoint`` (digests, atomic writes) and resumed with the same
``diffplan.train._resume`` (a damaged newest checkpoint is moved aside, a checkpoint of other
settings refuses to resume). The key of step i is ``diffplan.train.step_key(seed, i)``, so a
resumed run computes exactly what an uninterrupted one would.
"""
from __future__ import annotations

import json
import math
import os
import time
from typing import Any, Callable, Mapping, NamedTuple

import jax
import numpy as np

from diffplan import checkpoint as ckpt
from diffplan import sharding as shd
from diffplan.train import NonFiniteLossError, _resume, _truncate_metrics, step_key

__all__ = ["fit", "FitResult", "run_metadata"]


class FitResult(NamedTuple):
    state: Any
    wall_time: float
    """Seconds of optimisation over all runs of this out_dir (resumes included)."""
    last_record: Any


def run_metadata(model, model_config, train_config: Mapping, input_shapes: Mapping,
                 extra: Mapping | None = None) -> dict:
    """The checkpoint metadata of a baseline run, in the layout ``diffplan.train`` uses (what
    ``_resume`` compares): model and config classes, train config, input shapes, extra."""
    return ckpt.config_to_dict({
        "model_config": ckpt.config_to_dict(model_config),
        "model_config_class": ckpt.class_path(model_config),
        "model_class": ckpt.class_path(model),
        "train_config": dict(train_config),
        "extra": dict(extra or {}),
        "input_shapes": dict(input_shapes),
    })


def fit(step_fn: Callable, init_fn: Callable, *, steps: int, seed: int, out_dir: str,
        metadata: Mapping, data: Any = None, checkpoint_every: int = 1000,
        log_every: int = 100, progress: bool = True, desc: str = "train") -> FitResult:
    """Runs ``state, metrics = step_fn(state, key, data)`` (jitted; metrics a dict of scalars
    with "loss") from step ``state.step`` to ``steps``, resuming from ``out_dir``.

    init_fn() -> the initial TrainState (also its structure when resuming). data: a pytree of
    arrays passed to every step (e.g. a replay buffer; an argument, not a constant of the
    compiled step). Checkpoints every ``checkpoint_every`` steps and at the end; metrics to
    ``out_dir/metrics.jsonl`` every ``log_every`` steps (means over the window). Raises
    NonFiniteLossError when a logged loss is not finite (nothing after the last checkpoint is
    saved) and diffplan.train.ConfigMismatchError when out_dir holds another run.
    """
    os.makedirs(out_dir, exist_ok=True)
    repl = shd.replicated_sharding(shd.data_mesh())
    last_ckpt, state, stored = _resume(out_dir, init_fn, metadata, repl)
    wall_before = float(stored.get("wall_time", 0.0)) if stored else 0.0
    if state is None:
        state = init_fn()
    start = int(state.step)
    metrics_path = os.path.join(out_dir, "metrics.jsonl")
    _truncate_metrics(metrics_path, start)
    jitted = jax.jit(step_fn)
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=steps, initial=start, desc=desc, dynamic_ncols=True)
    t0 = time.perf_counter()
    window, record = [], None
    try:
        for i in range(start, steps):
            state, metrics = jitted(state, step_key(seed, i), data)
            window.append(metrics)
            done = i + 1
            if bar is not None:
                bar.update(1)
            is_last = done == steps
            if done % log_every == 0 or is_last:
                values = jax.device_get(window)
                window = []
                record = {k: float(np.mean([v[k] for v in values])) for k in values[0]}
                if not all(math.isfinite(v) for v in record.values()):
                    raise NonFiniteLossError(
                        f"{desc}: non-finite metrics {record} in steps {done - len(values) + 1}"
                        f"..{done}; the last good checkpoint is step {last_ckpt} in "
                        f"{out_dir!r}", done, last_ckpt)
                record = {"step": done, **record,
                          "wall_time": wall_before + time.perf_counter() - t0}
                with open(metrics_path, "a") as f:
                    f.write(json.dumps(record) + "\n")
                if bar is not None:
                    bar.set_postfix(loss=f"{record['loss']:.4f}")
            if done % checkpoint_every == 0 or is_last:
                meta = dict(metadata, wall_time=wall_before + time.perf_counter() - t0)
                ckpt.save_checkpoint(out_dir, done, state, meta)
                last_ckpt = done
    finally:
        if bar is not None:
            bar.close()
    wall = wall_before + time.perf_counter() - t0 if start < steps else wall_before
    return FitResult(state, wall, record)
