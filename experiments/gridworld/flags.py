"""The flags of the grid-world experiment CLIs (compile_1o1g, compile_mo1g, compile_p_mo2g,
compile_p_mo2g_far) and their checks, run before any work: a user error ends in one line on
stderr, exit code 2."""
from __future__ import annotations

import argparse
import os

from envs.gridworld.task import PSI_KINDS, check_follow_mark
from experiments.harness import cli, core as harness
from experiments.gridworld.spec import (LANGUAGE_CHOICES, MODE_REPLAN, TRAINING_NAME,
                                        TRIGGER_WORDS, ExperimentSpec)
from experiments.harness.processes import add_process_flags
from experiments.harness.recipes import MODEL_SIZES


def build_parser(spec: ExperimentSpec) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=f"python -m experiments.{spec.name}",
        description=(f"CompILE grid world, setting {spec.setting}: evaluate the diffusion planner "
                     "on fresh seeded episodes in each planning mode, measured on what the agent "
                     "executed (with collisions), and print/write the results table."))
    harness.add_seed_flags(p, episodes=1000, episodes_help="number of evaluation episodes")
    p.add_argument("--json", metavar="PATH", help="write the results (contract 2) as JSON")
    p.add_argument("--trajectories", metavar="PATH.npz",
                   help="write the executed trajectories of the main row and the episodes "
                        "(of every seed, in order)")
    served = ("all three paper settings" if spec.checkpoint_name == TRAINING_NAME
              else f"{spec.setting} (and the paper settings it also trained on)")
    cli.add_training_flags(p, training_name=spec.checkpoint_name, served=served,
                           train_steps=spec.train_steps if spec.pretrained_train_steps is None
                           else f"{spec.train_steps}; {spec.pretrained_train_steps} with --text "
                                "pretrained", checkpoint_every=500,
                           model_sizes=MODEL_SIZES)
    p.add_argument("--prediction", choices=("eps", "x0"), default=None,
                   help="network target of --train: the noise (the paper) or the clean plan "
                        f"(default {spec.prediction}; evaluation follows the checkpoint)")
    p.add_argument("--objective", choices=("diffusion", "goal"), default=None,
                   help="what --train learns: the diffusion planner (default) or the "
                        "learned-goal baseline, the same network trained on the same batches "
                        "to predict the goal and sub-goal cells directly (a classification "
                        "over cells; diffplan.baselines.goal), evaluated through the same "
                        "planner and psi with --num-steps 1")
    p.add_argument("--modes", default=",".join(spec.modes),
                   help=f"comma-separated planning modes to evaluate (default "
                        f"{','.join(spec.modes)})")
    p.add_argument("--num-steps", type=int, default=spec.num_steps,
                   help=f"denoising steps per full plan (default {spec.num_steps})")
    p.add_argument("--warm-start-step", type=int, default=spec.warm_start_step,
                   help="steps of the warm-start schedule skipped by its re-plans: each costs "
                        "--warm-num-steps minus this denoiser calls "
                        f"(default {spec.warm_start_step})")
    p.add_argument("--warm-num-steps", type=int, default=spec.warm_num_steps,
                   help="steps of the warm-start row's schedule (default "
                        f"{spec.warm_num_steps or 'the --num-steps'}): its first plan runs all "
                        "of them from noise, each re-plan resumes at --warm-start-step")
    p.add_argument("--noise", choices=("fresh", "episode"),
                   default="fresh" if spec.fresh_noise else "episode",
                   help="initial noise of re-plans: 'fresh' draws new noise at every move, "
                        "'episode' reuses the episode's noise so plans change only where the "
                        "observation did (default %(default)s)")
    p.add_argument("--eta", type=float, default=spec.eta,
                   help="sampler stochasticity: 0 = DDIM (default), 1 = DDPM-like")
    p.add_argument("--replan", choices=tuple(TRIGGER_WORDS), default=spec.replan,
                   help="re-planning trigger of every re-planning row: before every move "
                        "('always', the paper), only when new cells were seen or the plan's "
                        "sub-goal was reached ('on_change'), or only when a seen cell disproved "
                        "where the plan heads (it is not the object sought, or that object is "
                        "seen elsewhere) or the sub-goal was reached ('on_refuted': a guess of "
                        "a hidden target is kept until disproved); default: each row's own, "
                        + ", ".join(f"{m} {r}" for m, r in MODE_REPLAN.items()))
    p.add_argument("--psi", choices=PSI_KINDS, default=spec.psi,
                   help="how a plan becomes a move: 'search' (a Dijkstra search toward the "
                        "plan's sub-goal over the cells not known to be obstacles, the plan's "
                        "path cells cheaper) or 'follow' (the paper's: step onto the neighbour "
                        "the plan marks most strongly as path; where none is marked plan again "
                        "once, then step greedily toward the sub-goal; the table's fb%% column "
                        f"is the share of such fallback moves) (default {spec.psi})")
    p.add_argument("--follow-mark", type=float, default=spec.follow_mark,
                   help="with --psi follow: the path value (the channel spans [-1, 1]) above "
                        "which a neighbour counts as marked by the plan; lower values also "
                        "follow the faint marks a drawn path leaves where it has a gap "
                        f"(default {spec.follow_mark:g})")
    p.add_argument("--samples", type=int, default=spec.samples,
                   help="plans drawn from different noise each time a plan is made; of "
                        "several, the one heading for the cell nearest the agent (over cells "
                        "not known to be obstacles) and not yet disproved is kept: the agent "
                        "checks the nearest of several guesses of a hidden target first. Costs "
                        f"that many times the denoiser calls (default {spec.samples})")
    p.add_argument("--language", choices=tuple(LANGUAGE_CHOICES), default="canonical",
                   help="instruction phrasing of the episodes: 'canonical' (the paper's, "
                        "default), 'paraphrased' (the training paraphrases), 'unseen' (held-out "
                        "phrasings training never saw, made of its words), 'natural' (the "
                        "sealed natural-language set, sentences as people type them: only a "
                        "checkpoint on pretrained text features reads them; never part of 'all', "
                        "it is measured once, by name), or 'all' (a row per phrasing other "
                        "than the sealed set, and mode; the same worlds in each)")
    p.add_argument("--text", choices=("tokens", "pretrained"), default="tokens",
                   help="the denoiser's instruction input: 'tokens' (the grammar's word ids, "
                        "default) or 'pretrained' (the frozen pretrained text encoder's "
                        "features of each sentence, checkpoints/text_encoder: any English "
                        "sentence). Selects what --train trains and the default checkpoint "
                        f"(checkpoints/{spec.checkpoint_name}_pretrained); with --checkpoint "
                        "the checkpoint decides")
    p.add_argument("--batch-size", type=int, default=spec.eval_batch,
                   help=f"episodes per jitted evaluation call and device: the re-planning "
                        f"modes' slots (default {spec.eval_batch})")
    p.add_argument("--figures", metavar="DIR",
                   help="write PNGs of a few episodes: map, executed path, and the predicted "
                        "paths and goal estimates at several re-plans")
    p.add_argument("--num-figures", type=int, default=None,
                   help="episodes drawn with --figures (default 4)")
    p.add_argument("--profile", metavar="DIR",
                   help="write a JAX profiler trace (TensorBoard / Perfetto) of one batch of "
                        "the main planning mode to DIR, after the evaluation")
    p.add_argument("--baselines", nargs="?", const="bc,cql,dd", default=None,
                   metavar="NAMES",
                   help="add rows of the shipped baselines (checkpoints/baselines; "
                        "comma-separated of bc,cql,dd; the flag alone: all three), measured on "
                        "the same episodes and seeds as the planner's rows")
    add_reference_agents_flag(p)
    p.add_argument("--control", choices=("names", "direction"), default=None,
                   help="add control rows: every mode again on the same episodes with one word "
                        "of the instruction changed: 'names' names a distractor seen at t = 0 "
                        "as the reference, or in mo1g as the goal (episodes with one; the "
                        "row's named_first_percent: the agent stood on it before the true "
                        "reference, in mo1g before the true target), 'direction' "
                        "reverses the direction word (SR and SPL show whether it was read)")
    p.add_argument("--posterior-denoiser", action="store_true",
                   help="add a row per planning mode planned with a denoiser that needs no "
                        "learning and guesses the hidden target exactly: each plan heads for "
                        "the reference, then for the target once seen, else for a cell drawn "
                        "uniformly among those the episode generator could have put it in "
                        "(envs/gridworld/posterior.py); the same planner, psi and triggers, "
                        "on every episode: what perfect inference would score (search psi "
                        "only)")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    add_process_flags(p)
    return p


def add_reference_agents_flag(parser) -> None:
    """--no-reference-agents, shared by every grid-world table."""
    parser.add_argument("--no-reference-agents", action="store_true",
                        help="leave out the rows of the reference agents, which bound what a "
                             "planner can do and are measured on the same episodes and seeds "
                             "(no network; shown by default): 'oracle' (a shortest path with "
                             "the whole map known) and 'searcher' (nothing learned, only what "
                             "the agent has seen: the reference, then exploration of the "
                             "instructed sector, then the target once seen)")


TRAIN_FLAGS = {"train_dir": "--train-dir", "train_steps": "--train-steps",
               "train_seed": "--train-seed", "checkpoint_every": "--checkpoint-every",
               "prediction": "--prediction", "model_size": "--model-size",
               "objective": "--objective"}


def check_args(parser, args, spec):
    """Validates the arguments (one-line errors before any work) and fills the defaults of
    the flags that only make sense together with another one. Returns the modes."""
    from diffplan.planner import MODES

    cli.check_training_flags(parser, args, TRAIN_FLAGS)
    cli.only_with(parser, args, "figures", {"num_figures": "--num-figures"})
    cli.check_at_least(parser, "--num-figures", args.num_figures, 1)
    cli.check_output_file(parser, "--json", args.json)
    cli.check_output_file(parser, "--trajectories", args.trajectories, suffix=".npz")
    cli.check_output_dir(parser, "--figures", args.figures)
    cli.check_output_dir(parser, "--train-dir", args.train_dir)
    cli.check_output_dir(parser, "--profile", args.profile)
    if args.train_steps is None:
        args.train_steps = spec.default_train_steps(args.text)
    args.train_seed = 0 if args.train_seed is None else args.train_seed
    args.checkpoint_every = 500 if args.checkpoint_every is None else args.checkpoint_every
    args.prediction = spec.prediction if args.prediction is None else args.prediction
    args.model_size = "default" if args.model_size is None else args.model_size
    args.objective = "diffusion" if args.objective is None else args.objective
    args.num_figures = 4 if args.num_figures is None else args.num_figures
    if args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    if not 0 <= args.eta <= 10 or args.eta != args.eta:
        parser.error(f"--eta must be in [0, 10], got {args.eta}")
    for flag, value in (("--episodes", args.episodes), ("--batch-size", args.batch_size),
                        ("--num-steps", args.num_steps), ("--samples", args.samples)):
        cli.check_at_least(parser, flag, value, 1)
    warm_steps = args.num_steps if args.warm_num_steps is None else args.warm_num_steps
    if warm_steps < 1:
        parser.error(f"--warm-num-steps must be >= 1, got {warm_steps}")
    if not 0 <= args.warm_start_step < warm_steps:
        parser.error(f"--warm-start-step must be in 0..{warm_steps - 1}")
    modes = tuple(m.strip() for m in args.modes.split(",") if m.strip())
    bad = [m for m in modes if m not in MODES]
    if bad or not modes:
        parser.error(f"unknown --modes {bad}; choose from {MODES}")
    args.baselines = check_baselines(parser, args.baselines)
    try:
        check_follow_mark(args.follow_mark, "--follow-mark")
    except ValueError as e:
        parser.error(str(e))
    if args.psi != "follow" and args.follow_mark != spec.follow_mark:
        parser.error("--follow-mark sets the follow psi's threshold: it needs --psi follow")
    if args.control == "direction" and not spec.grid_config().has_reference:
        parser.error(f"--control direction reverses the direction word, which {spec.setting} "
                     "instructions do not have")
    if args.control == "names" and spec.setting == "1o1g":
        parser.error("--control names names another visible object, and 1o1g episodes have "
                     "one object")
    if args.posterior_denoiser and args.psi != "search":
        parser.error("--posterior-denoiser plans no path, so it serves --psi search only")
    return modes


def check_baselines(parser, names: str | None) -> tuple[str, ...]:
    """The --baselines names (distinct, known, with a shipped checkpoint); () without it."""
    from diffplan.baselines.policies import BASELINES

    return cli.check_baselines(parser, names, BASELINES,
                               os.path.join(harness.CHECKPOINT_ROOT, "baselines"))
