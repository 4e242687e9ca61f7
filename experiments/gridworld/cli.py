"""The CompILE grid-world experiments (the paper's Tables 1, 4 and 6): ``experiments.compile_1o1g``,
``compile_mo1g``, ``compile_p_mo2g`` (and ``compile_p_mo2g_far``, beyond the paper) call
:func:`main`: load (or train) the denoiser, evaluate it on fresh seeded episodes in every
planning mode, print a table, write JSON (contract 2 of docs/DESIGN.md), and optionally the
executed trajectories, a profile and figures.

Seeds: see experiments.harness.core. Training draws its examples from ``fold_in(step_key,
TRAIN_STREAM)`` keys of its own seed (``envs.gridworld.training``), so training never sees the
evaluation episodes; tests/test_training_disjoint.py recomputes every episode of the shipped
runs and compares their worlds with the validation and evaluation seeds' (1O1G, whose worlds
repeat, has its overlapping episodes counted and left out of the rows).
"""
from __future__ import annotations

import dataclasses
import os
from typing import Sequence

from experiments.gridworld import eval as ge, text
from experiments.harness import cli, core as harness, processes, tables
from experiments.gridworld.flags import build_parser, check_args
from experiments.gridworld.spec import (METHOD_NAMES, MODE_REPLAN, SPECS, TRIGGER_WORDS,
                                        load_checked, method_name, train_setting)


def _denoiser(spec, args, modes, parser, progress):
    """(checkpoint, train seconds or None, LoadedDenoiser): --train's result or a checkpoint."""
    if not args.train:
        checkpoint = args.checkpoint or spec.default_checkpoint()
        return checkpoint, None, load_checked(checkpoint, spec, modes, parser)
    from diffplan.train import ConfigMismatchError

    spec = dataclasses.replace(spec, prediction=args.prediction)
    checkpoint = args.train_dir or spec.default_train_dir()
    try:
        _, _, seconds = train_setting(spec, checkpoint, seed=args.train_seed,
                                      steps=args.train_steps, progress=progress,
                                      model_size=args.model_size,
                                      checkpoint_every=args.checkpoint_every,
                                      objective=args.objective)
    except ConfigMismatchError as e:
        harness.fail(str(e))
    return checkpoint, seconds, load_checked(checkpoint, spec, modes, parser)


def _result(spec, args, seeds, modes, main_mode, checkpoint, train_seconds, rows) -> dict:
    return {
        "experiment": spec.name,
        "episodes": args.episodes,
        "seed": seeds[0],
        "seeds": list(seeds),
        "validation": bool(harness.VALIDATION_SEED in seeds),
        "setting": spec.setting,
        "language": args.language,
        "checkpoint": os.path.relpath(checkpoint, harness.REPO_ROOT) if checkpoint else None,
        "num_steps": spec.num_steps,
        "warm_start_step": spec.warm_start_step,
        "warm_num_steps": spec.warm_num_steps or spec.num_steps,
        "noise": "fresh" if spec.fresh_noise else "episode",
        "eta": spec.eta,
        "psi": spec.psi,
        "follow_mark": spec.follow_mark,
        "samples": spec.samples,
        "replan": {mode: spec.replan_of(mode) for mode in modes if mode in MODE_REPLAN},
        "trajectories_method": METHOD_NAMES[main_mode],
        "train_seconds": train_seconds,
        "machine": harness.machine(),
        "rows": rows,
    }


def _print_summary(spec, args, seeds, result) -> None:
    triggers = "; ".join(f"{METHOD_NAMES[m]} re-plans {TRIGGER_WORDS[r]}"
                         for m, r in result["replan"].items())
    print(f"\n{spec.name}: {args.episodes} episodes per seed, seed(s) "
          f"{','.join(map(str, seeds))}, {spec.num_steps} denoising steps per plan (warm start: "
          f"{result['warm_num_steps']}-step schedule from step {spec.warm_start_step}), "
          f"checkpoint {result['checkpoint']}, psi {spec.psi}"
          + (f" (marked: path > {spec.follow_mark:g})" if spec.psi == "follow" else "")
          + (f", best of {spec.samples} plans" if spec.samples > 1 else "")
          + (f"\n{triggers}" if triggers else ""))
    excluded = sum(result["excluded_training_episodes"].values())
    if excluded:
        print(f"{excluded} of {args.episodes * len(seeds)} episodes equal a training episode of "
              "this checkpoint and are left out of every row")
    print(ge.format_table(result["rows"]))
    for row in result["rows"]:
        if "named_first_percent" in row:
            true = "reference" if spec.grid_config().has_reference else "target"
            print(f"{row['method']}: stood on the named distractor before the true {true} "
                  f"in {row['named_first_percent']:.1f}% of {row['control_episodes']} episodes")
    if phrasings := tables.format_phrasings(result["rows"]):
        print(phrasings)
    if len(seeds) > 1:
        print(ge.format_intervals(result["rows"], seeds))


def _mode_row(spec, task, denoiser, mode, name, all_episodes, args, progress, keep=None):
    """(row, pooled rollout) of one planning mode over the seeds' episodes ({seed: episodes});
    keep ({seed: bool (N,)}, default all) selects the episodes the row counts (all are run)."""
    outs = {seed: ge.evaluate_mode(spec, task, denoiser, eps, seed, mode, args.batch_size,
                                   progress)
            for seed, eps in all_episodes.items()}
    if keep is not None:
        outs = {seed: (ge.select(r, keep[seed]), t) for seed, (r, t) in outs.items()}
        all_episodes = {seed: ge.select(eps, keep[seed]) for seed, eps in all_episodes.items()}
    row, rollout = ge.pooled_row(method_name(name, spec.language), outs, all_episodes,
                                 spec.grid_config().has_reference)
    row["language"] = spec.language
    return row, rollout


def _posterior_rows(spec, task, modes, episodes_by_seed, args, progress) -> list[dict]:
    """--posterior-denoiser: each mode planned with envs.gridworld.posterior's denoiser (no
    learning, exact guesses; it reads the instruction's token ids) on every episode, rows
    named "<mode>, exact posterior"."""
    from envs.gridworld.posterior import posterior_denoiser

    denoiser = posterior_denoiser(spec.grid_config())
    task = spec.task(task.num_gen_channels)
    return [_mode_row(spec, task, denoiser, mode, f"{METHOD_NAMES[mode]}, exact posterior",
                      episodes_by_seed, args, progress)[0] for mode in modes]


def _policy_rows(setting, seeds, args, progress, episodes_by_seed, language,
                 keep=None) -> list[dict]:
    """The rows of --baselines and, unless --no-reference-agents, of the reference agents on
    the episodes of one phrasing, their methods naming it, counting the episodes keep marks
    (the planner's rows count the same ones)."""
    from experiments.gridworld.baselines import baseline_rows, reference_rows

    extra = []
    if args.baselines:
        try:
            extra += baseline_rows(setting, seeds, args.episodes, args.batch_size, progress,
                                   methods=args.baselines, episodes_by_seed=episodes_by_seed,
                                   keep=keep)
        except (FileNotFoundError, ValueError) as e:
            harness.fail(f"cannot evaluate the baselines: {e}")
    if not args.no_reference_agents:
        extra += reference_rows(setting, seeds, args.episodes, args.batch_size, progress,
                                episodes_by_seed=episodes_by_seed, keep=keep)
    for row in extra:
        row["method"] = method_name(row["method"], language)
        row["language"] = language
    return extra


def main(setting: str, argv: Sequence[str] | None = None) -> dict:
    spec = SPECS[setting]
    parser = build_parser(spec)
    args = parser.parse_args(argv)
    processes.start(parser, args)
    modes = check_args(parser, args, spec)
    seeds = harness.parse_seeds(parser, args)
    spec = dataclasses.replace(spec, num_steps=args.num_steps,
                               warm_start_step=args.warm_start_step,
                               warm_num_steps=args.warm_num_steps,
                               fresh_noise=args.noise == "fresh", eta=args.eta,
                               replan=args.replan, psi=args.psi, samples=args.samples,
                               follow_mark=args.follow_mark, text=args.text)
    from diffplan.jax_cache import enable_compilation_cache

    enable_compilation_cache()
    progress = not args.no_progress
    checkpoint, train_seconds, denoiser = _denoiser(spec, args, modes, parser, progress)
    encoder = text.checkpoint_encoder(checkpoint, denoiser)  # None: it reads token ids
    languages = text.languages_of(args.language, encoder is not None)
    text.check_languages(languages, encoder, checkpoint)
    task = spec.task(denoiser.num_gen_channels, features=encoder is not None)
    rows, rollouts, episodes_of = [], {}, {}
    keep = None
    for language in languages:
        lspec = dataclasses.replace(spec, language=language)
        all_episodes = {seed: text.with_features(ge.eval_episodes(
            lspec.grid_config(), args.episodes, seed), setting, encoder) for seed in seeds}
        if keep is None:
            # Episodes whose world the model trained on are run (so every other episode keeps
            # its key) but left out of every row and the trajectories: the planner's, the
            # baselines' and the reference agents' rows count the same episodes. The phrasing
            # changes the tokens only: every language has the same worlds, the same keep.
            keep = {seed: ~ge.training_overlap(checkpoint, setting, eps)
                    for seed, eps in all_episodes.items()}
        per_seed = {seed: ge.select(eps, keep[seed]) for seed, eps in all_episodes.items()}
        episodes_of[language] = per_seed
        for mode in modes:
            row, rollouts[language, mode] = _mode_row(lspec, task, denoiser, mode, mode,
                                                      all_episodes, args, progress, keep)
            rows.append(row)
        if args.posterior_denoiser:
            rows += _posterior_rows(lspec, task, modes, all_episodes, args, progress)
        if args.control:
            from experiments.gridworld.controls import control_rows

            rows += control_rows(args.control, lspec, modes, all_episodes, lambda s, m, n, e, k:
                                 _mode_row(s, task, denoiser, m, n, e, args, progress, k),
                                 lambda e, **slots: text.with_features(e, setting, encoder,
                                                                        **slots))
        rows += _policy_rows(setting, seeds, args, progress, all_episodes, language, keep)

    language = languages[0]
    per_seed = episodes_of[language]
    rollouts = {mode: r for (lang, mode), r in rollouts.items() if lang == language}
    spec = dataclasses.replace(spec, language=language)
    grid_config = spec.grid_config()
    main_mode = spec.main_mode if spec.main_mode in modes else modes[0]
    result = _result(spec, args, seeds, modes, main_mode, checkpoint, train_seconds, rows)
    result["excluded_training_episodes"] = {str(s): int((~k).sum()) for s, k in keep.items()}
    _print_summary(spec, args, seeds, result)
    if args.json:
        cli.write_json(args.json, result)
    if args.trajectories and processes.writes():
        ge.write_trajectories(args.trajectories, rollouts[main_mode],
                              harness.concat_trees(list(per_seed.values())), grid_config)
        print(f"wrote {args.trajectories} ({METHOD_NAMES[main_mode]} trajectories)")
    if args.profile:
        ge.write_profile(args.profile, spec, task, denoiser, per_seed[seeds[0]], seeds[0],
                         main_mode, args.batch_size)
        print(f"wrote a profiler trace of one {METHOD_NAMES[main_mode]} batch to {args.profile}")
    if args.figures and processes.writes():
        from experiments.gridworld.figures import write_figures
        paths = write_figures(args.figures, spec, task, denoiser, per_seed[seeds[0]], seeds[0],
                              min(args.num_figures, args.episodes),
                              text.texts(per_seed[seeds[0]], setting))
        print(f"wrote {len(paths)} figures to {args.figures}")
    return result
