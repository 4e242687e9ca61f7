"""Sweep configurations: the keys of each world, their defaults (the experiment CLIs'), and the
checks that turn a raw configuration into a complete one or refuse it in one line.

A configuration names its task by its registry name (``envs.names()``): "task":
"gridworld/p_mo2g", "kuka/stacking", ... A grid-world configuration may name its setting
instead ("setting": "p_mo2g", as the shipped sweep files do); without either the task is
gridworld/p_mo2g. The keys every task takes: task, checkpoint, modes (one planning mode),
num_steps, seed, episodes, batch_size. The grid world's: setting, eta, warm_start_step,
warm_num_steps, noise ("fresh" | "episode"), replan ("always" | "on_change" | "on_refuted";
missing: the mode's own, as in the experiment CLIs), language, psi ("search" | "follow", the
CLIs' --psi), follow_mark (the follow psi's threshold, the CLIs' --follow-mark), samples (plans
drawn per re-plan, the nearest guess kept: the CLIs' --samples),
denoiser ("learned": the checkpoint's; "posterior": envs.gridworld.posterior's, which learns
nothing and guesses the hidden target exactly, the CLIs' --posterior-denoiser rows).
The Kuka world's: multi (several instructed relations: the multi-constraint column),
language, carry ("path" | "arc"), reader (a reader directory, e.g. "checkpoints/kuka_reader":
every instruction restated canonically before the planner reads it, the CLIs' --reader;
missing: none). language is the
instructions' phrasing in both worlds: "canonical" | "paraphrased" | "unseen" (the grid
world's held-out phrasings training never saw) | the Kuka world's "development" (phrasings
training never saw, chosen on).
"""
from __future__ import annotations

import dataclasses
import itertools

from diffplan.language import LANGUAGES as GRID_LANGUAGES
from envs.gridworld.task import PSI_KINDS, check_follow_mark
from experiments.gridworld import spec as gs
from experiments.kuka import spec as ks
from experiments.harness.core import DEFAULT_EVAL_SEED

_SPEC = gs.SPECS["p_mo2g"]
GRID_DEFAULTS = {"setting": "p_mo2g", "checkpoint": None, "modes": "on_the_fly",
                 "num_steps": _SPEC.num_steps, "eta": _SPEC.eta,
                 "warm_start_step": _SPEC.warm_start_step,
                 "warm_num_steps": _SPEC.warm_num_steps or _SPEC.num_steps,
                 "noise": "fresh" if _SPEC.fresh_noise else "episode", "replan": None,
                 "language": "canonical", "psi": _SPEC.psi, "samples": _SPEC.samples,
                 "follow_mark": _SPEC.follow_mark,
                 "denoiser": "learned",
                 "seed": DEFAULT_EVAL_SEED,
                 "episodes": 1000, "batch_size": _SPEC.eval_batch}
"""The grid-world CLIs' defaults (replan None: the mode's own trigger, MODE_REPLAN)."""
KUKA_DEFAULTS = {"checkpoint": None, "modes": ks.MAIN_MODE, "num_steps": ks.NUM_STEPS,
                 "multi": False, "language": "canonical", "carry": "path", "reader": None,
                 "seed": DEFAULT_EVAL_SEED, "episodes": ks.DEFAULT_EPISODES,
                 "batch_size": ks.DEFAULT_BATCH}
"""The Kuka CLIs' defaults (one column per configuration: multi False is the single one)."""
DEFAULTS = {"gridworld": GRID_DEFAULTS, "kuka": KUKA_DEFAULTS}
DEFAULT_TASK = "gridworld/p_mo2g"
KEYS = ("task",) + tuple(dict.fromkeys(itertools.chain(GRID_DEFAULTS, KUKA_DEFAULTS)))
"""Every configuration key (the command line's per-key flags)."""
TYPES = {"task": str, "setting": str, "checkpoint": str, "modes": str, "num_steps": int,
         "eta": float, "warm_start_step": int, "warm_num_steps": int, "noise": str,
         "replan": str, "seed": int, "episodes": int, "batch_size": int, "multi": bool,
         "language": str, "carry": str, "psi": str, "samples": int, "denoiser": str,
         "follow_mark": float,
         "reader": str}
CHOICES = {"setting": tuple(gs.SPECS), "noise": ("fresh", "episode"),
           "replan": tuple(gs.TRIGGER_WORDS), "carry": ks.CARRIES,
           "psi": PSI_KINDS, "denoiser": ("learned", "posterior")}
LANGUAGES = {"gridworld": GRID_LANGUAGES, "kuka": ks.LANGUAGES}
"""The language key's values in each world (the CLIs' single phrasings)."""
MINIMUMS = {"episodes": 1, "batch_size": 1, "seed": 0, "num_steps": 1, "warm_num_steps": 1,
            "warm_start_step": 0, "samples": 1}


class SweepError(ValueError):
    """A configuration that cannot run (the message says which and why)."""


def tasks() -> tuple[str, ...]:
    """The registered tasks a sweep can run (those of the grid world and the Kuka world)."""
    import envs

    return tuple(n for n in envs.names() if n.split("/")[0] in DEFAULTS)


def world(config: dict) -> str:
    return config["task"].split("/")[0]


def _task_of(raw: dict, index: int) -> str:
    """The task a raw configuration names ("task", or a grid-world "setting")."""
    setting, task = raw.get("setting"), raw.get("task")
    if setting is not None and setting not in gs.SPECS:
        raise SweepError(f"configuration {index}: setting must be one of {tuple(gs.SPECS)}, "
                         f"got {setting!r}")
    if task is None:
        return DEFAULT_TASK if setting is None else f"gridworld/{setting}"
    if task not in tasks():
        raise SweepError(f"configuration {index}: task must be one of {tasks()}, got {task!r}")
    if setting is not None and task != f"gridworld/{setting}":
        raise SweepError(f"configuration {index}: setting {setting!r} contradicts task "
                         f"{task!r}")
    return task


def _checked(config: dict, index: int, key: str):
    value, kind = config[key], TYPES[key]
    if value is None and key in ("checkpoint", "replan", "reader"):
        return None
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, kind) or (isinstance(value, bool) and kind is not bool):
        raise SweepError(f"configuration {index}: {key} must be {kind.__name__}, got "
                         f"{value!r}")
    choices = LANGUAGES[world(config)] if key == "language" else CHOICES.get(key)
    if choices is not None and value not in choices:
        raise SweepError(f"configuration {index}: {key} must be one of {choices}, got "
                         f"{value!r}")
    if key in MINIMUMS and value < MINIMUMS[key]:
        raise SweepError(f"configuration {index}: {key} must be >= {MINIMUMS[key]}, got "
                         f"{value}")
    return value


def normalise(raw: dict, index: int) -> dict:
    """A configuration with its task's defaults filled in and every value checked."""
    if not isinstance(raw, dict):
        raise SweepError(f"configuration {index} must be a JSON object, got {raw!r}")
    unknown = sorted(set(raw) - set(KEYS))
    if unknown:
        raise SweepError(f"configuration {index}: unknown keys {unknown}; allowed: "
                         f"{sorted(KEYS)}")
    task = _task_of(raw, index)
    defaults = DEFAULTS[task.split("/")[0]]
    foreign = sorted(set(raw) - set(defaults) - {"task"})
    if foreign:
        raise SweepError(f"configuration {index}: {foreign} do not apply to {task}; its keys: "
                         f"{sorted(defaults)}")
    config = {"task": task, **defaults, **{k: v for k, v in raw.items() if k != "task"}}
    if "setting" in defaults:
        config["setting"] = task.split("/")[1]
    for key in defaults:
        config[key] = _checked(config, index, key)
    from diffplan.planner import MODES

    modes = MODES if "setting" in defaults else ks.MODES
    if config["modes"] not in modes:
        raise SweepError(f"configuration {index}: modes must be one planning mode of {modes}, "
                         f"got {config['modes']!r}")
    if "setting" not in defaults:
        return config
    if config["replan"] is None:
        config["replan"] = gs.SPECS[config["setting"]].replan_of(config["modes"])
    if not 0 <= config["eta"] <= 10:
        raise SweepError(f"configuration {index}: eta must be in [0, 10], got {config['eta']}")
    try:
        check_follow_mark(config["follow_mark"])
    except ValueError as e:
        raise SweepError(f"configuration {index}: {e}") from e
    if config["psi"] != "follow" and config["follow_mark"] != GRID_DEFAULTS["follow_mark"]:
        raise SweepError(f"configuration {index}: follow_mark is the follow psi's threshold: "
                         f"it needs psi 'follow'")
    if config["denoiser"] == "posterior" and (config["psi"] != "search" or config["checkpoint"]):
        raise SweepError(f"configuration {index}: the posterior denoiser plans no path and "
                         f"loads no checkpoint: it takes psi 'search' and no checkpoint")
    try:
        planner_config(config)
    except ValueError as e:
        raise SweepError(f"configuration {index}: {e}") from e
    return config


def spec_of(config: dict) -> gs.ExperimentSpec:
    """A grid-world configuration's ExperimentSpec."""
    return dataclasses.replace(
        gs.SPECS[config["setting"]], num_steps=config["num_steps"],
        warm_start_step=config["warm_start_step"], warm_num_steps=config["warm_num_steps"],
        fresh_noise=config["noise"] == "fresh", eta=config["eta"], replan=config["replan"],
        language=config["language"], psi=config["psi"], samples=config["samples"],
        follow_mark=config["follow_mark"])


def planner_config(config: dict):
    """The PlannerConfig of a configuration."""
    if world(config) == "kuka":
        from diffplan.planner import PlannerConfig
        return PlannerConfig(mode=config["modes"], num_steps=config["num_steps"])
    return spec_of(config).planner_config(config["modes"])


def default_checkpoint(config: dict) -> str:
    if world(config) == "kuka":
        return ks.DEFAULT_CHECKPOINT
    return spec_of(config).default_checkpoint()


def _parse(key: str, text: str):
    kind = TYPES[key]
    if kind is bool:
        if text.lower() not in ("true", "false", "1", "0"):
            raise ValueError(text)
        return text.lower() in ("true", "1")
    return kind(text)


def expand(values: dict) -> list[dict]:
    """Every combination of comma-separated command-line values."""
    keys = [k for k in KEYS if values.get(k) is not None]
    lists = [[v.strip() for v in str(values[k]).split(",")] for k in keys]
    out = []
    for combo in itertools.product(*lists):
        config = {}
        for key, value in zip(keys, combo):
            try:
                config[key] = _parse(key, value)
            except ValueError as e:
                raise SweepError(f"--{key.replace('_', '-')}: {value!r} is not a "
                                 f"{TYPES[key].__name__}") from e
        out.append(config)
    return out
