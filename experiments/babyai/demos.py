"""Sample efficiency the way BabyAI measures it (``python -m experiments.babyai --level L
--demos-sweep 100,300,1000,3000``): the fewest training episodes (expert demonstrations,
training layouts 0..N-1) with which ours reaches >= 99% success on 1000 held-out episodes,
measured in minigrid.

For each N, ascending: train ours on layouts 0..N-1 into ``<sweep-dir>/demos_N`` (the level's
recipe and steps; resuming), evaluate it on the validation seed (``--episodes`` episodes,
the first of ``--modes``) and write ``demos_N/validation.json`` atomically; a setting whose
file exists is not run again, so a killed sweep resumes where it stopped. The fewest N whose
validation SR is >= 99% is then evaluated on ``--seeds`` (evaluation seeds; the number
reported; ``demos_N/evaluation.json``). The table and figure show success against demos (log
axis) beside the published numbers (``spec.PUBLISHED``).
"""
from __future__ import annotations

import json
import os

from experiments.babyai import eval as be, tables as bt
from experiments.babyai.spec import METHOD_NAMES, published, train
from experiments.harness import cli, core as harness

TARGET = 99.0


def _read(path: str):
    if not os.path.exists(path):
        return None
    with open(path) as f:
        return json.load(f)


def _evaluate(spec, denoiser, mode: str, seeds, episodes: int, batch: int, progress: bool):
    """Ours (one mode) on episodes 0..episodes-1 of each seed, pooled (no BC, no bot)."""
    import numpy as np
    from envs.babyai.config import make_config

    config, task = make_config(spec.level), spec.task()
    per_seed = {}
    for seed in seeds:
        eps = be.episodes(config, seed, episodes, progress)
        per_seed[seed] = be.run_planner(spec, task, denoiser, mode, eps, seed,
                                        np.arange(episodes), batch, progress)
    return be.pooled_row(METHOD_NAMES[mode], per_seed)


def _run(spec, args, n: int, mode: str, seeds, name: str, progress: bool) -> dict:
    """The row of demos_N on seeds, read from demos_N/<name>.json if it holds the same
    seeds, episodes, mode and detours, else trained (resuming) and evaluated, and written."""
    from diffplan.train import ConfigMismatchError
    from experiments.babyai.baselines import denoiser_minutes

    run_dir = os.path.join(args.sweep_dir, f"demos_{n}")
    path = os.path.join(run_dir, f"{name}.json")
    key = {"seeds": list(seeds), "episodes": args.episodes, "mode": mode, "demos": n,
           "detour_prob": spec.detour_prob if args.detour_prob is None else args.detour_prob}
    done = _read(path)
    if done is not None and all(done.get(k) == v for k, v in key.items()):
        return done
    try:
        train(spec, run_dir, demos=n, seed=args.train_seed or 0, steps=args.train_steps,
              model_size=args.model_size, detour_prob=args.detour_prob,
              checkpoint_every=args.checkpoint_every, progress=progress)
    except ConfigMismatchError as e:
        harness.fail(str(e))
    denoiser = harness.load_checked(run_dir, spec.train_command(), spec.mismatch)
    row = _evaluate(spec, denoiser, mode, seeds, args.episodes, args.batch_size, progress)
    row.update(key, SR_low=row["SR_ci95"][0], train_minutes=denoiser_minutes(run_dir))
    cli.write_json(path, row, announce=False)
    return row


def fewest_reaching(rows, target: float = TARGET):
    """The row with the fewest demos whose SR is >= target, or None."""
    reached = [r for r in rows if r["SR"] >= target]
    return min(reached, key=lambda r: r["demos"]) if reached else None


def run_sweep(spec, args, seeds, mode: str, progress: bool) -> dict:
    validation = (harness.VALIDATION_SEED,)
    rows = [_run(spec, args, n, mode, validation, "validation", progress)
            for n in args.demos_sweep]
    best = fewest_reaching(rows)
    evaluation = (None if best is None else
                  _run(spec, args, best["demos"], mode, seeds, "evaluation", progress))
    papers = published(spec.level)
    needed = [p for p in papers if p.get("what") == "demos to reach 99%"]
    result = {"experiment": f"{spec.name}_demos", "level": spec.level, "mode": mode,
              "episodes": args.episodes, "seed": validation[0], "seeds": list(seeds),
              "target_SR": TARGET, "detour_prob": rows[0]["detour_prob"], "rows": rows,
              "fewest_demos": None if best is None else best["demos"],
              "evaluation": evaluation, "published": papers,
              "ratio_to_published": ([best["demos"] / p["demos"] for p in needed]
                                     if best is not None and needed else None),
              "machine": harness.machine()}
    print(f"\n{spec.name}: {METHOD_NAMES[mode]} trained on N demonstrations (layouts 0..N-1), "
          f"validation seed {validation[0]}, {args.episodes} episodes, measured in minigrid")
    print(bt.format_sweep(rows))
    if best is None:
        print(f"no setting reached {TARGET:g}% on validation; the largest measured: "
              f"{rows[-1]['demos']} demos, SR {rows[-1]['SR']:.2f}")
    else:
        lo, hi = evaluation["SR_ci95"]
        print(f"fewest demos reaching {TARGET:g}% on validation: {best['demos']}; on seed(s) "
              f"{','.join(map(str, seeds))}: SR {evaluation['SR']:.2f} [{lo:.2f}, {hi:.2f}] "
              f"({evaluation['episodes']} episodes, {evaluation.get('mismatches')} mismatches)")
    print(bt.format_published(papers))
    from experiments.babyai.figures import sweep_figure

    figure = args.figure or os.path.join(args.sweep_dir, "success_vs_demos.png")
    sweep_figure(figure, spec.level, rows, evaluation, papers, TARGET)
    print(f"wrote {figure}")
    if args.json:
        cli.write_json(args.json, result)
    return result
