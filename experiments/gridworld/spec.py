"""What the CompILE grid-world experiments fix (Tables 1, 4 and 6 of the paper): per setting, the
world, the model, its training recipe and the planning defaults (:class:`ExperimentSpec`), and
training the one denoiser that serves the three settings."""
from __future__ import annotations

import dataclasses
import os

from envs.gridworld.task import FOLLOW_MARK
from experiments.harness import recipes
from experiments.harness import core as harness
from experiments.harness.core import CHECKPOINT_ROOT, REPO_ROOT

TRAINING_NAME = "compile_gridworld"
"""One denoiser, trained on a mixture of the three settings (envs.gridworld.training.
TRAINING_MIXTURE), serves them all; `--train` of any setting trains it."""

FAR_TRAINING_NAME = "compile_gridworld_far"
"""The P-MO2G-far denoiser (the paper settings' denoiser never trained on P-MO2G-far)."""

MODE_REPLAN = {"on_the_fly": "always", "warm_start": "on_change"}
TRIGGER_WORDS = {"always": "before every move",
                 "on_change": "when new cells were seen or the sub-goal was reached",
                 "on_refuted": "when what was seen disproved the plan's guess or the sub-goal "
                               "was reached"}
"""Each re-planning mode's default trigger: paper-style on-the-fly before every move (the paper's
Algorithm 1); warm start when the observation changed or the sub-goal was reached."""

METHOD_NAMES = {"one_shot": "one-shot", "k_shot": "two-shot", "on_the_fly": "on-the-fly",
                "warm_start": "warm-start on-the-fly"}

LANGUAGE_CHOICES = {**harness.LANGUAGE_CHOICES, "natural": ("natural",)}
"""--language: one phrasing, or "all" (canonical, paraphrased, unseen; never the sealed natural
set, measured only when named, experiments.gridworld.text.languages_of)."""

CHECKPOINT_EVERY = 500


def method_name(mode_or_name: str, language: str = "canonical") -> str:
    """A row's method: the mode's name (or a baseline's), with the phrasing unless
    canonical ("on-the-fly, unseen")."""
    name = METHOD_NAMES.get(mode_or_name, mode_or_name)
    return name if language == "canonical" else f"{name}, {language}"


@dataclasses.dataclass(frozen=True)
class ExperimentSpec:
    """Everything a setting's experiment fixes: world, model, training and planning defaults."""

    setting: str
    grid_repr: str = "embed"
    goal_channel: bool = True
    prediction: str = "x0"
    detour_prob: float = 0.5
    goal_loss_weight: float = 3.0
    # The path target on the route's leg after the reference (Recipe.later_leg_value).
    later_leg_value: float = 1.0
    # Settings and examples per batch of the training mixture (None: TRAINING_MIXTURE), and the
    # name of the checkpoint it trains and evaluates (checkpoints/<name>, runs/<name>).
    mixture: tuple | None = None
    checkpoint_name: str = TRAINING_NAME
    # Training recipe: 8000 steps of 64, 100 diffusion timesteps (~35-40 min here). Shorter
    # recipes (docs/benchmarks.md, bench_train) stay below its SR_ordered 100.0 on 1000
    # validation episodes: 3000 steps 99.3 on-the-fly / 99.6 warm start, 4000: 99.6 / 99.8.
    train_steps: int = 8000
    # --text pretrained (None: train_steps): 5000 steps, about the token model's minutes (its
    # steps are slower), chosen on validation seed 1000 (docs/results.md, "Any English").
    pretrained_train_steps: int | None = 5000
    num_train_timesteps: int = 100
    batch_size: int = 64
    lr: float = 1e-3
    warmup_steps: int = 200
    num_steps: int = 10
    # Warm re-plans (the warm-start row; chosen on validation seed 1000 x 1000 P-MO2G episodes):
    # the last plan re-noised to step 1 of a 2-step schedule, denoised in one call, only when
    # new cells were seen or the sub-goal was reached: SR 100.0 at 11.5 calls/episode (paper-
    # style on-the-fly: 152.2; 3-step schedule 22.0). docs/results.md, "Cheaper re-planning".
    warm_start_step: int = 1
    warm_num_steps: int | None = 2
    eval_batch: int = 250
    fresh_noise: bool = True
    eta: float = 0.0
    # Re-planning trigger of every re-planning row; None: each mode's own (MODE_REPLAN).
    replan: str | None = None
    modes: tuple[str, ...] = ("one_shot", "k_shot", "on_the_fly", "warm_start")
    main_mode: str = "on_the_fly"
    # How the evaluation episodes' instructions are phrased (diffplan.language.LANGUAGES).
    language: str = "canonical"
    # psi (envs.gridworld.task.PSI_KINDS): "search" (Dijkstra toward the sub-goal, the plan's
    # path cheaper) or "follow" (the paper's: the neighbour the plan marks most strongly).
    psi: str = "search"
    # The path value above which the follow psi reads a cell as marked (GridTask.follow_mark).
    follow_mark: float = FOLLOW_MARK
    # Plans drawn per re-plan, the nearest guess kept (PlannerConfig.samples).
    samples: int = 1
    text: str = "tokens"  # the instruction input (training.TEXTS): token ids or "pretrained"

    @property
    def name(self) -> str:
        return f"compile_{self.setting}"

    def grid_config(self):
        """The setting's GridConfig, its episodes phrased in self.language."""
        from envs.gridworld.config import make_config
        return make_config(self.setting, language=self.language)

    def task(self, num_gen_channels: int | None = None, features: bool = False):
        """The setting's GridTask for a denoiser with num_gen_channels generated channels
        (default: the current recipe's), reading token ids or (features) the episodes'
        pretrained text features. The phrasing only changes the episodes' instruction, so
        every language shares one task (one compiled rollout)."""
        from envs.gridworld.config import make_config
        from envs.gridworld.task import NUM_GEN_CHANNELS, GridTask
        return GridTask(make_config(self.setting), use_goal_channel=self.goal_channel,
                        num_gen_channels=num_gen_channels or NUM_GEN_CHANNELS,
                        psi_kind=self.psi, follow_mark=self.follow_mark,
                        text="features" if features else "tokens")

    def model_config(self, size: str = "default"):
        from envs.gridworld import grammar
        from envs.gridworld.task import NUM_COND_CHANNELS, NUM_GEN_CHANNELS
        if self.text == "pretrained":
            from envs.gridworld.sentences import FEATURE_TOKENS, instruction_encoder
            words = dict(vocab_size=len(grammar.CELL_TOKENS), max_tokens=FEATURE_TOKENS,
                         context_dim=instruction_encoder().dim)
        else:
            words = dict(vocab_size=len(grammar.VOCAB), max_tokens=grammar.MAX_TOKENS)
        return recipes.denoiser_config(size, num_cond_channels=NUM_COND_CHANNELS,
                                       num_gen_channels=NUM_GEN_CHANNELS,
                                       grid_repr=self.grid_repr, **words)

    def recipe(self):
        from envs.gridworld.training import Recipe
        mixture = {} if self.mixture is None else {"mixture": self.mixture}
        return Recipe(detour_prob=self.detour_prob, goal_loss_weight=self.goal_loss_weight,
                      goal_channel=self.goal_channel, later_leg_value=self.later_leg_value,
                      text=self.text, **mixture)

    def train_config(self, seed: int = 0, steps: int | None = None,
                     checkpoint_every: int = CHECKPOINT_EVERY, objective: str = "diffusion"):
        from envs.gridworld.task import NUM_GEN_CHANNELS
        return recipes.train_config(
            seed=seed, steps=self.default_train_steps(self.text) if steps is None else steps,
            batch_size=self.batch_size, lr=self.lr, warmup_steps=self.warmup_steps,
            num_gen_channels=NUM_GEN_CHANNELS, prediction=self.prediction,
            checkpoint_every=checkpoint_every, max_log_every=100,
            num_train_timesteps=self.num_train_timesteps, objective=objective)

    def default_train_steps(self, text: str = "tokens") -> int:
        """--train's steps by default for the instruction input ``text``."""
        if text == "pretrained" and self.pretrained_train_steps is not None:
            return self.pretrained_train_steps
        return self.train_steps

    def replan_of(self, mode: str) -> str:
        """The re-planning trigger of a mode's row: self.replan if set, else the mode's own
        (paper-style on-the-fly re-plans before every move; warm start on change)."""
        return self.replan or MODE_REPLAN.get(mode, "always")

    def planner_config(self, mode: str, **overrides):
        from diffplan.planner import PlannerConfig
        return PlannerConfig(mode=mode, num_steps=self.num_steps,
                             warm_start_step=self.warm_start_step,
                             warm_num_steps=self.warm_num_steps,
                             fresh_noise=self.fresh_noise, eta=self.eta,
                             replan=self.replan_of(mode), samples=self.samples, **overrides)

    @property
    def training_name(self) -> str:
        """The denoiser's name: the main one, or an ablation's (other grid repr / no g)."""
        suffix = ("" if self.grid_repr == "embed" else f"_{self.grid_repr}") + \
            ("" if self.goal_channel else "_no_goal") + \
            ("" if self.text == "tokens" else f"_{self.text}")
        return self.checkpoint_name + suffix

    def default_checkpoint(self) -> str:
        return os.path.join(CHECKPOINT_ROOT, self.training_name)

    def default_train_dir(self) -> str:
        return os.path.join(REPO_ROOT, "runs", self.training_name)

    def mismatch(self, denoiser) -> str | None:
        """Why a denoiser cannot plan this grid world (None if it can)."""
        from envs.gridworld.task import NUM_COND_CHANNELS

        size = self.grid_config().size
        h, w, g = denoiser.plan_shape
        if (denoiser.num_cond_channels, h, w) != (NUM_COND_CHANNELS, size, size) or \
                g not in (2, 3):
            return (f"plans {h}x{w} maps with {denoiser.num_cond_channels} condition and {g} "
                    f"generated channels; the grid world needs {size}x{size} with "
                    f"{NUM_COND_CHANNELS} and 2 or 3")
        return None


SPECS = {
    "1o1g": ExperimentSpec("1o1g", modes=("one_shot", "on_the_fly", "warm_start")),
    "mo1g": ExperimentSpec("mo1g", modes=("one_shot", "on_the_fly", "warm_start")),
    "p_mo2g": ExperimentSpec("p_mo2g"),
    # Beyond the paper (envs.gridworld.config), with a denoiser of its own
    # (checkpoints/compile_gridworld_far): the paper settings' mixture with P-MO2G-far examples
    # in it, 10 diffusion timesteps, 10000 steps of 32 (28 min here), the path target 0.5 on the
    # leg after the reference; chosen on validation seed 1000 (docs/results.md).
    "p_mo2g_far": ExperimentSpec(
        "p_mo2g_far", checkpoint_name=FAR_TRAINING_NAME, later_leg_value=0.5,
        mixture=(("p_mo2g", 14), ("p_mo2g_far", 8), ("mo1g", 6), ("1o1g", 4)),
        num_train_timesteps=10, train_steps=10000, pretrained_train_steps=None, batch_size=32),
}


def train_setting(spec: ExperimentSpec, out_dir: str, *, seed: int = 0, steps: int | None = None,
                  progress: bool = True, model_size: str = "default",
                  checkpoint_every: int = CHECKPOINT_EVERY, callback=None,
                  objective: str = "diffusion"):
    """Trains the setting's denoiser into out_dir with the grid world's training recipe
    (envs.gridworld.training.Recipe), resuming if out_dir holds a checkpoint; objective "goal"
    trains the learned-goal baseline on the same batches (diffplan.baselines.goal).
    Returns (ema params, model config, seconds)."""
    model_config = spec.model_config(model_size)
    result, seconds = recipes.train_denoiser(
        model_config, spec.train_config(seed, steps, checkpoint_every, objective),
        spec.recipe(), out_dir,
        model_size=model_size, progress=progress, callback=callback)
    return result.ema_params, model_config, seconds


def load_checked(checkpoint: str, spec: ExperimentSpec, modes, parser,
                 train_command: str | None = None):
    """The checkpoint's LoadedDenoiser, checked against the grid world and the requested step
    counts; one-line errors for a missing, unreadable or mismatched checkpoint (naming
    train_command, default the setting's `--train`, as the way to get one)."""
    from diffplan.checkpoint import read_metadata, resolve_checkpoint
    from envs.gridworld import grammar
    from experiments.harness.core import fail, load_checked as load, vocabulary_mismatch

    denoiser = load(checkpoint, train_command or f"python -m experiments.{spec.name} --train"
                    + ("" if spec.text == "tokens" else f" --text {spec.text}"), spec.mismatch)
    meta = read_metadata(resolve_checkpoint(checkpoint))  # features: cells index cell tokens
    features = bool(getattr(denoiser.model_config, "context_dim", 0))
    cells = {"extra": {"vocabulary": meta["extra"].get("cell_tokens")}}
    problem = vocabulary_mismatch(cells if features else meta, denoiser.model_config.vocab_size,
                                  grammar.CELL_TOKENS if features else grammar.VOCAB)
    if problem:
        fail(f"the checkpoint {checkpoint} {problem}")
    for mode in modes:
        try:
            spec.planner_config(mode).check_schedule(denoiser.schedule.num_train_steps)
        except ValueError as e:
            parser.error(str(e))
    return denoiser
