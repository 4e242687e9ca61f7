"""The grid world's evaluation: seeded episodes, one planning mode run over them (batched or on
the slot pool), the metrics row of contract 2 pooled over seeds with intervals, the results
table, and the trajectories file.

Evaluation episode i of ``--seed S`` is ``episode.generate(fold_in(PRNGKey(S), i))``, the
convention of ``envs.gridworld.export`` (so ``export --seed S`` writes the same episodes); see
experiments.harness.core for the seeds and the planner's keys.
"""
from __future__ import annotations

import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments.gridworld.spec import METHOD_NAMES
from experiments.harness.core import (ROLLOUT_STREAM, concat_trees, per_seed_values, planner_keys,
                                      rollout_fn, seeded_episodes)
from experiments.gridworld.tables import format_intervals, format_table
from experiments.harness.intervals import rate_interval

__all__ = ["ROLLOUT_STREAM", "concat_trees", "eval_episodes", "evaluate_mode", "metrics_row",
           "training_overlap", "select", "OVERLAP_SETTINGS",
           "add_intervals", "pooled_row", "format_table", "format_intervals",
           "write_trajectories", "PER_SEED_FIELDS", "STREAM_MODES"]

STREAM_MODES = ("on_the_fly", "warm_start")
"""Modes run on the slot pool (a slot starts the next episode as soon as its episode ends)."""
PER_SEED_FIELDS = ("SR", "SR_ordered", "GD", "path_f1", "SPL", "denoiser_calls_per_episode",
                   "fallback_percent", "seconds")


def eval_episodes(grid_config, n: int, seed: int, chunk: int = 1024):
    """Evaluation episodes: episode i = generate(fold_in(PRNGKey(seed), i)). (Episode, n)."""
    from envs.gridworld.episode import generate

    return seeded_episodes(generate, grid_config, n, seed, chunk)


OVERLAP_SETTINGS = ("1o1g",)
"""Settings whose evaluation episodes can equal a training episode: 1O1G has 979,200 possible
episodes and the shipped recipe draws 80,000, so ~8% of its evaluation episodes were seen in
training; they are excluded from its rows. MO1G and P-MO2G have far more: over the shipped
model's whole run (144,000 and 288,000 episodes) none of the 1000 episodes of seeds 1000,
2001, 2002, 2003 was a training episode (tests/test_training_disjoint.py)."""


def training_overlap(checkpoint: str, setting: str, episodes) -> np.ndarray:
    """bool (N,): the episodes whose world (grid, agent, objects; any wording) equals that of
    an episode the checkpoint's training run generated (its seed, steps, batch size, mixture
    and phrasing from its metadata); all False for settings not in OVERLAP_SETTINGS or a run
    that did not train on this setting."""
    from diffplan.checkpoint import read_metadata
    from envs.gridworld.episode import fingerprints
    from envs.gridworld.training import training_episodes

    n = int(np.shape(episodes.tokens)[0])
    meta = read_metadata(checkpoint)
    mixture = tuple((name, int(count)) for name, count in meta["extra"].get("mixture", ()))
    if setting not in OVERLAP_SETTINGS or setting not in dict(mixture):
        return np.zeros(n, bool)
    seen = set(fingerprints(training_episodes(
        setting, seed=int(meta["train_config"]["seed"]), steps=int(meta["step"]),
        batch_size=int(meta["train_config"]["batch_size"]), mixture=mixture,
        language=meta["extra"].get("language", "canonical")), instruction=False))
    return np.array([f in seen for f in fingerprints(episodes, instruction=False)], bool)


def select(tree, keep):
    """The rows of a pytree of numpy arrays where keep (bool (N,)) holds."""
    return jax.tree.map(lambda x: np.asarray(x)[keep], tree)


def evaluate_mode(spec, task, denoiser, episodes, seed, mode, batch_size, progress=True,
                  record_plans=False):
    """Runs one planning mode on the episodes (N of them); returns (Rollout as numpy, seconds).

    Re-planning modes run the slot pool (diffplan.rollout_stream) with batch_size slots over
    calls of up to 4 x batch_size episodes (a slot starts the next episode as soon as its
    episode ends; the progress bar moves as episodes end); the other modes run batches of
    batch_size episodes, processed in order of expert length (a batch's loop runs until its
    slowest episode ends). Episode i always uses the key fold_in(fold_in(PRNGKey(seed),
    ROLLOUT_STREAM), i), so nothing depends on the batching.
    """
    from diffplan.planner import Planner
    from experiments.harness.progress import PARTS, RELAY, bar as progress_bar

    from diffplan.distributed import gather
    from diffplan.sharding import data_mesh

    n = int(np.shape(episodes.tokens)[0])
    planner = Planner(denoiser, spec.planner_config(mode, record_plans=record_plans))
    stream = mode in STREAM_MODES and not record_plans
    start = time.time()
    bar = progress_bar(total=n, desc=f"{spec.setting} {METHOD_NAMES[mode]} (seed {seed})",
                       unit="ep", disable=not progress, file=sys.stderr, leave=True,
                       dynamic_ncols=True)
    # batch_size is per device: a call holds devices x (its episodes per device); each device
    # runs its share (harness.rollout_fn over the mesh of every process's devices). Recorded
    # plans are for figures, which process 0 draws alone: on its own first device.
    mesh = data_mesh(jax.local_devices()[:1]) if record_plans else data_mesh()
    devices = mesh.size
    per_device = min(-(-n // devices), 4 * batch_size) if stream else batch_size
    per_call = per_device * devices
    if stream:
        run = rollout_fn(task, min(batch_size, per_device), mesh, progress=progress)
        order = np.arange(n)
    else:
        run = rollout_fn(task, None, mesh)
        order = np.argsort(np.asarray(episodes.expert_length), kind="stable")
    outs = []
    try:
        for lo in range(0, n, per_call):
            idx = order[lo:lo + per_call]
            chunk = jax.tree.map(lambda x: x[idx], episodes)
            keys = planner_keys(seed, idx)
            size = per_call if lo > 0 or n >= per_call else -(-n // devices) * devices
            if len(idx) < size:
                # Pad the last call to the compiled size (padding results are dropped).
                pad = size - len(idx)
                chunk = jax.tree.map(lambda x: np.concatenate([x, x[np.arange(pad) % len(x)]]),
                                     chunk)
                keys = jnp.concatenate([keys, keys[np.arange(pad) % len(idx)]])
            token = RELAY.attach(bar, offset=lo)
            try:
                out = gather(run(planner, keys, chunk, jnp.int32(token * PARTS)))
            finally:
                RELAY.detach(token)
            outs.append(jax.tree.map(lambda x: x[:len(idx)], out))
            bar.update(min(lo + len(idx), n) - bar.n)
    finally:
        bar.close()
    seconds = time.time() - start
    merged = concat_trees(outs)
    inverse = np.argsort(order)
    return jax.tree.map(lambda x: x[inverse], merged), seconds


def metrics_row(method, rollout, episodes, seconds, has_reference):
    """Contract 2's row of a rollout (numpy) on its episodes."""
    from envs.gridworld.metrics import per_phrasing_metrics, plan_metrics, trajectory_metrics

    row = {"method": method}
    row.update(trajectory_metrics(rollout.positions, rollout.steps, episodes.target,
                                  episodes.expert_path,
                                  episodes.reference if has_reference else None,
                                  episodes.expert_length))
    row.update(plan_metrics(rollout.first_plan[..., 0], episodes.expert_path))
    row["collisions_per_episode"] = float(np.mean(rollout.final_state.collisions))
    row["denoiser_calls_per_episode"] = float(np.mean(rollout.denoiser_calls))
    row["plans_per_episode"] = float(np.mean(rollout.num_plans))
    if getattr(rollout, "fallback_moves", None) is not None:  # psi "follow"
        row["fallback_percent"] = (100.0 * float(np.sum(rollout.fallback_moves))
                                   / max(int(np.sum(rollout.steps)), 1))
    row["seconds"] = float(seconds)
    phrasings = per_phrasing_metrics(rollout.positions, rollout.steps, episodes,
                                     has_reference)
    if len(phrasings) > 1:
        row["per_phrasing"] = phrasings
    return row


def add_intervals(row, rollout, episodes, has_reference):
    """Adds SR_ci95 (and SR_ordered_ci95) over the pooled episodes to a metrics row."""
    n = len(rollout.steps)
    row["SR_ci95"] = rate_interval(row["SR"], n)
    if has_reference:
        row["SR_ordered_ci95"] = rate_interval(row["SR_ordered"], n)


def pooled_row(method, outs: dict, episodes_by_seed: dict, has_reference: bool,
               row_fn=metrics_row):
    """The row of a method over several seeds and its pooled rollout: outs maps each seed to
    (rollout as numpy, seconds) on episodes_by_seed[seed]; row_fn(method, rollout, episodes,
    seconds, has_reference) makes a row (default metrics_row). With more than one seed the row
    holds the 95% intervals of the pooled rates and per-seed values (PER_SEED_FIELDS)."""
    rollout = concat_trees([r for r, _ in outs.values()])
    episodes = concat_trees(list(episodes_by_seed.values()))
    row = row_fn(method, rollout, episodes, sum(t for _, t in outs.values()), has_reference)
    if len(outs) > 1:
        add_intervals(row, rollout, episodes, has_reference)
        row["per_seed"] = per_seed_values(
            {seed: row_fn(method, r, episodes_by_seed[seed], t, has_reference)
             for seed, (r, t) in outs.items()}, PER_SEED_FIELDS)
    return row, rollout


def contract_arrays(episodes, grid_config) -> dict:
    """The episodes in the export format of contract 1 (numpy)."""
    from envs.gridworld import env, grammar
    from envs.gridworld.sentences import episode_texts

    reset = jax.jit(jax.vmap(lambda e: env.reset(e, grid_config)))
    seen0 = np.asarray(reset(episodes).seen)
    return {
        "grid": np.asarray(episodes.grid, np.int8),
        "agent": np.asarray(episodes.agent, np.int32),
        "target": np.asarray(episodes.target, np.int32),
        "reference": np.asarray(episodes.reference, np.int32),
        "expert_path": np.asarray(episodes.expert_path, bool),
        "expert_length": np.asarray(episodes.expert_length, np.int32),
        "visible0": seen0.astype(bool),
        # Rendered from the phrasing: the tokens of a natural-language episode are canonical.
        "instruction": np.array(episode_texts(episodes, grid_config.setting)),
        "object_names": np.array(grammar.OBJECT_NAMES),
    }


def write_trajectories(path, rollout, episodes, grid_config):
    """Contract 2's trajectories file: the episodes (contract 1) and what the agent executed."""
    arrays = contract_arrays(episodes, grid_config)
    final = rollout.positions[np.arange(len(rollout.steps)), rollout.steps]
    arrays.update(positions=np.asarray(rollout.positions, np.int32),
                  steps=np.asarray(rollout.steps, np.int32),
                  success=np.all(final == np.asarray(episodes.target), axis=-1))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    np.savez_compressed(path, **arrays)


def write_profile(out_dir: str, spec, task, denoiser, episodes, seed: int, mode: str,
                  batch_size: int) -> None:
    """A profiler trace of one (already compiled) batch of ``mode`` (process 0's, in a
    multi-process run)."""
    n = min(batch_size, int(np.shape(episodes.tokens)[0]))
    batch = jax.tree.map(lambda x: x[:n], episodes)
    evaluate_mode(spec, task, denoiser, batch, seed, mode, n, progress=False)  # compile
    from contextlib import nullcontext

    from experiments.harness.processes import writes

    # Every process evaluates its share; process 0 writes its trace.
    with jax.profiler.trace(out_dir) if writes() else nullcontext():
        evaluate_mode(spec, task, denoiser, batch, seed, mode, n, progress=False)
