"""Training cost: steps/s of the default grid-world training, and the training time it takes to
reach a success rate on held-out validation episodes.

    python -m experiments.bench_train [--target 99] [--eval-every 1000] [--json bench_train.json]

Runs the default training recipe (experiments.compile_p_mo2g --train: model, recipe, 8000
steps, seed 0) into --train-dir, pausing every --eval-every steps (the training's own
checkpoint; diffplan.train resumes bit-exactly) to evaluate the EMA weights on --episodes
validation P-MO2G episodes (seed 1000, never an evaluation seed) in --mode. Reports for every
evaluation the training wall time so far (the checkpoint's recorded time: training only,
evaluations excluded), SR and SR_ordered, and the first step at which SR >= --target.
--max-steps stops earlier; --stop-at-target stops at the first evaluation that reaches
--target (the rest of the run cannot change when it was first reached). Steps/s: steps over training seconds (checkpointing included).
"""
from __future__ import annotations

import argparse
import os
import sys

from experiments import cli, gridworld_eval as ge, harness
from experiments.gridworld_spec import SPECS, train_setting
from experiments.recipes import MODEL_SIZES


class _Pause(Exception):
    pass


def build_parser():
    p = argparse.ArgumentParser(prog="python -m experiments.bench_train",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--train-dir", default=os.path.join(harness.REPO_ROOT, "runs", "bench_train"),
                   help="training output (resumed if it holds a checkpoint of this recipe)")
    p.add_argument("--eval-every", type=int, default=1000, help="steps between evaluations")
    p.add_argument("--max-steps", type=int, default=None,
                   help="stop after this many steps (default: the full 8000)")
    p.add_argument("--episodes", type=int, default=200, help="validation episodes per "
                   "evaluation (default 200)")
    p.add_argument("--mode", default="warm_start", choices=("on_the_fly", "warm_start"),
                   help="planning mode of the evaluations (default warm_start: the same SR "
                        "as on_the_fly on the validation episodes at a fifth of the cost)")
    p.add_argument("--target", type=float, default=99.0, help="SR to reach (default 99)")
    p.add_argument("--target-metric", choices=("SR", "SR_ordered"), default="SR",
                   help="the metric that must reach --target (default SR; SR_ordered also "
                        "asks that the reference was visited before the target)")
    p.add_argument("--stop-at-target", action="store_true",
                   help="stop training at the first evaluation with SR >= --target")
    p.add_argument("--model-size", choices=sorted(MODEL_SIZES), default="default")
    p.add_argument("--json", metavar="PATH", help="write the results as JSON")
    p.add_argument("--no-progress", action="store_true")
    return p


def main(argv=None) -> dict:
    from diffplan.checkpoint import read_metadata
    from diffplan.jax_cache import enable_compilation_cache

    parser = build_parser()
    args = parser.parse_args(argv)
    cli.check_at_least(parser, "--eval-every", args.eval_every, 1)
    cli.check_at_least(parser, "--episodes", args.episodes, 1)
    cli.check_at_least(parser, "--max-steps", args.max_steps, 2)
    cli.check_output_file(parser, "--json", args.json)
    cli.check_output_dir(parser, "--train-dir", args.train_dir)
    enable_compilation_cache()
    spec = SPECS["p_mo2g"]
    total = spec.train_steps if args.max_steps is None else args.max_steps
    episodes = ge.eval_episodes(spec.grid_config(), args.episodes, harness.VALIDATION_SEED)
    evaluations, reached = [], None

    def pause(step, record):
        if step % args.eval_every == 0 or step >= total:
            raise _Pause()

    while True:
        try:
            train_setting(spec, args.train_dir, steps=spec.train_steps,
                             progress=not args.no_progress, model_size=args.model_size,
                             checkpoint_every=args.eval_every, callback=pause)
            finished = True
        except _Pause:
            finished = False
        denoiser, meta = harness.load_model(args.train_dir)
        step = int(meta["step"])
        rollout, seconds = ge.evaluate_mode(spec, spec.task(denoiser.num_gen_channels),
                                            denoiser, episodes, harness.VALIDATION_SEED,
                                            args.mode, min(250, args.episodes), progress=False)
        row = ge.metrics_row(args.mode, rollout, episodes, seconds, True)
        evaluations.append({"step": step, "train_seconds": float(meta.get("wall_time", 0.0)),
                            "SR": row["SR"], "SR_ordered": row["SR_ordered"],
                            "path_f1": row["path_f1"]})
        print(f"step {step}: train {evaluations[-1]['train_seconds'] / 60:.1f} min, SR "
              f"{row['SR']:.1f}, SR_ordered {row['SR_ordered']:.1f}", file=sys.stderr)
        if reached is None and row[args.target_metric] >= args.target:
            reached = evaluations[-1]
        if finished or step >= total or (args.stop_at_target and reached is not None):
            break
    last = evaluations[-1]
    result = {"experiment": "bench_train", "episodes": args.episodes,
              "seed": harness.VALIDATION_SEED, "mode": args.mode, "target_SR": args.target,
              "target_metric": args.target_metric,
              "steps_per_second": last["step"] / max(last["train_seconds"], 1e-9),
              "reached": reached, "rows": [dict(method=f"step {e['step']}", **e)
                                           for e in evaluations],
              "final_metadata_step": int(read_metadata(args.train_dir)["step"])}
    print(f"{'step':>6} {'train min':>9} {'SR':>7} {'SR_ord':>7} {'F1':>6}")
    for e in evaluations:
        print(f"{e['step']:>6} {e['train_seconds'] / 60:>9.1f} {e['SR']:>7.2f} "
              f"{e['SR_ordered']:>7.2f} {e['path_f1']:>6.1f}")
    print(f"mean training speed {result['steps_per_second']:.2f} steps/s; "
          + (f"{args.target_metric} >= {args.target} first at step {reached['step']} after "
             f"{reached['train_seconds'] / 60:.1f} min of training" if reached else
             f"{args.target_metric} never reached {args.target}"))
    if args.json:
        cli.write_json(args.json, result)
    return result


if __name__ == "__main__":
    main()
