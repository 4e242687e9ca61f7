"""A BabyAI level's evaluation, measured in minigrid itself.

Evaluation episode i of seed S is minigrid's level reset with ``envs.babyai.seeds.
evaluation_seed(S, i)`` (= S * 2**20 + i; training layouts use a disjoint stream). Our planner
and BC act in the jitted port (``envs.babyai.env``) through ``envs.babyai.metrics.ActionLog``,
which records every executed action; each episode's actions are then stepped in minigrid reset
with the same seed (``metrics.replay``), and minigrid's own reward, termination and truncation
are what a row reports (success: reward > 0). A row also counts the episodes whose end differs
between the port and minigrid (``mismatches``: must be 0). The BabyAI bot runs in minigrid.
The planner's key of episode i is ``harness.core.planner_keys(S, [i])``, whatever the batching.
"""
from __future__ import annotations

import functools
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from envs.babyai import episode as E
from envs.babyai import metrics, seeds as babyai_seeds
from experiments.babyai.spec import METHOD_NAMES
from experiments.harness.core import concat_trees, planner_keys, policy_runner, rollout_fn
from experiments.harness.intervals import wilson_interval
from experiments.harness.progress import PARTS, RELAY, bar as progress_bar

PER_SEED_FIELDS = ("SR", "mean_reward", "mean_steps", "mismatches", "seconds")


def seed_list(seed: int, idx) -> list[int]:
    """The minigrid seeds of evaluation episodes idx (ints) of a seed."""
    return [babyai_seeds.evaluation_seed(seed, int(i)) for i in idx]


def _bar(desc: str, n: int, progress: bool, compiles: bool = False):
    """A progress bar over episodes; one over minigrid's Python (compiles=False) runs at once."""
    bar = progress_bar(total=n, desc=desc, unit="ep", disable=not progress, file=sys.stderr,
                       leave=True, dynamic_ncols=True)
    if not compiles:
        bar.running()
    return bar


def episodes(config, seed: int, n: int, progress: bool = True):
    """The Episodes (numpy, leading axis n) of seed's evaluation episodes 0 .. n - 1, from
    minigrid resets."""
    env = E.make_env(config)
    bar = _bar(f"{config.level} minigrid resets (seed {seed})", n, progress)
    out = []
    try:
        for s in seed_list(seed, range(n)):
            out.append(E.layout(env, config, s)[0])
            bar.update(1)
    finally:
        bar.close()
    return jax.tree.map(lambda *xs: np.stack(xs), *out)


def _in_calls(call, eps, seed: int, idx, per_call: int, bar):
    """call(keys, episodes, token int32 ()) -> Rollout over calls of per_call of the episodes
    (evaluation episodes idx of the seed; the last call padded with repeats of its own, the
    padding dropped), with their planner keys; the bar moves with the program's reports
    (RELAY, token) and after each call."""
    n = len(idx)
    outs = []
    for lo in range(0, n, per_call):
        part = np.arange(lo, min(n, lo + per_call))
        take = part if lo == 0 else np.concatenate([part, part[np.arange(per_call - len(part))
                                                                  % len(part)]])
        token = RELAY.attach(bar, offset=lo)
        try:
            out = jax.device_get(call(planner_keys(seed, np.asarray(idx)[take]),
                                      jax.tree.map(lambda x: x[take], eps),
                                      jnp.int32(token * PARTS)))
        finally:
            RELAY.detach(token)
        outs.append(jax.tree.map(lambda x: x[:len(part)], out))
        bar.update(lo + len(part) - bar.n)
    return concat_trees(outs)


def _measured(config, task_rollout, seed: int, idx, t0: float, progress: bool, desc: str):
    """(port outcome, minigrid outcome, calls (N,), seconds) of a rollout: its logged actions
    replayed in minigrid."""
    port = metrics.port_outcome(task_rollout.final_state)
    bar = _bar(f"{desc}: minigrid replay", len(idx), progress)
    try:
        replayed = metrics.replay(config, seed_list(seed, idx), port["actions"],
                                  tick=lambda: bar.update(1))
    finally:
        bar.close()
    return port, replayed, np.asarray(task_rollout.denoiser_calls), time.time() - t0


@functools.lru_cache(maxsize=None)
def _planner_runner(task, slots: int, progress: bool = True):
    """rollout_fn of the action-logging task on a pool of ``slots``, kept for the process: with
    a bar its program reports progress through a host callback, which the persistent
    compilation cache does not keep, so a second evaluation in the process (another seed, mode
    or sweep setting) reuses the compiled program instead of compiling it again."""
    return rollout_fn(metrics.ActionLog(task), slots, progress=progress)


def run_planner(spec, task, denoiser, mode: str, eps, seed: int, idx, slots: int,
                progress: bool = True, name: str | None = None):
    """One planning mode on the episodes (evaluation episodes idx of the seed; a slot pool of
    ``slots``): :func:`_measured`'s tuple; seconds include compiling and the replay. name: the
    row's name in the bar (default the mode's)."""
    from diffplan.planner import Planner
    from envs.babyai.config import make_config

    t0 = time.time()
    n = int(np.shape(eps.tokens)[0])
    planner = Planner(denoiser, spec.planner_config(mode))
    per_call = min(n, 4 * slots)
    run = _planner_runner(task, min(slots, per_call), progress)
    desc = f"{spec.level} {name or METHOD_NAMES[mode]} (seed {seed})"
    bar = _bar(desc, n, progress, compiles=True)
    try:
        out = _in_calls(lambda k, e, token: run(planner, k, e, token), eps, seed, idx, per_call,
                        bar)
    finally:
        bar.close()
    return _measured(make_config(spec.level), out, seed, idx, t0, progress, desc)


def run_policy(spec, task, policy, eps, seed: int, idx, batch: int, progress: bool = True):
    """A trained baseline (``diffplan.baselines.policies.LoadedPolicy``) on the episodes
    (evaluation episodes idx of the seed), in calls of ``batch``: :func:`_measured`'s tuple."""
    from envs.babyai.config import make_config

    t0 = time.time()
    n = int(np.shape(eps.tokens)[0])
    run = policy_runner(metrics.ActionLog(task), policy.act_fn, policy.calls_per_move,
                        policy.plan_channels, policy.observe)
    desc = f"{spec.level} {policy.method} (seed {seed})"
    bar = _bar(desc, n, progress, compiles=True)
    try:
        out = _in_calls(lambda k, e, token: run(policy.params, k, e), eps, seed, idx,
                        min(n, batch), bar)
    finally:
        bar.close()
    return _measured(make_config(spec.level), out, seed, idx, t0, progress, desc)


def run_bot(spec, seed: int, idx, progress: bool = True):
    """The BabyAI bot in minigrid on the seed's evaluation episodes idx: (None, minigrid
    outcome, None, seconds)."""
    from envs.babyai.config import make_config

    t0 = time.time()
    bar = _bar(f"{spec.level} BabyAI bot in minigrid (seed {seed})", len(idx), progress)
    try:
        out = metrics.bot_episodes(make_config(spec.level), seed_list(seed, idx),
                                   tick=lambda: bar.update(1))
    finally:
        bar.close()
    return None, out, None, time.time() - t0


def _row_of(method: str, port, replayed, calls, seconds) -> dict:
    row = {"method": method, **metrics.success_metrics(replayed)}
    row["SR_ci95"] = wilson_interval(row["successes"], row["episodes"])
    row["seconds"] = float(seconds)
    if port is not None:
        row["mismatches"] = int(metrics.mismatches(port, replayed).sum())
    if calls is not None:
        row["denoiser_calls_per_episode"] = float(np.mean(calls))
    if "errors" in replayed:
        row["bot_errors"] = int(np.sum(replayed["errors"]))
    return row


def pooled_row(method: str, per_seed: dict) -> dict:
    """The row of a method over its seeds' results ({seed: (port, minigrid, calls, seconds)}):
    pooled rates, the Wilson interval of the pooled SR, and with several seeds each seed's
    PER_SEED_FIELDS."""
    parts = list(per_seed.values())
    pool = lambda i: None if parts[0][i] is None else concat_trees([p[i] for p in parts])
    row = _row_of(method, pool(0), pool(1), pool(2), sum(p[3] for p in parts))
    if len(per_seed) > 1:
        row["per_seed"] = {str(s): {k: v for k, v in _row_of(method, *p).items()
                                    if k in PER_SEED_FIELDS} for s, p in per_seed.items()}
    return row


def select(tree, idx):
    """The rows idx of a pytree of numpy arrays."""
    return jax.tree.map(lambda x: np.asarray(x)[idx], tree)
