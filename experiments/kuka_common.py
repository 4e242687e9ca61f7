"""Shared machinery of the Kuka block experiments (the paper's Tables 2 and 5).

``experiments.kuka_stacking`` and ``experiments.kuka_rearrangement`` are thin wrappers around
:func:`main`: run a policy on fresh seeded episodes of the kind's single- and multi-constraint
tasks under MJX physics, measure success on the final physical block poses, print a table and
write JSON (contract 2 of DESIGN.md), the final states (contract 4), figures and videos.

Seeds: episode i of ``--seed S`` is ``tasks.generate(fold_in(PRNGKey(S), i), spec)`` in both
columns (so the two columns share their initial layouts).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from typing import Sequence

import numpy as np

DEFAULT_SEED = 2000
DEFAULT_EPISODES = 500
DEFAULT_BATCH = 64
POLICIES = ("expert", "planner")
AVAILABLE_POLICIES = ("expert",)
PAPER = {
    # Table 2 of the paper: (single, multi) for each kind; Diffuser has no multi-constraint number.
    "stacking": {"ours (paper)": (99.50, 98.38), "DD (paper)": (58.00, 60.30),
                 "Diffuser (paper)": (45.60, None)},
    "rearrangement": {"ours (paper)": (99.80, 98.85), "DD (paper)": (62.70, 67.20),
                      "Diffuser (paper)": (58.90, None)},
}

# MJX casts some of MuJoCo's float64 "infinite" defaults to float32 when it builds the model.
warnings.filterwarnings("ignore", "overflow encountered in cast")


def build_parser(kind: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=f"python -m experiments.kuka_{kind}",
        description=(f"Kuka block world, {kind}: run a policy on fresh seeded episodes of the "
                     f"single- and multi-constraint {kind} tasks (the paper's Table 2 columns) "
                     "in MuJoCo MJX physics, measure success on the final physical block poses "
                     "(strict, contract 4, and Diffuser's looser check), and print/write the "
                     "results table."))
    p.add_argument("--episodes", type=int, default=DEFAULT_EPISODES,
                   help=f"evaluation episodes per column (single and multi constraint; default "
                        f"{DEFAULT_EPISODES})")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED,
                   help="evaluation seed: episode i is generated from fold_in(PRNGKey(seed), i) "
                        f"in each column (default {DEFAULT_SEED})")
    p.add_argument("--policy", choices=POLICIES, default="expert",
                   help="who acts: 'expert' is the scripted expert through the same primitive "
                        "and physics; 'planner' (the diffusion planner) comes with issue 11 "
                        "(default expert)")
    p.add_argument("--language", choices=("canonical", "paraphrased"), default="canonical",
                   help="instruction phrasing: 'canonical' (Table 2) or 'paraphrased' with "
                        "inverted prepositions (Table 5) (default canonical)")
    p.add_argument("--json", metavar="PATH", help="write the results (contract 2) as JSON")
    p.add_argument("--states", metavar="PATH.npz",
                   help="write the final physics state of every episode (contract 4): "
                        "single-constraint episodes first, then multi-constraint")
    p.add_argument("--batch-size", type=int, default=DEFAULT_BATCH,
                   help=f"episodes per jitted, vmapped call (default {DEFAULT_BATCH})")
    p.add_argument("--figures", metavar="DIR",
                   help="write PNGs of a few episodes: the top-down view at the start, the "
                        "expert's first path and place cell, and the view at the end")
    p.add_argument("--num-figures", type=int, default=3,
                   help="episodes per column drawn with --figures (default 3)")
    p.add_argument("--video", metavar="DIR",
                   help="render a few episodes offscreen to animated GIFs (needs an EGL or "
                        "OSMesa GL backend; without one a line says so and the run goes on)")
    p.add_argument("--num-videos", type=int, default=2,
                   help="episodes per column rendered with --video (default 2)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return p


def check_args(parser, args) -> None:
    if args.policy not in AVAILABLE_POLICIES:
        parser.error(f"--policy {args.policy} is not available yet (issue 11); "
                     f"available: {', '.join(AVAILABLE_POLICIES)}")
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if args.batch_size < 1:
        parser.error(f"--batch-size must be >= 1, got {args.batch_size}")
    for flag in ("num_figures", "num_videos"):
        if getattr(args, flag) < 0:
            parser.error(f"--{flag.replace('_', '-')} must be >= 0, got {getattr(args, flag)}")
    if args.states and not args.states.endswith(".npz"):
        parser.error(f"--states must name a .npz file, got {args.states!r}")


# ----------------------------------------------------------------------------- running

def generate_episodes(spec, n: int, seed: int, batch: int):
    """Episodes 0..n-1 of a seed (numpy Episode with a leading (n,) axis)."""
    import jax

    from envs.kuka import tasks

    gen = jax.jit(jax.vmap(tasks.generate, in_axes=(0, None)), static_argnums=1)
    parts = [jax.device_get(gen(tasks.episode_keys(seed, min(batch, n - lo), lo), spec))
             for lo in range(0, n, batch)]
    return jax.tree.map(lambda *xs: np.concatenate(xs), *parts)


def run_policy(policy: str, episodes, batch: int, bar=None):
    """Runs the policy on every episode in calls of `batch` (the last padded and trimmed).

    Returns dict of numpy arrays: block_pos (n, 4, 3), block_quat (n, 4, 4), held (n, 4),
    placements (n,), done (n,), frames (n, MAX_STEPS, F, nq)."""
    import jax

    from envs.kuka import env, expert, physics

    if policy != "expert":
        raise ValueError(f"policy {policy!r} is not available yet (issue 11)")
    n = episodes.block_xy.shape[0]
    outs = []
    for lo in range(0, n, batch):
        idx = np.arange(lo, min(n, lo + batch))
        idx = np.concatenate([idx, np.full(batch - len(idx), idx[-1])])  # pad to the compiled size
        chunk = jax.tree.map(lambda x: x[idx], episodes)
        states, frames = expert.run_expert(env.reset_batch(chunk))
        keep = min(batch, n - lo)
        out = {
            "block_pos": jax.vmap(physics.block_pos)(states.data),
            "block_quat": jax.vmap(physics.block_quat)(states.data),
            "held": jax.vmap(physics.held)(states.data),
            "placements": states.t, "done": states.done, "frames": frames,
        }
        outs.append({k: np.asarray(v)[:keep] for k, v in out.items()})
        if bar is not None:
            bar.update(keep)
    return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}


def column_metrics(method: str, column: str, episodes, final, seconds: float) -> dict:
    """A results row from the final physical states (numpy)."""
    import jax

    from envs.kuka import success

    pos, held = final["block_pos"], final["held"]
    constraints = np.asarray(episodes.constraints)
    strict = np.asarray(jax.vmap(lambda p, h, c: success.satisfied(success.on_matrix(p, h), c))(
        pos, held, constraints))
    loose = np.asarray(jax.vmap(
        lambda p, h, c: success.satisfied(success.diffuser_on_matrix(p, h), c))(
        pos, held, constraints))
    valid = constraints[..., 0] >= 0
    tower = np.asarray(jax.vmap(success.single_tower)(pos, held))
    is_stacking = bool(np.asarray(episodes.tower).all())
    return {
        "method": method, "column": column, "episodes": int(len(pos)),
        "constraints": int(valid.sum()),
        "SR": 100.0 * strict.sum() / valid.sum(),
        "SR_diffuser": 100.0 * loose.sum() / valid.sum(),
        "all_constraints": 100.0 * np.mean((strict | ~valid).all(-1)),
        "tower": 100.0 * tower.mean() if is_stacking else None,
        "placements_per_episode": float(np.mean(final["placements"])),
        "seconds": float(seconds),
    }


TABLE_COLUMNS = (("method", "{:<34}", "method"), ("episodes", "{:>6d}", "eps"),
                 ("SR", "{:>7.2f}", "SR"), ("SR_diffuser", "{:>8.2f}", "SR_Diff"),
                 ("all_constraints", "{:>7.2f}", "all"), ("tower", "{:>7.2f}", "tower"),
                 ("placements_per_episode", "{:>6.2f}", "moves"), ("seconds", "{:>7.1f}", "sec"))


def format_table(rows) -> str:
    """A plain-text table of result rows (missing values shown as '-')."""
    widths = [len(fmt.format(0 if key != "method" else "")) for key, fmt, _ in TABLE_COLUMNS]
    head = " ".join(h.ljust(w) if k == "method" else h.rjust(w)
                    for (k, _, h), w in zip(TABLE_COLUMNS, widths))
    lines = [head, "-" * len(head)]
    for row in rows:
        cells = [fmt.format(row[k]) if row.get(k) is not None else "-".rjust(w)
                 for (k, fmt, _), w in zip(TABLE_COLUMNS, widths)]
        lines.append(" ".join(cells))
    return "\n".join(lines)


def pooled_row(method: str, rows, seconds: float) -> dict:
    """The main row: every column's constraints pooled (the contract-4 SR of the states file)."""
    total = sum(r["constraints"] for r in rows)
    episodes = sum(r["episodes"] for r in rows)

    def mean(key, weight):
        values = [(r[key], r[weight]) for r in rows if r.get(key) is not None]
        if not values:
            return None
        return sum(v * w for v, w in values) / sum(w for _, w in values)

    return {"method": method, "column": "all", "episodes": episodes, "constraints": total,
            "SR": mean("SR", "constraints"), "SR_diffuser": mean("SR_diffuser", "constraints"),
            "all_constraints": mean("all_constraints", "episodes"),
            "tower": mean("tower", "episodes"),
            "placements_per_episode": mean("placements_per_episode", "episodes"),
            "seconds": float(seconds)}


def write_json(path: str, result: dict) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(result, f, indent=2)
    print(f"wrote {path}")


def write_states(path: str, parts) -> None:
    """Contract 4: the final physics state of every episode (parts: (episodes, final) pairs)."""
    from envs.kuka import grammar, scene

    arrays = {
        "block_pos": np.concatenate([f["block_pos"] for _, f in parts]).astype(np.float32),
        "block_quat": np.concatenate([f["block_quat"] for _, f in parts]).astype(np.float32),
        "held": np.concatenate([f["held"] for _, f in parts]).astype(bool),
        "block_half_size": np.asarray(scene.BLOCK_HALF_SIZE, np.float32),
        "constraints": np.concatenate([np.asarray(e.constraints) for e, _ in parts]).astype(
            np.int32),
        "instruction": np.array([grammar.decode(t) for e, _ in parts
                                 for t in np.asarray(e.tokens)]),
    }
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    np.savez_compressed(path, **arrays)


def write_figures(out_dir: str, spec, episodes, final, count: int) -> list[str]:
    """PNGs of the first `count` episodes: the view at t = 0 (blocks flat at their initial
    centres) with the expert's first path and place cell, and the view at the end."""
    import jax

    from envs.kuka import expert, grammar, grid, render, scene

    paths = []
    for i in range(min(count, episodes.block_xy.shape[0])):
        episode = jax.tree.map(lambda x: x[i], episodes)
        pos0 = np.concatenate([episode.block_xy, np.full((4, 1), scene.BLOCK_HALF_SIZE[2])], 1)
        flat = np.tile(np.array([1.0, 0, 0, 0], np.float32), (4, 1))
        first = expert.decide(pos0, np.zeros(4, bool), episode)
        top0, height0 = grid.top_down_view(pos0, flat)
        top1, height1 = grid.top_down_view(final["block_pos"][i], final["block_quat"][i],
                                           final["held"][i])
        panels = [
            dict(top=top0, height=height0, path=first.path, goal=first.goal,
                 title="t = 0, expert's first path"),
            dict(top=top1, height=height1,
                 title=f"end ({int(final['placements'][i])} placements)"),
        ]
        paths.append(render.episode_figure(
            os.path.join(out_dir, f"{spec.name}_{i:03d}.png"), panels,
            grammar.decode(np.asarray(episode.tokens))))
    return paths


def video_frames(spec, final, count: int) -> dict:
    """{name: qpos frames (F, nq)} of the first `count` episodes (every placement made)."""
    videos = {}
    for i in range(min(count, final["frames"].shape[0])):
        used = max(int(final["placements"][i]), 1)
        frames = final["frames"][i, :used]
        videos[f"{spec.name}_{i:03d}"] = frames.reshape(-1, frames.shape[-1])
    return videos


def write_videos(out_dir: str, videos: dict) -> list[str]:
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


# --------------------------------------------------------------------------------- CLI

def main(kind: str, argv: Sequence[str] | None = None) -> dict:
    parser = build_parser(kind)
    args = parser.parse_args(argv)
    check_args(parser, args)

    from diffplan.jax_cache import enable_compilation_cache

    enable_compilation_cache()
    import jax
    from tqdm import tqdm

    from envs.kuka import tasks

    specs = [tasks.TaskSpec(kind, multi, args.language) for multi in (False, True)]
    bar = tqdm(total=args.episodes * len(specs), desc=f"kuka {kind} ({args.policy})", unit="ep",
               disable=args.no_progress, file=sys.stderr, leave=False)
    rows, parts = [], []
    start = time.time()
    for spec in specs:
        t0 = time.time()
        episodes = generate_episodes(spec, args.episodes, args.seed, args.batch_size)
        final = run_policy(args.policy, episodes, args.batch_size, bar)
        column = "multi" if spec.multi else "single"
        label = "multi-constraint" if spec.multi else "single constraint"
        rows.append(column_metrics(f"{args.policy}, {label}", column, episodes, final,
                                   time.time() - t0))
        parts.append((episodes, final))
    bar.close()
    main_row = pooled_row(args.policy, rows, time.time() - start)
    rows = [main_row] + rows
    result = {
        "experiment": f"kuka_{kind}",
        "episodes": args.episodes,
        "seed": args.seed,
        "policy": args.policy,
        "language": args.language,
        "states_method": main_row["method"],
        "paper": {name: dict(zip(("single", "multi"), values))
                  for name, values in PAPER[kind].items()},
        "machine": f"{os.cpu_count()} CPU cores, jax {jax.__version__} on "
                   f"{jax.devices()[0].platform}",
        "rows": rows,
    }
    print(f"\nkuka_{kind}: {args.episodes} episodes per column, seed {args.seed}, "
          f"policy {args.policy}, {args.language} instructions; success on final physical "
          "poses (SR strict, contract 4; SR_Diff Diffuser's check)")
    print(format_table(rows))
    print("paper (Table 2): " + "; ".join(
        f"{name} {s:.2f}" + (f" / {m:.2f}" if m is not None else " / -")
        for name, (s, m) in PAPER[kind].items()) + "  (single / multi)")
    if args.json:
        write_json(args.json, result)
    if args.states:
        write_states(args.states, parts)
        print(f"wrote {args.states} ({sum(len(f['placements']) for _, f in parts)} final states "
              f"of the '{main_row['method']}' row)")
    if args.figures and args.num_figures:
        written = [p for spec, (eps, fin) in zip(specs, parts)
                   for p in write_figures(args.figures, spec, eps, fin, args.num_figures)]
        print(f"wrote {len(written)} figures to {args.figures}")
    if args.video and args.num_videos:
        videos = {}
        for spec, (_, fin) in zip(specs, parts):
            videos.update(video_frames(spec, fin, args.num_videos))
        write_videos(args.video, videos)
    return result
