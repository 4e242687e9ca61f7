"""The CompILE-style grid world (jax.numpy): settings 1o1g, mo1g and p_mo2g, and p_mo2g_far
(beyond the paper: the target out of the reference's view).

``make(setting, **overrides)`` is what ``envs.make("gridworld/<setting>")`` calls.
"""
from __future__ import annotations


def make(setting: str, **overrides):
    """(GridTask, generate: key -> Episode) of a setting. Overrides naming a ``GridTask`` field
    (path_weight, use_goal_channel, num_gen_channels) go to the task, the others to
    ``make_config`` (``GridConfig`` fields); unknown names raise a ValueError."""
    import functools

    from envs.gridworld.config import GridConfig, make_config
    from envs.gridworld.episode import generate
    from envs.gridworld.task import GridTask
    from envs.overrides import split_overrides

    parts = split_overrides(f"gridworld/{setting}", overrides, task=(GridTask, {"config"}),
                            config=(GridConfig, {"setting"}))
    config = make_config(setting, **parts["config"])
    return GridTask(config, **parts["task"]), functools.partial(generate, config=config)
