"""The two worlds of experiments.bench_train: each world's default training recipe (what its
experiments' ``--train`` runs), its validation episodes and the evaluation of a checkpoint.

Grid world: the recipe of ``experiments.compile_p_mo2g --train`` (``gridworld.spec``), evaluated
on P-MO2G validation episodes; metrics SR and SR_ordered. Kuka world: the recipe of
``experiments.kuka_stacking --train`` (``kuka.spec``), evaluated with the planner on every
Table 2 column (``envs.kuka.config.COLUMNS``) under MJX physics; metric SR (strict, contract 4),
which must reach the target in every column. Only --batch-size may differ from the recipe.
"""
from __future__ import annotations

import dataclasses
import os
import sys

from experiments.harness import core as harness, recipes


@dataclasses.dataclass(frozen=True)
class World:
    name: str
    metrics: tuple[str, ...]
    """What --target-metric may name (each must reach --target; Kuka's SR in every column)."""
    modes: tuple[str, ...]
    default_mode: str
    default_batch: int
    train_steps: int
    train_command: str
    checkpoint_every: int
    """The world's --train checkpoint interval (steps)."""

    def checkpoint_interval(self, eval_every: int) -> int:
        """Steps between checkpoints of a run evaluated every eval_every steps: the largest
        divisor of eval_every that is at most the world's own interval, so every evaluation
        step has its checkpoint and a stopped run loses at most that many steps."""
        import math

        return math.gcd(int(eval_every), self.checkpoint_every)

    def default_train_dir(self) -> str:
        suffix = "" if self.name == "gridworld" else f"_{self.name}"
        return os.path.join(harness.REPO_ROOT, "runs", f"bench_train{suffix}")


def _kuka_world() -> World:
    from experiments.kuka import spec as ks

    return World("kuka", ("SR",), ks.MODES, ks.MAIN_MODE, ks.TRAIN_BATCH, ks.TRAIN_STEPS,
                 "python -m experiments.kuka_stacking --train", ks.CHECKPOINT_EVERY)


def _grid_world() -> World:
    from experiments.gridworld.spec import CHECKPOINT_EVERY, SPECS

    spec = SPECS["p_mo2g"]
    return World("gridworld", ("SR", "SR_ordered"), ("on_the_fly", "warm_start"), "warm_start",
                 spec.batch_size, spec.train_steps,
                 "python -m experiments.compile_p_mo2g --train", CHECKPOINT_EVERY)


WORLDS = {"gridworld": _grid_world(), "kuka": _kuka_world()}


def _tuples(value):
    """JSON lists as (nested) tuples, as the frozen configs hold them."""
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def parse_settings(items, recipe) -> tuple[dict, dict, dict]:
    """--set FIELD=VALUE items -> ({TrainConfig field: value}, {DenoiserConfig field: value},
    {field of the world's training-data recipe: value}); VALUE is JSON (numbers, booleans,
    lists for tuple fields, quoted or bare strings). Raises ValueError naming an unknown field
    or a malformed item."""
    import dataclasses
    import json

    from diffplan.denoiser import DenoiserConfig
    from diffplan.train_state import TrainConfig

    train_fields = {f.name for f in dataclasses.fields(TrainConfig)}
    model_fields = {f.name for f in dataclasses.fields(DenoiserConfig)} - {
        "vocab_size", "max_tokens", "num_cond_channels", "num_gen_channels"}
    recipe_fields = {f.name for f in dataclasses.fields(recipe)}
    train, model, data = {}, {}, {}
    for item in items or ():
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise ValueError(f"--set takes FIELD=VALUE, got {item!r}")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        value = _tuples(value)
        if name in train_fields:
            train[name] = value
        elif name in model_fields:
            model[name] = value
        elif name in recipe_fields:
            data[name] = value
        else:
            raise ValueError(f"--set {name}: not a field of the training, the model or the "
                             f"data recipe (training: {', '.join(sorted(train_fields))}; "
                             f"model: {', '.join(sorted(model_fields))}; recipe: "
                             f"{', '.join(sorted(recipe_fields))})")
    return train, model, data


def training(world: World, model_size: str, checkpoint_every: int, settings=(), **overrides):
    """(model config, TrainConfig, recipe) of the world's default training (its whole run of
    train_steps steps, seed 0); overrides: TrainConfig fields (None: the recipe's), e.g.
    batch_size, or log_every (which does not change the computation); settings: --set items
    (:func:`parse_settings`), applied to the TrainConfig, the DenoiserConfig and the recipe
    (the warm-up stays at most a tenth of the steps, recipes.warmup; --set seed=N trains
    another seed)."""
    if world.name == "kuka":
        from envs.kuka.training import Recipe
        from experiments.kuka import spec as ks

        config = ks.train_config(0, ks.TRAIN_STEPS, checkpoint_every)
        model_config, recipe = ks.model_config(model_size), Recipe()
    else:
        from experiments.gridworld.spec import SPECS

        spec = SPECS["p_mo2g"]
        config = spec.train_config(0, None, checkpoint_every)
        recipe = spec.recipe()
        text = parse_settings(settings, recipe)[2].get("text", spec.text)
        spec = dataclasses.replace(spec, text=text)  # the model reads what the recipe gives
        model_config, recipe = spec.model_config(model_size), spec.recipe()
    train_set, model_set, recipe_set = parse_settings(settings, recipe)
    recipe = dataclasses.replace(recipe, **recipe_set)
    overrides = {**train_set, **{k: v for k, v in overrides.items() if v is not None}}
    if "steps" in overrides and "warmup_steps" not in overrides:
        overrides["warmup_steps"] = recipes.warmup(config.warmup_steps, overrides["steps"])
    return (dataclasses.replace(model_config, **model_set),
            dataclasses.replace(config, **overrides), recipe)


def run_training(world: World, train_dir: str, *, model_size: str, checkpoint_every: int,
                 progress: bool, callback=None, settings=(), **overrides):
    """The world's default training into train_dir (resumed; one line on a settings clash),
    the checkpoint's metadata recording the recipe and model size (recipes.train_denoiser,
    the call both worlds' --train make)."""
    from diffplan.train import ConfigMismatchError

    model_config, config, recipe = training(world, model_size, checkpoint_every, settings,
                                            **overrides)
    try:
        recipes.train_denoiser(model_config, config, recipe, train_dir, model_size=model_size,
                               progress=progress, callback=callback)
    except ConfigMismatchError as e:
        harness.fail(str(e))


# -------------------------------------------------------------------------- evaluation

def grid_evaluator(episodes: int, mode: str, batch: int, progress: bool):
    """evaluate(denoiser) -> {"SR", "SR_ordered", "path_f1"} on validation P-MO2G episodes."""
    from experiments.gridworld import eval as ge
    from experiments.gridworld.spec import SPECS

    spec = SPECS["p_mo2g"]
    eps = ge.eval_episodes(spec.grid_config(), episodes, harness.VALIDATION_SEED)

    def evaluate(denoiser) -> dict:
        rollout, seconds = ge.evaluate_mode(spec, spec.task(denoiser.num_gen_channels),
                                            denoiser, eps, harness.VALIDATION_SEED, mode,
                                            batch, progress=progress)
        row = ge.metrics_row(mode, rollout, eps, seconds, True)
        return {k: row[k] for k in ("SR", "SR_ordered", "path_f1")}

    return evaluate


def kuka_evaluator(episodes: int, mode: str, batch: int, progress: bool):
    """evaluate(denoiser) -> {"SR": pooled strict SR, "SR_min": the lowest column's,
    "SR_columns": {column: strict SR}} on validation episodes of each Table 2 column."""
    import numpy as np

    from experiments.harness.progress import bar as progress_bar

    from diffplan.planner import Planner, PlannerConfig
    from envs.kuka.config import COLUMNS
    from envs.kuka.task import KukaTask
    from experiments.kuka import eval as ke, spec as ks

    seed, task = harness.VALIDATION_SEED, KukaTask()
    run = harness.rollout_fn(task)  # one jitted program for every column and evaluation
    eps = {name: ke.generate_episodes(spec, episodes, seed, batch)
           for name, spec in COLUMNS.items()}

    def evaluate(denoiser) -> dict:
        planner = Planner(denoiser, PlannerConfig(mode=mode, num_steps=ks.NUM_STEPS))
        columns, held, total = {}, 0, 0
        with progress_bar(total=episodes * len(eps), desc=f"kuka {mode} (seed {seed})",
                          unit="ep", disable=not progress, file=sys.stderr, leave=False,
                          dynamic_ncols=True) as bar:
            for name, column in eps.items():
                final = ke.run_planner(task, planner, column, seed, batch, bar, run=run)
                strict, _ = ke.constraint_success(column, final)
                valid = np.asarray(column.constraints)[..., 0] >= 0
                columns[name] = 100.0 * float(strict[valid].sum()) / int(valid.sum())
                held, total = held + int(strict[valid].sum()), total + int(valid.sum())
        return {"SR": 100.0 * held / total, "SR_min": min(columns.values()),
                "SR_columns": columns}

    return evaluate


def evaluator(world: World, episodes: int, mode: str, batch: int, progress: bool):
    make = kuka_evaluator if world.name == "kuka" else grid_evaluator
    return make(episodes, mode, batch, progress)


def reached(world: World, row: dict, metrics, target: float) -> bool:
    """Every metric >= target (Kuka's in every column)."""
    if world.name == "kuka":
        return all(v >= target for v in row["SR_columns"].values())
    return all(row[m] >= target for m in metrics)
