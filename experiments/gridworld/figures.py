"""Qualitative figures of the grid-world experiments (the paper's Figs. 7-8): for a few episodes,
the map with the executed path over the expert's, and the predicted path, goal estimate and
sub-goal at several re-plans; the instruction once and one legend per figure."""
from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np


def _replan_moments(steps: int, count: int = 4):
    """Moves at which to show the plan: evenly spread over the executed moves."""
    if steps <= 0:
        return [0]
    return sorted(set(int(round(x)) for x in np.linspace(0, steps - 1, count)))


def write_figures(out_dir, spec, task, denoiser, episodes, seed, count, instructions=None):
    """Runs the main planning mode on the first `count` episodes with plans recorded and
    writes one PNG per episode (envs.gridworld.render.episode_figure: the executed path over
    the expert's, then the plan at a few moves). instructions: each episode's instruction as
    the figure shows it (default: its tokens decoded). Returns the written paths."""
    from envs.gridworld import env, grammar, render
    from experiments.gridworld.eval import evaluate_mode

    os.makedirs(out_dir, exist_ok=True)
    subset = jax.tree.map(lambda x: x[:count], episodes)
    rollout, _ = evaluate_mode(spec, task, denoiser, subset, seed, spec.main_mode, count,
                               progress=False, record_plans=True)
    grid_config = task.config
    paths = []
    for i in range(count):
        steps = int(rollout.steps[i])
        positions = np.asarray(rollout.positions[i])
        cells = dict(grid=np.asarray(episodes.grid[i]), target=np.asarray(episodes.target[i]),
                     reference=np.asarray(episodes.reference[i]))
        success = bool(np.all(positions[steps] == cells["target"]))
        panels = [dict(cells, agent=np.asarray(episodes.agent[i]),
                       path=np.asarray(episodes.expert_path[i]), path_label="expert path",
                       executed=positions[: steps + 1],
                       title=f"executed: {steps} moves, {'success' if success else 'failure'}")]
        for t in _replan_moments(steps):
            # The agent's knowledge at move t: replay the executed moves to get the seen area.
            state = env.reset(jax.tree.map(lambda x: x[i], subset), grid_config)
            for move in range(t):
                delta = positions[move + 1] - positions[move]
                action = {(-1, 0): 0, (0, 1): 1, (1, 0): 2, (0, -1): 3}.get(tuple(delta), None)
                if action is not None:
                    state = env.step(state, jnp.int32(action), grid_config)
            plan = np.asarray(rollout.plans[i, t])
            panels.append(dict(cells, agent=positions[t], seen=np.asarray(state.seen),
                               path=plan[..., 0], path_label="planned path", goal=plan[..., 1],
                               subgoal=plan[..., 2] if plan.shape[-1] > 2 else None,
                               executed=positions[: t + 1], title=f"plan at move {t}"))
        path = os.path.join(out_dir, f"{spec.name}_episode{i:03d}.png")
        render.episode_figure(path, panels, grammar.decode(episodes.tokens[i])
                              if instructions is None else instructions[i])
        paths.append(path)
    return paths
