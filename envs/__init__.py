"""Worlds by name (contract 6 of docs/DESIGN.md), in the style of brax's ``register_environment``
and mujoco_playground's ``registry.load``:

    import envs
    task, generate = envs.make("gridworld/p_mo2g")    # a diffplan.Task and key -> Episode
    episode = generate(key)                           # pure: jit / vmap over keys

``envs.make(name, **overrides)`` builds the planner task of a registered world and setting and
its pure episode generator; overrides reach the world's configuration (a grid-world
``GridConfig`` field such as ``max_obstacles``, a Kuka ``TaskSpec`` field such as ``multi``) or
its task (``GridTask``'s ``path_weight``, ``KukaTask``'s ``follow_path``); an unknown override is
refused with a ValueError naming it. ``envs.names()`` lists the registered names;
``envs.register(name, factory)`` adds a world of your own (``factory(**overrides) -> (task,
generate)``). A world's modules are imported only when one of its names is made (the Kuka world
needs MuJoCo, the BabyAI levels minigrid; their ``generate`` resets minigrid on the host through
``jax.pure_callback``, still jit- and vmap-able).
"""
from __future__ import annotations

from typing import Any, Callable

__all__ = ["make", "names", "register", "World"]

World = tuple[Any, Callable[[Any], Any]]
"""(task: a diffplan.Task, generate: key -> Episode)."""


def _gridworld(setting: str) -> Callable[..., World]:
    def factory(**overrides) -> World:
        from envs.gridworld import make
        return make(setting, **overrides)
    return factory


def _babyai(level: str) -> Callable[..., World]:
    def factory(**overrides) -> World:
        from envs.babyai import make
        return make(level, **overrides)
    return factory


def _kuka(kind: str) -> Callable[..., World]:
    def factory(**overrides) -> World:
        from envs.kuka import make
        return make(kind, **overrides)
    return factory


_BUILTIN: dict[str, Callable[..., World]] = {
    "gridworld/1o1g": _gridworld("1o1g"),
    "gridworld/mo1g": _gridworld("mo1g"),
    "gridworld/p_mo2g": _gridworld("p_mo2g"),
    "gridworld/p_mo2g_far": _gridworld("p_mo2g_far"),
    "kuka/stacking": _kuka("stacking"),
    "kuka/rearrangement": _kuka("rearrangement"),
    "babyai/goto_local": _babyai("goto_local"),
    "babyai/goto_obj_maze": _babyai("goto_obj_maze"),
    "babyai/goto": _babyai("goto"),
}
_USER: dict[str, Callable[..., World]] = {}


def names() -> tuple[str, ...]:
    """Every registered name, the built-in worlds first."""
    return tuple(_BUILTIN) + tuple(n for n in _USER if n not in _BUILTIN)


def register(name: str, factory: Callable[..., World]) -> None:
    """Registers ``factory(**overrides) -> (task, generate)`` under ``name`` ("world/setting").
    A built-in name cannot be replaced."""
    if not isinstance(name, str) or "/" not in name or not all(name.split("/")):
        raise ValueError(f"a world's name is 'world/setting', got {name!r}")
    if name in _BUILTIN:
        raise ValueError(f"{name!r} is a built-in world and cannot be replaced")
    if not callable(factory):
        raise ValueError(f"the factory of {name!r} must be callable, got {factory!r}")
    _USER[name] = factory


def make(name: str, **overrides) -> World:
    """(task, generate) of a registered world and setting; see the module docstring."""
    factory = _BUILTIN.get(name) or _USER.get(name)
    if factory is None:
        raise ValueError(f"unknown world {name!r}; registered: {', '.join(names())}")
    return factory(**overrides)
