"""The language controls' rows (``--control``; envs.gridworld.controls): each planning mode
run on the same seeded episodes with one word of the instruction changed, beside the normal
rows, measured on what the agent executed.

``names``: the reference (a setting with no reference, MO1G: the goal) named as a distractor
visible at t = 0; the row counts only episodes with one (``control_episodes``) and adds
``named_first_percent``, the share in which the agent stood on the named distractor before the
true reference (MO1G: before the true target).
``direction``: the direction word reversed; the row's metrics (SR, SPL) are the measure.
"""
from __future__ import annotations

import functools

import jax
import numpy as np

CONTROL_NAMES = {"names": "reference named as a visible distractor (control)",
                 "direction": "direction reversed (control)"}
GOAL_NAMES = "goal named as a visible distractor (control)"
"""The names control's row where the setting has no reference (MO1G)."""


def control_episodes(control: str, grid_config, episodes, seed: int):
    """(episodes with the control's instruction (numpy), keep bool (N,), named cells int32
    (N, 2) or None): keep marks the episodes the control applies to."""
    from envs.gridworld import controls, env
    from experiments.harness.core import episode_keys

    setting = grid_config.setting
    n = int(np.shape(episodes.tokens)[0])
    if control == "direction":
        changed = jax.jit(jax.vmap(functools.partial(controls.reverse_direction,
                                                     setting=setting)))(episodes)
        return jax.tree.map(np.asarray, changed), np.asarray(episodes.direction) >= 0, None
    keys = jax.vmap(lambda k: jax.random.fold_in(k, controls.CONTROL_STREAM))(
        episode_keys(seed, 0, n))
    visible0 = jax.jit(jax.vmap(lambda e: env.reset(e, grid_config).seen))(episodes)
    changed, cells, valid = jax.jit(jax.vmap(functools.partial(
        controls.name_a_distractor, setting=setting)))(keys, episodes, visible0)
    return jax.tree.map(np.asarray, changed), np.asarray(valid), np.asarray(cells)


def changed_slots(control: str, episodes, keep, named) -> dict:
    """The slots the control writes into the instruction's text (where keep holds; elsewhere
    the episode's own): {"reference_class" (no reference: "target_class"): the named
    distractor's class} or {"direction": the reversed direction}."""
    if control == "direction":
        d = np.asarray(episodes.direction)
        return {"direction": np.where(keep, (d + 4) % 8, d)}
    grid = np.asarray(episodes.grid)
    cls = grid[np.arange(len(grid)), named[:, 0], named[:, 1]].astype(np.int32)
    ref = np.asarray(episodes.reference_class)
    target = np.asarray(episodes.target_class)
    return {"reference_class": np.where(keep & (ref > 0), cls, ref),
            "target_class": np.where(keep & (ref <= 0), cls, target)}


def control_rows(control: str, spec, modes, all_episodes: dict, mode_row,
                 refill=None) -> list[dict]:
    """One row per mode: ``mode_row(spec, mode, name, episodes_by_seed, keep) -> (row, pooled
    rollout)`` on the control's episodes of every seed, named "<mode>, <control>".
    refill(episodes, reference_class=..., direction=...) -> episodes: recomputes what a
    denoiser on pretrained features reads (the text with the control's word) where given."""
    from envs.gridworld import controls
    from experiments.gridworld.spec import METHOD_NAMES

    grid_config = spec.grid_config()
    changed, keep, named = {}, {}, {}
    for seed, eps in all_episodes.items():
        changed[seed], keep[seed], named[seed] = control_episodes(control, grid_config, eps,
                                                                  seed)
        if refill is not None:
            changed[seed] = refill(changed[seed], **changed_slots(control, eps, keep[seed],
                                                                    named[seed]))
    rows = []
    has_reference = grid_config.has_reference
    label = CONTROL_NAMES[control] if has_reference or control != "names" else GOAL_NAMES
    for mode in modes:
        row, rollout = mode_row(spec, mode, f"{METHOD_NAMES[mode]}, {label}", changed, keep)
        row["control"] = control
        row["control_episodes"] = int(sum(k.sum() for k in keep.values()))
        if named[next(iter(named))] is not None:
            cells = np.concatenate([named[s][keep[s]] for s in all_episodes])
            field = "reference" if has_reference else "target"
            reference = np.concatenate([np.asarray(getattr(all_episodes[s], field))[keep[s]]
                                        for s in all_episodes])
            first = controls.named_first(rollout.positions, rollout.steps, cells, reference)
            row["named_first_percent"] = 100.0 * float(first.mean()) if first.size else 0.0
        rows.append(row)
    return rows
