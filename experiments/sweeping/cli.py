"""Batched evaluation sweeps: many planner configurations of any registered task (the grid world's
settings, the Kuka world's tasks), each one jitted evaluation over all its episodes.

    python -m experiments.sweep --config experiments/sweeps/p_mo2g_pareto.json --json s.json
    python -m experiments.sweep --setting p_mo2g --modes on_the_fly,warm_start \\
        --num-steps 10,3 --seed 2001 --episodes 200 --csv s.csv --figures figs/
    python -m experiments.sweep --task kuka/stacking --modes on_the_fly,one_shot \\
        --episodes 8 --batch-size 8 --json kuka.json

A configuration holds the experiment CLIs' flags, with underscores, and names its task: "task"
(a registry name, ``envs.names()``: gridworld/1o1g, gridworld/mo1g, gridworld/p_mo2g,
gridworld/p_mo2g_far, kuka/stacking, kuka/rearrangement) or, for the grid world, "setting"
(1o1g, mo1g, p_mo2g, p_mo2g_far; the default task is gridworld/p_mo2g). Every task:
checkpoint, modes (one planning mode), num_steps, seed, episodes, batch_size. The grid world:
eta, warm_start_step, warm_num_steps, noise ("fresh" | "episode"), replan ("always" |
"on_change" | "on_refuted"; missing: the mode's own, as in the experiment CLIs: on_the_fly
"always", warm_start "on_change"), language, psi ("search" | "follow"), samples (plans drawn
per re-plan), denoiser ("learned" | "posterior": no checkpoint, exact guesses); batch_size is the slots per device of the re-planning modes' pool. The Kuka
world: multi (true: the multi-constraint column), language ("canonical" | "paraphrased" |
"development"), carry ("path" | "arc"), reader (a reader directory, e.g. checkpoints/kuka_reader:
instructions restated canonically first, as the CLIs' --reader); batch_size is the episodes per
jitted call. ``--config FILE`` reads a JSON list of such objects (missing keys
take the experiment CLIs' defaults, listed below); on the command line, comma-separated values
give every combination.

Grid world: each configuration runs as one call of a jitted function over all its episodes,
split over the devices of every process (the CLIs' program); each episode's result is the same
on any number of devices and processes. Kuka world: the Kuka CLIs' batched rollout under MJX
physics, so a row equals the CLI's row of the same column. Compiled functions are kept and
reused by configurations of the same shapes and planner settings (another seed or another
checkpoint of the same architecture costs no compilation); ``compile_seconds`` is the lowering
and compilation time of a configuration (0 when reused).

Several processes (--coordinator, --num-processes, --process-id, or a SLURM / TPU-pod job):
episodes split over all their devices, process 0 prints and writes. Each finished
configuration's row is kept at once in <--json or --csv>.parts/; a sweep that died (a process
killed, a host lost) and is run again with the same command resumes from those rows.

Rows: the metrics of contract 2 (grid world: SR, SR_ordered, GD, path P/R/F1; Kuka: strict SR,
SR_diffuser, all_constraints, tower; both: denoiser calls per episode, seconds) plus
compile_seconds and the configuration (its task included). ``--json``, ``--csv``, ``--figures
DIR`` (SR against denoiser calls per episode and against seconds, Pareto front marked) and
``--trajectories DIR`` (per configuration: the executed trajectories, or Kuka's final states).
"""
from __future__ import annotations

import argparse
import json
import sys

from experiments.harness import cli, core as harness, processes
from experiments.sweeping import resume
from experiments.sweeping.config import DEFAULTS, KEYS, SweepError, expand, normalise
from experiments.sweeping.output import format_rows, write_csv, write_figures

__all__ = ["build_parser", "main"]


def _default_text(key: str) -> str:
    if key == "task":
        return "gridworld/p_mo2g"
    values = {w: d[key] for w, d in DEFAULTS.items() if key in d}
    if len(set(map(repr, values.values()))) == 1:
        return repr(next(iter(values.values())))
    return ", ".join(f"{w} {v!r}" for w, v in values.items())


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m experiments.sweep",
                                description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="Configuration keys and defaults per world: "
                                       + json.dumps(DEFAULTS))
    p.add_argument("--config", metavar="FILE",
                   help="a JSON list of configurations (objects with the keys below)")
    for key in KEYS:
        p.add_argument(f"--{key.replace('_', '-')}", default=None, metavar="V[,V...]",
                       help=f"{key} (comma-separated values: every combination; default "
                            f"{_default_text(key)}; not with --config)")
    p.add_argument("--json", metavar="PATH", help="write the rows (contract 2 layout)")
    p.add_argument("--csv", metavar="PATH", help="write the rows as CSV")
    p.add_argument("--figures", metavar="DIR", help="write the Pareto figures")
    p.add_argument("--trajectories", metavar="DIR",
                   help="write each configuration's executed trajectories and episodes "
                        "(contract 2's format; Kuka: the final states, contract 4) to "
                        "DIR/config_NNN.npz")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    processes.add_process_flags(p)
    return p


def _configurations(parser, args, given: dict) -> list[dict]:
    """The checked configurations of --config or of the per-key flags."""
    try:
        if args.config:
            if given:
                parser.error(f"--config excludes the per-key flags ({', '.join(given)})")
            try:
                with open(args.config) as f:
                    raw = json.load(f)
            except (OSError, json.JSONDecodeError) as e:
                parser.error(f"--config {args.config!r} cannot be read as JSON: {e}")
            if not isinstance(raw, list) or not raw:
                parser.error(f"--config {args.config!r} must hold a non-empty JSON list")
        else:
            raw = expand(given)
        return [normalise(c, i) for i, c in enumerate(raw)]
    except SweepError as e:
        parser.error(str(e))


def main(argv=None) -> dict:
    from diffplan.jax_cache import enable_compilation_cache

    parser = build_parser()
    args = parser.parse_args(argv)
    processes.start(parser, args)
    given = {k: getattr(args, k) for k in KEYS if getattr(args, k) is not None}
    cli.check_output_file(parser, "--json", args.json)
    cli.check_output_file(parser, "--csv", args.csv, suffix=".csv")
    cli.check_output_dir(parser, "--figures", args.figures)
    cli.check_output_dir(parser, "--trajectories", args.trajectories)
    configs = _configurations(parser, args, given)
    enable_compilation_cache()
    from experiments.harness.progress import bar
    from experiments.sweeping.run import Runner

    runner = Runner(progress=not args.no_progress)
    for i, config in enumerate(configs):  # every checkpoint loads before any work
        try:
            runner.denoiser(config, i)
            runner.reader(config, i)
        except SweepError as e:
            parser.error(str(e))
    parts = resume.directory(args)
    done = resume.finished(parts, configs, args.trajectories)
    if done:
        print(f"resuming: {len(done)} of {len(configs)} configurations already finished "
              f"({parts}; delete it to start over)")
    rows = []
    outer = bar(total=len(configs), desc="configurations", unit="cfg", file=sys.stderr,
                disable=args.no_progress, leave=True, position=0, initial=len(done))
    for i, config in enumerate(configs):
        if i not in done:
            rows.append(runner.run(config, i, args.trajectories))
            resume.save(parts, i, config, rows[-1])
            outer.update(1)
        else:
            rows.append(done[i])
    outer.close()
    result = {"experiment": "sweep", "episodes": int(sum(c["episodes"] for c in configs)),
              "seed": configs[0]["seed"], "devices": runner.devices,
              "machine": harness.machine(), "rows": rows}
    if not processes.writes():
        return result  # process 0 prints and writes
    print(format_rows(rows))
    if args.json:
        cli.write_json(args.json, result)
    if args.csv:
        write_csv(args.csv, rows)
        print(f"wrote {args.csv}")
    if args.figures:
        for path in write_figures(args.figures, rows):
            print(f"wrote {path}")
    resume.clear(parts)
    return result


if __name__ == "__main__":
    main()
