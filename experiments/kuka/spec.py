"""What the Kuka block experiments fix (the paper's Tables 2 and 5): defaults, planning modes, the
paper's numbers, the denoiser's model and training configuration, and the checkpoint check."""
from __future__ import annotations

import os
import warnings

from diffplan import instruction
from experiments.harness import recipes
from envs.kuka.grammar import LANGUAGES
from experiments.harness.core import CHECKPOINT_ROOT, REPO_ROOT
from experiments.kuka.baselines import KUKA_BASELINES

DEFAULT_EPISODES = 200
DEFAULT_BATCH = 64
POLICIES = ("planner", "expert") + KUKA_BASELINES
"""Who acts in the main rows: the diffusion planner, the scripted expert, or a shipped Kuka
baseline (experiments.kuka.baselines)."""
MODES = ("on_the_fly", "one_shot")
"""Planning modes of the Kuka experiments: a plan before every placement (the paper's
on-the-fly planning, the main rows), or one plan at t = 0 followed to the end."""
MAIN_MODE = "on_the_fly"
METHOD_NAMES = {"on_the_fly": "on-the-fly", "one_shot": "one-shot"}

# Instruction phrasings (envs.kuka.grammar.LANGUAGES): Table 2's, the training paraphrases
# (Table 5's "complex" instructions), the development phrasings (never trained on, chosen on),
# the sealed held-out phrasings (never trained on, never chosen on).
LANGUAGE_CHOICES = {**{language: (language,) for language in LANGUAGES}, "all": LANGUAGES,
                    "both": ("canonical", "paraphrased"), "natural": ("natural",)}
"""--language of the Kuka CLIs: one phrasing, canonical and paraphrased ("both", the README's
Table 5 command), every one that may be looked at ("all": never the sealed natural-language
set, which is measured once, by name, and only with a denoiser on pretrained features), or the
natural set ("natural")."""
CARRIES = ("path", "arc")
"""How a block is carried: along the in-painted path, or the expert's arc around the base."""
NUM_STEPS = 10
"""Denoising steps per plan."""
PAPER = {
    # (single, multi) for each kind: Table 2 of the paper (Diffuser has no multi-constraint
    # number) and Table 5's "Complex LI" row (paraphrased instructions).
    "stacking": {"ours (paper)": (99.50, 98.38), "DD (paper)": (58.00, 60.30),
                 "Diffuser (paper)": (45.60, None), "ours, paraphrased (paper)": (98.70, 97.33)},
    "rearrangement": {"ours (paper)": (99.80, 98.85), "DD (paper)": (62.70, 67.20),
                      "Diffuser (paper)": (58.90, None),
                      "ours, paraphrased (paper)": (97.80, 78.55)},
}

# MJX casts some of MuJoCo's float64 "infinite" defaults to float32 when it builds the model.
warnings.filterwarnings("ignore", "overflow encountered in cast")

TRAINING_NAME = "kuka"
"""One denoiser serves both experiments, all four Table 2 columns and both phrasings: the
shipped one is checkpoints/kuka, and `--train` of either experiment trains it (into
runs/kuka by default)."""
DEFAULT_CHECKPOINT = os.path.join(CHECKPOINT_ROOT, TRAINING_NAME)
DEFAULT_TRAIN_DIR = os.path.join(REPO_ROOT, "runs", TRAINING_NAME)
TEXTS = instruction.TEXTS
"""The denoiser's instruction input (``--text``, ``envs.kuka.training.Recipe.text``): the
grammar's token ids (every shipped Kuka checkpoint), or the frozen pretrained text encoder's
features of each sentence."""


def training_name(text: str = "tokens") -> str:
    """The denoiser's name: "kuka", or "kuka_pretrained" on pretrained text features."""
    return TRAINING_NAME if text == "tokens" else f"{TRAINING_NAME}_{text}"


def default_checkpoint(text: str = "tokens") -> str:
    """checkpoints/<training_name>: what the CLIs load without --checkpoint."""
    return os.path.join(CHECKPOINT_ROOT, training_name(text))


def default_train_dir(text: str = "tokens") -> str:
    """runs/<training_name>: where --train writes without --train-dir."""
    return os.path.join(REPO_ROOT, "runs", training_name(text))
TRAIN_STEPS = 4600
TRAIN_BATCH = 32
TRAIN_TIMESTEPS = 10
"""Diffusion training timesteps (the paper's 100; with 10, drawn as TIMESTEP_POWER says, the
Kuka model reaches the validation target in 15.6 training minutes: docs/benchmarks.md); the
planner denoises in NUM_STEPS = 10 steps."""
TIMESTEP_POWER = 3.0
"""Training timesteps are drawn towards the noisy end (diffplan.losses.draw_timesteps)."""
TRAIN_LR = 1e-3
WARMUP_STEPS = 200
CHECKPOINT_EVERY = 250
PREDICTION = "x0"


def model_config(size: str = "default", text: str = "tokens"):
    """The Kuka denoiser's DenoiserConfig: a model size of experiments.harness.recipes on the Kuka
    planning tensor (24 x 24, 2 condition and 3 generated channels, the Kuka vocabulary, cells
    embedded with the instruction words' table); text "pretrained": the instruction is the
    pretrained text encoder's features (context_dim D, L = sentences.FEATURE_TOKENS), the
    cells (grammar.CELL_TOKENS) embedded by their colour names' features through the
    instruction's projection (``DenoiserConfig.cell_context``)."""
    from envs.kuka import grammar
    from envs.kuka.task import NUM_COND_CHANNELS, NUM_GEN_CHANNELS

    if text == "pretrained":
        from envs.kuka.sentences import FEATURE_TOKENS, instruction_encoder

        words = dict(vocab_size=len(grammar.CELL_TOKENS), max_tokens=FEATURE_TOKENS,
                     context_dim=instruction_encoder().dim)
    else:
        words = dict(vocab_size=len(grammar.VOCAB), max_tokens=grammar.MAX_TOKENS)
    return recipes.denoiser_config(size, num_cond_channels=NUM_COND_CHANNELS,
                                   num_gen_channels=NUM_GEN_CHANNELS, **words)


def train_config(seed: int = 0, steps: int = TRAIN_STEPS,
                 checkpoint_every: int = CHECKPOINT_EVERY, prediction: str = PREDICTION):
    from envs.kuka.task import NUM_GEN_CHANNELS

    return recipes.train_config(seed=seed, steps=steps, batch_size=TRAIN_BATCH, lr=TRAIN_LR,
                                warmup_steps=WARMUP_STEPS, num_gen_channels=NUM_GEN_CHANNELS,
                                prediction=prediction, checkpoint_every=checkpoint_every,
                                max_log_every=50, num_train_timesteps=TRAIN_TIMESTEPS,
                                timestep_power=TIMESTEP_POWER)


def train_denoiser(out_dir: str, *, seed: int = 0, steps: int = TRAIN_STEPS,
                   model_size: str = "default", checkpoint_every: int = CHECKPOINT_EVERY,
                   prediction: str = PREDICTION, progress: bool = True,
                   text: str = "tokens") -> float:
    """Trains the Kuka denoiser into out_dir with envs.kuka.training.Recipe (resuming if
    out_dir holds a checkpoint of the same settings), on token ids or (text "pretrained") on
    pretrained text features. Returns the wall seconds of this call."""
    from envs.kuka.training import Recipe

    _, seconds = recipes.train_denoiser(
        model_config(model_size, text), train_config(seed, steps, checkpoint_every, prediction),
        Recipe(text=text), out_dir, model_size=model_size, progress=progress)
    return seconds


def mismatch(denoiser, num_steps: int) -> str | None:
    """Why a denoiser cannot plan the Kuka world with num_steps steps (None if it can)."""
    from envs.kuka import grid
    from envs.kuka.task import NUM_COND_CHANNELS, NUM_GEN_CHANNELS

    want = (grid.GRID_SIZE, grid.GRID_SIZE, NUM_GEN_CHANNELS)
    if tuple(denoiser.plan_shape) != want or denoiser.num_cond_channels != NUM_COND_CHANNELS:
        return (f"plans {tuple(denoiser.plan_shape)} with {denoiser.num_cond_channels} "
                f"condition channels; the Kuka world needs {want} with {NUM_COND_CHANNELS}")
    if num_steps > denoiser.schedule.num_train_steps:
        return (f"cannot take --num-steps {num_steps}: it exceeds its schedule of "
                f"{denoiser.schedule.num_train_steps} training timesteps")
    return None


def load_checked(checkpoint: str, num_steps: int, kind: str, text: str = "tokens"):
    """The checkpoint's LoadedDenoiser, checked against the Kuka planning tensor, the step
    count and the world's instruction input (its vocabulary, or for a checkpoint on
    pretrained features its cell tokens); one-line errors for a missing, unreadable or
    mismatched checkpoint (a missing one names `--train`, with `--text` text)."""
    from envs.kuka import grammar
    from experiments.harness.core import fail, load_checked as load
    from experiments.harness.text import input_mismatch

    train = f"python -m experiments.kuka_{kind} --train" + (
        "" if text == "tokens" else f" --text {text}")
    denoiser = load(checkpoint, train, lambda denoiser: mismatch(denoiser, num_steps))
    problem = input_mismatch(checkpoint, denoiser, grammar.VOCAB, grammar.CELL_TOKENS)
    if problem:
        fail(f"the checkpoint {checkpoint} {problem}")
    return denoiser


def label(mode: str | None, multi: bool, language: str, policy: str, read: bool = False
          ) -> str:
    """A row's method: who acts (the planner and how it plans; mode None: policy, e.g. the
    expert or a baseline's method name), which column, which phrasing (", read": restated
    canonically by a reader first)."""
    who = policy if mode is None else f"planner {METHOD_NAMES[mode]}"
    what = "multi-constraint" if multi else "single constraint"
    return f"{who}, {what}" + (f", {language}" if language != "canonical" else "") + (
        ", read" if read else "")


def policy_name(policy: str) -> str:
    """The rows' name of a --policy: "expert", or a baseline's method name ("BC")."""
    from diffplan.baselines.policies import METHOD_NAMES

    return METHOD_NAMES.get(policy, policy)


def load_reader(directory: str, name: str = "--reader"):
    """(ReaderConfig, params) of a reader directory (``diffplan.reader.load_reader``), checked
    to be the Kuka world's (its tagger's vocabulary and instruction length); SystemExit with
    one line, starting with name (the flag or key that gave it), otherwise."""
    from diffplan.reader import load_reader as load
    from envs.kuka.reader import reader_config

    try:
        config, params, _ = load(directory)
    except (OSError, ValueError, KeyError) as e:
        raise SystemExit(f"{name} {directory!r}: {e}") from None
    sized = ("dim", "num_layers", "num_heads", "sentence_local")
    if config != reader_config(**{k: getattr(config, k) for k in sized}):
        raise SystemExit(f"{name} {directory!r} was trained for another vocabulary or "
                         f"instruction length ({config}), not the Kuka world's")
    return config, params
