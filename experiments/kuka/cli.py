"""The Kuka block experiments (the paper's Tables 2 and 5): ``experiments.kuka_stacking`` and
``experiments.kuka_rearrangement`` call :func:`main`: load (or ``--train``) the Kuka denoiser,
run the diffusion planner (``--policy expert``: the scripted expert) on fresh seeded episodes
of the kind's single- and multi-constraint tasks under MJX physics, measure success on the
final physical block poses, print a table and write JSON (contract 2 of docs/DESIGN.md), the
final states (contract 4), figures and videos. Seeds: experiments.harness.core and
experiments.kuka.eval; choices were made on validation seed 1000, the README reports seeds
2001-2003, training draws from another key stream.
"""
from __future__ import annotations

import functools
import os
import sys
import time
from typing import Sequence

import numpy as np

from experiments.harness import cli, compiling, core as harness, processes, tables
from experiments.kuka import eval as ke, spec as ks, tables as kt, text
from experiments.kuka.figures import figures_and_videos, write_videos  # noqa: F401
from experiments.kuka.flags import build_parser, check_args


def _denoiser(kind: str, args, languages, progress: bool):
    """(checkpoint, train seconds or None, LoadedDenoiser, its InstructionEncoder or None for
    token ids): --train's result or a checkpoint, checked to read the languages (and
    --reader's token ids) in one line otherwise."""
    train_seconds = None
    if args.train:
        from diffplan.train import ConfigMismatchError

        checkpoint = args.train_dir or ks.default_train_dir(args.text)
        try:
            train_seconds = ks.train_denoiser(
                checkpoint, seed=args.train_seed or 0, steps=args.train_steps or ks.TRAIN_STEPS,
                model_size=args.model_size or "default",
                checkpoint_every=args.checkpoint_every or ks.CHECKPOINT_EVERY,
                progress=progress, text=args.text)
        except ConfigMismatchError as e:
            harness.fail(str(e))
    else:
        checkpoint = args.checkpoint or ks.default_checkpoint(args.text)
    denoiser = ks.load_checked(checkpoint, args.num_steps, kind, args.text)
    return checkpoint, train_seconds, denoiser, text.checkpoint_input(
        checkpoint, denoiser, languages, args.reader)


def _columns(args, seeds, specs, episodes, run, label, key, mode):
    """{(key, spec): row}, {(key, spec): (episodes, final)} of one actor in every column,
    pooled over the seeds: run(episodes, seed) -> final physical states; label(spec) -> the
    row's method; mode: the rows' "mode"."""
    rows, finals = {}, {}
    for spec in specs:
        per_seed, parts = {}, []
        for seed in seeds:
            t0 = time.time()
            eps = episodes[spec, seed]
            final = run(eps, seed)
            per_seed[seed] = ke.column_metrics("", "", eps, final, time.time() - t0)
            parts.append(final)
        final = {k: np.concatenate([d[k] for d in parts]) for k in parts[0]}
        eps = harness.concat_trees([episodes[spec, s] for s in seeds])
        row = ke.column_metrics(label(spec), "multi" if spec.multi else "single", eps, final,
                                sum(r["seconds"] for r in per_seed.values()))
        row.update(mode=mode, language=spec.language)
        if len(seeds) > 1:
            ke.add_intervals(row, ke.episode_counts(eps, final), per_seed)
        rows[key, spec], finals[key, spec] = row, (eps, final)
    return rows, finals


def _evaluate(args, seeds, modes, specs, episodes, task, denoiser, bar):
    """{(mode, spec): row} and {(mode, spec): (episodes, final)} of every mode and column,
    pooled over the seeds (mode None: the expert), then of every --baselines policy (mode
    its method name)."""
    rows, finals = {}, {}
    reader = ks.load_reader(args.reader) if args.reader else None
    if denoiser is not None:
        from diffplan.planner import PlannerConfig

        # Every mode's MJX program compiled at once, then used for all columns and seeds.
        runs = compiling.compiled_planners(task, denoiser, {m: PlannerConfig(
            mode=m, num_steps=args.num_steps) for m in modes}, episodes[specs[0], seeds[0]],
            args.batch_size, bar)
    for mode in modes:
        if denoiser is not None:
            planner, run = runs[mode]
            act = functools.partial(ke.run_planner, task, planner, batch=args.batch_size,
                                    bar=bar, run=run, settle=args.settle, reader=reader)
        elif args.policy == "expert":
            def act(eps, seed):
                return ke.run_expert(eps, args.batch_size, bar, settle=args.settle)
        else:  # a baseline
            _, act = _baseline_actor(args, args.policy, bar)
        out = _columns(args, seeds, specs, episodes, act, lambda spec: ks.label(
            mode, spec.multi, spec.language, ks.policy_name(args.policy), reader is not None),
            mode, mode)
        rows.update(out[0])
        finals.update(out[1])
    for name in args.baselines:
        method, act = _baseline_actor(args, name, bar)
        bar.compiling(f"compiling {method}")  # its program compiles in its first batch
        out = _columns(args, seeds, specs, episodes, act, lambda spec: ks.label(
            None, spec.multi, spec.language, method), method, None)
        rows.update(out[0])
        finals.update(out[1])
    return rows, finals


def _baseline_actor(args, name: str, bar):
    """(method, run(episodes, seed) -> final states) of the shipped Kuka baseline name."""
    from envs.kuka.task import KukaTask
    from experiments.kuka import baselines as kbl

    (policy,) = kbl.load_baselines((name,))
    return policy.method, functools.partial(kbl.run_policy, KukaTask(), policy,
                                            batch=args.batch_size, bar=bar, settle=args.settle)


def _print_summary(kind, args, seeds, checkpoint, all_rows) -> None:
    print(f"\nkuka_{kind}: {args.episodes} episodes per column and seed, seed(s) "
          f"{','.join(map(str, seeds))}, policy {args.policy}"
          + (f" ({os.path.relpath(checkpoint, harness.REPO_ROOT)}, {args.num_steps} denoising "
             f"steps per plan)" if checkpoint else "")
          + f"; success on the physical poses after {args.settle:g} s at rest (SR strict, "
            "contract 4; SR_Diff Diffuser's check; SPL over placements)")
    print(kt.format_table(all_rows))
    if phrasings := tables.format_phrasings(all_rows, "constraints"):
        print(phrasings)
    if len(seeds) > 1:
        print(tables.format_intervals(all_rows[1:], seeds, 46))
    print("paper (single / multi): " + "; ".join(
        f"{name} {s:.2f} / " + (f"{m:.2f}" if m is not None else "-")
        for name, (s, m) in ks.PAPER[kind].items()))


def main(kind: str, argv: Sequence[str] | None = None) -> dict:
    parser = build_parser(kind)
    args = parser.parse_args(argv)
    processes.start(parser, args)  # before any JAX computation; process 0 alone writes
    modes = check_args(parser, args)
    seeds = harness.parse_seeds(parser, args)
    from diffplan.jax_cache import enable_compilation_cache
    enable_compilation_cache()
    from envs.kuka.config import TaskSpec
    from experiments.harness.progress import bar as progress_bar

    progress = not args.no_progress
    planner_policy = args.policy == "planner"
    train_seconds, checkpoint, task, denoiser, encoder = None, None, None, None, None
    languages = text.languages_of(args.language)
    if planner_policy:
        from envs.kuka.task import KukaTask

        checkpoint, train_seconds, denoiser, encoder = _denoiser(kind, args, languages, progress)
        task = KukaTask(follow_path=args.carry == "path", text=text.task_input(encoder))
    else:
        modes = (None,)

    specs = [TaskSpec(kind, multi, language) for language in languages
             for multi in (False, True)]
    # A denoiser on pretrained text: features on the host, once per episode, before any rollout
    episodes = {(spec, seed): text.with_features(
        ke.generate_episodes(spec, args.episodes, seed, args.batch_size), encoder)
        for spec in specs for seed in seeds}
    actors = len(modes) + len(args.baselines)
    bar = progress_bar(total=args.episodes * len(seeds) * len(specs) * actors,
                       desc=f"kuka {kind} ({args.policy})", unit="ep", disable=not progress,
                       file=sys.stderr, leave=False, dynamic_ncols=True)
    start = time.time()
    rows, finals = _evaluate(args, seeds, modes, specs, episodes, task, denoiser, bar)
    bar.close()
    main_mode, main_language = modes[0], languages[0]
    main_specs = [s for s in specs if s.language == main_language]
    main_name = (ks.policy_name(args.policy) if not planner_policy else
                 f"planner {ks.METHOD_NAMES[main_mode]}" + (", read" if args.reader else ""))
    main_row = ke.pooled_row(main_name + (f", {main_language}" if main_language != "canonical"
                                          else ""),
                             [rows[main_mode, s] for s in main_specs],
                             sum(rows[main_mode, s]["seconds"] for s in main_specs))
    if len(seeds) > 1:
        counts = [ke.episode_counts(*finals[main_mode, s]) for s in main_specs]
        ke.add_intervals(main_row, tuple(np.concatenate(c) for c in zip(*counts)))
    from diffplan.baselines.policies import METHOD_NAMES

    baselines = tuple(METHOD_NAMES[name] for name in args.baselines)
    all_rows = [main_row] + [rows[m, s] for m in modes + baselines for s in specs]
    result = {
        "experiment": f"kuka_{kind}", "episodes": args.episodes, "seed": seeds[0],
        "seeds": list(seeds), "validation": harness.VALIDATION_SEED in seeds,
        "policy": args.policy, "language": args.language,
        "modes": [m for m in modes if m is not None], "baselines": list(args.baselines),
        "checkpoint": os.path.relpath(checkpoint, harness.REPO_ROOT) if checkpoint else None,
        "num_steps": args.num_steps if planner_policy else None, "reader": args.reader,
        "carry": args.carry if planner_policy else None, "settle_seconds": args.settle,
        "train_seconds": train_seconds, "states_method": main_row["method"],
        "paper": {name: dict(zip(("single", "multi"), values))
                  for name, values in ks.PAPER[kind].items()},
        "machine": harness.machine(), "seconds": time.time() - start, "rows": all_rows,
    }
    _print_summary(kind, args, seeds, checkpoint, all_rows)
    if args.json:
        cli.write_json(args.json, result)
    if args.states and processes.writes():
        parts = [finals[main_mode, s] for s in main_specs]
        ke.write_states(args.states, parts)
        print(f"wrote {args.states} ({sum(len(f['placements']) for _, f in parts)} final states "
              f"of the '{main_row['method']}' row)")
    planner = None
    if planner_policy:
        from diffplan.planner import Planner, PlannerConfig
        planner = Planner(denoiser, PlannerConfig(mode=main_mode, num_steps=args.num_steps))
    figures_and_videos(args, specs, episodes, finals, task, planner, seeds[0])
    return result
