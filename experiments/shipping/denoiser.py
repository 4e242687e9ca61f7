"""Exports a training run as a shipped evaluation checkpoint with its NOTE.md.

    python -m experiments.ship_checkpoint --train-dir runs/compile_gridworld \
        --results results/compile_p_mo2g.json [--results results/compile_mo1g.json ...]
    python -m experiments.ship_checkpoint --world kuka --train-dir runs/kuka \
        --results results/kuka_stacking.json --results results/kuka_rearrangement.json

writes checkpoints/compile_gridworld/ (or checkpoints/kuka/) (EMA parameters + metadata only) and NOTE.md beside them:
the training command, seed, steps, training time read from the run's metrics.jsonl, and the
results tables of the given experiment JSONs (contract 2), so every shipped number can be traced
to the command that measured it.
"""
from __future__ import annotations

import argparse
import json
import os

from envs.babyai.config import LEVELS
from experiments.gridworld import eval as gridworld_eval
from experiments.kuka import spec as ks, tables as kuka_tables
from experiments.gridworld.spec import FAR_TRAINING_NAME, MODE_REPLAN, TRAINING_NAME
from experiments.harness.core import CHECKPOINT_ROOT


def _training_summary(train_dir):
    from diffplan.checkpoint import read_metadata
    meta = read_metadata(train_dir)
    records = []
    path = os.path.join(train_dir, "metrics.jsonl")
    if os.path.exists(path):
        with open(path) as f:
            records = [json.loads(line) for line in f if line.strip()]
    last = records[-1] if records else {}
    return meta, last


WORLDS = {
    # world: (default destination, default training command, what the model is)
    "gridworld": (os.path.join(CHECKPOINT_ROOT, TRAINING_NAME),
                  "python -m experiments.compile_p_mo2g --train",
                  "The grid-world denoiser shipped with diffplan (one model for 1O1G, MO1G and "
                  "P-MO2G)."),
    "gridworld_far": (os.path.join(CHECKPOINT_ROOT, FAR_TRAINING_NAME),
                      "python -m experiments.compile_p_mo2g_far --train",
                      "The P-MO2G-far denoiser shipped with diffplan (trained on P-MO2G-far "
                      "beside the paper's three settings; compile_p_mo2g_far evaluates it)."),
    "gridworld_pretrained": (os.path.join(CHECKPOINT_ROOT, f"{TRAINING_NAME}_pretrained"),
                             "python -m experiments.compile_p_mo2g --train --text pretrained",
                             "The grid-world denoiser on the frozen pretrained text encoder's "
                             "features (checkpoints/text_encoder: any English instruction; one "
                             "model for 1O1G, MO1G and P-MO2G)."),
    "gridworld_far_pretrained": (
        os.path.join(CHECKPOINT_ROOT, f"{FAR_TRAINING_NAME}_pretrained"),
        "python -m experiments.compile_p_mo2g_far --train --text pretrained",
        "The P-MO2G-far denoiser on the frozen pretrained text encoder's features (trained on "
        "P-MO2G-far beside the paper's three settings)."),
    "gridworld_goal": (os.path.join(CHECKPOINT_ROOT, "baselines", "goal"),
                       "python -m experiments.compile_p_mo2g --train --objective goal",
                       "The learned-goal baseline (the grid-world denoiser's network, config, "
                       "batches, optimiser and steps, trained to classify the goal and sub-goal "
                       "cells instead of in-painting a plan; evaluated with --num-steps 1 "
                       "through the same planner, triggers and psi)."),
    "kuka": (os.path.join(CHECKPOINT_ROOT, "kuka"),
             "python -m experiments.kuka_stacking --train",
             "The Kuka block-world denoiser shipped with diffplan (one model for stacking and "
             "rearrangement, single and multiple constraints, canonical and paraphrased "
             "instructions)."),
    "kuka_pretrained": (os.path.join(CHECKPOINT_ROOT, "kuka_pretrained"),
                        "python -m experiments.kuka_stacking --train --text pretrained",
                        "The Kuka block-world denoiser on the frozen pretrained text encoder's "
                        "features (checkpoints/text_encoder: any English instruction; one model "
                        "for stacking and rearrangement, single and multiple constraints)."),
    **{f"babyai_{level}{bc}": (
        os.path.join(CHECKPOINT_ROOT, f"babyai_{level}{bc}"),
        f"python -m experiments.babyai --level {level} --train",
        f"The BabyAI {level} " + ("BC baseline (trained with ours, on the same demonstrations, "
                                  "until it converged or used our training minutes)." if bc
                                  else "denoiser (minigrid's level; every number measured in "
                                       "minigrid).")) for level in LEVELS for bc in ("", "_bc")},
}


def _is_kuka(result) -> bool:
    """Whether a result is a Kuka CLI's (kuka_stacking, kuka_rearrangement)."""
    return str(result.get("experiment", "")).startswith("kuka_")


def _is_babyai(result) -> bool:
    return str(result.get("experiment", "")).startswith("babyai_")


def _result_table(result) -> str:
    if _is_babyai(result):
        from experiments.babyai.tables import format_table

        return format_table(result["rows"])
    if _is_kuka(result):
        return kuka_tables.format_table(result["rows"])
    return gridworld_eval.format_table(result["rows"])


def _kuka_flags(result) -> str:
    """The Kuka CLIs' own flags, where a result departs from their defaults."""
    flags = ""
    if result.get("modes") and tuple(result["modes"]) != ks.MODES:
        flags += f" --modes {','.join(result['modes'])}"
    if result.get("carry", ks.CARRIES[0]) != ks.CARRIES[0]:
        flags += f" --carry {result['carry']}"
    if result.get("reader"):
        flags += f" --reader {result['reader']}"
    return flags


def _result_command(result) -> str:
    seeds = result.get("seeds") or [result["seed"]]
    seed_flag = (f"--seeds {','.join(map(str, seeds))}" if len(seeds) > 1
                 else f"--seed {seeds[0]}")
    extra = f" --language {result['language']}" if result.get("language") not in (
        None, "canonical") else ""
    triggers = set((result.get("replan") or {}).items())
    if triggers and not triggers <= set(MODE_REPLAN.items()) and len(
            {t for _, t in triggers}) == 1:
        extra += f" --replan {triggers.pop()[1]}"
    if result.get("psi", "search") != "search":
        extra += f" --psi {result['psi']}"
        if "follow_mark" in result:
            extra += f" --follow-mark {result['follow_mark']:g}"
    if result.get("samples", 1) > 1:
        extra += f" --samples {result['samples']}"
    if _is_kuka(result):
        extra += _kuka_flags(result)
    if _is_babyai(result):
        return (f"python -m experiments.babyai --level {result['level']} --episodes "
                f"{result['episodes']} {seed_flag}")
    return (f"python -m experiments.{result['experiment']} --episodes {result['episodes']} "
            f"{seed_flag}{extra}")


def write_note(out_dir, train_dir, results, command, remarks=(), world: str = "gridworld"):
    meta, last = _training_summary(train_dir)
    train_config = meta.get("train_config", {})
    lines = [
        f"# {os.path.basename(os.path.normpath(out_dir))}",
        "",
        WORLDS[world][2],
        "",
        "## How it was made",
        "",
        f"- command: `{command}`",
        f"- training seed: {train_config.get('seed')}; steps: {meta.get('step')}; batch "
        f"{train_config.get('batch_size')}; lr {train_config.get('lr')}",
        *([f"- mixture per batch: {meta['extra']['mixture']}"]
          if "mixture" in meta.get("extra", {}) else []),
        *([f"- task specs (kind, multi, language), one share of every batch each (a spec "
           f"listed twice has twice the share): {meta['extra']['specs']}"]
          if "specs" in meta.get("extra", {}) else []),
        *([f"- diffusion training timesteps: {train_config['num_train_timesteps']}, drawn "
           f"with timestep_power {train_config.get('timestep_power', 1.0)} (1: uniform)"]
          if train_config.get("num_train_timesteps") else []),
        f"- training wall time: {last.get('wall_time', float('nan')) / 60:.1f} min on a 2-core "
        f"CPU (last logged loss {last.get('loss', float('nan')):.4f})",
        "- exported with: `python -m experiments.ship_checkpoint` (EMA parameters only)",
        *[f"- {remark}" for remark in remarks],
        "",
        "## What it achieved (SR in percent, measured on what the agent executed: trajectories "
        "with collisions in the grid world, final physical block poses in the Kuka world)",
        "",
    ]
    for result in results:
        lines += [f"`{_result_command(result)}` ({result.get('machine', '')}):", "", "```",
                  _result_table(result), "```", ""]
    with open(os.path.join(out_dir, "NOTE.md"), "w") as f:
        f.write("\n".join(lines))


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m experiments.ship_checkpoint",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--train-dir", required=True, help="the training run to export")
    p.add_argument("--world", choices=sorted(WORLDS), default="gridworld",
                   help="which world's denoiser the run trained (sets the defaults of --out "
                        "and --command and NOTE.md's description; default gridworld)")
    p.add_argument("--out", default=None,
                   help="destination (default checkpoints/compile_gridworld, "
                        "checkpoints/compile_gridworld_far with --world gridworld_far, "
                        "checkpoints/<that>_pretrained with --world <that>_pretrained, "
                        "checkpoints/baselines/goal with --world gridworld_goal, "
                        "checkpoints/kuka with --world kuka, or checkpoints/<world> with a "
                        "babyai_<level>[_bc] world)")
    p.add_argument("--results", action="append", default=[], metavar="JSON",
                   help="experiment results (contract 2) to record in NOTE.md; repeatable")
    p.add_argument("--command", default=None,
                   help="the training command recorded in NOTE.md (default: the world's "
                        "--train command)")
    p.add_argument("--remark", action="append", default=[],
                   help="a sentence added to NOTE.md's 'How it was made' (e.g. what else ran "
                        "on the machine during training); repeatable")
    p.add_argument("--overwrite", action="store_true", help="replace an existing export")
    args = p.parse_args(argv)
    out_default, command_default, _ = WORLDS[args.world]
    args.out = out_default if args.out is None else args.out
    args.command = command_default if args.command is None else args.command
    from diffplan.checkpoint import CorruptCheckpointError, export_eval_checkpoint, latest_step
    from experiments.harness import cli
    if latest_step(args.train_dir) is None:
        p.error(f"--train-dir {args.train_dir!r} holds no checkpoint")
    cli.check_output_dir(p, "--out", args.out)
    results = []
    for path in args.results:
        try:
            with open(path) as f:
                results.append(json.load(f))
        except (OSError, json.JSONDecodeError) as e:
            p.error(f"--results {path!r} cannot be read as JSON: {e}")
        if not isinstance(results[-1], dict) or "rows" not in results[-1]:
            p.error(f"--results {path!r} is not an experiment's results JSON (no 'rows')")
    try:
        export_eval_checkpoint(args.train_dir, args.out, overwrite=args.overwrite)
    except CorruptCheckpointError as e:
        p.error(str(e))
    except ValueError as e:
        p.error(str(e))
    write_note(args.out, args.train_dir, results, args.command, args.remark, args.world)
    print(f"wrote {args.out} and its NOTE.md")


if __name__ == "__main__":
    main()
