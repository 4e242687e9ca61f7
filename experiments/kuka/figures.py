"""Figures and videos of the Kuka experiments: for a few episodes, the top-down view before every
placement with the plan the planner in-painted there (its path shaded, psi's pick cell framed
black and place cell, on the goal estimate, framed red), the view at the end, and GIFs of the
executed placements.

The planner's episodes are re-run move by move with ``diffplan.rollouts.move`` (the one move
that ``diffplan.rollout`` and ``rollout_stream`` loop over, with the same per-episode keys, so
the traced episodes are those of the results table), keeping what a figure needs between moves.
"""
from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np

from envs.kuka import env, scene
from envs.kuka.sentences import episode_texts


@functools.lru_cache(maxsize=None)
def _move_fn(task):
    """jitted (planner, states, planner states, active) -> (states, planner states, plans,
    actions): one diffplan move and the action psi took in it."""
    from diffplan.rollouts import move

    def step(planner, states, planner_states, active):
        new_states, planner_states, plans = move(task, planner, states, planner_states, active)
        return new_states, planner_states, plans, jax.vmap(task.psi)(states, plans)

    return jax.jit(step)


_views = jax.jit(jax.vmap(env.view))


def _panel(top, height, title, plan=None, cells=None):
    panel = dict(top=np.asarray(top), height=np.asarray(height), title=title)
    if plan is not None:
        panel.update(path=np.asarray(plan)[..., 0] > 0)
    if cells is not None:
        panel.update(pick=np.asarray(cells)[:2], goal=np.asarray(cells)[2:])
    return panel


def _describe(top, cells) -> str:
    names = scene.BLOCK_NAMES
    pick, place = int(top[cells[0], cells[1]]), int(top[cells[2], cells[3]])
    return f"{names[pick] if pick >= 0 else 'nothing'} on {names[place] if place >= 0 else 'floor'}"


def trace(task, planner, episodes, keys) -> list[dict]:
    """Runs the episodes (a batch, numpy Episode) with the planner move by move.

    Returns one dict per episode: panels (a draw_view panel before every placement, with the
    plan and psi's cells, and one of the end), frames float32 (F, nq) of every placement made,
    placements int, instruction str (rendered from its phrasings: a natural-language
    episode's own text)."""
    move_fn = _move_fn(task)
    states = env.reset_batch(episodes.replace(features=None))
    planner_states = jax.vmap(planner.init)(keys, jax.vmap(task.tokens)(episodes))
    n = int(np.shape(episodes.tokens)[0])
    texts = episode_texts(episodes)
    panels = [[] for _ in range(n)]
    frames = [[] for _ in range(n)]
    for t in range(task.max_steps):
        active = ~np.asarray(states.done)
        if not active.any():
            break
        top, height = (np.asarray(a) for a in _views(states))
        states, planner_states, plans, actions = move_fn(planner, states, planner_states,
                                                         jnp.asarray(active))
        cells, plans = np.asarray(actions.cells), np.asarray(plans)
        for i in np.flatnonzero(active):
            panels[i].append(_panel(top[i], height[i],
                                    f"plan {t + 1}: {_describe(top[i], cells[i])}",
                                    plans[i], cells[i]))
            frames[i].append(np.asarray(states.frames[i]))
    top, height = (np.asarray(a) for a in _views(states))
    placements = np.asarray(states.t)
    out = []
    for i in range(n):
        panels[i].append(_panel(top[i], height[i], f"end ({int(placements[i])} placements)"))
        out.append(dict(panels=panels[i], frames=np.concatenate(frames[i] or [
            np.asarray(states.frames[i])]), placements=int(placements[i]),
            instruction=texts[i]))
    return out


def expert_trace(episodes, final) -> list[dict]:
    """The expert's counterpart of :func:`trace` from its results (final: run_expert's dict):
    the view at t = 0 with the expert's first path, support and moved block, and the end."""
    from envs.kuka import expert, grid

    out = []
    texts = episode_texts(episodes)
    for i in range(int(np.shape(episodes.tokens)[0])):
        episode = jax.tree.map(lambda x: x[i], episodes)
        pos0 = np.concatenate([episode.block_xy, np.full((4, 1), scene.BLOCK_HALF_SIZE[2])], 1)
        flat = np.tile(np.array([1.0, 0, 0, 0], np.float32), (4, 1))
        first = expert.decide(pos0, np.zeros(4, bool), episode)
        top0, height0 = grid.top_down_view(pos0, flat)
        top1, height1 = grid.top_down_view(final["block_pos"][i], final["block_quat"][i],
                                           final["held"][i])
        used = max(int(final["placements"][i]), 1)
        first_panel = _panel(top0, height0, "t = 0, expert's first path",
                             cells=np.asarray(first.action))
        first_panel["path"] = np.asarray(first.path)
        out.append(dict(panels=[first_panel, _panel(top1, height1, f"end ({used} placements)")],
                        frames=final["frames"][i, :used].reshape(
                            -1, final["frames"].shape[-1]),
                        placements=int(final["placements"][i]),
                        instruction=texts[i]))
    return out


def write_figures(out_dir: str, spec, traced: list[dict], count: int) -> list[str]:
    """One PNG per traced episode (the first `count`): its panels side by side."""
    from envs.kuka import render

    return [render.episode_figure(os.path.join(out_dir, f"{spec.name}_{spec.language}_{i:03d}"
                                               ".png"), t["panels"], t["instruction"])
            for i, t in enumerate(traced[:count])]


def video_frames(spec, traced: list[dict], count: int) -> dict:
    """{name: qpos frames (F, nq)} of the first `count` traced episodes."""
    return {f"{spec.name}_{spec.language}_{i:03d}": t["frames"]
            for i, t in enumerate(traced[:count])}


def write_videos(out_dir: str, videos: dict) -> list[str]:
    """GIFs of the videos ({name: qpos frames}) in out_dir (the paths), or a line saying that
    no GL backend renders offscreen here (no paths)."""
    from envs.kuka import render

    if not videos:
        return []
    result = render.write_videos(out_dir, videos)
    if result is None:
        print(f"--video: no GL backend for offscreen rendering ({'/'.join(render.GL_BACKENDS)} "
              "failed); no videos written")
        return []
    print(f"wrote {len(result[0])} videos to {out_dir} (MUJOCO_GL={result[1]})")
    return result[0]


def figures_and_videos(args, specs, episodes, finals, task, planner, seed) -> None:
    """The CLIs' --figures and --video: the first episodes of each column, re-run move by move
    (planner None: the expert's, from its results)."""
    from experiments.harness import processes
    from experiments.harness.core import planner_keys

    count = max(args.num_figures if args.figures else 0, args.num_videos if args.video else 0)
    if not count or not processes.writes():
        return
    traces = {}
    for spec in specs:
        eps = jax.tree.map(lambda x: x[:count], episodes[spec, seed])
        traces[spec] = (trace(task, planner, eps, planner_keys(seed, np.arange(count)))
                        if planner is not None else expert_trace(eps, finals[None, spec][1]))
    if args.figures and args.num_figures:
        written = [p for spec in specs for p in write_figures(
            args.figures, spec, traces[spec], args.num_figures)]
        print(f"wrote {len(written)} figures to {args.figures}")
    if args.video and args.num_videos:
        videos = {}
        for spec in specs:
            videos.update(video_frames(spec, traces[spec], args.num_videos))
        write_videos(args.video, videos)
