"""The flags of ``python -m experiments.babyai`` and their checks, run before any work: a user
error (an unknown level, one the Task cannot plan, a mission outside the GoTo grammar, a bad
count or path) ends in one line on stderr, exit code 2."""
from __future__ import annotations

import argparse
import os

from envs.babyai.config import LEVELS
from experiments.babyai.spec import MODES, SPECS
from experiments.harness import cli, core as harness
from experiments.harness.recipes import MODEL_SIZES

TRAIN_FLAGS = {"train_dir": "--train-dir", "train_steps": "--train-steps",
               "train_seed": "--train-seed", "checkpoint_every": "--checkpoint-every",
               "model_size": "--model-size", "bc_steps": "--bc-steps"}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m experiments.babyai",
        description="BabyAI GoTo levels (minigrid's BabyAI-GoToLocal-v0, -GoToObjMaze-v0, "
                    "-GoTo-v0): our planner (on-the-fly and warm start), BC on the same "
                    "demonstrations and the BabyAI bot on minigrid's own episodes. The planner "
                    "and BC act in the jitted port; every executed action is then stepped in "
                    "minigrid, whose reward (> 0: success), termination and truncation are "
                    "what the table reports, with the port/minigrid mismatches (must be 0). "
                    "--train trains ours on the level's cached minigrid layouts, then BC on the "
                    "same demonstrations; --demos-sweep measures sample efficiency.")
    p.add_argument("--level", required=True, metavar="LEVEL",
                   help=f"the level: {', '.join(LEVELS)} (or its minigrid id, e.g. "
                        "BabyAI-GoTo-v0)")
    harness.add_seed_flags(p, episodes=1000, episodes_help="evaluation episodes per seed",
                           episode_of="minigrid's level reset with seed S * 2**20 + i "
                                      "(envs/babyai/seeds.py)")
    p.add_argument("--json", metavar="PATH", help="write the results (contract 2) as JSON")
    cli.add_training_flags(p, training_name="babyai_<level>", served="its level",
                           train_steps="the level's: 4000 GoToLocal, 1900 GoToObjMaze, 5400 GoTo",
                           checkpoint_every=250, model_sizes=MODEL_SIZES)
    p.add_argument("--demos", type=int, default=None, metavar="N",
                   help="training episodes (minigrid layouts with the expert's demonstration) "
                        "--train and --demos-sweep may learn from: training layouts 0..N-1 "
                        "only, for ours and BC (default 2000)")
    p.add_argument("--detour-prob", type=float, default=None, metavar="P",
                   help="share of the denoiser's examples taken off the demonstration after a "
                        "few random actions, labelled by the expert from there (default 0.5; "
                        "0: states along the demonstrations only, as BC and BabyAI's "
                        "imitation learning)")
    p.add_argument("--bc-steps", type=int, default=None,
                   help="BC's step limit with --train (default 30000); it stops earlier once "
                        "converged or once it has used our denoiser's training minutes")
    p.add_argument("--bc-checkpoint", metavar="DIR",
                   help="BC to evaluate (default: the denoiser's directory + '_bc')")
    p.add_argument("--modes", default=None,
                   help=f"our planning modes, comma-separated, of {','.join(MODES)} (default the "
                        "level's: both for GoToLocal; warm_start for the maze levels, where "
                        "1000 on-the-fly episodes take about 27 min on 2 cores)")
    p.add_argument("--num-steps", type=int, default=None,
                   help="denoising steps of an on-the-fly plan (default: the level's, 10 "
                        "GoToLocal, 5 the maze levels)")
    p.add_argument("--batch-size", type=int, default=64,
                   help="episodes planned at once (the slot pool; default 64)")
    p.add_argument("--mission", metavar="TEXT",
                   help="count only the episodes whose mission is TEXT ('go to the red ball')")
    p.add_argument("--random-weights", action="store_true",
                   help="add a control row: the same planner (warm start, the same psi) with "
                        "a denoiser of random weights, showing what the hand-written parts "
                        "achieve without anything learned")
    p.add_argument("--no-bc", action="store_true", help="leave out the BC row")
    p.add_argument("--no-bot", action="store_true", help="leave out the BabyAI bot's row")
    p.add_argument("--demos-sweep", metavar="N1,N2,...",
                   help="sample efficiency: train ours with each number of demonstrations "
                        "(in --sweep-dir/demos_N, resumable), evaluate each on the validation "
                        "seed, report the fewest reaching 99%% and its SR on --seeds, and draw "
                        "success against demos")
    p.add_argument("--sweep-dir", metavar="DIR",
                   help="the sweep's runs and results (default runs/babyai_<level>_demos)")
    p.add_argument("--figure", metavar="PATH.png",
                   help="the sweep's figure (default <sweep-dir>/success_vs_demos.png)")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    return p


def _counts(text: str, flag: str, parser) -> tuple[int, ...]:
    try:
        values = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        parser.error(f"{flag} must be comma-separated integers, got {text!r}")
    if not values or min(values) < 1 or len(set(values)) != len(values):
        parser.error(f"{flag} must be distinct integers >= 1, got {text!r}")
    return tuple(sorted(values))


def check_args(parser, args):
    """Checks and fills the arguments; returns (LevelSpec, modes, seeds)."""
    import dataclasses

    from envs.babyai.config import level_name
    from envs.babyai.grammar import parse

    try:
        args.level = level_name(args.level)
        if args.mission is not None:
            parse(args.mission)
    except ValueError as e:
        parser.error(str(e))
    spec = SPECS[args.level]
    sweep = args.demos_sweep is not None
    cli.only_with(parser, args, "train", {k: v for k, v in TRAIN_FLAGS.items()
                                          if not sweep or k in ("train_dir", "bc_steps")})
    if args.train and args.checkpoint is not None:
        parser.error("--checkpoint and --train exclude each other: --train evaluates what it "
                     "trains (its output directory is --train-dir)")
    if sweep and (args.train or args.checkpoint or args.bc_checkpoint):
        parser.error("--demos-sweep trains its own runs: leave out --train, --checkpoint and "
                     "--bc-checkpoint")
    if not (args.train or sweep) and (args.demos is not None or args.detour_prob is not None):
        parser.error("--demos and --detour-prob set what --train (or --demos-sweep) learns from")
    if sweep and args.demos is not None:
        parser.error("--demos-sweep gives the numbers of demonstrations; leave out --demos")
    cli.only_with(parser, args, "demos_sweep", {"sweep_dir": "--sweep-dir",
                                                "figure": "--figure"})
    for flag, value in (("--episodes", args.episodes), ("--batch-size", args.batch_size),
                        ("--num-steps", args.num_steps), ("--demos", args.demos),
                        ("--bc-steps", args.bc_steps)):
        cli.check_at_least(parser, flag, value, 1)
    cli.check_at_least(parser, "--train-steps", args.train_steps, 2)
    cli.check_at_least(parser, "--checkpoint-every", args.checkpoint_every, 1)
    cli.check_at_least(parser, "--seed", args.seed, 0)
    if args.detour_prob is not None and not 0.0 <= args.detour_prob <= 1.0:
        parser.error(f"--detour-prob must be in [0, 1], got {args.detour_prob}")
    cli.check_output_file(parser, "--json", args.json)
    cli.check_output_file(parser, "--figure", args.figure, suffix=".png")
    for flag, path in (("--train-dir", args.train_dir), ("--sweep-dir", args.sweep_dir)):
        cli.check_output_dir(parser, flag, path)
    if args.modes is None:
        args.modes = ",".join(spec.modes)
    modes = tuple(m.strip() for m in args.modes.split(",") if m.strip())
    if not modes or any(m not in MODES for m in modes) or len(set(modes)) != len(modes):
        parser.error(f"--modes must be distinct names of {','.join(MODES)}, got {args.modes!r}")
    seeds = harness.parse_seeds(parser, args)
    from envs.babyai.seeds import EPISODE_BITS, SEED_BITS

    for seed in seeds:
        if seed >= 2 ** SEED_BITS:
            parser.error(f"a BabyAI evaluation seed must be below {2 ** SEED_BITS} (episode i of "
                         f"seed S is minigrid's seed S * 2**{EPISODE_BITS} + i), got {seed}")
    if args.episodes is not None and args.episodes > 2 ** EPISODE_BITS:
        parser.error(f"--episodes must be at most {2 ** EPISODE_BITS} per seed, got "
                     f"{args.episodes}")
    if sweep:
        args.demos_sweep = _counts(args.demos_sweep, "--demos-sweep", parser)
        args.sweep_dir = args.sweep_dir or os.path.join(harness.REPO_ROOT, "runs",
                                                        f"{spec.name}_demos")
    if args.num_steps is not None:
        spec = dataclasses.replace(spec, num_steps=args.num_steps)
    return spec, modes, seeds
