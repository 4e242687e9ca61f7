"""Trains the CompILE baselines (BC, CQL, the DD-style planner) and ships them.

    python -m experiments.train_baselines                 # train all three (resumes)
    python -m experiments.train_baselines --ship --results results/baselines.json

One model per baseline (``diffplan.baselines`` on ``envs.gridworld.baselines``' data) serves
the three settings, trained on a mixture of them (``TRAINING_MIXTURE``); with
``--per-setting`` a baseline gets one model per setting instead, trained on that setting's
examples only (as the paper trains its baselines), in ``<name>/<setting>/``. Runs go to
``runs/baselines/<name>`` (``dd`` has ``diffusion/`` and ``inverse_dynamics/``) with a
checkpoint every few minutes; a killed run resumes exactly. ``--ship`` exports the finished
runs as small evaluation checkpoints under ``checkpoints/baselines/<name>/`` with a NOTE.md
each (command, seed, steps, training time, and the rows of ``experiments.baselines_eval``
JSONs given with ``--results``; ``experiments.shipping.baselines``); ``experiments.baselines_eval``
uses a setting's own model where there is one.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from typing import Sequence

from diffplan.baselines import bc, cql, dd
from diffplan.jax_cache import enable_compilation_cache
from diffplan.train import ConfigMismatchError
from envs.gridworld import baselines as gb
from envs.gridworld.training import TRAINING_MIXTURE
from experiments.harness import cli
from experiments.shipping.baselines import ship
from experiments.harness.core import CHECKPOINT_ROOT, REPO_ROOT, fail
from experiments.kuka.baselines import KUKA_BASELINES

DEFAULT_RUN_DIR = os.path.join(REPO_ROOT, "runs", "baselines")
SHIP_DIR = os.path.join(CHECKPOINT_ROOT, "baselines")
NAMES = ("bc", "cql", "dd")
WORLDS = ("gridworld", "kuka")

def _json_file(path: str) -> dict:
    """argparse type: the results JSON (contract 2) at path."""
    try:
        with open(path) as f:
            result = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        raise argparse.ArgumentTypeError(f"{path!r} cannot be read as JSON: {e}") from e
    if not isinstance(result, dict) or "rows" not in result:
        raise argparse.ArgumentTypeError(f"{path!r} holds no results rows")
    return result


def build_parser() -> argparse.ArgumentParser:
    b, c, d = bc.BCTrainConfig(), cql.CQLTrainConfig(), dd.DDTrainConfig()
    p = argparse.ArgumentParser(
        prog="python -m experiments.train_baselines",
        description="Train the baselines BC, CQL and DD-style (the grid world's: one model for "
                    "the three settings, or one per setting; the Kuka world's: one for its four "
                    "columns), resuming from the last checkpoint; optionally ship them "
                    "to checkpoints/baselines with a NOTE.md each.")
    p.add_argument("--world", choices=WORLDS, default="gridworld",
                   help="whose baselines: the CompILE grid world's (default) or the Kuka "
                        f"world's ({','.join(KUKA_BASELINES)}; runs in DIR/kuka/<name>, "
                        "shipped to checkpoints/baselines/kuka/<name>)")
    p.add_argument("--baselines", default=None,
                   help="comma-separated baselines to train / ship among bc,cql,dd "
                        "(default all of the world's)")
    p.add_argument("--run-dir", metavar="DIR", default=DEFAULT_RUN_DIR,
                   help="training output root; each baseline trains into DIR/<name> "
                        "(default runs/baselines)")
    p.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    p.add_argument("--bc-steps", type=int, default=b.steps,
                   help=f"BC optimisation steps (default {b.steps}, batch {b.batch_size})")
    p.add_argument("--cql-steps", type=int, default=c.steps,
                   help=f"CQL optimisation steps (default {c.steps}, batch {c.batch_size})")
    p.add_argument("--cql-buffer", type=int, default=c.buffer_size,
                   help=f"CQL replay buffer size in transitions (default {c.buffer_size})")
    p.add_argument("--dd-steps", type=int, default=d.steps,
                   help=f"DD-style diffusion steps (default {d.steps}, batch {d.batch_size})")
    p.add_argument("--id-steps", type=int, default=d.id_steps,
                   help=f"DD-style inverse dynamics steps (default {d.id_steps}, batch "
                        f"{d.id_batch_size})")
    p.add_argument("--dd-change-weight", type=float, default=None, metavar="W",
                   help="DD-style loss: the entries where a frame differs from frame 0 weigh "
                        f"1 + W times the others (default: the grid world's {d.change_weight:g}, "
                        "where 2 of 256 cells change; the Kuka world's 0, where most of the 12 "
                        "block-state values do)")
    p.add_argument("--checkpoint-every", type=int, default=None, metavar="N",
                   help="write a checkpoint every N steps in every run (default: BC / CQL "
                        f"{b.checkpoint_every}, DD {d.checkpoint_every}: minutes on this CPU)")
    p.add_argument("--per-setting", action="store_true",
                   help="train one model per setting (DIR/<name>/<setting>, each on its "
                        "setting's examples only, as the paper trains its baselines) instead "
                        "of one on the mixture of the three; evaluation uses a setting's own "
                        "model where there is one")
    p.add_argument("--no-train", action="store_true",
                   help="do not train (e.g. --ship finished runs only)")
    p.add_argument("--ship", action="store_true",
                   help="export the finished runs to --ship-dir/<name> with a NOTE.md each")
    p.add_argument("--ship-dir", metavar="DIR", default=SHIP_DIR,
                   help="where --ship writes (default checkpoints/baselines)")
    p.add_argument("--results", action="append", default=[], metavar="JSON", type=_json_file,
                   help="experiments.baselines_eval JSON whose rows --ship records in the "
                        "NOTE.md files; repeatable")
    p.add_argument("--command", default=None,
                   help="the training command recorded in NOTE.md (default: this command "
                        "without --ship / --results)")
    p.add_argument("--remark", action="append", default=[],
                   help="a sentence added to every NOTE.md (e.g. what shared the CPU)")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    return p


def configs(args):
    """(bc, cql, dd) training configs from the arguments."""
    every = {} if args.checkpoint_every is None else {"checkpoint_every": args.checkpoint_every}
    return (bc.BCTrainConfig(seed=args.seed, steps=args.bc_steps, **every),
            cql.CQLTrainConfig(seed=args.seed, steps=args.cql_steps,
                               buffer_size=args.cql_buffer, **every),
            dd.DDTrainConfig(seed=args.seed, steps=args.dd_steps, id_steps=args.id_steps,
                             change_weight=_change_weight(args), **every))


def _change_weight(args) -> float:
    if args.dd_change_weight is not None:
        return args.dd_change_weight
    if args.world == "kuka":
        from envs.kuka.baselines import DD_CHANGE_WEIGHT

        return DD_CHANGE_WEIGHT
    return dd.DDTrainConfig().change_weight


def runs_of(name: str, run_dir: str, mixture=TRAINING_MIXTURE, per_setting: bool = False):
    """((directory, mixture), ...): baseline name's training runs, run_dir/<name> on the
    mixture, or with per_setting run_dir/<name>/<setting> on that setting alone."""
    out = os.path.join(run_dir, name)
    if not per_setting:
        return ((out, mixture),)
    return tuple((os.path.join(out, setting), ((setting, 1),)) for setting, _ in mixture)


def train_all(names, run_dir, bc_config, cql_config, dd_config, progress=True, *,
              mixture=TRAINING_MIXTURE, dd_model=dd.DDConfig(), per_setting=False,
              world: str = "gridworld") -> dict:
    """Trains the named baselines into run_dir/<name> on the mixture of settings (with
    per_setting: one model per setting of the mixture, :func:`runs_of`; world "kuka": the Kuka
    world's baselines on its training specs, mixture and per_setting unused); returns {name:
    seconds of this call}."""
    seconds = {}
    for name in names:
        start = time.time()
        runs = (((os.path.join(run_dir, name), None),) if world == "kuka"
                else runs_of(name, run_dir, mixture, per_setting))
        for out, data in runs:
            if world == "kuka":
                from envs.kuka import baselines as kb

                if name == "bc":
                    kb.train_bc(out, bc_config, progress=progress)
                elif name == "cql":
                    kb.train_cql(out, cql_config, progress=progress)
                else:
                    kb.train_dd(os.path.join(out, "diffusion"), dd_config, progress=progress)
                    kb.train_inverse_dynamics(os.path.join(out, "inverse_dynamics"),
                                              dd_config, progress=progress)
            elif name == "bc":
                gb.train_bc(out, bc_config, mixture=data, progress=progress)
            elif name == "cql":
                gb.train_cql(out, cql_config, mixture=data, progress=progress)
            else:
                gb.train_dd(os.path.join(out, "diffusion"), dd_config, dd_model, data,
                            progress)
                gb.train_inverse_dynamics(os.path.join(out, "inverse_dynamics"), dd_config,
                                          mixture=data, progress=progress)
        seconds[name] = time.time() - start
        print(f"{name}: {seconds[name] / 60:.1f} min in this call", file=sys.stderr)
    return seconds


def _default_command(argv) -> str:
    """The command without --ship, --no-train and the shipping flags with their values."""
    drop_values = ("--results", "--command", "--remark", "--ship-dir")
    kept, skip = [], False
    for a in argv:
        if not (skip or a in ("--ship", "--no-train") + drop_values
                or a.startswith(tuple(f + "=" for f in drop_values))):
            kept.append(a)
        skip = not skip and a in drop_values
    return " ".join(["python -m experiments.train_baselines", *map(shlex.quote, kept)])


def main(argv: Sequence[str] | None = None):
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    known = KUKA_BASELINES if args.world == "kuka" else NAMES
    names = tuple(n.strip() for n in (args.baselines or ",".join(known)).split(",")
                  if n.strip())
    if not names or any(n not in known for n in names):
        parser.error(f"--baselines of the {args.world} world must be among {','.join(known)}, "
                     f"got {args.baselines!r}")
    if args.world == "kuka":
        if args.per_setting:
            parser.error("--per-setting is the grid world's (the Kuka baselines serve every "
                         "column with one model)")
        args.run_dir = os.path.join(args.run_dir, "kuka")
    for flag in ("bc_steps", "cql_steps", "dd_steps", "id_steps", "cql_buffer"):
        cli.check_at_least(parser, "--" + flag.replace("_", "-"), getattr(args, flag), 2)
    cli.check_at_least(parser, "--checkpoint-every", args.checkpoint_every, 1)
    if args.dd_change_weight is not None and not args.dd_change_weight >= 0:
        parser.error(f"--dd-change-weight must be >= 0, got {args.dd_change_weight}")
    cli.check_at_least(parser, "--seed", args.seed, 0)
    cli.check_output_dir(parser, "--run-dir", args.run_dir)
    if args.ship:
        cli.check_output_dir(parser, "--ship-dir", args.ship_dir)
    elif args.results or args.remark or args.command or args.ship_dir != SHIP_DIR:
        parser.error("--results, --remark, --command and --ship-dir only make sense with "
                     "--ship")
    if args.no_train and not args.ship:
        parser.error("--no-train without --ship does nothing")
    if args.world == "kuka":
        args.ship_dir = os.path.join(args.ship_dir, "kuka")
    bc_config, cql_config, dd_config = configs(args)
    enable_compilation_cache()
    if not args.no_train:
        try:
            seconds = train_all(names, args.run_dir, bc_config, cql_config, dd_config,
                                not args.no_progress, per_setting=args.per_setting,
                                world=args.world)
        except ConfigMismatchError as e:
            fail(str(e))
        print(f"trained {','.join(names)} in {sum(seconds.values()) / 60:.1f} min",
              file=sys.stderr)
    if args.ship:
        ship(names, args.run_dir, args.ship_dir, args.results,
             args.command or _default_command(argv), args.remark, args.world)


if __name__ == "__main__":
    main()
