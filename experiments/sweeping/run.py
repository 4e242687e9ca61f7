"""Runs sweep configurations (experiments.sweeping.config), keeping loaded denoisers, episodes and
compiled evaluations for reuse by later configurations of the same shapes and planner settings.

Grid world: each configuration is one call of a jitted function over all its episodes: the
re-planning modes on a pool of slots per device (diffplan.rollout_stream), the others as one
diffplan.rollout batch, episodes split over the devices of every process (the CLIs' program,
experiments.harness.core.rollout_fn); each episode's result is the same on any number of
devices and processes. Kuka world: the Kuka CLIs' evaluation
(experiments.kuka.eval.run_planner: diffplan.rollout in calls of batch_size episodes) of one
Table 2 column, with the CLIs' per-episode keys, so a row equals the CLI's row of that column.
"""
from __future__ import annotations

import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments.gridworld import eval as ge, spec as gs
from diffplan.distributed import gather
from experiments.harness import core as harness
from experiments.harness.cli import atomic_file
from experiments.harness.processes import writes
from experiments.kuka import eval as ke, spec as ks
from experiments.sweeping.config import (SweepError, default_checkpoint, planner_config, spec_of,
                                         world)
from experiments.sweeping.output import label


def _checkpoint(config: dict):
    """The checkpoint a configuration plans with (None: the posterior denoiser, no checkpoint;
    it trained on no episode)."""
    if config.get("denoiser") == "posterior":
        return None
    return config["checkpoint"] or default_checkpoint(config)


class Runner:
    """Runs configurations, keeping compiled evaluations for reuse."""

    def __init__(self, mesh=None, progress: bool = True):
        from diffplan import sharding as shd
        self.mesh = shd.data_mesh() if mesh is None else mesh
        self.devices = self.mesh.size
        self.progress = progress
        self._compiled = {}
        self._denoisers = {}
        self._episodes = {}

    def denoiser(self, config: dict, index: int):
        """The configuration's denoiser, checked against its world and step counts."""
        if config.get("denoiser") == "posterior":
            from envs.gridworld.posterior import posterior_denoiser
            key = ("posterior", config["task"])
            if key not in self._denoisers:
                self._denoisers[key] = posterior_denoiser(spec_of(config).grid_config())
            return self._denoisers[key]
        checkpoint = config["checkpoint"] or default_checkpoint(config)
        if checkpoint not in self._denoisers:
            from diffplan.checkpoint import CorruptCheckpointError
            try:
                self._denoisers[checkpoint], _ = harness.load_model(checkpoint)
            except (FileNotFoundError, CorruptCheckpointError, ValueError) as e:
                raise SweepError(f"configuration {index}: checkpoint {checkpoint}: {e}") from e
        den = self._denoisers[checkpoint]
        kuka = world(config) == "kuka"
        problem = (ks.mismatch(den, config["num_steps"]) if kuka
                   else spec_of(config).mismatch(den))
        if problem:
            raise SweepError(f"configuration {index}: the checkpoint {checkpoint} {problem}")
        try:
            for mode in () if kuka else ("on_the_fly", "warm_start"):
                spec_of(config).planner_config(mode).check_schedule(
                    den.schedule.num_train_steps)
        except ValueError as e:
            raise SweepError(f"configuration {index}: {e}") from e
        return den

    def reader(self, config: dict, index: int):
        """(ReaderConfig, parameters) of a Kuka configuration's reader, None without one."""
        directory = config.get("reader")
        if directory is None:
            return None
        if ("reader", directory) not in self._denoisers:
            try:
                self._denoisers["reader", directory] = ks.load_reader(directory, "reader")
            except SystemExit as e:
                raise SweepError(f"configuration {index}: {e}") from None
        return self._denoisers["reader", directory]

    def _cached(self, key, build):
        """(compiled function, compile seconds: 0 when reused) of a cache key."""
        if key in self._compiled:
            return self._compiled[key], 0.0
        t0 = time.time()
        self._compiled[key] = build()
        return self._compiled[key], time.time() - t0

    def _bar(self, config: dict, index: int):
        from experiments.harness.progress import bar
        return bar(total=config["episodes"], desc=f"[{index + 1}] {label(config)} seed "
                    f"{config['seed']}", unit="ep", disable=not self.progress,
                    file=sys.stderr, leave=True, dynamic_ncols=True)

    def run(self, config: dict, index: int, trajectories: str | None = None) -> dict:
        """The configuration's row: its world's metrics, compile_seconds, wall_seconds,
        devices, the configuration's keys; with trajectories (a directory) its
        config_NNN.npz (grid world: trajectories, contract 2; Kuka: final states, contract
        4)."""
        run = self._run_kuka if world(config) == "kuka" else self._run_grid
        row, compile_seconds, seconds = run(config, index, trajectories and os.path.join(
            trajectories, f"config_{index:03d}.npz"))
        checkpoint = _checkpoint(config)
        row.update(compile_seconds=compile_seconds, wall_seconds=seconds + compile_seconds,
                   devices=self.devices,
                   **{k: v for k, v in config.items() if k != "checkpoint"},
                   checkpoint=checkpoint and os.path.relpath(checkpoint, harness.REPO_ROOT))
        return row

    def _episodes_of(self, key, make):
        if key not in self._episodes:
            self._episodes[key] = make()
        return self._episodes[key]

    def _run_grid(self, config: dict, index: int, trajectories: str | None):
        from diffplan import sharding as shd
        from diffplan.planner import Planner
        from experiments.harness.progress import PARTS, RELAY

        spec = spec_of(config)
        den = self.denoiser(config, index)
        task = spec.task(den.num_gen_channels)
        n, seed = config["episodes"], config["seed"]
        episodes = self._episodes_of((config["task"], config["language"], n, seed),
                                     lambda: ge.eval_episodes(spec.grid_config(), n, seed))
        padded = -(-n // self.devices) * self.devices
        idx = np.arange(padded) % n
        chunk = shd.shard_batch(jax.tree.map(lambda x: x[idx], episodes), self.mesh)
        keys = shd.shard_batch(harness.planner_keys(seed, idx), self.mesh)
        planner = shd.replicate(Planner(den, planner_config(config)), self.mesh)
        slots = min(config["batch_size"], padded // self.devices)
        cache_key = (task, planner.config, padded, slots, config["modes"],
                     jax.tree.structure(planner),
                     tuple((x.shape, str(x.dtype)) for x in jax.tree.leaves(planner)))
        bar = self._bar(config, index)
        token = RELAY.attach(bar)
        try:
            # The CLIs' program (harness.rollout_fn), so the two share compilations.
            compiled, compile_seconds = self._cached(cache_key, lambda: harness.rollout_fn(
                task, slots if config["modes"] in ge.STREAM_MODES else None, self.mesh,
                progress=self.progress).lower(
                    planner, keys, chunk, jnp.int32(0)).compile())
            t0 = time.time()
            out = gather(compiled(planner, keys, chunk, jnp.int32(token * PARTS)))
            seconds = time.time() - t0
        finally:
            RELAY.detach(token)
            bar.update(n - bar.n)
            bar.close()
        out = jax.tree.map(lambda x: np.asarray(x)[:n], out)
        checkpoint = _checkpoint(config)
        keep = np.ones(n, bool) if checkpoint is None else ~self._cached(
            ("overlap", checkpoint, config["task"], n, seed),
            lambda: ge.training_overlap(checkpoint, spec.setting, episodes))[0]
        out, episodes = ge.select(out, keep), ge.select(episodes, keep)
        if trajectories and writes():
            atomic_file(trajectories, lambda tmp: ge.write_trajectories(
                tmp, out, episodes, spec.grid_config()))
        row = ge.metrics_row(gs.method_name(config["modes"], config["language"]), out,
                             episodes, seconds, spec.grid_config().has_reference)
        row["excluded_training_episodes"] = int((~keep).sum())
        return row, compile_seconds, seconds

    def _run_kuka(self, config: dict, index: int, trajectories: str | None):
        from diffplan.planner import Planner
        from diffplan.rollouts import rollout
        from envs.kuka.config import TaskSpec
        from envs.kuka.task import KukaTask

        den = self.denoiser(config, index)
        kind = config["task"].split("/")[1]
        spec = TaskSpec(kind, config["multi"], config["language"])
        task = KukaTask(follow_path=config["carry"] == "path")
        n, seed, batch = config["episodes"], config["seed"], config["batch_size"]
        episodes = self._episodes_of((spec, n, seed, batch),
                                     lambda: ke.generate_episodes(spec, n, seed, batch))
        reader = self.reader(config, index)
        planner = Planner(den, planner_config(config))
        calls = batch * self.devices  # run_planner: batch episodes per device and call
        first = jax.tree.map(lambda x: x[np.zeros(calls, int)], episodes)
        keys = harness.planner_keys(seed, np.zeros(calls, int))
        cache_key = (task, planner.config, batch, jax.tree.structure(planner),
                     tuple((x.shape, str(x.dtype)) for x in jax.tree.leaves(planner)))
        program = (harness.rollout_fn(task, mesh=self.mesh) if self.devices > 1 else jax.jit(
            lambda p, k, e, token: rollout(task, p, k, e)))
        compiled, compile_seconds = self._cached(
            cache_key, lambda: program.lower(planner, keys, first, 0).compile())
        bar = self._bar(config, index)
        t0 = time.time()
        try:
            final = ke.run_planner(task, planner, episodes, seed, batch, bar, run=compiled,
                                   reader=reader)
        finally:
            bar.close()
        seconds = time.time() - t0
        if trajectories and writes():
            atomic_file(trajectories, lambda tmp: ke.write_states(tmp, [(episodes, final)]))
        method = ks.label(config["modes"], spec.multi, spec.language, "planner",
                          reader is not None)
        row = ke.column_metrics(method, "multi" if spec.multi else "single", episodes, final,
                                seconds)
        return row, compile_seconds, seconds
