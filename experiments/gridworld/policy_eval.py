"""Measures a policy (a baseline or a reference agent: ``diffplan.baselines.policies
.LoadedPolicy``) in the grid world exactly as our planner is measured: the same seeded
evaluation episodes (``gridworld.eval.eval_episodes``), executed trajectories with collisions
(``diffplan.baselines.rollout.policy_rollout``), the same ``metrics_row`` pooled over seeds.
``experiments.baselines_eval`` builds its rows on these.
"""
from __future__ import annotations

import sys
import time
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from diffplan.baselines.policies import LoadedPolicy
from envs.gridworld.config import make_config
from envs.gridworld.task import GridTask
from experiments.gridworld.eval import eval_episodes, metrics_row, pooled_row
from experiments.harness.core import concat_trees, planner_keys, policy_runner

PLAN_FIELDS = ("plan_precision", "plan_recall", "plan_f1")


def evaluate_policy(policy, task, episodes, seed: int, batch_size: int, progress: bool = True,
                    desc: str = ""):
    """Runs a LoadedPolicy on the episodes (N) in calls of batch_size; episode i uses the key
    ``harness.planner_keys(seed, [i])``, as our planner's evaluation does.
    Returns (Rollout of numpy arrays, seconds)."""
    from experiments.harness.progress import bar as progress_bar

    n = int(np.shape(episodes.tokens)[0])
    run = policy_runner(task, policy.act_fn, policy.calls_per_move, policy.plan_channels,
                        policy.observe)
    per_call = min(n, batch_size)
    outs = []
    start = time.time()
    with progress_bar(total=n, desc=desc, unit="ep", disable=not progress, file=sys.stderr,
                      dynamic_ncols=True) as bar:
        for lo in range(0, n, per_call):
            idx = np.arange(lo, min(n, lo + per_call))
            chunk = jax.tree.map(lambda x: x[idx], episodes)
            keys = planner_keys(seed, idx)
            pad = per_call - len(idx)
            if pad:  # the last call padded to the compiled size; padding results dropped
                chunk = jax.tree.map(lambda x: np.concatenate([x, x[:pad]]), chunk)
                keys = jnp.concatenate([keys, keys[:pad]])
            out = jax.device_get(run(policy.params, keys, chunk))
            outs.append(jax.tree.map(lambda x: x[:len(idx)], out))
            bar.update(len(idx))
    return concat_trees(outs), time.time() - start


def _row_fn(policy):
    """pooled_row's row_fn for a policy: metrics_row without the plan metrics of a policy that
    makes no plan (they would be meaningless zeros)."""
    def row_fn(method, rollout, episodes, seconds, has_reference):
        row = metrics_row(method, rollout, episodes, seconds, has_reference)
        if policy.plan_channels is None:
            for key in PLAN_FIELDS:
                row.pop(key)
        return row

    return row_fn


def policy_rows(policies: Sequence[LoadedPolicy], setting: str, seeds: tuple[int, ...],
                episodes: int, batch_size: int, progress: bool, *,
                episodes_by_seed: dict | None = None, keep: dict | None = None) -> list[dict]:
    """One metrics row per policy (its ``method``) on ``episodes`` evaluation episodes of each
    seed (pooled; with several seeds also SR_ci95 and per_seed values, as the grid-world
    experiments write them; ``gridworld.eval.pooled_row``). episodes_by_seed: {seed: Episode
    batch} already generated with eval_episodes (default: generated here). keep: {seed: bool
    (N,)}, the episodes the rows count (all are run, so every episode keeps its key; the
    planner's rows leave out the same ones: 1O1G worlds its training saw)."""
    from experiments.gridworld.eval import select

    grid_config = make_config(setting)
    task = GridTask(grid_config)
    per_seed = {seed: (episodes_by_seed or {}).get(seed) for seed in seeds}
    per_seed = {seed: eval_episodes(grid_config, episodes, seed) if eps is None else eps
                for seed, eps in per_seed.items()}
    rows = []
    for policy in policies:
        outs = {seed: evaluate_policy(policy, task, eps, seed, batch_size, progress,
                                      f"{setting} {policy.method} (seed {seed})")
                for seed, eps in per_seed.items()}
        counted = per_seed
        if keep is not None:
            outs = {seed: (select(r, keep[seed]), t) for seed, (r, t) in outs.items()}
            counted = {seed: select(eps, keep[seed]) for seed, eps in per_seed.items()}
        row, _ = pooled_row(policy.method, outs, counted, grid_config.has_reference,
                            _row_fn(policy))
        rows.append(row)
    return rows
