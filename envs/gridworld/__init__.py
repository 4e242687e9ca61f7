"""The CompILE-style grid world (jax.numpy): settings 1o1g, mo1g and p_mo2g.

``make(setting, **overrides)`` is what ``envs.make("gridworld/<setting>")`` calls.
"""
from __future__ import annotations


def make(setting: str, **overrides):
    """(GridTask, generate: key -> Episode) of a setting. Overrides naming a ``GridTask`` field
    (path_weight, use_goal_channel, num_gen_channels) go to the task, the others to
    ``make_config`` (``GridConfig`` fields); unknown names raise a ValueError."""
    import dataclasses
    import functools

    from envs.gridworld.config import GridConfig, make_config
    from envs.gridworld.episode import generate
    from envs.gridworld.task import GridTask

    task_fields = {f.name for f in dataclasses.fields(GridTask)} - {"config"}
    config_fields = {f.name for f in dataclasses.fields(GridConfig)} - {"setting"}
    unknown = sorted(set(overrides) - task_fields - config_fields)
    if unknown:
        raise ValueError(f"unknown override(s) {unknown} for gridworld/{setting}; the task "
                         f"takes {sorted(task_fields)}, the config {sorted(config_fields)}")
    config = make_config(setting, **{k: v for k, v in overrides.items() if k in config_fields})
    task = GridTask(config, **{k: v for k, v in overrides.items() if k in task_fields})
    return task, functools.partial(generate, config=config)
