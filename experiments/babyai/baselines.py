"""BC on a BabyAI level (``envs.babyai.baselines``: the appendix's network on our condition
channels and the mission's one-hot colour and type), trained on the same demonstrations as our
denoiser (the cached layouts 0 .. demos - 1 and their expert actions), with the grid world's
budget rule: it trains until it converges or until it has used our denoiser's training minutes,
whichever comes first (:func:`train_bc`).

Converged: at a record (every ``RECORD_EVERY`` steps, each with a checkpoint), the mean loss
of the last ``PATIENCE`` records is not 1% below the best record before them. Where it stopped
and why is written to ``stopped.json`` in its directory, so a rerun does not train it again.
"""
from __future__ import annotations

import json
import os

from experiments.harness.cli import write_json

RECORD_EVERY = 500
PATIENCE = 3
STOPPED = "stopped.json"


class _Stop(Exception):
    """Raised by the budget callback: training stops at this (checkpointed) step."""

    def __init__(self, step: int, reason: str):
        super().__init__(reason)
        self.step, self.reason = step, reason


def budget_callback(minutes: float | None, patience: int = PATIENCE):
    """fit's callback: raises _Stop at a record once the run's optimisation time (its record's
    wall_time, resumes included) reaches ``minutes`` (None: no limit), or once the loss stopped
    improving (module docstring)."""
    losses = []

    def callback(step, record):
        if record is None:
            return
        losses.append(float(record["loss"]))
        if minutes is not None and record["wall_time"] >= 60.0 * minutes:
            raise _Stop(step, f"our training minutes ({minutes:.1f}) used")
        if len(losses) > patience and min(losses[-patience:]) > 0.99 * min(losses[:-patience]):
            raise _Stop(step, f"converged (no 1% lower loss in {patience} records)")

    return callback


def denoiser_minutes(checkpoint: str) -> float | None:
    """Minutes of optimisation our denoiser's run recorded (its metadata's wall_time)."""
    from diffplan.checkpoint import read_metadata

    seconds = read_metadata(checkpoint).get("wall_time")
    return None if seconds is None else float(seconds) / 60.0


def train_bc(spec, out_dir: str, *, demos: int, minutes: float | None, steps: int | None = None,
             seed: int = 0, progress: bool = True) -> dict:
    """Trains BC into out_dir (resuming) on layouts 0 .. demos - 1 under the budget rule;
    returns what stopped it ({"step", "reason", "minutes_budget"})."""
    from diffplan.baselines.bc import BCTrainConfig
    from envs.babyai import baselines as bb
    from envs.babyai.training import cached_layouts

    path = os.path.join(out_dir, STOPPED)
    if os.path.exists(path):
        with open(path) as f:
            return json.load(f)
    config = BCTrainConfig(seed=seed, steps=steps or spec.bc_steps,
                           checkpoint_every=RECORD_EVERY, log_every=RECORD_EVERY)
    layouts = cached_layouts(spec.level, demos)
    try:
        result = bb.train_bc(out_dir, spec.task(), layouts, config, progress=progress,
                             callback=budget_callback(minutes))
        stop = {"step": int(result.state.step), "reason": "step limit"}
    except _Stop as e:
        stop = {"step": e.step, "reason": e.reason}
    stop["minutes_budget"] = minutes
    write_json(path, stop, announce=False)
    return stop


def load_bc(directory: str):
    """The trained BC (LoadedPolicy) of a directory; FileNotFoundError when there is none."""
    from diffplan.baselines.policies import load_policy
    from envs.babyai.baselines import POLICY_WORLD

    return load_policy("bc", directory, POLICY_WORLD)
