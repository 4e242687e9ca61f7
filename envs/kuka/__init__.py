"""The Kuka block world in MuJoCo MJX: stacking and rearrangement (the paper's Table 2).

``make(kind, **overrides)`` is what ``envs.make("kuka/<kind>")`` calls.
"""
from __future__ import annotations


def make(kind: str, **overrides):
    """(KukaTask, generate: key -> Episode) of a task kind. Overrides naming a ``TaskSpec``
    field (multi: several instructed relations, default False; language) go to the task spec,
    those naming a ``KukaTask`` field (follow_path) to the planner task; unknown names raise a
    ValueError."""
    import functools

    from envs.kuka.config import TaskSpec
    from envs.kuka.episode import generate
    from envs.kuka.task import KukaTask
    from envs.overrides import split_overrides

    parts = split_overrides(f"kuka/{kind}", overrides, task=(KukaTask, ()),
                            spec=(TaskSpec, {"kind"}))
    spec = TaskSpec(kind, **parts["spec"])
    return KukaTask(**parts["task"]), functools.partial(generate, spec=spec)
