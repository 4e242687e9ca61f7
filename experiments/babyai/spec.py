"""What a BabyAI level's experiment fixes (:class:`LevelSpec`): the model and its training on
the level's cached minigrid layouts, the planning modes, where its checkpoints live, and the
published imitation-learning numbers it is shown beside (:data:`PUBLISHED`).

Training budget (issue 54: each level's default training <= 60 min on this 2-core CPU),
measured with short runs of ``--train`` while other jobs held a load of 11-13 (docs/results.md,
BabyAI): GoToLocal (8 x 8), default model, batch 64: 1.25 steps/s (0.28 CPU-seconds a step);
GoTo (22 x 22, planned 24 x 24), batch 32: 0.55 steps/s (0.61 CPU-s a step; the 'small'
widths barely cheaper, 0.52). The defaults below fit 60 minutes at those rates.
"""
from __future__ import annotations

import dataclasses
import os

from envs.babyai.config import LEVELS
from experiments.harness import recipes
from experiments.harness.core import CHECKPOINT_ROOT, REPO_ROOT

MODES = ("on_the_fly", "warm_start")
METHOD_NAMES = {"on_the_fly": "ours, on-the-fly", "warm_start": "ours, warm start"}
MODE_REPLAN = {"on_the_fly": "always", "warm_start": "on_change"}
"""On-the-fly plans from noise before every action (Algorithm 1); warm start re-plans from the
last plan, re-noised to step 1 of a 2-step schedule (one denoiser call), when a cell looks
different or the agent stands beside the plan's goal (the grid world's cheap default)."""


@dataclasses.dataclass(frozen=True)
class LevelSpec:
    """One level's experiment: training (steps of batch_size, demos training layouts, the
    recipe's detours), the model and the planner's step counts (on-the-fly: num_steps per
    plan), the evaluation's slots (eval_batch) and BC's step limit."""

    level: str
    train_steps: int
    batch_size: int
    demos: int = 2000
    detour_prob: float = 0.5
    model_size: str = "default"
    lr: float = 1e-3
    warmup_steps: int = 200
    num_train_timesteps: int = 100
    prediction: str = "x0"
    num_steps: int = 10
    warm_num_steps: int = 2
    warm_start_step: int = 1
    eval_batch: int = 64
    bc_steps: int = 30000
    checkpoint_every: int = 250

    @property
    def name(self) -> str:
        return f"babyai_{self.level}"

    @property
    def env_id(self) -> str:
        return LEVELS[self.level].env_id

    def default_checkpoint(self) -> str:
        return os.path.join(CHECKPOINT_ROOT, self.name)

    def default_train_dir(self) -> str:
        return os.path.join(REPO_ROOT, "runs", self.name)

    def train_command(self) -> str:
        return f"python -m experiments.babyai --level {self.level} --train"

    def task(self):
        from envs.babyai.config import make_config
        from envs.babyai.task import BabyAITask

        return BabyAITask(make_config(self.level))

    def model_config(self, size: str | None = None):
        from envs.babyai.config import make_config
        from envs.babyai.task import NUM_COND_CHANNELS, NUM_GEN_CHANNELS

        return recipes.denoiser_config(size or self.model_size,
                                       vocab_size=self.task().vocab_size,
                                       max_tokens=make_config(self.level).max_tokens,
                                       num_cond_channels=NUM_COND_CHANNELS,
                                       num_gen_channels=NUM_GEN_CHANNELS)

    def recipe(self, demos: int | None = None, detour_prob: float | None = None,
               cache_dir: str | None = None):
        """The training recipe on layouts 0 .. demos - 1 (the training seed stream)."""
        from envs.babyai.training import Recipe

        return Recipe(level=self.level, num_layouts=demos or self.demos, start=0,
                      detour_prob=self.detour_prob if detour_prob is None else detour_prob,
                      cache_dir=cache_dir)

    def train_config(self, seed: int = 0, steps: int | None = None,
                     checkpoint_every: int | None = None):
        from envs.babyai.task import NUM_GEN_CHANNELS

        return recipes.train_config(
            seed=seed, steps=steps or self.train_steps, batch_size=self.batch_size, lr=self.lr,
            warmup_steps=self.warmup_steps, num_gen_channels=NUM_GEN_CHANNELS,
            prediction=self.prediction, checkpoint_every=checkpoint_every or
            self.checkpoint_every, max_log_every=50,
            num_train_timesteps=self.num_train_timesteps)

    def planner_config(self, mode: str):
        from diffplan.planner import PlannerConfig

        return PlannerConfig(mode=mode, num_steps=self.num_steps,
                             warm_num_steps=self.warm_num_steps,
                             warm_start_step=self.warm_start_step, replan=MODE_REPLAN[mode])

    def mismatch(self, denoiser) -> str | None:
        """Why a denoiser cannot plan this level (None if it can)."""
        from envs.babyai.task import NUM_COND_CHANNELS, NUM_GEN_CHANNELS

        task = self.task()
        h, w, g = denoiser.plan_shape
        if (denoiser.num_cond_channels, h, w, g) != (NUM_COND_CHANNELS, task.height,
                                                     task.width, NUM_GEN_CHANNELS):
            return (f"plans {h}x{w} maps with {denoiser.num_cond_channels} condition and {g} "
                    f"generated channels; {self.level} needs {task.height}x{task.width} with "
                    f"{NUM_COND_CHANNELS} and {NUM_GEN_CHANNELS}")
        vocab = getattr(denoiser.model_config, "vocab_size", None)
        if vocab is not None and vocab != task.vocab_size:
            return f"reads {vocab} token ids; {self.level}'s task uses {task.vocab_size}"
        return None


SPECS = {
    # 4000 steps of 64: 53 min at the measured 1.25 steps/s.
    "goto_local": LevelSpec("goto_local", train_steps=4000, batch_size=64),
    # 1900 steps of 32: 58 min at 0.55 steps/s. On-the-fly plans in 5 steps here: the
    # expert's GoTo route is 23 actions on average (our agent, which must find the object,
    # takes more), a default-size call on the 24 x 24 map costs ~3 CPU-ms, so 10 steps a plan
    # would cost ~0.7 CPU-s per episode, past the 10-minute budget of 1000 (not yet chosen on
    # validation: --num-steps; docs/results.md).
    "goto_obj_maze": LevelSpec("goto_obj_maze", train_steps=1900, batch_size=32, num_steps=5),
    "goto": LevelSpec("goto", train_steps=1900, batch_size=32, num_steps=5),
}


def train(spec: LevelSpec, out_dir: str, *, demos: int | None = None, seed: int = 0,
          steps: int | None = None, model_size: str | None = None,
          detour_prob: float | None = None, checkpoint_every: int | None = None,
          cache_dir: str | None = None, progress: bool = True):
    """Trains the level's denoiser into out_dir (resuming) on layouts 0 .. demos - 1; returns
    the seconds of this call."""
    size = model_size or spec.model_size
    _, seconds = recipes.train_denoiser(
        spec.model_config(size), spec.train_config(seed, steps, checkpoint_every),
        spec.recipe(demos, detour_prob, cache_dir), out_dir, model_size=size,
        progress=progress)
    return seconds


PUBLISHED: tuple[dict, ...] = ()
"""The BabyAI papers' imitation-learning numbers shown beside ours: dicts with "paper" (e.g.
"BabyAI 1.1 (Hui et al. 2020)"), "table" (the table's number and caption as printed), "level"
(a key of SPECS), "demos" (the demonstrations it was trained on, or needed to reach 99%),
"success" (percent) and "what" (a few words: "success with N demos" or "demos to reach 99%").
Only numbers read in the paper itself go here, each with its table: none has been transcribed
yet (the papers' tables could not be read from this machine; docs/results.md, BabyAI, says
which tables to copy)."""


def published(level: str) -> list[dict]:
    """The PUBLISHED entries of a level."""
    return [dict(p) for p in PUBLISHED if p["level"] == level]
