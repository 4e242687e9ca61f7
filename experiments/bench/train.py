"""Training cost of either world: the training time it takes to reach a success rate on
held-out validation episodes, and the time split of one training step.

    python -m experiments.bench_train [--world gridworld|kuka] [--target 99]
        [--target-metric SR,SR_ordered] [--eval-every 1000] [--split] [--json bench_train.json]
    python -m experiments.bench_train --world kuka --split-only --split-seconds 60

Runs the world's default training recipe (gridworld: experiments.compile_p_mo2g --train;
kuka: experiments.kuka_stacking --train; seed 0; --batch-size changes the examples per step)
into --train-dir, pausing every --eval-every steps (the training's own checkpoint;
diffplan.train resumes bit-exactly) to evaluate the EMA weights on --episodes validation
episodes (seed 1000, never an evaluation seed): P-MO2G episodes in --mode (SR, SR_ordered), or,
for kuka, --episodes per Table 2 column with on-the-fly planning under MJX
physics (strict SR per column, contract 4). Reports for every evaluation the training wall time
so far (the checkpoint's recorded time: training only, evaluations excluded) and the first step
at which every --target-metric >= --target (kuka: strict SR in all four columns). --max-steps
stops earlier; --stop-at-target stops at the first evaluation that reaches --target (the rest
of the run cannot change when it was first reached). Steps/s: steps over training seconds
(checkpointing included). --split / --split-only: the time split of a step (below).
"""
from __future__ import annotations

import argparse
import sys

from experiments.bench import train_split as split_mod, train_text, train_worlds as bw
from experiments.bench.common import LEGENDS
from experiments.harness import cli, core as harness, tables
from experiments.harness.recipes import MODEL_SIZES


class _Pause(Exception):
    pass


def build_parser():
    paragraphs = __doc__.split("\n\n")
    p = argparse.ArgumentParser(prog="python -m experiments.bench_train",
                                description=paragraphs[0], epilog=paragraphs[2]
                                + "\n\n" + split_mod.__doc__.split("\n\n")[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--world", choices=sorted(bw.WORLDS), default="gridworld",
                   help="the world whose default training is measured (default gridworld)")
    p.add_argument("--train-dir", default=None,
                   help="training output, resumed if it holds a checkpoint of this recipe "
                        "(default runs/bench_train for gridworld, runs/bench_train_kuka)")
    p.add_argument("--eval-every", type=int, default=1000, help="steps between evaluations "
                   "(default 1000)")
    p.add_argument("--max-steps", type=int, default=None,
                   help="stop after this many steps, a multiple of --eval-every (default: the "
                        "recipe's whole run, " + " / ".join(
                            f"{w.train_steps} {name}" for name, w in bw.WORLDS.items()) + ")")
    p.add_argument("--episodes", type=int, default=200, help="validation episodes per "
                   "evaluation, per Table 2 column for kuka (default 200)")
    p.add_argument("--mode", default=None, choices=("on_the_fly", "warm_start", "one_shot"),
                   help="planning mode of the evaluations (gridworld: on_the_fly or warm_start, "
                        "default warm_start: the same SR as on_the_fly on the validation "
                        "episodes at a fifth of the cost; kuka: on_the_fly (default) or "
                        "one_shot)")
    p.add_argument("--eval-batch", type=int, default=None,
                   help="episodes per jitted evaluation call (default min(--episodes, 250) "
                        "gridworld, min(--episodes, 64) kuka)")
    p.add_argument("--target", type=float, default=99.0, help="success rate in percent to "
                   "reach (default 99)")
    p.add_argument("--target-metric", default="SR", metavar="M[,M...]",
                   help="comma-separated metrics that must all reach --target (default SR). "
                        "gridworld: SR, SR_ordered (the reference visited before the target); "
                        "e.g. SR,SR_ordered. kuka: SR (strict, in every column)")
    p.add_argument("--stop-at-target", action="store_true",
                   help="stop training at the first evaluation that reaches --target")
    p.add_argument("--batch-size", type=int, default=None,
                   help="training examples per step (default the recipe's: 64 gridworld, a "
                        "multiple of the mixture's examples per batch, 64 unless --set "
                        "mixture=... changes it; 32 kuka, a multiple of its 8 task specs)")
    p.add_argument("--model-size", choices=sorted(MODEL_SIZES), default="default",
                   help="denoiser size ('tiny' is for smoke tests; default 'default')")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="change one field of the recipe's training configuration "
                        "(TrainConfig), model (DenoiserConfig) or training data (the world's "
                        "Recipe); repeatable, VALUE as JSON, e.g. --set steps=3000 --set "
                        "num_train_timesteps=10 --set 'cross_attn_levels=[1,2]' --set "
                        "'mixture=[[\"p_mo2g\",48],[\"mo1g\",10],[\"1o1g\",6]]' (grid) or "
                        "'specs=[[\"rearrangement\",true,\"canonical\"],...]' (Kuka: task "
                        "specs as [kind, multi, language], a spec listed twice has twice the "
                        "share). The checkpoint records every setting, so a --train-dir of other settings "
                        "is refused")
    split_mod.add_flags(p)
    p.add_argument("--text-compare", action="store_true",
                   help="time the training step and a denoiser call (batch 64) of the grid "
                        "recipe on token ids and on pretrained text features (--set text=...), "
                        "alternating, --split-repeats rounds; then the text encoder's time per "
                        "instruction; and exit")
    p.add_argument("--json", metavar="PATH", help="write the results as JSON")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    return p


def check_args(parser, args):
    """One-line errors before any work; returns (world, metrics, mode, eval batch)."""
    world = bw.WORLDS[args.world]
    for flag, value, minimum in (("--eval-every", args.eval_every, 1),
                                 ("--episodes", args.episodes, 1),
                                 ("--max-steps", args.max_steps, 2),
                                 ("--eval-batch", args.eval_batch, 1),
                                 ("--batch-size", args.batch_size, 1)):
        cli.check_at_least(parser, flag, value, minimum)
    try:
        _, config, recipe = bw.training(world, args.model_size, 1, args.set,
                                        batch_size=args.batch_size)
    except ValueError as e:
        parser.error(str(e))
    if config.batch_size % recipe.batch_multiple:
        parser.error(f"--batch-size must be a multiple of {recipe.batch_multiple} for this "
                     f"{world.name} recipe, got {config.batch_size}")
    args.recipe_steps = config.steps
    if (args.max_steps is not None and args.max_steps < config.steps
            and args.max_steps % args.eval_every):
        parser.error(f"--max-steps ({args.max_steps}) must be a multiple of --eval-every "
                     f"({args.eval_every}): training pauses at evaluations")
    if not 0 <= args.target <= 100:
        parser.error(f"--target is a rate in percent, in [0, 100]; got {args.target}")
    metrics = [m.strip() for m in args.target_metric.split(",") if m.strip()]
    if not metrics or len(set(metrics)) != len(metrics) or set(metrics) - set(world.metrics):
        parser.error(f"--target-metric must be distinct metrics of {', '.join(world.metrics)} "
                     f"for {world.name}, got {args.target_metric!r}")
    mode = args.mode or world.default_mode
    if mode not in world.modes:
        parser.error(f"--mode {mode} is not a mode of {world.name} ({', '.join(world.modes)})")
    split_mod.check_flags(parser, args)
    cli.check_output_file(parser, "--json", args.json)
    cli.check_output_dir(parser, "--train-dir", args.train_dir)
    cap = 250 if world.name == "gridworld" else 64
    return world, metrics, mode, min(args.eval_batch or cap, args.episodes)


def _train_to_target(world, args, metrics, mode, eval_batch, train_dir):
    """Trains with pauses at evaluations; (evaluations, the first that reached the target)."""
    progress = not args.no_progress
    total = min(args.recipe_steps, args.max_steps or args.recipe_steps)
    evaluate = bw.evaluator(world, args.episodes, mode, eval_batch, progress)
    evaluations, reached = [], None

    def pause(step, record):
        if step % args.eval_every == 0 or step >= total:
            raise _Pause()

    while True:
        try:
            bw.run_training(world, train_dir, model_size=args.model_size,
                            checkpoint_every=world.checkpoint_interval(args.eval_every),
                            progress=progress,
                            callback=pause, settings=args.set,
                            batch_size=args.batch_size)
            finished = True
        except _Pause:
            finished = False
        denoiser, meta = harness.load_model(train_dir)
        step = int(meta["step"])
        if evaluations and step <= evaluations[-1]["step"]:
            break  # nothing new was trained (never expected: pauses fall on checkpoints)
        row = {"step": step, "train_seconds": float(meta.get("wall_time", 0.0)),
               **evaluate(denoiser)}
        evaluations.append(row)
        print(f"step {step}: train {row['train_seconds'] / 60:.1f} min, "
              + ", ".join(f"{k} {row[k]:.1f}" for k in ("SR", "SR_ordered", "SR_min")
                          if k in row), file=sys.stderr)
        if reached is None and bw.reached(world, row, metrics, args.target):
            reached = row
        if finished or step >= total or (args.stop_at_target and reached is not None):
            return evaluations, reached


def _print_table(world, evaluations) -> None:
    rows = [{**e, **e.get("SR_columns", {}), "label": str(e["step"]),
             "minutes": e["train_seconds"] / 60} for e in evaluations]
    columns = [("label", "{:<6}", "step"), ("minutes", "{:>9.1f}", "train min"),
               ("SR", "{:>7.2f}", "SR")]
    if world.name == "kuka":  # strict SR per column, e.g. stack_single
        columns += [(n, "{:>12.2f}", n.replace("stacking", "stack").replace("rearrangement",
                                                                           "rearr"))
                    for n in evaluations[0]["SR_columns"]]
    else:
        columns += [("SR_ordered", "{:>7.2f}", "SR_ord"), ("path_f1", "{:>6.1f}", "F1")]
    print(tables.format_table(rows, columns, LEGENDS["train"]))


def main(argv=None) -> dict:
    from diffplan.checkpoint import read_metadata
    from diffplan.jax_cache import enable_compilation_cache

    parser = build_parser()
    args = parser.parse_args(argv)
    world, metrics, mode, eval_batch = check_args(parser, args)
    enable_compilation_cache()
    result = {"experiment": "bench_train", "world": world.name, "model_size": args.model_size,
              "settings": list(args.set),
              "batch_size": args.batch_size or world.default_batch,
              "machine": harness.machine()}
    if args.text_compare:
        result["text_compare"] = train_text.compare(world, args)
        print(train_text.format_compare(result["text_compare"]))
        if args.json:
            cli.write_json(args.json, result)
        return result
    if args.split or args.split_only:
        result["split"] = split_mod.measure(world, args)
        print(split_mod.format_split(result["split"]))
    if args.split_only:
        result["split_only"] = True
        if args.json:
            cli.write_json(args.json, result)
        return result
    train_dir = args.train_dir or world.default_train_dir()
    evaluations, reached = _train_to_target(world, args, metrics, mode, eval_batch, train_dir)
    last = evaluations[-1]
    speed = last["step"] / max(last["train_seconds"], 1e-9)
    target = f"{' and '.join(metrics)}" + (" in every column" if world.name == "kuka" else "")
    result.update({
        "episodes": args.episodes, "seed": harness.VALIDATION_SEED, "mode": mode,
        "target_SR": args.target, "target_metric": ",".join(metrics),
        "target_metrics": metrics, "steps_per_second": speed,
        "examples_per_second": speed * result["batch_size"], "reached": reached,
        "rows": [dict(method=f"step {e['step']}", **e) for e in evaluations],
        "final_metadata_step": int(read_metadata(train_dir)["step"])})
    _print_table(world, evaluations)
    print(f"mean training speed {speed:.2f} steps/s ({result['examples_per_second']:.0f} "
          f"examples/s); " + (f"{target} >= {args.target} first at step {reached['step']} "
                              f"after {reached['train_seconds'] / 60:.1f} min of training"
                              if reached else f"{target} never reached {args.target}"))
    if args.json:
        cli.write_json(args.json, result)
    return result


if __name__ == "__main__":
    main()
