"""The baselines in the Kuka world (the paper's Table 2 BC, CQL and a Decision-Diffuser-style
planner): the shipped checkpoints (``checkpoints/baselines/kuka/<name>``, made by ``python -m
experiments.train_baselines --world kuka --ship``) acting through
``envs.kuka.baselines.POLICY_WORLDS``, run on the same seeded episodes as the planner's rows
with ``diffplan.baselines.rollout.policy_rollout`` (the same primitive and MJX physics,
re-observed after every placement) and measured on the final physical poses after the same rest
(``experiments.kuka.eval``). The Kuka CLIs' ``--baselines`` rows.
"""
from __future__ import annotations

import os

from envs.kuka.env import SETTLE_SECONDS
from experiments.harness.core import CHECKPOINT_ROOT, planner_keys, policy_runner

CHECKPOINT_DIR = os.path.join(CHECKPOINT_ROOT, "baselines", "kuka")
KUKA_BASELINES = ("bc", "cql", "dd")
"""The baselines trained for the Kuka world."""


def load_baselines(names, root: str | None = None) -> list:
    """The LoadedPolicy of each named baseline from root/<name> (default CHECKPOINT_DIR;
    FileNotFoundError when one is missing, ValueError when it does not fit the Kuka world)."""
    from diffplan.baselines.policies import load_policy
    from envs.kuka.baselines import POLICY_WORLDS

    root = CHECKPOINT_DIR if root is None else root
    return [load_policy(name, os.path.join(root, name), POLICY_WORLDS[name]) for name in names]


def run_policy(task, policy, episodes, seed: int, batch: int, bar=None,
               settle: float = SETTLE_SECONDS) -> dict:
    """A policy (LoadedPolicy) on every episode, in calls of ``batch`` (the last padded), with
    the planner's keys of the seed; the final physical states as ``kuka.eval.run_planner``
    returns them (at rest after ``settle`` simulated seconds)."""
    from experiments.kuka import eval as ke

    run = policy_runner(task, policy.act_fn, policy.calls_per_move, policy.plan_channels,
                        policy.observe)

    def run_batch(idx, chunk):
        out = run(policy.params, planner_keys(seed, idx), chunk)
        return dict(ke.at_rest(out.final_state, settle), denoiser_calls=out.denoiser_calls,
                    num_plans=out.num_plans)

    return ke.batches(episodes, batch, bar, run_batch)
