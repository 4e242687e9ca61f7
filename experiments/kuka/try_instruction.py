"""One Kuka episode planned for your own sentence (``python -m experiments.try_instruction "Put
the red block on the blue block, please." --world kuka --task stacking --seed 3 --video
out.gif``): the initial blocks of an evaluation episode are kept, its instruction replaced by
the user's text, encoded by the checkpoint's frozen pretrained text encoder; the planner runs
under MJX physics as in the Kuka CLIs (experiments.kuka.cli: the same planner keys, so the
episode's own text would give the CLI's episode), and the outcome is printed in one line:
success against the episode's own relations (the user's sentence is free English, and may ask
for others), measured on the final physical poses, and the relations actually built. With
--figure the top-down view before every placement with its plan (experiments.kuka.figures),
with --video an animated GIF of the blocks seen from above, move by move."""
from __future__ import annotations

import argparse
import os
from typing import Sequence

import jax
import numpy as np

from envs.kuka.config import KINDS, TaskSpec
from envs.kuka.env import SETTLE_SECONDS
from experiments.harness import cli, core as harness
from experiments.kuka import eval as ke, spec as ks

TRAIN_COMMAND = "python -m experiments.kuka_stacking --train --text pretrained"
VIDEO_EVERY = 2
"""Every VIDEO_EVERY-th recorded physics frame (0.04 s apart) is drawn in --video's GIF."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m experiments.try_instruction --world kuka",
        description="Plan one Kuka block episode for an instruction of your own: the blocks "
                    "of evaluation episode --episode of --seed are kept, its instruction "
                    "replaced by TEXT (any English; only an empty instruction or one over the "
                    "encoder's length limit is refused), read by a denoiser on a frozen "
                    "pretrained text encoder's features. Name the blocks by colour (red, "
                    "green, blue, yellow). Success is measured on the final physical poses "
                    "against the episode's own instruction (printed too); the line also says "
                    "which block ended on which, whatever was asked. (python -m "
                    "experiments.try_instruction --help: the grid world's flags.)")
    p.add_argument("text", help="the instruction, e.g. \"Put the red block on the blue "
                                "block, please.\"")
    p.add_argument("--world", choices=("kuka",), default="kuka",
                   help=argparse.SUPPRESS)  # in the prog: experiments.try_instruction's choice
    p.add_argument("--task", choices=KINDS, default="stacking",
                   help="the kind of the episode (default stacking: a tower of all four "
                        "blocks and one relation)")
    p.add_argument("--multi", action="store_true",
                   help="a multi-constraint episode (3 relations stacking, 2 rearrangement)")
    p.add_argument("--seed", type=int, default=harness.DEFAULT_EVAL_SEED,
                   help="the evaluation seed the episode is drawn from, the Kuka CLIs' --seed "
                        f"(default {harness.DEFAULT_EVAL_SEED})")
    p.add_argument("--episode", type=int, default=0,
                   help="the episode of that seed (default 0): the Kuka CLIs' episode of this "
                        "index, its blocks where they stood and the planner's key its own")
    p.add_argument("--checkpoint", default=None,
                   help="a Kuka denoiser checkpoint on pretrained text features (default "
                        f"checkpoints/{ks.training_name('pretrained')})")
    p.add_argument("--mode", choices=ks.MODES, default=ks.MAIN_MODE,
                   help=f"planning mode (default {ks.MAIN_MODE}: a plan before every placement)")
    p.add_argument("--figure", metavar="OUT.png",
                   help="write the top-down view before every placement with the plan made "
                        "there, and the view at the end")
    p.add_argument("--video", metavar="OUT.gif",
                   help="write an animated GIF of the blocks seen from above over the "
                        "executed placements")
    p.add_argument("--json", metavar="PATH", help="write the outcome as JSON")
    return p


def check_args(parser, args) -> None:
    """One-line errors (exit 2) for bad flags, before any work."""
    cli.check_at_least(parser, "--episode", args.episode, 0)
    cli.check_at_least(parser, "--seed", args.seed, 0)
    cli.check_output_file(parser, "--json", args.json)
    cli.check_output_file(parser, "--figure", args.figure, suffix=".png")
    cli.check_output_file(parser, "--video", args.video, suffix=".gif")


def load_denoiser(checkpoint: str | None, kind: str):
    """(checkpoint, LoadedDenoiser, InstructionEncoder) of a checkpoint on pretrained text
    features (default ks.default_checkpoint("pretrained")); one line (exit 2) for a missing
    default, an unreadable or mismatched checkpoint, or a token-id one."""
    from experiments.harness.text import checkpoint_encoder

    if checkpoint is None:
        checkpoint = ks.default_checkpoint("pretrained")
        if not os.path.isdir(checkpoint):
            harness.fail(f"no Kuka denoiser on pretrained text features is shipped yet "
                         f"({checkpoint}): train one with `{TRAIN_COMMAND}` and pass "
                         f"--checkpoint runs/{ks.training_name('pretrained')}")
    denoiser = ks.load_checked(checkpoint, ks.NUM_STEPS, kind, "pretrained")
    encoder = checkpoint_encoder(checkpoint, denoiser)
    if encoder is None:
        harness.fail(f"the checkpoint {checkpoint} reads token ids, not pretrained text "
                     f"features: pass one trained with --text pretrained")
    return checkpoint, denoiser, encoder


def user_episode(spec: TaskSpec, seed: int, index: int, features):
    """Episode ``index`` of the seed (numpy Episode, leading axis 1) with ``features`` float32
    (L, D), the user's encoded sentence, as the instruction the planner reads."""
    episodes = ke.generate_episodes(spec, index + 1, seed, min(index + 1, ks.DEFAULT_BATCH))
    return jax.tree.map(lambda x: x[-1:], episodes).replace(features=features[None])


def run_episode(task, planner, episodes, seed: int, index: int) -> dict:
    """The planner on the one episode (keys of episode ``index`` of the seed, as the CLIs'),
    then the CLIs' SETTLE_SECONDS at rest: ke.at_rest's numpy dict (block_pos (1, 4, 3),
    held (1, 4), placements (1,), ...) plus denoiser_calls (1,)."""
    run = harness.rollout_fn(task, progress=False)
    out = run(planner, harness.planner_keys(seed, np.array([index])), episodes, 0)
    final = jax.device_get(ke.at_rest(out.final_state, SETTLE_SECONDS))
    return dict(final, denoiser_calls=np.asarray(out.denoiser_calls))


def built_relations(pos, held) -> list[str]:
    """"top on bottom" for every block resting on another (strict, contract 4) in the poses
    pos float (4, 3), held bool (4,)."""
    from envs.kuka import metrics, scene

    on = np.asarray(metrics.on_matrix(pos, held))
    return [f"{scene.BLOCK_NAMES[t]} on {scene.BLOCK_NAMES[b]}" for t, b in zip(*np.nonzero(on))]


def outcome(episodes, final) -> dict:
    """The episode's result on its final physical poses: its own relations held (of how
    many), whether the tower of four it asks for stands (None: it asks for none), success
    (all of them), moves, denoiser calls and the relations built."""
    from envs.kuka import metrics

    strict, _ = ke.constraint_success(episodes, final)
    valid = np.asarray(episodes.constraints)[0, :, 0] >= 0
    pos, held = final["block_pos"][0], final["held"][0]
    tower = (bool(metrics.single_tower(pos, held)) if bool(np.asarray(episodes.tower)[0])
             else None)
    relations_held = int(strict[0][valid].sum())
    return {"success": relations_held == int(valid.sum()) and tower is not False,
            "relations_held": relations_held, "relations": int(valid.sum()), "tower": tower,
            "moves": int(final["placements"][0]),
            "denoiser_calls": int(final["denoiser_calls"][0]),
            "built": built_relations(pos, held)}


def outcome_line(result: dict) -> str:
    """The one line a run prints first, starting with "success" or "failure"."""
    tower = {None: "", True: ", one tower", False: ", no tower of four"}[result["tower"]]
    column = result["task"] + (" multi" if result["multi"] else "")
    return (f"{'success' if result['success'] else 'failure'}: {result['relations_held']}/"
            f"{result['relations']} relations held{tower}; {result['moves']} moves, "
            f"{result['denoiser_calls']} denoiser calls ({ks.METHOD_NAMES[result['mode']]}, "
            f"{column} seed {result['seed']} episode {result['episode']}); built: "
            f"{', '.join(result['built']) or 'nothing (no block on another)'}")


def write_video(path: str, frames, title: str) -> str:
    """An animated GIF of the blocks seen from above (envs.kuka.render.draw_view) at every
    VIDEO_EVERY-th recorded frame of qpos float (F, nq), F = placements x NUM_FRAMES, each
    titled with its placement and time; the last held longer. Returns path."""
    import textwrap

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from PIL import Image

    from envs.kuka import grid, physics, primitive, render, scene

    n = scene.NUM_BLOCKS
    picked = np.unique(np.r_[np.arange(0, len(frames), VIDEO_EVERY), len(frames) - 1])
    blocks = np.asarray(frames)[picked, physics.BLOCK_QPOS0:physics.BLOCK_QPOS0 + 7 * n]
    blocks = blocks.reshape(len(picked), n, 7)
    tops, heights = jax.device_get(jax.jit(jax.vmap(grid.top_down_view))(
        blocks[..., :3], blocks[..., 3:]))
    seconds = primitive.FRAME_EVERY * scene.TIMESTEP
    images = []
    for k, top, height in zip(picked, tops, heights):
        fig = Figure(figsize=(3.4, 3.8), dpi=80, layout="constrained")
        canvas = FigureCanvasAgg(fig)
        fig.suptitle("\n".join(textwrap.wrap(title, 48)), fontsize=7)
        render.draw_view(fig.add_subplot(), top, height, title=(
            f"placement {k // primitive.NUM_FRAMES + 1}, "
            f"{(k % primitive.NUM_FRAMES) * seconds:.2f} s"))
        canvas.draw()
        images.append(Image.fromarray(np.asarray(canvas.buffer_rgba())[..., :3]))
    durations = [int(1000 * seconds * VIDEO_EVERY)] * (len(images) - 1) + [1500]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    images[0].save(path, save_all=True, append_images=images[1:], duration=durations, loop=0)
    return path


def write_pictures(args, task, planner, episodes, own: str) -> None:
    """--figure and --video: the episode re-run move by move (experiments.kuka.figures.trace,
    the same keys, so the same episode)."""
    from envs.kuka import render
    from experiments.kuka.figures import trace

    traced, = trace(task, planner, episodes, harness.planner_keys(
        args.seed, np.array([args.episode])))
    title = f"{args.text} (success measured against the episode's own: {own})"
    if args.figure:
        print(f"wrote {render.episode_figure(args.figure, traced['panels'], title)}")
    if args.video:
        print(f"wrote {write_video(args.video, traced['frames'], args.text)}")


def main(argv: Sequence[str] | None = None) -> dict:
    """Plans the one episode; prints its outcome line first; returns the outcome dict (the
    --json)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    check_args(parser, args)
    from diffplan.jax_cache import enable_compilation_cache
    from diffplan.planner import Planner, PlannerConfig
    from envs.kuka.sentences import episode_texts
    from envs.kuka.task import KukaTask

    enable_compilation_cache()
    checkpoint, denoiser, encoder = load_denoiser(args.checkpoint, args.task)
    try:
        features = encoder.encode(args.text)
    except ValueError as e:
        harness.fail(str(e))
    episodes = user_episode(TaskSpec(args.task, args.multi), args.seed, args.episode, features)
    task = KukaTask(text="features")
    planner = Planner(denoiser, PlannerConfig(mode=args.mode, num_steps=ks.NUM_STEPS))
    final = run_episode(task, planner, episodes, args.seed, args.episode)
    own = episode_texts(episodes)[0]
    result = {"text": args.text, "world": "kuka", "task": args.task, "multi": args.multi,
              "seed": args.seed, "episode": args.episode, "checkpoint": checkpoint,
              "mode": args.mode, "settle_seconds": SETTLE_SECONDS, "episode_instruction": own,
              **outcome(episodes, final)}
    print(outcome_line(result))
    print(f"(success is measured against the episode's own instruction: \"{own}\")")
    if args.figure or args.video:
        write_pictures(args, task, planner, episodes, own)
    if args.json:
        cli.write_json(args.json, result)
    return result
