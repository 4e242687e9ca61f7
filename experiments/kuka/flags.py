"""The flags of the Kuka experiment CLIs (kuka_stacking, kuka_rearrangement) and their checks, run
before any work: a user error ends in one line on stderr, exit code 2."""
from __future__ import annotations

import argparse
import os

from envs.kuka.env import SETTLE_SECONDS
from experiments.harness import cli, core as harness
from experiments.kuka import baselines as kuka_baselines
from experiments.kuka.spec import (CARRIES, CHECKPOINT_EVERY, DEFAULT_BATCH, DEFAULT_EPISODES,
                                   LANGUAGE_CHOICES, MODES, NUM_STEPS, POLICIES, TEXTS,
                                   TRAIN_STEPS, TRAINING_NAME)
from experiments.kuka.baselines import KUKA_BASELINES
from experiments.harness.processes import add_process_flags
from experiments.harness.recipes import MODEL_SIZES


def build_parser(kind: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=f"python -m experiments.kuka_{kind}",
        description=(f"Kuka block world, {kind}: run the diffusion planner (or the scripted "
                     f"expert) on fresh seeded episodes of the single- and multi-constraint "
                     f"{kind} tasks (the paper's Table 2 columns; Table 5 with paraphrased "
                     "instructions) in MuJoCo MJX physics, measure success on the final "
                     "physical block poses (strict, contract 4, and Diffuser's looser check), "
                     "and print/write the results table."))
    harness.add_seed_flags(p, episodes=DEFAULT_EPISODES,
                           episodes_help="evaluation episodes per column and seed",
                           where=" in each column")
    p.add_argument("--policy", choices=POLICIES, default="planner",
                   help="who acts: 'planner' (the diffusion planner, default), 'expert' (the "
                        "scripted expert through the same primitive and physics) or a shipped "
                        f"baseline ({', '.join(KUKA_BASELINES)}: checkpoints/baselines/kuka), "
                        "whose final states --states then writes")
    p.add_argument("--language", choices=tuple(LANGUAGE_CHOICES), default="canonical",
                   help="instruction phrasing: 'canonical' (Table 2, default), 'paraphrased' "
                        "with inverted prepositions (Table 5, the training paraphrases), "
                        "'development' (phrasings training never saw, made of its words, but "
                        "chosen on: development numbers), 'heldout' (sealed held-out phrasings "
                        "in new frames: never trained on, never chosen on), 'natural' (the "
                        "sealed natural-language set, sentences as people type them: only a "
                        "checkpoint on pretrained text features reads them; never part of "
                        "'all', it is measured once, by name), 'both' (canonical and "
                        "paraphrased: every row for each) or 'all' (every one but 'natural')")
    p.add_argument("--text", choices=TEXTS, default="tokens",
                   help="the denoiser's instruction input: 'tokens' (the grammar's word ids, "
                        "default) or 'pretrained' (the frozen pretrained text encoder's "
                        "features of each sentence, checkpoints/text_encoder: any English "
                        "sentence). Selects what --train trains and the default checkpoint "
                        f"(checkpoints/{TRAINING_NAME}_pretrained); with --checkpoint the "
                        "checkpoint decides")
    p.add_argument("--modes", default=",".join(MODES),
                   help=f"comma-separated planning modes (default {','.join(MODES)}); the "
                        "first of them gives the main row")
    cli.add_training_flags(p, training_name=TRAINING_NAME, served="both Kuka experiments",
                           train_steps=TRAIN_STEPS, checkpoint_every=CHECKPOINT_EVERY,
                           model_sizes=MODEL_SIZES)
    p.add_argument("--reader", metavar="DIR",
                   help="restate every instruction canonically before the planner reads it, "
                        "with a reader (taggers of which block is the upper one, trained on "
                        "the training phrasings only: python -m experiments.train_reader); "
                        "its rows say 'read'")
    p.add_argument("--num-steps", type=int, default=NUM_STEPS,
                   help=f"denoising steps per plan (default {NUM_STEPS})")
    p.add_argument("--carry", choices=CARRIES, default="path",
                   help="carry blocks along the in-painted path ('path', default) or the "
                        "expert's arc around the base ('arc')")
    p.add_argument("--settle", type=float, default=SETTLE_SECONDS, metavar="SECONDS",
                   help="simulated seconds the blocks rest (suction off, the arm in its retreat "
                        f"pose) before success is read (default {SETTLE_SECONDS:g}; 0 reads the "
                        "poses as the last placement left them)")
    p.add_argument("--json", metavar="PATH", help="write the results (contract 2) as JSON")
    p.add_argument("--states", metavar="PATH.npz",
                   help="write the final physics state of every episode of the main row "
                        "(contract 4): single-constraint episodes first, then multi-constraint "
                        "(each over the seeds in order)")
    p.add_argument("--batch-size", type=int, default=DEFAULT_BATCH,
                   help=f"episodes per jitted, vmapped call and device (default {DEFAULT_BATCH})")
    p.add_argument("--figures", metavar="DIR",
                   help="write PNGs of a few episodes: the top-down view before every "
                        "placement with the in-painted path, pick and goal estimate, and the "
                        "view at the end (expert: its first path)")
    p.add_argument("--num-figures", type=int, default=3,
                   help="episodes per column drawn with --figures (default 3)")
    p.add_argument("--video", metavar="DIR",
                   help="render a few episodes offscreen to animated GIFs (needs an EGL or "
                        "OSMesa GL backend; without one a line says so and the run goes on)")
    p.add_argument("--num-videos", type=int, default=2,
                   help="episodes per column rendered with --video (default 2)")
    p.add_argument("--baselines", nargs="?", const=",".join(KUKA_BASELINES), default=None,
                   metavar="NAMES",
                   help="add rows of the shipped Kuka baselines (checkpoints/baselines/kuka; "
                        f"comma-separated of {','.join(KUKA_BASELINES)}; the flag alone: all), "
                        "measured on the same episodes, seeds and physics as the main rows")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    add_process_flags(p)
    return p


TRAIN_FLAGS = {"train_dir": "--train-dir", "train_steps": "--train-steps",
               "train_seed": "--train-seed", "checkpoint_every": "--checkpoint-every",
               "model_size": "--model-size"}


MAX_SETTLE = 10.0
"""Longest --settle (2000 physics steps per episode)."""


def check_args(parser, args) -> tuple[str, ...]:
    """Validates the arguments (one-line errors before any work); returns the modes."""
    cli.check_training_flags(parser, args, TRAIN_FLAGS)
    if args.policy != "planner" and (args.train or args.checkpoint or args.reader):
        parser.error("--train, --checkpoint and --reader only make sense with --policy "
                     "planner")
    if args.policy != "planner" and args.text != "tokens":
        parser.error("--text selects the planner's denoiser: it needs --policy planner")
    if args.language == "natural":
        _check_natural(parser, args)
    if args.reader and not os.path.isdir(args.reader):
        parser.error(f"--reader {args.reader!r} is not a directory (write one with python -m "
                     "experiments.train_reader --out DIR)")
    if args.policy in KUKA_BASELINES:
        if args.figures or args.video:
            parser.error("--figures and --video draw the planner or the expert, not a "
                         "baseline")
        _check_baselines(parser, args.policy)
    for flag, value, minimum in (("--episodes", args.episodes, 1), ("--seed", args.seed, 0),
                                 ("--batch-size", args.batch_size, 1),
                                 ("--num-steps", args.num_steps, 1),
                                 ("--num-figures", args.num_figures, 0),
                                 ("--num-videos", args.num_videos, 0)):
        cli.check_at_least(parser, flag, value, minimum)
    if not 0.0 <= args.settle <= MAX_SETTLE:
        parser.error(f"--settle must be between 0 and {MAX_SETTLE:g} simulated seconds, got "
                     f"{args.settle}")
    cli.check_output_file(parser, "--json", args.json)
    cli.check_output_file(parser, "--states", args.states, suffix=".npz")
    for flag in ("figures", "video", "train_dir"):
        cli.check_output_dir(parser, f"--{flag.replace('_', '-')}", getattr(args, flag))
    modes = tuple(m.strip() for m in args.modes.split(",") if m.strip())
    bad = [m for m in modes if m not in MODES]
    if bad or not modes or len(set(modes)) != len(modes):
        parser.error(f"--modes must be distinct modes of {MODES}, got {args.modes!r}")
    args.baselines = _check_baselines(parser, args.baselines)
    return modes


def _check_natural(parser, args) -> None:
    """--language natural: read only by the planner's denoiser on pretrained text features
    (whether the checkpoint is one is checked once it is loaded, experiments.harness.text);
    the expert reads no instruction, and the baselines and the reader read token ids."""
    if args.policy != "planner":
        parser.error("--language natural is read only by a denoiser on pretrained text "
                     "features: it needs --policy planner")
    if args.baselines or args.reader:
        parser.error(f"--{'baselines' if args.baselines else 'reader'} reads token ids, which "
                     "natural sentences have no way to give: leave it out with --language "
                     "natural")


def _check_baselines(parser, names: str | None) -> tuple[str, ...]:
    """Kuka baseline names (``cli.check_baselines``: known, distinct, shipped)."""
    return cli.check_baselines(parser, names, KUKA_BASELINES, kuka_baselines.CHECKPOINT_DIR,
                               "python -m experiments.train_baselines --world kuka --ship")
