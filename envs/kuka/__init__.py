"""The Kuka block world in MuJoCo MJX: stacking and rearrangement (the paper's Table 2).

``make(kind, **overrides)`` is what ``envs.make("kuka/<kind>")`` calls.
"""
from __future__ import annotations


def make(kind: str, **overrides):
    """(KukaTask, generate: key -> Episode) of a task kind. Overrides naming a ``TaskSpec``
    field (multi: several instructed relations, default False; language) go to the task spec,
    those naming a ``KukaTask`` field (follow_path) to the planner task; unknown names raise a
    ValueError."""
    import dataclasses
    import functools

    from envs.kuka.config import TaskSpec
    from envs.kuka.episode import generate
    from envs.kuka.task import KukaTask

    task_fields = {f.name for f in dataclasses.fields(KukaTask)}
    spec_fields = {f.name for f in dataclasses.fields(TaskSpec)} - {"kind"}
    unknown = sorted(set(overrides) - task_fields - spec_fields)
    if unknown:
        raise ValueError(f"unknown override(s) {unknown} for kuka/{kind}; the task takes "
                         f"{sorted(task_fields)}, the task spec {sorted(spec_fields)}")
    spec = TaskSpec(kind, **{k: v for k, v in overrides.items() if k in spec_fields})
    task = KukaTask(**{k: v for k, v in overrides.items() if k in task_fields})
    return task, functools.partial(generate, spec=spec)
