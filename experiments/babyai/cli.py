"""``python -m experiments.babyai --level LEVEL``: load (or ``--train``) the level's denoiser
and BC, evaluate ours (on-the-fly, warm start), BC and the BabyAI bot on minigrid's own
episodes, each row measured in minigrid (``experiments.babyai.eval``), print a table with its
legend beside the published imitation-learning numbers, write JSON (contract 2); or, with
``--demos-sweep``, the sample-efficiency study (``experiments.babyai.demos``).
"""
from __future__ import annotations

import os
from typing import Sequence

import numpy as np

from experiments.babyai import eval as be, tables as bt
from experiments.babyai.flags import build_parser, check_args
from experiments.babyai.spec import METHOD_NAMES, published, train
from experiments.harness import cli, core as harness


def _train(spec, args, progress: bool) -> tuple[str, dict]:
    """--train: ours, then (unless --no-bc) BC on the same demonstrations within our minutes;
    (checkpoint, what training did)."""
    from diffplan.train import ConfigMismatchError
    from experiments.babyai.baselines import denoiser_minutes, train_bc

    checkpoint = args.train_dir or spec.default_train_dir()
    demos = args.demos or spec.demos
    info = {"demos": demos}
    try:
        info["train_seconds"] = train(
            spec, checkpoint, demos=demos, seed=args.train_seed or 0, steps=args.train_steps,
            model_size=args.model_size, detour_prob=args.detour_prob,
            checkpoint_every=args.checkpoint_every, progress=progress)
        if not args.no_bc:
            info["bc"] = train_bc(spec, bc_directory(args, checkpoint), demos=demos,
                                  minutes=denoiser_minutes(checkpoint), steps=args.bc_steps,
                                  seed=args.train_seed or 0, progress=progress)
    except ConfigMismatchError as e:
        harness.fail(str(e))
    return checkpoint, info


def bc_directory(args, checkpoint: str) -> str:
    return args.bc_checkpoint or os.path.normpath(checkpoint) + "_bc"


def _load_bc(spec, args, checkpoint: str):
    from experiments.babyai.baselines import load_bc

    directory = bc_directory(args, checkpoint)
    try:
        return directory, load_bc(directory)
    except FileNotFoundError:
        harness.fail(f"no BC checkpoint in {directory}: train it with `{spec.train_command()}` "
                     "(ours and BC), or pass --bc-checkpoint DIR or --no-bc")
    except ValueError as e:
        harness.fail(f"cannot read the BC checkpoint {directory}: {e}")


def evaluate(spec, args, seeds, modes, denoiser, bc, progress: bool) -> tuple[list, dict]:
    """The rows (ours in each mode, with --random-weights the same denoiser with random
    weights, BC, the bot) pooled over the seeds, and the number of episodes each seed counted
    (all, or those of --mission)."""
    from envs.babyai.config import make_config
    from experiments.harness.ablations import random_weights

    config, task = make_config(spec.level), spec.task()
    control = random_weights(denoiser) if args.random_weights else None
    parts = {}
    counted = {}
    for seed in seeds:
        eps = be.episodes(config, seed, args.episodes, progress)
        idx = np.arange(args.episodes)
        if args.mission is not None:
            idx = idx[np.all(eps.tokens == config.tokenize(args.mission), axis=-1)]
            if len(idx) == 0:
                harness.fail(f"no episode of seed {seed} (of {args.episodes}) has the mission "
                             f"{args.mission!r}; try more --episodes")
            eps = be.select(eps, idx)
        counted[str(seed)] = int(len(idx))
        for mode in modes:
            parts.setdefault(METHOD_NAMES[mode], {})[seed] = be.run_planner(
                spec, task, denoiser, mode, eps, seed, idx, args.batch_size, progress)
        if control is not None:
            parts.setdefault(bt.RANDOM_ROW, {})[seed] = be.run_planner(
                spec, task, control, "warm_start", eps, seed, idx, args.batch_size, progress,
                name=bt.RANDOM_ROW)
        if bc is not None:
            parts.setdefault("BC", {})[seed] = be.run_policy(
                spec, task, bc, eps, seed, idx, max(args.batch_size, 250), progress)
        if not args.no_bot:
            parts.setdefault("BabyAI bot", {})[seed] = be.run_bot(spec, seed, idx, progress)
    return [be.pooled_row(method, per_seed) for method, per_seed in parts.items()], counted


def _metadata(checkpoint: str) -> dict:
    from diffplan.checkpoint import read_metadata

    meta = read_metadata(checkpoint)
    return {"demos": (meta.get("extra") or {}).get("num_layouts", meta.get("num_layouts")),
            "train_seconds_recorded": meta.get("wall_time"), "step": meta.get("step")}


def main(argv: Sequence[str] | None = None) -> dict:
    parser = build_parser()
    args = parser.parse_args(argv)
    spec, modes, seeds = check_args(parser, args)
    from diffplan.jax_cache import enable_compilation_cache

    enable_compilation_cache()
    progress = not args.no_progress
    if args.demos_sweep is not None:
        from experiments.babyai.demos import run_sweep

        return run_sweep(spec, args, seeds, modes[0], progress)
    info = {}
    if args.train:
        checkpoint, info = _train(spec, args, progress)
    else:
        checkpoint = args.checkpoint or spec.default_checkpoint()
    denoiser = harness.load_checked(checkpoint, spec.train_command(), spec.mismatch)
    bc_dir, bc = _load_bc(spec, args, checkpoint) if not args.no_bc else (None, None)
    rows, counted = evaluate(spec, args, seeds, modes, denoiser, bc, progress)
    relative = lambda p: None if p is None else (
        os.path.relpath(p, harness.REPO_ROOT) if os.path.abspath(p).startswith(
            harness.REPO_ROOT + os.sep) else os.path.abspath(p))
    result = {"experiment": spec.name, "level": spec.level, "env_id": spec.env_id,
              "episodes": args.episodes, "seed": seeds[0], "seeds": list(seeds),
              "validation": harness.VALIDATION_SEED in seeds, "mission": args.mission,
              "counted_episodes": counted, "checkpoint": relative(checkpoint),
              "bc_checkpoint": relative(bc_dir), **_metadata(checkpoint), **info,
              "num_steps": spec.num_steps, "warm_num_steps": spec.warm_num_steps,
              "warm_start_step": spec.warm_start_step, "measured_in": "minigrid",
              "machine": harness.machine(), "rows": rows,
              "published": published(spec.level)}
    print(f"\n{spec.name} ({spec.env_id}): {args.episodes} episodes per seed, seed(s) "
          f"{','.join(map(str, seeds))}" + (f", mission {args.mission!r} ({sum(counted.values())}"
                                            " episodes)" if args.mission else "")
          + f"; checkpoint {result['checkpoint']} (trained on {result['demos']} demos); "
          f"on-the-fly {spec.num_steps} steps a plan; every row measured in minigrid")
    print(bt.format_table(rows))
    if len(seeds) > 1:
        print(bt.format_intervals(rows, seeds))
    print(bt.format_published(result["published"]))
    if args.json:
        cli.write_json(args.json, result)
    bad = sum(r.get("mismatches", 0) for r in rows)
    if bad:
        harness.fail(f"{bad} episode(s) ended differently in the port and in minigrid (the "
                     "rows report minigrid's outcome)", code=1)
    return result
