"""The baselines' rows of the CompILE tables (BC, CQL, DD-style; the paper's Table 1), measured
exactly as our planner's: the same seeded evaluation episodes (``eval_episodes``), the executed
trajectories with collisions (``diffplan.baselines.rollout.policy_rollout``), the same
``metrics_row`` (plus 95% intervals and per-seed values for several seeds). The policies act
in the grid world through ``envs.gridworld.baselines.POLICY_WORLD``.

    python -m experiments.baselines_eval --settings 1o1g,mo1g,p_mo2g --seeds 2001,2002,2003

``baseline_rows(setting, seeds, episodes, batch_size, progress)`` is what the grid-world
experiments call for their ``--baselines`` rows. The shipped checkpoints are
``checkpoints/baselines/{bc,cql,dd}`` (``experiments.train_baselines`` makes them).
``reference_rows`` measures the reference agents (``envs.gridworld.agents``: the oracle, which
knows the whole map, and the searcher, a heuristic of what the agent has seen) the same way;
every grid-world table carries their rows unless ``--no-reference-agents``.
"""
from __future__ import annotations

import argparse
import os
import time
from typing import Sequence

import jax

from diffplan.baselines.policies import BASELINES, DD_PARTS, load_policy
from envs.gridworld.agents import REFERENCE_AGENTS, REFERENCE_POLICIES
from envs.gridworld.baselines import POLICY_WORLD
from envs.gridworld.config import SETTINGS
from experiments.gridworld.eval import format_intervals, format_table
from experiments.gridworld.flags import add_reference_agents_flag
from experiments.harness.core import (CHECKPOINT_ROOT, DEFAULT_EVAL_SEED, EVALUATION_SEEDS,
                                      VALIDATION_SEED, fail, parse_seeds)
from experiments.gridworld.policy_eval import policy_rows

CHECKPOINT_DIR = os.path.join(CHECKPOINT_ROOT, "baselines")
DEFAULT_DD_NUM_STEPS = 10
DEFAULT_DD_GUIDANCE = 1.0


def policy_directory(root: str, name: str, setting: str) -> str:
    """Where baseline ``name``'s model for ``setting`` is: ``root/name/setting`` when the
    baseline was trained one model per setting (``train_baselines --per-setting``; the paper
    trains its baselines per setting), else the one model ``root/name`` that serves every
    setting. Raises FileNotFoundError (naming the setting) when neither holds a checkpoint."""
    from diffplan.checkpoint import latest_step

    for directory in (os.path.join(root, name, setting), os.path.join(root, name)):
        # The DD-style planner's checkpoints are its parts (diffusion/, inverse_dynamics/).
        if latest_step(os.path.join(directory, DD_PARTS[0] if name == "dd" else "")) is not None:
            return directory
    raise FileNotFoundError(f"no {name} checkpoint for {setting} in {root} (neither "
                            f"{name}/{setting}/ nor {name}/): train and ship it with "
                            "`python -m experiments.train_baselines --ship`")


def baseline_rows(setting: str, seeds: tuple[int, ...], episodes: int, batch_size: int,
                  progress: bool, *, checkpoint_root: str | None = None,
                  methods: Sequence[str] | None = None,
                  dd_num_steps: int = DEFAULT_DD_NUM_STEPS,
                  dd_guidance: float = DEFAULT_DD_GUIDANCE,
                  episodes_by_seed: dict | None = None, keep: dict | None = None) -> list[dict]:
    """:func:`policy_rows` of the baselines ("BC", "CQL", "DD-style"; methods among
    BASELINES, default all) from the shipped checkpoints under checkpoint_root (default
    checkpoints/baselines; :func:`policy_directory` picks a baseline's model of the setting).
    Raises FileNotFoundError when a checkpoint is missing."""
    root = CHECKPOINT_DIR if checkpoint_root is None else checkpoint_root
    policies = [load_policy(name, policy_directory(root, name, setting), POLICY_WORLD,
                            dd_num_steps=dd_num_steps, dd_guidance=dd_guidance)
                for name in (BASELINES if methods is None else methods)]
    return policy_rows(policies, setting, seeds, episodes, batch_size, progress,
                       episodes_by_seed=episodes_by_seed, keep=keep)


def reference_rows(setting: str, seeds: tuple[int, ...], episodes: int, batch_size: int,
                   progress: bool, *, episodes_by_seed: dict | None = None,
                   keep: dict | None = None) -> list[dict]:
    """:func:`policy_rows` of the reference agents ("oracle", "searcher":
    envs.gridworld.agents), which bound what a planner can do; no checkpoint, no network."""
    return policy_rows([REFERENCE_POLICIES[name] for name in REFERENCE_AGENTS], setting, seeds,
                       episodes, batch_size, progress, episodes_by_seed=episodes_by_seed,
                       keep=keep)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m experiments.baselines_eval",
        description="Evaluate the shipped baselines (BC, CQL, DD-style) on the CompILE grid "
                    "world, measured on executed trajectories exactly as our planner is.")
    p.add_argument("--settings", default="1o1g,mo1g,p_mo2g",
                   help="comma-separated settings (default all three)")
    p.add_argument("--episodes", type=int, default=1000,
                   help="evaluation episodes per seed (default 1000)")
    p.add_argument("--seed", type=int, default=DEFAULT_EVAL_SEED,
                   help=f"evaluation seed (default {DEFAULT_EVAL_SEED}); episode i is "
                        "generate(fold_in(PRNGKey(seed), i))")
    p.add_argument("--seeds", metavar="S1,S2,...", default=None,
                   help="several seeds, pooled with 95%% intervals and per-seed values (the "
                        f"README uses {','.join(map(str, EVALUATION_SEEDS))}; "
                        f"{VALIDATION_SEED} is the validation seed)")
    p.add_argument("--methods", default="bc,cql,dd",
                   help="comma-separated baselines among bc,cql,dd (default all)")
    p.add_argument("--checkpoint-root", metavar="DIR", default=CHECKPOINT_DIR,
                   help="directory holding bc/, cql/ and dd/ (default checkpoints/baselines)")
    p.add_argument("--batch-size", type=int, default=250,
                   help="episodes per jitted call (default 250)")
    p.add_argument("--dd-num-steps", type=int, default=DEFAULT_DD_NUM_STEPS,
                   help=f"DDIM steps per move of the DD-style planner (default "
                        f"{DEFAULT_DD_NUM_STEPS})")
    p.add_argument("--dd-guidance", type=float, default=DEFAULT_DD_GUIDANCE,
                   help="classifier-free guidance weight of the DD-style planner (1: the "
                        f"conditional model alone; default {DEFAULT_DD_GUIDANCE})")
    p.add_argument("--json", metavar="PATH",
                   help="write the rows (contract 2; each row names its setting)")
    add_reference_agents_flag(p)
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    return p


def main(argv: Sequence[str] | None = None) -> dict:
    from diffplan.jax_cache import enable_compilation_cache
    from experiments.harness import cli

    parser = build_parser()
    args = parser.parse_args(argv)
    seeds = parse_seeds(parser, args)
    settings = tuple(s.strip() for s in args.settings.split(",") if s.strip())
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    if not settings or any(s not in SETTINGS for s in settings):
        parser.error(f"--settings must be among {','.join(SETTINGS)}, got {args.settings!r}")
    if not methods or any(m not in BASELINES for m in methods):
        parser.error(f"--methods must be among {','.join(BASELINES)}, got {args.methods!r}")
    for flag, value in (("--episodes", args.episodes), ("--batch-size", args.batch_size),
                        ("--dd-num-steps", args.dd_num_steps)):
        cli.check_at_least(parser, flag, value, 1)
    if not args.dd_guidance >= 0:
        parser.error(f"--dd-guidance must be >= 0, got {args.dd_guidance}")
    cli.check_output_file(parser, "--json", args.json)
    for m in methods:
        for setting in settings:
            try:
                policy_directory(args.checkpoint_root, m, setting)
            except FileNotFoundError as e:
                fail(str(e))
    enable_compilation_cache()
    start = time.time()
    rows = []
    for setting in settings:
        setting_rows = baseline_rows(setting, seeds, args.episodes, args.batch_size,
                                     not args.no_progress, checkpoint_root=args.checkpoint_root,
                                     methods=methods, dd_num_steps=args.dd_num_steps,
                                     dd_guidance=args.dd_guidance)
        if not args.no_reference_agents:
            setting_rows += reference_rows(setting, seeds, args.episodes, args.batch_size,
                                           not args.no_progress)
        print(f"\n{setting}: {args.episodes} episodes per seed, seed(s) "
              f"{','.join(map(str, seeds))}")
        print(format_table(setting_rows))
        if len(seeds) > 1:
            print(format_intervals(setting_rows, seeds))
        rows += [{"setting": setting, **row} for row in setting_rows]
    result = {"experiment": "baselines_eval", "episodes": args.episodes, "seed": seeds[0],
              "seeds": list(seeds), "validation": VALIDATION_SEED in seeds,
              "settings": list(settings), "dd_num_steps": args.dd_num_steps,
              "dd_guidance": args.dd_guidance, "seconds": time.time() - start,
              "machine": f"{os.cpu_count()} CPU cores, jax {jax.__version__} on "
                         f"{jax.devices()[0].platform}",
              "rows": rows}
    if args.json:
        cli.write_json(args.json, result)
    return result


if __name__ == "__main__":
    main()
