"""Qualitative figures of the grid-world experiments (the paper's Figs. 7-8): for a few episodes,
the map with the executed path, and the predicted path and goal estimate at several re-plans."""
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


def write_figures(out_dir, spec, task, denoiser, episodes, seed, count):
    """Runs the main planning mode on the first `count` episodes with plans recorded and
    writes one PNG per episode. Returns the written paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
        moments = _replan_moments(steps)
        positions = np.asarray(rollout.positions[i])
        fig, axes = plt.subplots(1, len(moments) + 1, figsize=(4 * (len(moments) + 1), 4.4))
        axes = np.atleast_1d(axes)
        instruction = grammar.decode(episodes.tokens[i])
        args = (np.asarray(episodes.grid[i]), np.asarray(episodes.agent[i]),
                np.asarray(episodes.target[i]), np.asarray(episodes.reference[i]), instruction)
        success = bool(np.all(positions[steps] == np.asarray(episodes.target[i])))
        render.render_episode(axes[0], *args, path=np.asarray(episodes.expert_path[i]),
                              executed=positions[: steps + 1],
                              title=f"executed ({steps} moves, "
                                    f"{'success' if success else 'failure'})")
        for ax, t in zip(axes[1:], moments):
            # The agent's knowledge at move t: replay the executed moves to get the seen area.
            state = env.reset(jax.tree.map(lambda x: x[i], subset), grid_config)
            for move in range(t):
                delta = positions[move + 1] - positions[move]
                action = {(-1, 0): 0, (0, 1): 1, (1, 0): 2, (0, -1): 3}.get(tuple(delta), None)
                if action is not None:
                    state = env.step(state, jnp.int32(action), grid_config)
            plan = np.asarray(rollout.plans[i, t])
            render.render_episode(ax, np.asarray(episodes.grid[i]), positions[t], *args[2:],
                                  seen=np.asarray(state.seen), path=plan[..., 0],
                                  goal=plan[..., 1],
                                  subgoal=plan[..., 2] if plan.shape[-1] > 2 else None,
                                  executed=positions[: t + 1],
                                  title=f"plan at move {t}")
        fig.suptitle(instruction, fontsize=10)
        fig.tight_layout()
        path = os.path.join(out_dir, f"{spec.name}_episode{i:03d}.png")
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    return paths
