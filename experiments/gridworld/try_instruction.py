"""One grid-world episode planned for your own sentence (``python -m experiments.try_instruction
"..." --setting p_mo2g --seed 3 --figure out.png``): the world of an evaluation episode is
kept, its instruction replaced by the user's text, encoded by the checkpoint's frozen
pretrained text encoder; the outcome printed in one line and, with --figure, the map, the
executed path and the plans at a few moves drawn (experiments.gridworld.figures)."""
from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import tempfile
from typing import Sequence

import numpy as np

from experiments.gridworld import eval as ge, text
from experiments.gridworld.spec import METHOD_NAMES, SPECS, load_checked
from experiments.harness import cli, core as harness

WORLDS = ("gridworld", "kuka")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m experiments.try_instruction",
        description="Plan one episode for an instruction of your own: the world of evaluation "
                    "episode --episode of --seed is kept, its instruction replaced by TEXT "
                    "(any English; only an empty instruction or one over the encoder's "
                    "length limit is refused). The sentence is read by a denoiser on a frozen "
                    "pretrained text encoder's features. It should name objects of this "
                    "episode (the map lists them, e.g. with --figure): an instruction naming "
                    "objects that are not there simply fails.")
    p.add_argument("text", help="the instruction, e.g. \"First go to the apple, then find the "
                                "pear north of it.\"")
    p.add_argument("--world", choices=WORLDS, default="gridworld",
                   help="the world (default gridworld; kuka: the Kuka blocks, planned by "
                        "experiments/kuka/try_instruction.py, whose flags `--world kuka "
                        "--help` shows)")
    p.add_argument("--setting", choices=sorted(SPECS), default="p_mo2g",
                   help="the grid-world setting of the episode (default p_mo2g)")
    p.add_argument("--seed", type=int, default=harness.DEFAULT_EVAL_SEED,
                   help=f"evaluation seed of the episode (default {harness.DEFAULT_EVAL_SEED})")
    p.add_argument("--episode", type=int, default=0,
                   help="which episode of the seed: episode i = generate(fold_in(PRNGKey(seed), "
                        "i)) (default 0)")
    p.add_argument("--checkpoint", default=None,
                   help="a denoiser checkpoint on pretrained text features (default the "
                        "shipped one of the setting: checkpoints/compile_gridworld_pretrained, "
                        "or compile_gridworld_far_pretrained for p_mo2g_far)")
    p.add_argument("--mode", choices=tuple(METHOD_NAMES), default=None,
                   help="planning mode (default the setting's main row, on_the_fly)")
    p.add_argument("--figure", metavar="OUT.png",
                   help="write the episode's figure: the map with the executed path over the "
                        "expert's, then the plan at a few moves")
    p.add_argument("--json", metavar="PATH", help="write the outcome as JSON")
    return p


def default_checkpoint(spec) -> str:
    """The shipped features checkpoint of the setting; one line (exit 2) saying how to train
    one where it is not there."""
    path = os.path.join(harness.CHECKPOINT_ROOT, spec.training_name)
    if not os.path.isdir(path):
        harness.fail(f"no denoiser on pretrained text features is shipped yet ({path}): train "
                     f"one with `python -m experiments.{spec.name} --train --text pretrained` "
                     f"and pass --checkpoint runs/{spec.training_name}")
    return path


def outcome(rollout, episodes, has_reference: bool) -> dict:
    """success, ordered (None without a reference), moves and denoiser calls of episode 0."""
    from envs.gridworld.metrics import trajectory_metrics

    row = trajectory_metrics(rollout.positions[:1], rollout.steps[:1], episodes.target[:1],
                             episodes.expert_path[:1],
                             episodes.reference[:1] if has_reference else None)
    return {"success": row["SR"] == 100.0,
            "ordered": row["SR_ordered"] == 100.0 if has_reference else None,
            "moves": int(rollout.steps[0]),
            "denoiser_calls": int(rollout.denoiser_calls[0])}


def main(argv: Sequence[str] | None = None) -> dict:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.world != "gridworld":
        harness.fail(f"--world {args.world} is planned by `python -m "
                     f"experiments.try_instruction --world {args.world}`, not the grid world's")
    cli.check_at_least(parser, "--episode", args.episode, 0)
    cli.check_output_file(parser, "--json", args.json)
    if args.figure:
        cli.check_output_file(parser, "--figure", args.figure, suffix=".png")
    spec = dataclasses.replace(SPECS[args.setting], text="pretrained")
    spec = dataclasses.replace(spec, main_mode=args.mode or spec.main_mode)
    from diffplan.jax_cache import enable_compilation_cache

    enable_compilation_cache()
    checkpoint = args.checkpoint or default_checkpoint(spec)
    denoiser = load_checked(checkpoint, spec, (spec.main_mode,), parser,
                            f"python -m experiments.{spec.name} --train --text pretrained")
    encoder = text.checkpoint_encoder(checkpoint, denoiser)
    if encoder is None:
        harness.fail(f"the checkpoint {checkpoint} reads token ids, not pretrained text "
                     f"features: pass one trained with --text pretrained")
    try:
        features = encoder.encode(args.text)
    except ValueError as e:
        harness.fail(str(e))
    episodes = ge.eval_episodes(spec.grid_config(), args.episode + 1, args.seed)
    episodes = ge.select(episodes, np.arange(args.episode + 1) == args.episode)
    episodes = episodes.replace(features=features[None])
    task = spec.task(denoiser.num_gen_channels, features=True)
    rollout, _ = ge.evaluate_mode(spec, task, denoiser, episodes, args.seed, spec.main_mode,
                                  1, progress=False, record_plans=bool(args.figure))
    result = {"text": args.text, "setting": args.setting, "seed": args.seed,
              "episode": args.episode, "checkpoint": checkpoint, "mode": spec.main_mode,
              **outcome(rollout, episodes, spec.grid_config().has_reference)}
    ordered = ("" if result["ordered"] is None else
               f", ordered {'yes' if result['ordered'] else 'no'}")
    print(f"{'success' if result['success'] else 'failure'}{ordered}, {result['moves']} moves, "
          f"{result['denoiser_calls']} denoiser calls ({METHOD_NAMES[spec.main_mode]}, "
          f"{args.setting} seed {args.seed} episode {args.episode})")
    print(f"(success is measured against the episode's own instruction: "
          f"\"{text.texts(episodes, args.setting)[0]}\")")
    if args.figure:
        from experiments.gridworld.figures import write_figures

        with tempfile.TemporaryDirectory() as tmp:
            path, = write_figures(tmp, spec, task, denoiser, episodes, args.seed, 1,
                                  [args.text])
            shutil.move(path, args.figure)
        print(f"wrote {args.figure}")
    if args.json:
        cli.write_json(args.json, result)
    return result
