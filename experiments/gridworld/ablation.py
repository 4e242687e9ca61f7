"""The paper's ablation (Table 4) on MO1G and P-MO2G: each row a model we train.

Rows, as in the paper:
  baseline        class-id grid (one scalar channel), no goal estimate g, one-shot plan
  + grid repr     learned cell embeddings shared with the instruction words, no g, one-shot
  + g             + the goal-estimate channel, one-shot
  + on the fly    + re-planning before every move (the main model, Algorithm 1)
then the reference agents (oracle, searcher) on the same episodes, unless
--no-reference-agents. Models without g are followed by psi towards the far end of their
predicted path (the path cell farthest along the unvisited path cells connected to the agent:
envs.gridworld.task.path_end_cell).

`python -m experiments.ablation_compile --help`. The "+ g" and "+ on the fly" rows use the main
denoiser (checkpoints/compile_gridworld); the two others are trained by `--train` into
runs/compile_gridworld_class_id_no_goal and runs/compile_gridworld_no_goal (or read from there
if a training already ran), with the same recipe as the main one.
"""
from __future__ import annotations

import argparse
import dataclasses
import os

from diffplan.jax_cache import enable_compilation_cache
from experiments.gridworld import eval as ge
from experiments.harness import cli, core as harness
from experiments.gridworld.flags import add_reference_agents_flag
from experiments.gridworld.spec import ExperimentSpec, SPECS, load_checked, train_setting
from experiments.harness.recipes import MODEL_SIZES

VARIANTS = (
    ("baseline", dict(grid_repr="class_id", goal_channel=False), "one_shot"),
    ("+ grid repr", dict(grid_repr="embed", goal_channel=False), "one_shot"),
    ("+ g", dict(grid_repr="embed", goal_channel=True), "one_shot"),
    ("+ on the fly", dict(grid_repr="embed", goal_channel=True), "on_the_fly"),
)
SETTINGS = ("mo1g", "p_mo2g")
VARIANT_LEGEND = (("baseline", "class-id grid, no goal channel g, one_shot"),
                  ("+ grid repr", "cell embeddings, no g, one_shot"),
                  ("+ g", "+ the goal-estimate channel, one_shot"),
                  ("+ on the fly", "+ on_the_fly re-planning before every move"))
"""What each variant's row is (its name follows the setting), printed under the table."""


def build_parser():
    p = argparse.ArgumentParser(prog="python -m experiments.ablation_compile",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--episodes", type=int, default=1000, help="episodes per setting")
    p.add_argument("--seed", type=int, default=harness.DEFAULT_EVAL_SEED, help="evaluation seed")
    p.add_argument("--json", metavar="PATH", help="write the results (contract 2) as JSON")
    p.add_argument("--train", action="store_true",
                   help="train the ablation models that have no checkpoint yet")
    p.add_argument("--train-steps", type=int, default=ExperimentSpec("p_mo2g").train_steps,
                   help="optimisation steps of each ablation training")
    p.add_argument("--model-size", choices=sorted(MODEL_SIZES), default="default",
                   help="denoiser size of the ablation trainings")
    p.add_argument("--main-checkpoint", metavar="DIR", default=None,
                   help="the main denoiser (default: the shipped one)")
    p.add_argument("--checkpoint-root", metavar="DIR", default=None,
                   help="where ablation trainings live (default runs/)")
    p.add_argument("--settings", default=",".join(SETTINGS), help="comma-separated settings")
    p.add_argument("--batch-size", type=int, default=250, help="episodes per jitted call")
    p.add_argument("--num-steps", type=int, default=ExperimentSpec("p_mo2g").num_steps,
                   help="denoising steps per plan")
    add_reference_agents_flag(p)
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    return p


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    settings = tuple(s.strip() for s in args.settings.split(",") if s.strip())
    if any(s not in SETTINGS for s in settings) or not settings:
        parser.error(f"--settings must be a comma-separated list of {SETTINGS}, got "
                     f"{args.settings!r}")
    cli.check_at_least(parser, "--episodes", args.episodes, 1)
    cli.check_at_least(parser, "--batch-size", args.batch_size, 1)
    cli.check_at_least(parser, "--train-steps", args.train_steps, 2)
    cli.check_at_least(parser, "--num-steps", args.num_steps, 1)
    cli.check_at_least(parser, "--seed", args.seed, 0)
    cli.check_output_file(parser, "--json", args.json)
    if args.main_checkpoint is not None and not os.path.isdir(args.main_checkpoint):
        parser.error(f"--main-checkpoint {args.main_checkpoint!r} is not a directory")
    enable_compilation_cache()
    progress = not args.no_progress
    models = {}
    for name, fields, _ in VARIANTS:
        spec = dataclasses.replace(SPECS["p_mo2g"], num_steps=args.num_steps, **fields)
        key = spec.training_name
        if key in models:
            continue
        if fields["goal_channel"] and fields["grid_repr"] == "embed":
            checkpoint = args.main_checkpoint or spec.default_checkpoint()
        else:
            root = args.checkpoint_root or os.path.join(harness.REPO_ROOT, "runs")
            checkpoint = os.path.join(root, key)
            if args.train:
                train_setting(spec, checkpoint, steps=args.train_steps, progress=progress,
                                 model_size=args.model_size)
        models[key] = load_checked(checkpoint, spec, ("one_shot", "on_the_fly"), parser,
                                   "python -m experiments.ablation_compile --train")

    rows = []
    for setting in settings:
        # (No warm-start rows here; the default warm schedule is valid for any num_steps.)
        base = dataclasses.replace(SPECS[setting], num_steps=args.num_steps)
        episodes = ge.eval_episodes(base.grid_config(), args.episodes, args.seed)
        for name, fields, mode in VARIANTS:
            spec = dataclasses.replace(base, **fields)
            denoiser = models[spec.training_name]
            rollout, seconds = ge.evaluate_mode(spec, spec.task(denoiser.num_gen_channels),
                                                denoiser, episodes, args.seed, mode,
                                                args.batch_size, progress)
            row = ge.metrics_row(f"{setting} {name}", rollout, episodes, seconds,
                                 base.grid_config().has_reference)
            row["setting"] = setting
            rows.append(row)
        if not args.no_reference_agents:
            from experiments.gridworld.baselines import reference_rows

            for row in reference_rows(setting, (args.seed,), args.episodes, args.batch_size,
                                      progress, episodes_by_seed={args.seed: episodes}):
                rows.append({**row, "method": f"{setting} {row['method']}", "setting": setting})
    result = {"experiment": "ablation_compile", "episodes": args.episodes, "seed": args.seed,
              "rows": rows}
    print(ge.format_table(rows, VARIANT_LEGEND))
    if args.json:
        cli.write_json(args.json, result)
    return result


if __name__ == "__main__":
    main()
